"""``planar_c_hold_f``: stretch across the fibres with f held, n free."""

from __future__ import annotations

from .base import Planar
from .registry import register_load_case


@register_load_case
class PlanarCHoldF(Planar):
    """Planar (pure-shear) test along c with the fibres held: F = diag(1, λ, 1/λ), the n face free.

    ``stress`` = σ_cc = τ_cc − τ_nn, ``stress_2`` = σ_ff = τ_ff − τ_nn.  At strain < 0: semi-confined
    compression across the fibres with the fibre direction confined.
    """

    name = "planar_c_hold_f"
    description = "stretch along c, f held at 1, n face traction-free: F = diag(1, lambda, 1/lambda)"
    axes = ("c", "f")     # (loaded, held)
