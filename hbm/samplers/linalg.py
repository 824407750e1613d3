"""Covariances and Cholesky factors that never fail: the linear algebra shared by the samplers.

A degenerate population (one survivor after resampling, a flat direction, a non-identifiable
parameter) must still give a usable proposal, so every factorisation here has a fallback.
"""

from __future__ import annotations

import numpy as np

__all__ = ["safe_cholesky", "batched_cholesky", "box_covariance", "free_covariance"]


def safe_cholesky(cov: np.ndarray) -> np.ndarray:
    """Lower Cholesky factor of ``cov``, adding jitter (up to 12 tries) and then using the diagonal.

    Parameters
    ----------
    cov : ndarray (d, d)
        Symmetric, nominally positive (semi-)definite matrix.

    Returns
    -------
    ndarray (d, d)
        L with L Lᵀ ≈ cov (exact when ``cov`` is positive definite); the diagonal square root
        when even jitter of 10⁻¹²·10¹¹·mean(diag) fails.
    """
    jitter = 0.0
    scale = float(np.mean(np.diag(cov)))
    for _ in range(12):
        try:
            return np.linalg.cholesky(cov + jitter * np.eye(len(cov)))
        except np.linalg.LinAlgError:
            jitter = max(jitter * 10.0, 1e-12 * scale)
    return np.diag(np.sqrt(np.maximum(np.diag(cov), 1e-300)))


def batched_cholesky(g: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Cholesky factors of a stack (n, d, d) and a mask of the matrices where it succeeded.

    numpy raises for the whole batch if one matrix fails, so the failing ones are located by
    their smallest eigenvalue and replaced by the identity (caller falls back for them).
    """
    n, d, _ = g.shape
    ok = np.all(np.isfinite(g), axis=(1, 2))
    g = np.where(ok[:, None, None], g, np.eye(d))
    try:
        return np.linalg.cholesky(g), ok
    except np.linalg.LinAlgError:
        pass
    sym = 0.5 * (g + np.swapaxes(g, 1, 2))
    lam_min = np.linalg.eigvalsh(sym)[:, 0]
    lam_max = np.abs(np.linalg.eigvalsh(sym)[:, -1])
    good = lam_min > 1e-12 * np.maximum(lam_max, 1e-300)
    ok &= good
    g = np.where(ok[:, None, None], sym, np.eye(d))
    try:
        return np.linalg.cholesky(g), ok
    except np.linalg.LinAlgError:  # pragma: no cover - borderline matrices: test one by one
        chol = np.empty_like(g)
        for i in range(n):  # rare fallback path only, not the hot loop
            try:
                chol[i] = np.linalg.cholesky(g[i])
            except np.linalg.LinAlgError:
                ok[i] = False
                chol[i] = np.eye(d)
        return chol, ok


def box_covariance(x: np.ndarray, w: np.ndarray, bounds: np.ndarray) -> np.ndarray:
    """Weighted covariance of points in the prior box, with a tiny box-relative floor (always p.d.)."""
    w = w / w.sum()
    mu = w @ x
    xc = x - mu
    cov = (xc * w[:, None]).T @ xc
    width = bounds[:, 1] - bounds[:, 0]
    cov = 0.5 * (cov + cov.T) + np.diag((1e-10 * width) ** 2)
    return cov


def free_covariance(x: np.ndarray, w: np.ndarray) -> np.ndarray:
    """Weighted covariance in unbounded sampling coordinates, with a relative floor."""
    wn = w / w.sum()
    xc = x - wn @ x
    sigma = (xc * wn[:, None]).T @ xc
    # floor: a degenerate weight vector (one survivor) must not freeze the walk
    return 0.5 * (sigma + sigma.T) + np.diag(1e-9 * x.var(axis=0) + 1e-12)
