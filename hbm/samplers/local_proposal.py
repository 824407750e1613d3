"""Locally adapted random walk: each point proposes with the covariance of its neighbourhood.

A posterior concentrated near a thin *curved* manifold (the muscle benchmark: one direction ~70×
thinner than the population's spread, and turning across it) defeats a random walk with the
global population covariance: the step must fit the thin direction everywhere, so the walk
crawls along the broad ones (thousands of steps to decorrelate).  Cut the population into
neighbourhoods and the curvature inside each is small: the covariance of the k nearest stage-start
particles of a point is thin across the manifold *there* and long along it (on the benchmark the
whitened Fisher information drops from ~7600 with the global covariance to ~30 with local ones).

The kernel: a fixed reference set R (the stage-start population, unique rows) with one covariance
C_j per reference (its k nearest references, plus a small ridge of the global covariance); a
point u uses the covariance of its nearest reference, nn(u) (Euclidean distance after whitening
with the global covariance).  The proposal u' = u + s·L_{nn(u)} z is not symmetric, so the
Metropolis–Hastings ratio carries q(u | u')/q(u' | u) with the covariance of u'’s nearest
reference; R does not change during the stage, so the kernel is a fixed Markov kernel that
leaves the tempered target invariant.

Sampler-layer code: nothing here knows about muscles.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

__all__ = ["LocalMetric", "fit_local_metric", "nearest_reference", "local_step"]

#: references per block of the nearest-neighbour search (bounds the (points × refs) distance matrix)
_BLOCK = 2048


class LocalMetric(NamedTuple):
    """Reference points and their neighbourhood covariances.

    Attributes
    ----------
    whiten : ndarray (d, d)
        W with W·Σ·Wᵀ = I for the global covariance Σ (distances are measured in W·u).
    refs_w : ndarray (m, d)
        Whitened unique reference points.
    ref_sq : ndarray (m,)
        Their squared norms (distance computations).
    chols : ndarray (m, d, d)
        Cholesky factors of the neighbourhood covariances.
    logdets : ndarray (m,)
        log det of the neighbourhood covariances.
    """

    whiten: np.ndarray
    refs_w: np.ndarray
    ref_sq: np.ndarray
    chols: np.ndarray
    logdets: np.ndarray


def fit_local_metric(ref: np.ndarray, sigma: np.ndarray, k: int, ridge: float = 0.01) -> LocalMetric:
    """Neighbourhood covariances of the unique rows of ``ref``.

    Parameters
    ----------
    ref : ndarray (n, d)
        Reference population (duplicates after resampling are dropped).
    sigma : ndarray (d, d)
        Global covariance: defines the distance and the ridge ``ridge·sigma`` added to every
        neighbourhood covariance (keeps it positive definite and the walk able to leave a
        flat neighbourhood).
    k : int
        Neighbours per reference (itself included); at least d + 1 are used.

    Returns
    -------
    LocalMetric
    """
    u = np.unique(ref, axis=0)
    m, d = u.shape
    k = int(min(max(k, d + 1), m))
    lg = np.linalg.cholesky(sigma)
    whiten = np.linalg.inv(lg)
    w = u @ whiten.T
    sq = np.einsum("ij,ij->i", w, w)
    nbr = np.empty((m, k), dtype=np.int64)
    for s in range(0, m, _BLOCK):  # blocks of rows: at most _BLOCK × m distances at a time
        d2 = sq[s:s + _BLOCK, None] + sq[None, :] - 2.0 * w[s:s + _BLOCK] @ w.T
        nbr[s:s + _BLOCK] = np.argpartition(d2, k - 1, axis=1)[:, :k]
    nb = u[nbr]  # (m, k, d)
    nb = nb - nb.mean(axis=1, keepdims=True)
    cov = np.einsum("mki,mkj->mij", nb, nb) / (k - 1) + ridge * sigma[None]
    chols = np.linalg.cholesky(0.5 * (cov + np.swapaxes(cov, 1, 2)))
    logdets = 2.0 * np.sum(np.log(np.diagonal(chols, axis1=1, axis2=2)), axis=1)
    return LocalMetric(whiten, w, sq, chols, logdets)


def nearest_reference(metric: LocalMetric, x: np.ndarray) -> np.ndarray:
    """Index of the nearest reference (whitened Euclidean distance) of every row of ``x``."""
    xw = x @ metric.whiten.T
    best = np.full(len(x), np.inf)
    arg = np.zeros(len(x), dtype=np.int64)
    for s in range(0, len(metric.refs_w), _BLOCK):
        r = metric.refs_w[s:s + _BLOCK]
        d2 = metric.ref_sq[None, s:s + _BLOCK] - 2.0 * xw @ r.T  # |x|² is common to a row
        j = np.argmin(d2, axis=1)
        v = d2[np.arange(len(x)), j]
        better = v < best
        best = np.where(better, v, best)
        arg = np.where(better, j + s, arg)
    return arg


def _log_q(step: np.ndarray, chols: np.ndarray, logdets: np.ndarray, scale: float) -> np.ndarray:
    """log N(step; 0, scale²·L Lᵀ) up to the −d/2·log 2π − d·log scale shared by both directions."""
    z = np.linalg.solve(chols, step[:, :, None])[:, :, 0] / scale
    return -0.5 * np.einsum("ij,ij->i", z, z) - 0.5 * logdets


def local_step(x, ll, lp, near, beta, scale, evaluate, rng, metric: LocalMetric):
    """One MH step of the whole population with the locally adapted random walk.

    Parameters
    ----------
    x, ll, lp : ndarray
        Positions (n, d) in the sampling coordinates, log-likelihoods, log prior densities.
    near : ndarray (n,)
        Nearest reference of every particle (:func:`nearest_reference`).
    beta, scale : float
        Tempering exponent; step scale relative to the neighbourhood covariance.
    evaluate : callable
        u (m, d) → (log-likelihood (m,), log prior density (m,)).
    rng : numpy Generator
    metric : LocalMetric

    Returns
    -------
    x, ll, lp, near, accepted (n,) bool, evaluations (int)
    """
    n, d = x.shape
    z = rng.standard_normal((n, d))
    step = scale * np.einsum("nij,nj->ni", metric.chols[near], z)
    prop = x + step
    log_u = np.log(rng.random(n))
    near_p = nearest_reference(metric, prop)
    lq_fwd = -0.5 * np.einsum("ij,ij->i", z, z) - 0.5 * metric.logdets[near]
    lq_rev = _log_q(-step, metric.chols[near_p], metric.logdets[near_p], scale)
    ll_p, lp_p = evaluate(prop)
    with np.errstate(invalid="ignore"):
        log_ratio = beta * (ll_p - ll) + (lp_p - lp) + lq_rev - lq_fwd
    accept = np.isfinite(ll_p) & ((log_ratio >= log_u) | ~np.isfinite(ll))
    x = np.where(accept[:, None], prop, x)
    return (x, np.where(accept, ll_p, ll), np.where(accept, lp_p, lp), np.where(accept, near_p, near),
            accept, n)
