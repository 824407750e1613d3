"""Compiled inner loop of the collapsed likelihood (numba): the closed-form innermost column.

The innermost integral of :class:`~hbm.collapse.quadrature.BoxGaussianIntegral` is evaluated at
every outer Gauss–Legendre node of every population row (≈ 300 nodes per row for the base
model), and its numpy form spends most of a collapsed fit's CPU on temporary (n, M, K) arrays.
This kernel computes the same sum piece by piece in one pass.  It returns NaN where the total
underflows (every piece > 37 sd away), and the caller recomputes those entries in log space.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

__all__ = ["closed_form_linear"]

_SQRT_2PI = math.sqrt(2.0 * math.pi)
_INV_SQRT2 = 1.0 / math.sqrt(2.0)


@njit(cache=True, nogil=True)
def _tail(z: float) -> float:
    """Φ(−|z|), the tail probability beyond |z| (no cancellation)."""
    return 0.5 * math.erfc(abs(z) * _INV_SQRT2)


@njit(cache=True, nogil=True)
def closed_form_linear(knots: np.ndarray, values: np.ndarray, h: np.ndarray, mu: np.ndarray) -> np.ndarray:
    """log ∫ p(a)·exp(−h(a − μ)²/2) da for a piecewise-linear density p (knots, values per row).

    Parameters
    ----------
    knots, values : ndarray (n, K)
        Break points (first and last = the support) and the density there.
    h : ndarray (n,)
        Precision of the column given the others (0: the likelihood does not see it).
    mu : ndarray (n, M)
        Conditional centres, one per outer node.

    Returns
    -------
    ndarray (n, M): the log integral, NaN where the total underflows (below 1e-250).
    """
    n, m_nodes = mu.shape
    k = knots.shape[1]
    out = np.empty((n, m_nodes))
    for r in range(n):
        if h[r] == 0.0:  # flat column: ∫ p = the prior's mass over the support
            tot = 0.0
            for i in range(1, k):
                tot += (knots[r, i] - knots[r, i - 1]) * 0.5 * (values[r, i] + values[r, i - 1])
            v = math.log(tot) if tot > 0.0 else -math.inf
            for m in range(m_nodes):
                out[r, m] = v
            continue
        s = 1.0 / math.sqrt(h[r])
        for m in range(m_nodes):
            c = mu[r, m]
            z0 = (knots[r, 0] - c) / s
            u0 = _tail(z0)
            e0 = math.exp(-0.5 * z0 * z0)
            total = 0.0
            for i in range(1, k):
                z1 = (knots[r, i] - c) / s
                u1 = _tail(z1)
                e1 = math.exp(-0.5 * z1 * z1)
                if z0 >= 0.0:
                    dphi = u0 - u1
                elif z1 <= 0.0:
                    dphi = u1 - u0
                else:
                    dphi = 1.0 - u0 - u1
                width = knots[r, i] - knots[r, i - 1]
                slope = (values[r, i] - values[r, i - 1]) / width if width > 0.0 else 0.0
                if dphi > 0.0:  # the truncated Gaussian's mean (in sd units) on this piece
                    mz = min(max((e0 - e1) / (_SQRT_2PI * dphi), z0), z1)
                else:
                    mz = 0.5 * (z0 + z1)
                pm = values[r, i - 1] + slope * s * (mz - z0)  # the linear density at that mean
                if dphi > 0.0 and pm > 0.0:
                    total += dphi * pm
                z0, u0, e0 = z1, u1, e1
            total *= _SQRT_2PI * s
            out[r, m] = math.log(total) if total > 1e-250 else math.nan
    return out
