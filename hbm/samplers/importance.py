"""Importance-sampling evidence from a posterior population: a multivariate-t proposal, PSIS k̂.

Given posterior draws of a log-likelihood on a box with a uniform prior (e.g. a TMCMC run), fit a
multivariate t (mean and covariance of the draws, inflated) in the logit coordinates of the box
-- optionally refitted to a first round of its own weighted draws, as one t or as a mixture of t
components with the one t kept as a defensive component, and with a reserve of draws spent on a
further refit only when the estimate is refused -- and estimate

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
from scipy.special import logsumexp

from ..errors import HbmError
from .mixtures import TMixture, weighted_em, weighted_moments
from .psis import K_HAT_THRESHOLD, pareto_khat

__all__ = ["ImportanceResult", "importance_evidence", "MIN_ESS", "FINISH_MIXTURE", "FINISH_RESERVE"]

#: smallest accepted effective sample size of the weights: 1/√200 ≈ 7 % relative error of Ẑ
MIN_ESS = 200.0
#: the collapsed fit's finish (:func:`hbm.likelihood.collapsed.sample_collapsed`): components of the refitted
#: mixture proposal and the share of the draws held in reserve.  Measured on the muscle benchmark
#: (40 pilots, seeds 0–39, 10 000 draws): one refitted t accepted 40/40 but with ESS 370–2000 and a
#: worst φ mean up to 0.33 gold sd (a few heavy weights in EOPT's thin tail towards 0); a 3-component
#: mixture, ESS 840–5000 and ≤ 0.15 sd, but k̂ > 0.7 in 3/40; with the 20 % reserve spent on
#: those, 40/40 accepted, ESS ≥ 1760, ≤ 0.17 sd, 8 000 draws in the median.
FINISH_MIXTURE, FINISH_RESERVE = 3, 0.2


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


def _ess(w: np.ndarray) -> float:
    return float(w.sum() ** 2 / (w * w).sum()) if w.sum() > 0 else 0.0


def _fit_proposal(u, w, inflate, df, mixture, share, rng) -> TMixture:
    """The proposal refitted to weighted draws: one t, or ``mixture`` t components (share
    ``share``, each covariance × ``inflate``) plus the one t as a defensive component."""
    mean, cov = weighted_moments(u, w)
    one = [(1.0, mean, cov * inflate, df)]
    d = u.shape[1]
    k = min(int(mixture), int(_ess(w) // (10 * (d + 1))))  # ≥ 10 effective draws per covariance entry row
    if k < 2:
        return TMixture(one)
    fit = weighted_em(u, w, k, rng)
    if fit is None:
        return TMixture(one)
    comps = [(share * p, m, c * inflate, df) for p, m, c in zip(*fit) if p > 1e-3]
    try:
        return TMixture(comps + [(1.0 - share, mean, cov * inflate, df)])
    except np.linalg.LinAlgError:
        return TMixture(one)


def _draw_round(log_likelihood, lo, hi, proposal: TMixture, m, rng, batch):
    """m draws of the proposal: box points, their logit coordinates, log L and log(π/q_x)."""
    un = proposal.draw(m, rng)
    logq_u = proposal.logpdf(un)
    xn = lo + (hi - lo) / (1.0 + np.exp(-un))
    # the Jacobian of x = lo + (hi − lo)·sigmoid(u), log s(1 − s) without underflow
    log_dxdu = np.log(hi - lo) - np.logaddexp(0.0, -un) - np.logaddexp(0.0, un)
    log_prior = -np.log(hi - lo).sum()
    ll = np.concatenate([np.asarray(log_likelihood(xn[i:i + batch]), float) for i in range(0, m, batch)])
    ll = np.where(np.isfinite(ll), ll, -np.inf)
    return xn, un, ll, log_prior + log_dxdu.sum(axis=1)


def importance_evidence(log_likelihood, bounds, samples, n_draws: int, *, seed, df: float = 5.0,
                        inflate: float = 1.5, min_ess: float = MIN_ESS, batch: int = 5000,
                        adapt: float = 0.0, mixture: int = 0, mixture_share: float = 0.8,
                        reserve: float = 0.0) -> ImportanceResult:
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
        Proposal draws (at most; the ``reserve`` is drawn only when needed).
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
        estimate and diagnostics come from the later rounds only (0: one round).
    mixture : int
        With ``adapt``: refit as a mixture of up to this many t components (weighted EM on the
        first round's draws; fewer when its ESS is small), plus the single t as a defensive
        component of weight 1 − ``mixture_share``.  A posterior that is not one ellipse in the
        logit coordinates (on the muscle benchmark: a thin tail of EOPT towards 0) is covered
        where the single t leaves it to a few heavy weights.  0 or 1: the single t.
    mixture_share : float
        Weight of the fitted components in the mixture.
    reserve : float
        With ``adapt``: fraction of the draws held back and spent only when the estimate of the
        second round is refused -- the proposal is refitted to the first two rounds' weighted
        draws, and the estimate combines the second and third rounds (balance heuristic:
        each draw weighted against the draw-count mixture of both proposals).

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
    proposal = TMixture([(1.0, u.mean(axis=0), np.cov(u, rowvar=False) * inflate, df)])
    rng = np.random.default_rng(seed)
    m = int(n_draws)
    m1 = int(round(adapt * m)) if adapt > 0 else 0
    m3 = int(round(reserve * m)) if m1 else 0
    m2 = m - m1 - m3
    spent = 0
    if m1:
        # first round: refit the proposal to its own weighted draws (in the logit coordinates)
        x1, u1, ll1, lp1 = _draw_round(log_likelihood, lo, hi, proposal, m1, rng, batch)
        spent += m1
        lw1 = ll1 + lp1 - proposal.logpdf(u1)
        w1 = np.exp(lw1 - np.max(lw1)) if np.isfinite(lw1).any() else np.zeros(m1)
        if w1.sum() > 0 and _ess(w1) > 2 * (d + 2):
            proposal = _fit_proposal(u1, w1, inflate, df, mixture, mixture_share, rng)
    xn, un, ll, lp = _draw_round(log_likelihood, lo, hi, proposal, m2, rng, batch)
    spent += m2
    logw = ll + lp - proposal.logpdf(un)
    out = _estimate(xn, logw, min_ess, spent)
    if m3 and not out.accepted:
        # the reserve: refit to the weighted draws of rounds 1 and 2 (each round's normalised
        # weights scaled by its ESS), then combine rounds 2 and 3 by the balance heuristic
        parts_u, parts_w = [], []
        for uu, lw in ((u1, lw1), (un, logw)):
            if np.isfinite(lw).any():
                w = np.exp(lw - np.max(lw))
                parts_u.append(uu)
                parts_w.append(w / w.sum() * _ess(w))
        uu, ww = np.concatenate(parts_u), np.concatenate(parts_w)
        second = _fit_proposal(uu, ww, inflate, df, mixture, mixture_share, rng) if _ess(ww) > 2 * (d + 2) else proposal
        x3, u3, ll3, lp3 = _draw_round(log_likelihood, lo, hi, second, m3, rng, batch)
        spent += m3
        ua, xa = np.concatenate([un, u3]), np.concatenate([xn, x3])
        la, lpa = np.concatenate([ll, ll3]), np.concatenate([lp, lp3])
        log_bal = np.logaddexp(np.log(m2 / (m2 + m3)) + proposal.logpdf(ua),
                               np.log(m3 / (m2 + m3)) + second.logpdf(ua))
        out = _estimate(xa, la + lpa - log_bal, min_ess, spent)
    return out


def _estimate(xn: np.ndarray, logw: np.ndarray, min_ess: float, spent: int) -> ImportanceResult:
    """log Ẑ, SE, ESS, k̂ and the acceptance of draws ``xn`` with log weights L·π/q."""
    m = logw.size
    if not np.isfinite(logw).any():
        return ImportanceResult(float("nan"), float("nan"), 0.0, float("inf"), m, False,
                                "no proposal draw had a finite likelihood", xn, logw, spent)
    lz = float(logsumexp(logw) - np.log(m))
    w = np.exp(logw - logw.max())
    ess = _ess(w)
    se = float(np.std(w) / (np.mean(w) * np.sqrt(m)))
    khat = float(pareto_khat(np.where(np.isfinite(logw), logw, -1e300)))
    reason = None
    if not khat <= K_HAT_THRESHOLD:
        reason = f"Pareto k̂ {khat:.2f} > {K_HAT_THRESHOLD}: the proposal misses part of the posterior"
    elif ess < min_ess:
        reason = f"ESS {ess:.0f} of {m} draws ({100 * ess / m:.1f}%) is below {min_ess:.0f}"
    return ImportanceResult(lz, se, ess, khat, m, reason is None, reason, xn, logw - logsumexp(logw), spent)
