"""``shear_fc``: simple shear along the fibres (displacement along f varying along c)."""

from __future__ import annotations

from .base import SimpleShear
from .registry import register_load_case


@register_load_case
class ShearFC(SimpleShear):
    """Simple shear F = I + γ·e_f⊗e_c: the fibres keep their length (λf = 1, silent) and the collagen
    helix shears.  ``stress`` = σ_fc (= the nominal shear stress).  DESIGN.md §8 calls it fs."""

    name = "shear_fc"
    aliases = ("shear_fs",)
    description = "simple shear F = I + gamma e_f(x)e_c: displacement along f varying along c (fibres silent)"
    X, Y = "f", "c"
