"""``planar_c_hold_n``: stretch across the fibres with n held, the fibre faces free."""

from __future__ import annotations

from .base import Planar
from .registry import register_load_case


@register_load_case
class PlanarCHoldN(Planar):
    """Planar (pure-shear) test along c with n held: F = diag(1/λ, λ, 1), the f face traction-free.

    ``stress`` = σ_cc = τ_cc − τ_ff, ``stress_2`` = σ_nn = τ_nn − τ_ff.  At strain < 0: semi-confined
    compression across the fibres, free to expand along them.
    """

    name = "planar_c_hold_n"
    description = "stretch along c, n held at 1, f face traction-free: F = diag(1/lambda, lambda, 1)"
    axes = ("c", "n")     # (loaded, held)
