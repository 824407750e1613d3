"""``recruitment``: gradual collagen recruitment (distribution of straightening stretches)."""

from __future__ import annotations

import numpy as np

from ..model.core import Effect, Parameter
from ..model.spyrou import CollagenAmplitude
from ._common import COLLAGEN_IMAGING, EXP_CLIP, collagen_excess, collagen_kernel, needs


class Recruitment(CollagenAmplitude, Effect):  # a correction to the collagen column
    """Gradual recruitment of the helical collagen instead of a sharp onset at λH = 1.

    The crimped fibrils of one bundle straighten at different stretches.  With the excess
    helical stretch x = ⟨λH − 1⟩₊ of the base model and a fibril straightening offset u
    uniformly distributed on [0, W], the collagen nominal stress becomes the average::

        P̄_m(x) = T1 · (1/W) ∫₀^W ( exp(T2·⟨x − u⟩₊) − 1 ) du
               = T1 · ( exp(T2·(x − m)) · expm1(T2·m)/T2 − m ) / W,   m = min(x, W)

    (closed form, exact, no quadrature).  To keep the composition additive the effect
    contributes the *correction* λ·(1 − c)·(P̄_m − P_m) to the base collagen; W = 0 gives
    exactly 0.  W is in units of helical stretch: near the onset at THETA ≈ 60°,
    dλH/dλ ≈ 0.10, so W = 0.01 spreads the recruitment over Δε ≈ 0.1.

    Parameters
    ----------
    REC_W : -, box [0, 0.02], null 0.
        Crimp/straightening-stretch distributions of collagen span a few percent of fibril
        stretch (Shearer T 2015, J Biomech 48:290–297; Hamedzadeh A, Gasser TC, Federico S
        2018, J Mech Behav Biomed Mater 77:269–277), i.e. ~0.005–0.02 in λH here.
    """

    name = "recruitment"
    stage = "elastic"
    parameters = (Parameter("REC_W", 0.0, 0.02, "-", "width of the collagen straightening-stretch distribution",
                            null=0.0),)
    uses = ("VOLF", "T1", "T2", "THETA")
    strength = "REC_W"
    description = "gradual collagen recruitment (uniform distribution of straightening stretches)"
    reference = "Shearer T (2015) J Biomech 48:290-297"
    experiment = needs(COLLAGEN_IMAGING)

    @staticmethod
    def averaged_kernel(x: np.ndarray, t2, w) -> np.ndarray:
        """(1/W)∫₀^W (exp(T2⟨x−u⟩₊) − 1) du for x ≥ 0 and W > 0 (elementwise, broadcast)."""
        w_safe = np.where(w > 0, w, 1.0)
        m = np.minimum(x, w_safe)
        t2m = np.minimum(t2 * m, EXP_CLIP)
        t2_safe = np.where(t2 > 0, t2, 1.0)
        # expm1(T2 m)/T2 -> m as T2 -> 0
        q = np.where(t2 > 0, np.expm1(t2m) / t2_safe, m)
        lead = np.exp(np.minimum(t2 * (x - m), EXP_CLIP))
        return (lead * q - m) / w_safe

    def stress(self, state, p):
        lam = state.lam
        x = collagen_excess(lam, p["THETA"])
        t2, w = p["T2"], p["REC_W"]
        corr = self.averaged_kernel(x, t2, w) - collagen_kernel(x, t2)
        return np.where(w > 0, lam * (1.0 - p["VOLF"]) * p["T1"] * corr, 0.0)
