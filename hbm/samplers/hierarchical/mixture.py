"""The Gaussian-mixture independence proposal of the exact fallback's specimen moves.

k-means clusters of a specimen's stage-1 rows (whitened Lloyd iterations), each with its own
covariance: it follows the thin curved ridges of the posteriors where a random walk needs tiny
steps.  This module is sampler-layer code: it knows nothing about muscles.
"""

from __future__ import annotations

import numpy as np

from ..linalg import safe_cholesky

__all__ = ["fit_mixture", "pick"]


def pick(logp: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """One index per row of ``logp`` (n, M), drawn with probabilities ∝ exp(logp) (inverse CDF)."""
    w = np.exp(logp - logp.max(axis=1, keepdims=True))
    cw = np.cumsum(w, axis=1)
    return np.minimum((cw < (rng.random(logp.shape[0]) * cw[:, -1])[:, None]).sum(axis=1), logp.shape[1] - 1)


def fit_mixture(rows: np.ndarray, n_components: int, inflate: float, rng: np.random.Generator):
    """Gaussian mixture of k-means clusters of ``rows`` (whitened Lloyd iterations), covariances × inflate².

    Returns (log weights (M,), means (M, d), Cholesky factors (M, d, d), log determinants (M,)).
    Clusters with fewer than 2(d + 1) rows are dropped (the proposal need only be a density).
    """
    n, d = rows.shape
    Lg = safe_cholesky(np.cov(rows, rowvar=False).reshape(d, d))
    w = np.linalg.solve(Lg, (rows - rows.mean(axis=0)).T).T
    M = max(1, min(int(n_components), n // (4 * (d + 1))))
    cent = w[rng.choice(n, M, replace=False)]
    for _ in range(25):
        lab = np.argmin(np.sum(w * w, axis=1)[:, None] - 2 * w @ cent.T + np.sum(cent * cent, axis=1)[None, :], axis=1)
        cent = np.stack([w[lab == m].mean(axis=0) if np.any(lab == m) else cent[m] for m in range(M)])
    keep = [m for m in range(M) if np.sum(lab == m) >= 2 * (d + 1)]
    if not keep:
        keep, lab = [0], np.zeros(n, int)
    logw = np.log(np.array([np.sum(lab == m) for m in keep], float))
    mu = np.stack([rows[lab == m].mean(axis=0) for m in keep])
    L = np.stack([safe_cholesky(np.cov(rows[lab == m], rowvar=False).reshape(d, d)) * inflate for m in keep])
    logdet = np.sum(np.log(np.diagonal(L, axis1=1, axis2=2)), axis=1)
    return logw - np.log(np.exp(logw).sum()), mu, L, logdet
