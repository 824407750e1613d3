"""``series_compliance``: a compliant element (tendon, grips) in series with the tissue."""

from __future__ import annotations

import numpy as np

from ..model.core import Effect, Parameter
from ._common import needs


def solve_series(eps_applied: np.ndarray, compliance: np.ndarray, elastic, *, tol: float = 1e-11,
                 max_iter: int = 100, h: float = 1e-7) -> np.ndarray:
    """Tissue strain ε_t with ε_t + C·σ(ε_t) = ε_applied, elementwise (vectorised).

    Safeguarded secant iteration on the whole array: the root is bracketed by
    [ε_a − C·σ(ε_a), ε_a] (ordered), valid whenever σ is non-decreasing in strain (true for
    the base model in tension; its collagen also engages in compression, so far below 0 the
    bracket may fail and the result is only the best point found).  The first slope is a
    forward difference at ε_a, later slopes are secants through the last two iterates (one
    elastic evaluation per iteration); steps that leave the bracket are replaced by
    bisection and the bracket shrinks with the sign of the residual, so the iteration always
    converges, also across the kinks at EOPT and at the collagen onset.
    """
    ea = np.asarray(eps_applied, dtype=float)
    s_a = elastic(ea)
    ea, c = np.broadcast_arrays(ea, compliance)
    e1 = ea - c * s_a
    lo, hi = np.minimum(e1, ea), np.maximum(e1, ea)
    g_prev = c * s_a  # residual at x_prev = ε_a
    x_prev = ea
    slope = 1.0 + c * (elastic(ea + h) - s_a) / h
    x = np.clip(ea - g_prev / slope, lo, hi)
    for _ in range(max_iter):
        g = x + c * elastic(x) - ea
        hi = np.where(g > 0, x, hi)
        lo = np.where(g <= 0, x, lo)
        dx = x - x_prev
        moved = np.abs(dx) > 1e-15
        secant = np.where(moved, (g - g_prev) / np.where(moved, dx, 1.0), slope)
        slope = np.where(secant > 0, secant, slope)
        xn = x - g / slope
        xn = np.where((xn >= lo) & (xn <= hi), xn, 0.5 * (lo + hi))
        xn = np.where(g == 0, x, xn)
        done = np.max(np.abs(xn - x)) <= tol if xn.size else True
        x_prev, g_prev, x = x, g, xn
        if done:
            break
    return x


class SeriesCompliance(Effect):
    """Linear compliant element in series with the tissue (tendon, grips, clamps).

    The measured strain is the tissue strain plus the strain of the series element::

        ε_applied = ε_t + C·σ(ε_t),   C = C_S ≥ 0 (1/MPa)

    solved for ε_t by a vectorised safeguarded secant iteration (:func:`solve_series`)
    using the model's total elastic stress σ(·).  The curve is stretched to the right in
    proportion to the stress, so it softens most where the stress is high.  C = 0 returns
    the applied strain exactly.

    Parameters
    ----------
    C_S : 1/MPa, box [0, 1], null 0.
        Clamp slip and tendon/aponeurosis strain can amount to 10–30 % of the grip
        displacement at ~0.1 MPa in whole-muscle tests (Calvo et al. 2010 J Biomech 43:318;
        Zajac FE 1989, Crit Rev Biomed Eng 17:359–411 for tendon compliance), i.e. C ~ 0.1–1 /MPa.
    """

    name = "series_compliance"
    stage = "kinematics"
    parameters = (Parameter("C_S", 0.0, 1.0, "1/MPa", "compliance of a linear element in series", null=0.0),)
    strength = "C_S"
    description = "compliant tendon/grips in series (strain shared, stress equal)"
    reference = "Zajac FE (1989) Crit Rev Biomed Eng 17:359-411"
    experiment = needs("the tissue strain measured optically on the mid-belly (markers/DIC)")

    def strain(self, state, p, elastic):
        c = p["C_S"]
        if not np.any(c > 0):
            return state.eps
        return np.where(c > 0, solve_series(state.eps, c, elastic), state.eps)
