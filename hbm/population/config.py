"""Defaults of the population layer (its settings: :class:`hbm.settings.PopulationSettings`)."""

from __future__ import annotations

from ..model.spec import base_spec
from ..settings.population import (
    DEFAULT_SD_RANGE, JOINT_SD_RANGE, POOL_COMBINATIONS, POOL_INFORMED, POOL_MODES, PopulationSettings)

__all__ = ["PopulationConfig", "PopulationSettings", "POOL_MODES", "DEFAULT_TRANSFORMS", "DEFAULT_SD_RANGE",
           "JOINT_SD_RANGE", "POOL_COMBINATIONS", "POOL_INFORMED", "COMBINATION_COLUMNS", "combination_columns"]

#: the default base's population transforms (its spec's :attr:`~hbm.model.spec.ModelSpec.transforms`; the
#: layer asks the spec of the model it fits)
DEFAULT_TRANSFORMS = dict(base_spec().transforms)


def combination_columns(roles) -> tuple[str, ...]:
    """Pooled coordinates of ``--pool combinations`` for a mixture (:class:`hbm.model.spec.MixtureRoles`):
    the logs of its three combinations (identity transform: they are logs already)."""
    return tuple(f"log_{c}" for c in roles.names)


#: the default base's combination columns
COMBINATION_COLUMNS = combination_columns(base_spec().mixture)
#: the layer's settings (:class:`hbm.settings.PopulationSettings`; ``PopulationConfig`` is its older name)
PopulationConfig = PopulationSettings
