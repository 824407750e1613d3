"""The truncated normal distribution, in one place: its log mass, its mean and its quantile function.

The population layer's normalisers and draws (:mod:`hbm.samplers.hierarchical`), the grouped layer's
moves and the collapsed likelihood's box integrals (:mod:`hbm.likelihood.collapsed.quadrature`) all
use these.  Every function works on the mirror image of an interval in the upper tail, where Φ values
near 1 would cancel, so each stays accurate 40 standard deviations into either tail.
"""

from __future__ import annotations

import numpy as np
from scipy.special import log_ndtr, ndtr, ndtri

__all__ = ["log_mass", "ppf"]

_LOG_SQRT_2PI = 0.5 * float(np.log(2.0 * np.pi))
#: u is kept this far from 0 and 1 (the quantile function stays finite and smooth in u)
_U_EDGE = 1e-12


def log_mass(z0, z1, mean: bool = False):
    """log(Φ(z1) − Φ(z0)) for z0 ≤ z1 (elementwise, broadcasting), and with ``mean`` the mean of the
    standard normal truncated to [z0, z1].

    The interval is reflected to the left tail when its midpoint is positive, where log Φ is
    accurate, and the mean ratio φ/ΔΦ is formed from logs.  Zero-width intervals give −inf (and
    their point as the mean).

    Parameters
    ----------
    z0, z1 : array_like
        Standardised interval ends.
    mean : bool
        Also return the truncated mean.

    Returns
    -------
    ndarray, or (ndarray, ndarray) with ``mean``
    """
    z0, z1 = np.broadcast_arrays(np.asarray(z0, float), np.asarray(z1, float))
    flip = (z0 + z1) > 0
    a = np.where(flip, -z1, z0)
    b = np.where(flip, -z0, z1)
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        la, lb = log_ndtr(a), log_ndtr(b)
        logd = lb + np.log1p(-np.exp(la - lb))
        if mean:
            m = np.exp(-0.5 * a * a - _LOG_SQRT_2PI - logd) - np.exp(-0.5 * b * b - _LOG_SQRT_2PI - logd)
    logd = np.where(b > a, logd, -np.inf)
    if not mean:
        return logd
    m = np.where(flip, -m, m)
    m = np.where(np.isfinite(m), np.clip(m, z0, z1), 0.5 * (z0 + z1))
    return logd, m


def ppf(u, mu, sd, lo, hi) -> np.ndarray:
    """Quantile function of Normal(mu, sd²) truncated to [lo, hi], elementwise (broadcasting).

    Increasing and continuous in u, mu and sd (a TMCMC move sees a smooth map); u is kept 1e-12 from
    0 and 1.  In the upper tail (a = (lo − mu)/sd > 0) it works on the mirror image so that the cdf
    values stay small; both branches agree at a = 0.  With u uniform it draws the truncated normal.

    Parameters
    ----------
    u : array_like
        Probabilities.
    mu, sd, lo, hi : array_like
        Location, scale and truncation interval.

    Returns
    -------
    ndarray
    """
    u = np.clip(np.asarray(u, float), _U_EDGE, 1.0 - _U_EDGE)
    a = (lo - mu) / sd
    b = (hi - mu) / sd
    flip = a > 0
    with np.errstate(invalid="ignore"):
        fa, fb = ndtr(a), ndtr(b)
        fma, fmb = ndtr(-a), ndtr(-b)
        x = np.where(flip, -ndtri(fmb + (1.0 - u) * (fma - fmb)), ndtri(fa + u * (fb - fa)))
    return np.clip(mu + sd * x, lo, hi)
