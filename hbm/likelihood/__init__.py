"""The likelihood of a specimen's data: the vectorised log-likelihood (:mod:`.core`), its noise models
(:mod:`.noise`, a registry; :mod:`.student_t` registers heavy-tailed noise),
the prior (:mod:`.prior`) and the collapsed tier that integrates the linear
amplitudes out exactly (:mod:`.collapsed`)."""

from .core import Likelihood, make_likelihood
from .noise import NoiseModel, get_noise, noise_model_names, register_noise
from .prior import Prior, load_prior, resolve_prior
from . import student_t  # noqa: F401  (registers the "student_t" noise model)

__all__ = ["Likelihood", "make_likelihood", "NoiseModel", "get_noise", "noise_model_names", "register_noise",
           "Prior", "load_prior", "resolve_prior", "NOISE_MODELS"]


def __getattr__(name: str):
    # NOISE_MODELS is computed on access so that noise models registered later are listed
    if name == "NOISE_MODELS":
        return noise_model_names()
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
