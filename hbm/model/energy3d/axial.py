"""The thesis form read in 3-D ("axial", DESIGN.md §8): the collagen's stress is conjugate to the fibre
stretch.

The thesis applies the collagen's nominal stress T1·(exp(T2·(λH − 1)) − 1), a function of the helix
stretch of *uniaxial* kinematics λH² = cos²θ·λf² + sin²θ/λf, along the fibre axis.  As a 3-D material
that is an energy of the fibre stretch alone, W_ax(λf) with W_ax' = that stress: along the fibres it
gives the thesis's Cauchy stress exactly; elsewhere it is not convex (the compressive tangent
3μ + (1 − c)·T1·T2·(3cos²θ − 1)/2 is negative for all six shipped specimens) and it has no traction-free
state in cross-fibre tension.  hbm therefore evaluates the thesis form only in along-fibre tension
(:func:`hbm.model.loadcases.check_mode`); W_ax itself has no closed form and is not needed there.
"""

from __future__ import annotations

import numpy as np

from ...errors import HbmError
from .base import CollagenReading, Sym, collagen_force, collagen_stiffness


def _along(p, log_lf, d_f):
    """(λf, W_ax', λH, x) at fibre log-stretch ``log_lf`` and λf² − 1 = ``d_f``."""
    c2 = np.cos(np.deg2rad(p["THETA"])) ** 2
    l2m1 = c2 * d_f + (1.0 - c2) * np.expm1(-log_lf)   # λH² − 1 without cancellation
    lh = np.sqrt(1.0 + l2m1)
    x = np.maximum(l2m1 / (lh + 1.0), 0.0)
    return np.exp(log_lf), collagen_force(x, p["T1"], p["T2"]), lh, x, c2


class AxialCollagen(CollagenReading):
    """The thesis form's collagen: W_ax(λf) with dW_ax/dλf = T1·(exp(T2·(λH(λf) − 1)) − 1)."""

    name = "axial"
    description = "the thesis form: the collagen stress acts along the fibres (along-fibre tension only)"

    def energy(self, p, D):
        raise HbmError("the thesis form defines its collagen by a stress along the fibres; hbm does not "
                       "evaluate its energy (use the energy form, --form energy)")

    def pk2(self, p, D):
        d_f = np.asarray(D.ff, dtype=float)
        log_lf = 0.5 * np.log1p(d_f)
        lf, force, _, _, _ = _along(p, log_lf, d_f)
        return Sym(force / lf, 0.0, 0.0)

    def principal(self, p, e, tangent=False):
        log_lf = np.asarray(e[0], dtype=float)
        lf, force, lh, x, c2 = _along(p, log_lf, np.expm1(2.0 * log_lf))
        tau1 = lf * force
        zero = np.zeros_like(tau1)
        tau = (tau1, zero, zero)
        if not tangent:
            return tau, None
        slope = (c2 * lf - 0.5 * (1.0 - c2) / (lf * lf)) / lh      # dλH/dλf
        c11 = tau1 + lf * lf * collagen_stiffness(x, p["T1"], p["T2"]) * slope
        return tau, ((c11, zero, zero), (zero, zero, zero), (zero, zero, zero))
