"""Compiled inner loop of the collapsed likelihood (numba): the closed-form innermost column.

The innermost integral of :class:`~hbm.likelihood.collapsed.quadrature.BoxGaussianIntegral` is evaluated at
every outer Gauss–Legendre node of every population row (≈ 300 nodes per row for the base
model), and its numpy form spends most of a collapsed fit's CPU on temporary (n, M, K) arrays.
This kernel computes the same sum piece by piece in one pass.  It returns NaN where the total
underflows (every piece > 37 sd away), and the caller recomputes those entries in log space.
:func:`draw_linear_gaussian` draws from the same one-dimensional density by inverting its CDF.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

__all__ = ["closed_form_linear", "draw_linear_gaussian"]

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
                width = knots[r, i] - knots[r, i - 1]
                slope = (values[r, i] - values[r, i - 1]) / width if width > 0.0 else 0.0
                total += _term(values[r, i - 1], slope, s, z0, z1, u0, u1, e0, e1)
                z0, u0, e0 = z1, u1, e1
            total *= _SQRT_2PI * s
            out[r, m] = math.log(total) if total > 1e-250 else math.nan
    return out


@njit(cache=True, nogil=True)
def _term(v0: float, slope: float, s: float, z0: float, z1: float, u0: float, u1: float, e0: float,
          e1: float) -> float:
    """∫ over [z0, z1] (sd units) of (v0 + slope·s·(z − z0))·φ(z) dz, ≥ 0, from the tails
    u = Φ(−|z|) and e = exp(−z²/2) at both ends: ΔΦ times the linear density at the truncated mean."""
    if z0 >= 0.0:
        dphi = u0 - u1
    elif z1 <= 0.0:
        dphi = u1 - u0
    else:
        dphi = 1.0 - u0 - u1
    if not dphi > 0.0:
        return 0.0
    mz = min(max((e0 - e1) / (_SQRT_2PI * dphi), z0), z1)  # the truncated Gaussian's mean (sd units)
    pm = v0 + slope * s * (mz - z0)  # the linear density at that mean
    return dphi * pm if pm > 0.0 else 0.0


@njit(cache=True, nogil=True)
def _piece_mass(v0: float, slope: float, s: float, z0: float, z1: float) -> float:
    """:func:`_term` of the piece [z0, z1] (sd units)."""
    return _term(v0, slope, s, z0, z1, _tail(z0), _tail(z1), math.exp(-0.5 * z0 * z0), math.exp(-0.5 * z1 * z1))


@njit(cache=True, nogil=True)
def draw_linear_gaussian(knots: np.ndarray, values: np.ndarray, h: np.ndarray, mu: np.ndarray,
                         u: np.ndarray) -> np.ndarray:
    """Draws from ∝ p(a)·exp(−h(a − μ)²/2) for a piecewise-linear density p, by inverting the CDF.

    The piece is chosen by its mass (the terms of :func:`closed_form_linear`), the point inside
    it by bisection of the piece's partial mass (60 halvings: the width of a double).

    Parameters
    ----------
    knots, values : ndarray (n, K)
    h : ndarray (n,)
        Precision (> 0).
    mu : ndarray (n,)
    u : ndarray (n,)
        Uniform(0, 1) variates, one per row.

    Returns
    -------
    ndarray (n,): NaN where the total mass underflows (the caller draws those rows in log space).
    """
    n, k = knots.shape
    out = np.empty(n)
    for r in range(n):
        if not h[r] > 0.0:
            out[r] = math.nan
            continue
        s = 1.0 / math.sqrt(h[r])
        total = 0.0
        for i in range(1, k):
            w = knots[r, i] - knots[r, i - 1]
            slope = (values[r, i] - values[r, i - 1]) / w if w > 0.0 else 0.0
            total += _piece_mass(values[r, i - 1], slope, s, (knots[r, i - 1] - mu[r]) / s, (knots[r, i] - mu[r]) / s)
        if not total > 1e-250:
            out[r] = math.nan
            continue
        target = u[r] * total
        out[r] = knots[r, k - 1]
        for i in range(1, k):
            w = knots[r, i] - knots[r, i - 1]
            slope = (values[r, i] - values[r, i - 1]) / w if w > 0.0 else 0.0
            z0 = (knots[r, i - 1] - mu[r]) / s
            m = _piece_mass(values[r, i - 1], slope, s, z0, (knots[r, i] - mu[r]) / s)
            if target <= m or i == k - 1:
                lo, hi = knots[r, i - 1], knots[r, i]
                for _ in range(60):
                    mid = 0.5 * (lo + hi)
                    if _piece_mass(values[r, i - 1], slope, s, z0, (mid - mu[r]) / s) < target:
                        lo = mid
                    else:
                        hi = mid
                out[r] = 0.5 * (lo + hi)
                break
            target -= m
    return out
