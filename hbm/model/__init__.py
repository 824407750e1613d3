"""Constitutive model: effects, parameters, the Spyrou–Agoras–Danas base model."""

from .core import STAGES, Effect, Loading, Model, Parameter, State
from .linear import LinearStructure, structure_of, why_not_linear
from .spec import (
    BASES, Combination, Constituents, Manifold, MixtureRoles, ModelSpec, base_spec, register_base, spec_of,
    sweep_parameter)
from .spyrou import (
    BASE_EFFECTS, BASE_PARAMETERS, COMBINATIONS, FORMS, SHAPE_PARAMETERS, EnergyHelicalCollagen, HelicalCollagen,
    NeoHookeanMatrix, PassiveFibers, collagen_energy, collagen_onset_stretch, compression_check, model_form,
    helical_stretch, identifiable_combinations, spyrou_model)

__all__ = ["STAGES", "Effect", "Loading", "Model", "Parameter", "State", "LinearStructure", "structure_of",
           "why_not_linear", "BASE_PARAMETERS",
           "BASE_EFFECTS", "COMBINATIONS", "FORMS", "SHAPE_PARAMETERS", "EnergyHelicalCollagen", "HelicalCollagen",
           "NeoHookeanMatrix", "PassiveFibers", "collagen_energy", "collagen_onset_stretch", "compression_check",
           "model_form", "helical_stretch", "identifiable_combinations", "spyrou_model", "sweep_parameter",
           "BASES", "Combination", "Constituents", "Manifold", "MixtureRoles", "ModelSpec", "base_spec",
           "register_base", "spec_of"]
