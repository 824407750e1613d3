"""``shear_cn``: simple shear in the plane across the fibres (displacement along c varying along n)."""

from __future__ import annotations

from .base import SimpleShear
from .registry import register_load_case


@register_load_case
class ShearCN(SimpleShear):
    """Simple shear F = I + γ·e_c⊗e_n, in the transverse plane: the fibres keep their length.
    ``stress`` = σ_cn (= the nominal shear stress).  DESIGN.md §8 calls it sn."""

    name = "shear_cn"
    aliases = ("shear_sn",)
    description = "simple shear F = I + gamma e_c(x)e_n: displacement along c varying along n (transverse plane)"
    X, Y = "c", "n"
