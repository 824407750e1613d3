"""``biaxial_cn``: stretches along c and n (the plane across the fibres), the fibre faces free."""

from __future__ import annotations

from .base import Biaxial
from .registry import register_load_case


@register_load_case
class BiaxialCN(Biaxial):
    """Biaxial test across the fibres: F = diag(1/(λ1·λ2), λ1, λ2), the f face traction-free.

    λ1 = 1 + strain (along c), λ2 = 1 + strain_2 (along n; equal to λ1 when absent).
    ``stress`` = σ_cc = τ_cc − τ_ff, ``stress_2`` = σ_nn = τ_nn − τ_ff.
    """

    name = "biaxial_cn"
    description = "stretches along c (strain) and n (strain_2), f face traction-free"
    axes = ("c", "n")     # (strain, strain_2)
