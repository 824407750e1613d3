"""Constitutive model: effects, parameters, the Spyrou–Agoras–Danas base model."""

from .core import STAGES, Effect, Loading, Model, Parameter, State
from .spyrou import (BASE_EFFECTS, BASE_PARAMETERS, COMBINATIONS, SHAPE_PARAMETERS, HelicalCollagen, NeoHookeanMatrix, PassiveFibers,
                     collagen_onset_stretch, helical_stretch, identifiable_combinations, spyrou_model)

__all__ = ["STAGES", "Effect", "Loading", "Model", "Parameter", "State", "BASE_PARAMETERS",
           "BASE_EFFECTS", "COMBINATIONS", "SHAPE_PARAMETERS", "HelicalCollagen", "NeoHookeanMatrix", "PassiveFibers", "collagen_onset_stretch",
           "helical_stretch", "identifiable_combinations", "spyrou_model"]
