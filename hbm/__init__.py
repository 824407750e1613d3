"""hbm — Bayesian learning of skeletal-muscle model parameters across specimens."""

from ._version import __version__
from .model import Effect, Loading, Model, Parameter, State, spyrou_model
from .data import load_specimen, load_specimens, save_specimen, synthetic_specimen
from . import data, effects

__all__ = ["__version__", "Effect", "Loading", "Model", "Parameter", "State", "spyrou_model",
           "load_specimen", "load_specimens", "save_specimen", "synthetic_specimen", "data", "effects"]
