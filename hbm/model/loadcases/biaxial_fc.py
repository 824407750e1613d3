"""``biaxial_fc``: stretches along f and c, the n face free."""

from __future__ import annotations

from .base import Biaxial
from .registry import register_load_case


@register_load_case
class BiaxialFC(Biaxial):
    """Biaxial test in the f–c plane: F = diag(λ1, λ2, 1/(λ1·λ2)), the n face traction-free.

    λ1 = 1 + strain (along f), λ2 = 1 + strain_2 (along c; equal to λ1 when strain_2 is absent:
    equibiaxial).  ``stress`` = σ_ff = τ_ff − τ_nn, ``stress_2`` = σ_cc = τ_cc − τ_nn.
    """

    name = "biaxial_fc"
    description = "stretches along f (strain) and c (strain_2), n face traction-free"
    axes = ("f", "c")     # (strain, strain_2)
