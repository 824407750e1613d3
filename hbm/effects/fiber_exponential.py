"""``fiber_exponential``: titin-like exponential stiffening of the passive fibers."""

from __future__ import annotations

import numpy as np

from ..model.core import Effect, Parameter
from ..model.spyrou import unit_contribution
from ._common import EXP_CLIP, REFERENCE_LENGTH, needs


class FiberExponential(Effect):
    """Exponential (titin-like) passive fiber stress added to the linear fibers of the base model.

    ::

        σ_add = λ · c · A · (exp(B·x) − 1 − B·x),   x = ⟨ε − EOPT⟩₊,  c = VOLF

    The subtraction of the linear term keeps the initial slope at EOPT equal to the base
    model's P1 (the effect only adds curvature), and makes the contribution C¹ at EOPT.

    Parameters
    ----------
    FEXP_A : MPa, box [0, 0.05], null 0 (switches the effect off).
    FEXP_B : -, box [1, 40], null 10 (placeholder; irrelevant when FEXP_A = 0).
        Exponential passive-fiber laws in muscle use B ≈ 5–15 in stretch units, e.g. Blemker SS,
        Pinsky PM, Delp SL (2005) J Biomech 38:657–665 (P1 = 0.05 MPa, P2 = 6.6); titin-based
        passive tension rises steeply beyond ~1.3 sarcomere-length ratio (Granzier & Labeit 2004).
    """

    name = "fiber_exponential"
    stage = "elastic"
    parameters = (
        Parameter("FEXP_A", 0.0, 0.05, "MPa", "exponential passive-fiber stress scale", null=0.0),
        Parameter("FEXP_B", 1.0, 40.0, "-", "exponential passive-fiber stiffening rate", null=10.0),
    )
    uses = ("VOLF", "EOPT")
    strength = "FEXP_A"
    description = "titin-like exponential stiffening of the passive fibers beyond EOPT"
    reference = "Blemker SS, Pinsky PM, Delp SL (2005) J Biomech 38:657-665"
    experiment = needs(REFERENCE_LENGTH)
    linear_parameters = ("FEXP_A",)

    def amplitude_coefficients(self, p):
        return {"FEXP_A": ("VOLF*FEXP_A", p["VOLF"])}

    def unit_stress(self, state, p):
        return {"VOLF*FEXP_A": unit_contribution(self, state, p, VOLF=1.0, FEXP_A=1.0)}

    @staticmethod
    def _parts(state, p):
        x = np.maximum(state.eps - p["EOPT"], 0.0)
        bx = np.minimum(p["FEXP_B"] * x, EXP_CLIP)
        return x, bx, np.expm1(bx)

    def stress(self, state, p):
        _, bx, em1 = self._parts(state, p)
        return state.lam * p["VOLF"] * p["FEXP_A"] * (em1 - bx)

    def stress_jacobian(self, state, p):
        x, bx, em1 = self._parts(state, p)
        lam, c, a, b = state.lam, p["VOLF"], p["FEXP_A"], p["FEXP_B"]
        on = (state.eps > p["EOPT"]).astype(float)
        return {
            "VOLF": lam * a * (em1 - bx),
            "FEXP_A": lam * c * (em1 - bx),
            "FEXP_B": lam * c * a * x * em1,
            "EOPT": -lam * c * a * b * em1 * on,
        }
