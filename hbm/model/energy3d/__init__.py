"""The base model's strain energy in 3-D, with the collagen's 3-D reading as an option (DESIGN.md §8).

:class:`Energy3D` evaluates W(C), S = 2·∂W/∂C, τ = F·S·Fᵀ and the principal tangent, vectorised over
particles × points; :func:`energy_from_model` builds it from a :class:`~hbm.model.Model`.  The
collagen readings are registered in :data:`COLLAGEN_READINGS` (one class per file: :mod:`.cone`,
:mod:`.gst`), so a third reading is one class with :func:`register_collagen_reading`.
"""

from .base import (COLLAGEN_READINGS, DEFAULT_COLLAGEN3D, CollagenReading, DirectionalCollagen, Sym,
                   get_collagen_reading, register_collagen_reading)
from .cone import ConeCollagen, ConeFamilies
from .gst import GstCollagen
from .axial import AxialCollagen
from .energy import Energy3D, energy_from_model

__all__ = ["COLLAGEN_READINGS", "DEFAULT_COLLAGEN3D", "CollagenReading", "DirectionalCollagen", "Sym",
           "get_collagen_reading", "register_collagen_reading", "ConeCollagen", "ConeFamilies", "GstCollagen",
           "AxialCollagen", "Energy3D", "energy_from_model"]
