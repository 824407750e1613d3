"""Convergence of lock-step chains: rank-normalised split R-hat and bulk ESS (Vehtari et al. 2021).

This module is sampler-layer code: it knows nothing about muscles.
"""

from __future__ import annotations

import numpy as np
from scipy.special import ndtri

__all__ = ["rhat_ess", "average_ranks"]


def average_ranks(x: np.ndarray) -> np.ndarray:
    """Ranks 1..n of the flattened ``x``, ties given their average rank (``scipy.stats.rankdata``'s
    default, computed by the same formula; all NaN if any value is NaN, as rankdata propagates it); numpy
    only, so the commands that read a fit's R-hat (``hbm summary``) do not import ``scipy.stats`` (~0.4 s)."""
    flat = np.ravel(x)
    if np.isnan(flat).any():
        return np.full(flat.size, np.nan)
    order = np.argsort(flat, kind="mergesort")
    s = flat[order]
    first = np.r_[True, s[1:] != s[:-1]]
    dense = np.cumsum(first)
    count = np.r_[np.nonzero(first)[0], first.size]
    ranks = np.empty(flat.size, dtype=float)
    ranks[order] = 0.5 * (count[dense] + count[dense - 1] + 1)
    return ranks


def rhat_ess(x: np.ndarray) -> tuple[float, float]:
    """Rank-normalised split R-hat and bulk ESS of draws ``x`` (n_chains, n_draws) (Vehtari et al. 2021).

    Each chain is split in halves; the draws are replaced by normal scores of their ranks; R-hat
    compares between- and within-half-chain variances, the ESS sums the chain-averaged
    autocorrelations with Geyer's initial monotone positive sequence.
    """
    x = np.asarray(x, float)
    m, n = x.shape
    half = n // 2
    if half < 2:
        return float("nan"), float("nan")
    x = np.concatenate([x[:, :half], x[:, n - half:]], axis=0)
    r = average_ranks(x).reshape(x.shape)
    z = ndtri((r - 0.375) / (x.size + 0.25))
    M, N = z.shape
    w = z.var(axis=1, ddof=1).mean()
    b = N * z.mean(axis=1).var(ddof=1)
    if not w > 0:
        return float("nan"), float("nan")
    var_plus = (N - 1) / N * w + b / N
    rhat = float(np.sqrt(var_plus / w))
    zc = z - z.mean(axis=1, keepdims=True)
    f = np.fft.rfft(zc, n=2 * N, axis=1)
    acov = np.fft.irfft(f * np.conj(f), axis=1)[:, :N] / N  # biased autocovariance per chain
    rho = 1.0 - (w - acov.mean(axis=0)) / var_plus
    rho[0] = 1.0
    pairs = rho[: 2 * (N // 2)].reshape(-1, 2).sum(axis=1)
    neg = np.nonzero(pairs < 0)[0]
    pairs = pairs[: neg[0]] if neg.size else pairs
    pairs = np.minimum.accumulate(pairs) if pairs.size else pairs
    tau = max(-1.0 + 2.0 * float(pairs.sum()), 1.0 / np.log10(M * N))
    return rhat, float(M * N / tau)
