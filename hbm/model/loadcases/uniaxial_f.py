"""``uniaxial_f``: tension or compression along the fibres, lateral faces traction-free (today's test)."""

from __future__ import annotations

import numpy as np

from .base import Observable, PrescribedStretch, fill, full_shape, lateral_strain
from .registry import register_load_case


@register_load_case
class UniaxialF(PrescribedStretch):
    """Uniaxial load along the fibre axis f; the c and n faces are traction-free.

    F = diag(λ, λ^-1/2, λ^-1/2) with λ = 1 + strain: transverse isotropy makes τ_cc = τ_nn for any
    parameters, so both lateral stretches are λ^-1/2 and carry no information about the material
    (DESIGN.md §8).  ``stress`` = σ_ff = τ_ff − τ_cc, equal to the 1-D model's stress
    (:func:`hbm.model.spyrou_model`) of the same form (≤ 5e-14 relative).  The only mode the thesis
    form is evaluated in.
    """

    name = "uniaxial_f"
    aliases = ("uniaxial",)
    description = "load along the fibres f; c and n faces traction-free (lateral stretches lambda^-1/2)"
    observables = (Observable("stress", "MPa", "Cauchy stress along the fibres, sigma_ff", "f"),
                   lateral_strain("c", name), lateral_strain("n", name))
    free = "c"
    stress_axes = {"stress": "f"}

    def log_stretches(self, strain, strain_2):
        e = np.log1p(strain)
        return e, -0.5 * e, -0.5 * e

    def solve(self, energy, params, strain, strain_2=None):
        out = super().solve(energy, params, strain, strain_2)
        s, _ = self.controls(strain)
        lateral = fill(np.expm1(-0.5 * np.log1p(s)), full_shape(params, s.size))
        out["strain_c"], out["strain_n"] = lateral, lateral.copy()
        return out
