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

from __future__ import annotations

from ._version import __version__
# first: in the `hbm` command, Ctrl-C while it imports is one line, exit 130 (until hbm.cli.main takes over)
from .runtime import process as _process  # noqa: F401
from . import errors
from .errors import DataError, HbmError, HbmWarning, OutputError, OutputLockedError, SettingError, TooLargeError
from .runtime.lazy import attach as _attach

# The public names resolve on first use (PEP 562), so that `import hbm` -- and with it every `hbm`
# command -- loads only what it uses: the samplers, the detective, cma, scipy.stats, xarray and
# matplotlib are imported by the code that needs them.  Sub-packages load on attribute access too
# (``hbm.io`` after a bare ``import hbm``), as when this file imported them all.
__getattr__, __dir__ = _attach(__name__, {
    ".model": ["Effect", "Loading", "Model", "Parameter", "State", "spyrou_model"],
    ".data": ["load_specimen", "load_specimens", "save_specimen", "synthetic_specimen"],
    ".likelihood.core": ["Likelihood", "make_likelihood"],
    ".samplers.tmcmc": ["TMCMCResult", "tmcmc"],
    ".samplers.hierarchical": ["HierarchicalResult", "hierarchical"],
    ".fit.sensitivity": ["SobolResult", "sobol"],
    ".identifiability.identify": ["identifiable_directions", "volf_t1_manifold"],
    ".organ": ["FusiformGeometry", "load_geometry", "organ_response"],
    ".fit.specimen": ["FitResult", "fit_specimen"],
    ".likelihood.prior": ["Prior", "resolve_prior"],
    ".workflow.run": ["RunConfig", "run_workflow"],
    ".workflow.organ": ["predict_organ"],
    ".detective": ["Diagnosis", "diagnose", "extend"],
    ".fit.optimization": ["OptimizeResult", "optimize"],
}, submodules=["cli", "data", "detective", "effects", "export", "fit", "identifiability", "io", "likelihood", "model",
               "organ", "plots", "population", "runtime", "samplers", "settings", "workflow"])


__all__ = ["__version__", "Effect", "Loading", "Model", "Parameter", "State", "spyrou_model",
           "load_specimen", "load_specimens", "save_specimen", "synthetic_specimen",
           "Likelihood", "make_likelihood", "TMCMCResult", "tmcmc", "HierarchicalResult", "hierarchical",
           "SobolResult", "sobol", "OptimizeResult", "optimize", "identifiable_directions",
           "volf_t1_manifold", "FusiformGeometry", "load_geometry", "organ_response",
           "predict_organ", "FitResult", "fit_specimen", "Prior", "resolve_prior", "RunConfig", "run_workflow", "Diagnosis", "diagnose", "extend",
           "data", "effects", "io", "organ", "errors", "HbmError", "DataError", "SettingError",
           "TooLargeError", "OutputError", "OutputLockedError", "HbmWarning"]
