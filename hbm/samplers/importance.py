"""Importance-sampling evidence from a posterior population: a multivariate-t proposal, PSIS k̂.

Given posterior draws of a log-likelihood on a box with a uniform prior (e.g. a TMCMC run), fit a
multivariate t (mean and covariance of the draws, inflated) in the logit coordinates of the box
and estimate

    Z = E_q[ L(x)·π(x)/q(x) ],     π = 1/vol(box),

from fresh draws of q.  Reported with the estimate: its standard error (delta method on the
weights' mean), the effective sample size (Σw)²/Σw² and the Pareto k̂ of the weights
(:func:`hbm.samplers.psis.pareto_khat`).  The estimate is *refused* -- ``accepted`` False with
the reason, and the caller keeps its own value -- when k̂ > 0.7 (the weights' variance is
infinite or the proposal misses mass) or the ESS is below ``min_ess`` (an absolute number: the
relative Monte Carlo error of Ẑ is about 1/√ESS, so ESS ≥ 200 keeps log Ẑ within ~0.07 nats, and
the posterior resampled from the draws has at least that many distinct points).

Sampler-layer code: it knows nothing about muscles.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.special import gammaln, logsumexp

from ..errors import HbmError
from .psis import K_HAT_THRESHOLD, pareto_khat

__all__ = ["ImportanceResult", "importance_evidence", "MIN_ESS"]

#: smallest accepted effective sample size of the weights: 1/√200 ≈ 7 % relative error of Ẑ
MIN_ESS = 200.0


@dataclass
class ImportanceResult:
    """Outcome of :func:`importance_evidence`.

    Attributes
    ----------
    log_evidence, log_evidence_se : float
        log Ẑ and its standard error (NaN when no draw had a finite weight).
    ess : float
        Effective sample size of the weights.
    khat : float
        PSIS Pareto k̂ of the weights.
    n_draws : int
        Draws the estimate rests on (the last round's).
    accepted : bool
        k̂ ≤ 0.7 and ESS ≥ ``min_ess``.
    reason : str or None
        Why the estimate was refused.
    samples, log_weights : ndarray
        The proposal draws (box coordinates) and their normalised log weights.
    n_evaluations : int
        Log-likelihood evaluations of all rounds.
    """

    log_evidence: float
    log_evidence_se: float
    ess: float
    khat: float
    n_draws: int
    accepted: bool
    reason: str | None
    samples: np.ndarray
    log_weights: np.ndarray
    n_evaluations: int = 0

    def to_dict(self) -> dict:
        return {"log_evidence": self.log_evidence, "log_evidence_se": self.log_evidence_se, "ess": self.ess,
                "ess_fraction": self.ess / max(self.n_draws, 1), "khat": self.khat, "n_draws": self.n_draws,
                "accepted": self.accepted, "reason": self.reason,
                "n_evaluations": self.n_evaluations}


def _logit(x, lo, hi):
    t = np.clip((x - lo) / (hi - lo), 1e-12, 1 - 1e-12)
    return np.log(t) - np.log1p(-t)


def _draw_round(log_likelihood, lo, hi, mean, cov, m, df, rng, batch) -> tuple[np.ndarray, np.ndarray]:
    """m draws of the t proposal (mean, cov) in logit coordinates: box points and log weights L·π/q."""
    d = lo.size
    L = np.linalg.cholesky(cov + 1e-10 * np.eye(d))
    z = rng.standard_normal((m, d))
    g = rng.chisquare(df, m) / df
    un = mean + (z @ L.T) / np.sqrt(g)[:, None]
    # log q_u (multivariate t), then the Jacobian of x = lo + (hi − lo)·sigmoid(u)
    sol = np.linalg.solve(L, (un - mean).T).T
    maha = np.einsum("ij,ij->i", sol, sol)
    logq_u = (gammaln((df + d) / 2) - gammaln(df / 2) - 0.5 * d * np.log(df * np.pi)
              - np.log(np.diag(L)).sum() - 0.5 * (df + d) * np.log1p(maha / df))
    s = 1.0 / (1.0 + np.exp(-un))
    xn = lo + (hi - lo) * s
    log_dxdu = np.log(hi - lo) - np.logaddexp(0.0, -un) - np.logaddexp(0.0, un)  # log s(1 − s), no underflow
    logq_x = logq_u - log_dxdu.sum(axis=1)
    log_prior = -np.log(hi - lo).sum()
    ll = np.concatenate([np.asarray(log_likelihood(xn[i:i + batch]), float) for i in range(0, m, batch)])
    ll = np.where(np.isfinite(ll), ll, -np.inf)
    return xn, ll + log_prior - logq_x


def importance_evidence(log_likelihood, bounds, samples, n_draws: int, *, seed, df: float = 5.0,
                        inflate: float = 1.5, min_ess: float = MIN_ESS, batch: int = 5000,
                        adapt: float = 0.0) -> ImportanceResult:
    """log Z by importance sampling from a t proposal fitted to posterior ``samples``.

    Parameters
    ----------
    log_likelihood : callable
        x (n, d) -> log-likelihood (n,), called on batches of at most ``batch`` rows.
    bounds : array (d, 2)
        The uniform prior's box.
    samples : array (m, d)
        Posterior draws (equally weighted) inside the box; m > d.
    n_draws : int
        Proposal draws.
    seed : int or SeedSequence
    df : float
        Degrees of freedom of the t proposal (heavy tails keep the weights bounded where the fit
        is too narrow).
    inflate : float
        Factor on the draws' covariance.
    min_ess : float
        Smallest effective sample size accepted (absolute: it sets the estimate's precision,
        whatever the number of draws).
    batch : int
        Rows per call of ``log_likelihood``.
    adapt : float
        Fraction of the draws spent on a first round whose weighted draws refit the proposal; the
        estimate and diagnostics come from the second round only (0: one round).

    Returns
    -------
    ImportanceResult
    """
    b = np.asarray(bounds, float)
    lo, hi = b[:, 0], b[:, 1]
    x = np.asarray(samples, float)
    d = b.shape[0]
    if x.ndim != 2 or x.shape[1] != d or x.shape[0] <= d + 1:
        raise HbmError(f"importance_evidence: need (m > {d + 1}, {d}) posterior samples, got {x.shape}")
    if int(n_draws) < 10:
        raise HbmError(f"importance_evidence: n_draws must be >= 10, got {n_draws}")
    u = _logit(x, lo, hi)
    mean = u.mean(axis=0)
    cov = np.cov(u, rowvar=False) * inflate
    rng = np.random.default_rng(seed)
    m = int(n_draws)
    m1 = int(round(adapt * m)) if adapt > 0 else 0
    if m1:
        # first round: refit the proposal to its own weighted draws (in the logit coordinates)
        x1, lw1 = _draw_round(log_likelihood, lo, hi, mean, cov, m1, df, rng, batch)
        w1 = np.exp(lw1 - np.max(lw1)) if np.isfinite(lw1).any() else np.zeros(m1)
        if w1.sum() > 0 and w1.sum() ** 2 / (w1 * w1).sum() > 2 * (d + 2):
            w1 /= w1.sum()
            u1 = _logit(x1, lo, hi)
            mean = w1 @ u1
            cov = ((u1 - mean).T * w1) @ (u1 - mean) * inflate
    xn, logw = _draw_round(log_likelihood, lo, hi, mean, cov, m - m1, df, rng, batch)
    m = m - m1
    if not np.isfinite(logw).any():
        return ImportanceResult(float("nan"), float("nan"), 0.0, float("inf"), m, False,
                                "no proposal draw had a finite likelihood", xn, logw, m + m1)
    lz = float(logsumexp(logw) - np.log(m))
    w = np.exp(logw - logw.max())
    ess = float(w.sum() ** 2 / (w * w).sum())
    se = float(np.std(w) / (np.mean(w) * np.sqrt(m)))
    khat = float(pareto_khat(np.where(np.isfinite(logw), logw, -1e300)))
    reason = None
    if not khat <= K_HAT_THRESHOLD:
        reason = f"Pareto k̂ {khat:.2f} > {K_HAT_THRESHOLD}: the proposal misses part of the posterior"
    elif ess < min_ess:
        reason = f"ESS {ess:.0f} of {m} draws ({100 * ess / m:.1f}%) is below {min_ess:.0f}"
    return ImportanceResult(lz, se, ess, khat, m, reason is None, reason, xn, logw - logsumexp(logw), m + m1)
