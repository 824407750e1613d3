"""hbm — Bayesian learning of skeletal-muscle model parameters across specimens."""

from ._version import __version__
from .model import Effect, Loading, Model, Parameter, State, spyrou_model

__all__ = ["__version__", "Effect", "Loading", "Model", "Parameter", "State", "spyrou_model"]
