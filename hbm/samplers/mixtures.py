"""Mixture proposals fitted to posterior draws: t components by weighted EM, Gaussian ones by k-means.

Two samplers propose from a mixture fitted to a population; both fitters live here, each with
its mixture's density:

* the importance finish (:mod:`hbm.samplers.importance`) refits its proposal to its own
  *weighted* draws: the importance weights must enter the fit, so the components come from
  weighted EM with soft responsibilities (:func:`weighted_em`) and are then used as heavy-tailed
  t components beside a defensive one (:class:`TMixture`), since the evidence needs a proposal
  whose tails are wider than the target's;
* the population layer's joint sampler (:mod:`hbm.samplers.hierarchical.shards`) fits its
  independence proposal once to a specimen's equally weighted stage-1 rows: hard k-means clusters
  (:func:`kmeans_mixture`, whitened Lloyd iterations; clusters too small for a covariance are
  dropped) with Gaussian components, evaluated every sweep for all specimens at once.

Why two fitters: one cannot serve both callers without changing what either produces.  EM needs
the weights and a component density for its responsibilities, k-means needs neither; they seed
their centres from the random stream differently (a weighted choice of k draws against an
unweighted one); EM's covariances are the weighted maximum-likelihood ones plus 10⁻⁶ of the
overall covariance, k-means' the unbiased cluster covariances through a jittered Cholesky
(:func:`~hbm.samplers.linalg.safe_cholesky`) times an inflation.  Each caller's tests and
benchmarks rest on its own fitter's numbers.

Sampler-layer code: it knows nothing about muscles.
"""

from __future__ import annotations

import numpy as np
from scipy.special import gammaln, logsumexp

from .linalg import safe_cholesky

__all__ = ["TMixture", "weighted_moments", "weighted_em", "kmeans_mixture"]


# -- t components by weighted EM (the importance finish) --------------------------------------------

class TMixture:
    """A mixture of multivariate t components (the importance finish's proposal, in the box's logit coordinates).

    ``components``: (weight, mean (d,), covariance (d, d), df) tuples; weights are normalised.
    """

    def __init__(self, components) -> None:
        w = np.array([c[0] for c in components], float)
        self.weights = w / w.sum()
        d = np.asarray(components[0][1]).size
        self.means = [np.asarray(c[1], float) for c in components]
        self.chols = [np.linalg.cholesky(np.asarray(c[2], float) + 1e-10 * np.eye(d)) for c in components]
        self.dfs = [float(c[3]) for c in components]

    def draw(self, m: int, rng: np.random.Generator) -> np.ndarray:
        """``m`` draws (rows)."""
        d = self.means[0].size
        which = rng.choice(len(self.weights), size=m, p=self.weights) if len(self.weights) > 1 else np.zeros(m, int)
        z = rng.standard_normal((m, d))
        g = np.empty(m)
        u = np.empty((m, d))
        for i, (mean, L, df) in enumerate(zip(self.means, self.chols, self.dfs)):
            sel = which == i
            g[sel] = rng.chisquare(df, int(sel.sum())) / df
            u[sel] = mean + (z[sel] @ L.T) / np.sqrt(g[sel])[:, None]
        return u

    def logpdf(self, u: np.ndarray) -> np.ndarray:
        """log density at the rows of ``u``."""
        d = u.shape[1]
        terms = []
        for w, mean, L, df in zip(self.weights, self.means, self.chols, self.dfs):
            sol = np.linalg.solve(L, (u - mean).T).T
            maha = np.einsum("ij,ij->i", sol, sol)
            terms.append(np.log(w) + gammaln((df + d) / 2) - gammaln(df / 2) - 0.5 * d * np.log(df * np.pi)
                         - np.log(np.diag(L)).sum() - 0.5 * (df + d) * np.log1p(maha / df))
        return logsumexp(np.stack(terms), axis=0)


def weighted_moments(u: np.ndarray, w: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Mean and (maximum-likelihood) covariance of the rows of ``u`` with weights ``w`` (any normalisation)."""
    w = w / w.sum()
    mean = w @ u
    return mean, ((u - mean).T * w) @ (u - mean)


def weighted_em(u: np.ndarray, w: np.ndarray, k: int, rng: np.random.Generator, iters: int = 60):
    """Weighted EM for a k-component Gaussian mixture of draws ``u`` with weights ``w``.

    Returns (weights, means, covariances) or None when the fit degenerates (the caller keeps
    one component).  Each covariance gets 1e-6 of the overall one, so none collapses to a point.
    """
    n, d = u.shape
    w = w / w.sum()
    _, overall = weighted_moments(u, w)
    reg = 1e-6 * overall
    means = u[rng.choice(n, size=k, replace=False, p=w if np.count_nonzero(w) >= k else None)].copy()
    covs = np.array([overall.copy() for _ in range(k)])
    pis = np.full(k, 1.0 / k)
    for _ in range(iters):
        try:  # responsibilities (a t with df → ∞ is the Gaussian)
            lr = np.stack([np.log(p) + TMixture([(1.0, mu, c, 1e6)]).logpdf(u) for p, mu, c in zip(pis, means, covs)],
                          axis=1)
        except np.linalg.LinAlgError:
            return None
        lr -= logsumexp(lr, axis=1, keepdims=True)
        r = np.exp(lr) * w[:, None]
        nk = r.sum(axis=0)
        if not np.all(nk > 0):
            return None
        pis = nk / nk.sum()
        means = (r.T @ u) / nk[:, None]
        covs = np.array([((u - means[j]).T * r[:, j]) @ (u - means[j]) / nk[j] + reg for j in range(k)])
    if not (np.all(np.isfinite(means)) and np.all(np.isfinite(covs))):
        return None
    return pis, means, covs


# -- Gaussian components by k-means (the exact hierarchical fallback) --------------------------------

def kmeans_mixture(rows: np.ndarray, n_components: int, inflate: float, rng: np.random.Generator):
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
