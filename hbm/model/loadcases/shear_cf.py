"""``shear_cf``: simple shear across the fibres (displacement along c varying along f)."""

from __future__ import annotations

from .base import SimpleShear
from .registry import register_load_case


@register_load_case
class ShearCF(SimpleShear):
    """Simple shear F = I + γ·e_c⊗e_f: the fibres rotate and stretch to √(1 + γ²).
    ``stress`` = σ_cf (= the nominal shear stress).  DESIGN.md §8 calls it sf."""

    name = "shear_cf"
    aliases = ("shear_sf",)
    description = "simple shear F = I + gamma e_c(x)e_f: displacement along c varying along f (fibres stretch)"
    X, Y = "c", "f"
