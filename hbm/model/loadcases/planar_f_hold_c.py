"""``planar_f_hold_c``: stretch along the fibres with c held (pure shear / semi-confined), n free."""

from __future__ import annotations

from .base import Planar
from .registry import register_load_case


@register_load_case
class PlanarFHoldC(Planar):
    """Planar (pure-shear) test along f: F = diag(λ, 1, 1/λ), the n face traction-free.

    ``stress`` = σ_ff = τ_ff − τ_nn, ``stress_2`` = σ_cc = τ_cc − τ_nn (the reaction on the held
    face).  At strain < 0 this is semi-confined compression along f with c confined.
    """

    name = "planar_f_hold_c"
    description = "stretch along f, c held at 1, n face traction-free: F = diag(lambda, 1, 1/lambda)"
    axes = ("f", "c")     # (loaded, held)
