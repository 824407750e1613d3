"""hbm — Bayesian learning of skeletal-muscle model parameters across specimens.

The main entry points, by role:

* physics: :func:`spyrou_model`, :class:`Model`, :class:`Effect`, :mod:`hbm.effects`, :mod:`hbm.organ`
* data: :func:`load_specimen`, :func:`load_specimens`, :func:`save_specimen`, :func:`synthetic_specimen`
* inference: :func:`make_likelihood`, :func:`tmcmc`, :func:`optimize`, :func:`sobol`,
  :func:`fit_specimen`, :func:`hierarchical`
* workflow: :func:`run_workflow` (the six-specimen dask run behind ``hbm run``)
* the missing-physics loop: :func:`diagnose`, :func:`extend`
* errors: :class:`HbmError` and its subclasses (:mod:`hbm.errors`), raised for every bad input
"""

from ._version import __version__
from .runtime.process import restore_sigint as _restore_sigint  # Ctrl-C while `hbm` imports: one line, exit 130
from .model import Effect, Loading, Model, Parameter, State, spyrou_model
from .data import load_specimen, load_specimens, save_specimen, synthetic_specimen
from .likelihood.core import Likelihood, make_likelihood
from .samplers.tmcmc import TMCMCResult, tmcmc
from .samplers.hierarchical import HierarchicalResult, hierarchical
from .fit.sensitivity import SobolResult, sobol
from .identifiability.identify import identifiable_directions, volf_t1_manifold
from .organ import FusiformGeometry, load_geometry, organ_response
from .fit.specimen import FitResult, fit_specimen
from .likelihood.prior import Prior, resolve_prior
from .workflow.run import RunConfig, run_workflow
from .workflow.organ import predict_organ
from . import data, effects, errors, io, organ
from .detective import Diagnosis, diagnose, extend
from .fit.optimization import OptimizeResult, optimize
from .errors import DataError, HbmError, HbmWarning, OutputError, OutputLockedError, SettingError, TooLargeError

_restore_sigint()

__all__ = ["__version__", "Effect", "Loading", "Model", "Parameter", "State", "spyrou_model",
           "load_specimen", "load_specimens", "save_specimen", "synthetic_specimen",
           "Likelihood", "make_likelihood", "TMCMCResult", "tmcmc", "HierarchicalResult", "hierarchical",
           "SobolResult", "sobol", "OptimizeResult", "optimize", "identifiable_directions",
           "volf_t1_manifold", "FusiformGeometry", "load_geometry", "organ_response",
           "predict_organ", "FitResult", "fit_specimen", "Prior", "resolve_prior", "RunConfig", "run_workflow", "Diagnosis", "diagnose", "extend",
           "data", "effects", "io", "organ", "errors", "HbmError", "DataError", "SettingError",
           "TooLargeError", "OutputError", "OutputLockedError", "HbmWarning"]
