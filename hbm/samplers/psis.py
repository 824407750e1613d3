"""Pareto-smoothed importance sampling diagnostic: the generalized-Pareto shape k̂ of the ratio tail.

The importance ratios r_j = p(θ_j)/q(θ_j) of samples θ_j ~ q have a finite variance only if
the tail of their distribution is light enough.  PSIS (Vehtari, Simpson, Gelman, Yao & Gabry
2024, "Pareto smoothed importance sampling", JMLR 25(72)) fits a generalized Pareto
distribution (GPD) to the M largest ratios (M = ⌈min(S/5, 3√S)⌉ for S samples) and reads the
shape k̂: k̂ < 0.5 the ratios have a finite variance, 0.5–0.7 usable with slow convergence,
k̂ > 0.7 the estimate is unreliable (the samples miss part of the target's mass).

The GPD fit is the empirical-Bayes estimator of Zhang & Stephens (2009, Technometrics 51,
316–325), with the weakly informative prior on k of Vehtari et al. (pseudo-count 10 at 0.5),
as in the reference implementations (the R package loo and arviz).  Here it is vectorised over
many sets of ratios at once (rows), e.g. one set per hyper-posterior draw.

This module is sampler-layer code: it knows nothing about muscles.
"""

from __future__ import annotations

import numpy as np

from ..errors import HbmError

__all__ = ["gpd_fit", "pareto_khat", "tail_length", "K_HAT_THRESHOLD"]

#: k̂ above which the importance estimate is unreliable (Vehtari et al. 2024, sec. 3.2)
K_HAT_THRESHOLD = 0.7
_PRIOR_BS = 3.0  # Zhang & Stephens' prior scale on the b grid
_PRIOR_K = 10.0  # pseudo-observations of the weakly informative prior on k (centred at 0.5)


def tail_length(n: int, reff: float = 1.0) -> int:
    """Number M of largest ratios fitted: ⌈min(0.2·S, 3·√(S/r_eff))⌉."""
    return int(np.ceil(min(0.2 * n, 3.0 * np.sqrt(n / reff))))


def gpd_fit(x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Zhang–Stephens GPD fit of exceedances, row by row.

    Parameters
    ----------
    x : ndarray (R, M)
        Exceedances over the threshold (≥ 0), each row sorted ascending, M ≥ 5.

    Returns
    -------
    k, sigma : ndarray (R,)
        Posterior-mean shape (with the k prior of Vehtari et al. applied) and scale.
    """
    x = np.atleast_2d(np.asarray(x, float))
    r, n = x.shape
    m = 30 + int(np.sqrt(n))
    # grid of b = −k/σ values (Zhang & Stephens eq. 3), centred on the quartile and the maximum
    b = 1.0 - np.sqrt(m / (np.arange(1, m + 1, dtype=float) - 0.5))  # (m,)
    q1 = x[:, int(n / 4 + 0.5) - 1]
    b = b[None, :] / (_PRIOR_BS * q1[:, None]) + 1.0 / x[:, -1:]  # (R, m)
    with np.errstate(divide="ignore", invalid="ignore"):
        k = np.log1p(-b[:, :, None] * x[:, None, :]).mean(axis=2)  # (R, m): profile k(b)
        ll = n * (np.log(-b / k) - k - 1.0)  # profile log-likelihood
    ll = np.where(np.isfinite(ll), ll, -np.inf)
    # posterior weights of the grid points (uniform prior over the grid)
    w = np.exp(ll - ll.max(axis=1, keepdims=True))
    w = np.where(w >= 10 * np.finfo(float).eps * w.sum(axis=1, keepdims=True), w, 0.0)
    w /= w.sum(axis=1, keepdims=True)
    b_post = np.sum(b * w, axis=1)
    k_post = np.log1p(-b_post[:, None] * x).mean(axis=1)
    sigma = -k_post / b_post
    k_post = (n * k_post + _PRIOR_K * 0.5) / (n + _PRIOR_K)
    return k_post, sigma


def pareto_khat(log_ratios: np.ndarray, reff: float = 1.0) -> np.ndarray:
    """PSIS k̂ of importance ratios given on the log scale, one value per row.

    Parameters
    ----------
    log_ratios : ndarray (S,) or (R, S)
        log r_j (any additive constant per row).  −inf entries count as zero ratios.
    reff : float
        Relative efficiency of the samples (1 for independent draws).

    Returns
    -------
    ndarray (R,) (or a float for 1-d input)
        k̂; +inf when fewer than 5 ratios exceed the threshold (the tail is too short to fit:
        a handful of samples carry all the weight).
    """
    lr = np.asarray(log_ratios, float)
    one = lr.ndim == 1
    lr = np.atleast_2d(lr)
    if lr.ndim != 2 or lr.shape[1] < 10:
        raise HbmError(f"pareto_khat: need (R, S>=10) log ratios, got shape {np.shape(log_ratios)}")
    if np.any(np.isnan(lr)) or np.any(lr == np.inf):
        raise HbmError("pareto_khat: log ratios must not be NaN or +inf")
    s = lr.shape[1]
    m = tail_length(s, reff)
    lr = lr - lr.max(axis=1, keepdims=True)
    srt = np.sort(lr, axis=1)
    # threshold: the (M+1)-th largest, floored at the smallest normal number (as the reference)
    cut = np.maximum(srt[:, s - m - 1], np.log(np.finfo(float).tiny))
    tail = srt[:, s - m:]
    exceed = tail > cut[:, None]
    n_exc = exceed.sum(axis=1)
    out = np.full(lr.shape[0], np.inf)
    # rows with ties at the threshold have fewer exceedances; fit each distinct tail length once
    for n_t in np.unique(n_exc[n_exc > 4]):  # loop over distinct lengths (usually one), not rows
        rows = np.flatnonzero(n_exc == n_t)
        x = np.exp(tail[rows, m - n_t:]) - np.exp(cut[rows])[:, None]
        out[rows], _ = gpd_fit(x)
    return float(out[0]) if one else out
