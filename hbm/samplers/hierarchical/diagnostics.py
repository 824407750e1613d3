"""Per-specimen diagnostics of the reuse: the ESS summary and flags, the evidence parts, and what the
reused samples cannot represent.

What the reused samples cannot represent (issue 15)
--------------------------------------------------
The ESS measures how unevenly the existing samples are weighted, not the mass they never
reach.  Under the uniform stage-1 prior the density of log c·P1 falls off as e^y, and where the
data bound c·P1 only from above the samples barely reach the small values a population may put
mass on.  :func:`reuse_diagnostics` reports per specimen the PSIS k̂ of the ratios (over
hyper-posterior draws) and the conditional-posterior mass beyond the range of the stage-1
samples (the likelihood extrapolated with its log-slope at the samples' edge, from the stored
stage-1 log-likelihoods; flat without them, an upper bound that is reported but not acted on),
plus, with reference draws, the same mass measured with real likelihoods.
:func:`reuse_unreliable` turns them, with the ESS, into a per-specimen flag; the caller
refines flagged specimens (:func:`refine_individual`).


This module is sampler-layer code: it knows nothing about muscles.
"""

from __future__ import annotations

import warnings
from typing import Callable, Mapping, Sequence

import numpy as np

from ...errors import HbmError
from ..truncnorm import log_mass
from .model import HierarchicalModel
from ..psis import K_HAT_THRESHOLD, pareto_khat

__all__ = ["ess_checks", "evidence_parts", "reuse_diagnostics", "reuse_unreliable"]


def ess_checks(specimens: Sequence[str], n_rows: Sequence[int], ess: np.ndarray, ess_raw: np.ndarray, estimator: str,
               threshold: float, explain: Callable[[str, dict, bool], str], stacklevel: int = 2):
    """Per-specimen ESS summary and collapse flags, with a warning per collapsed specimen.

    Parameters
    ----------
    specimens : sequence of str
    n_rows : sequence of int
        Rows per specimen (the ``n`` of the summary).
    ess, ess_raw : ndarray (n_draws, n_specimens)
        ESS of the estimator used for p(d_i|ψ) and of the raw ratios (the updated individuals').
    estimator : str
    threshold : float
        A 10 % quantile over the draws below it flags the specimen.
    explain : callable (specimen, summary, hyper_collapsed) -> str
        The driver's warning text.
    stacklevel : int
        Of the warnings, as seen from :func:`ess_checks`' caller's caller.

    Returns
    -------
    (summary, collapsed, hyper_collapsed, messages)
        ``summary[s]``: min, q10, median (of ``ess``), n, estimator, raw_min, raw_q10, raw_median;
        ``hyper_collapsed``: q10 of ``ess`` below the threshold (p̂(d_i|ψ) unreliable);
        ``collapsed``: that, or q10 of ``ess_raw`` below it (the updated individual unreliable).
    """
    summary, collapsed, hyper_collapsed, msgs = {}, {}, {}, []
    for i, key in enumerate(specimens):
        e, er = ess[:, i], ess_raw[:, i]
        summary[key] = {"min": float(e.min()), "q10": float(np.quantile(e, 0.1)), "median": float(np.median(e)),
                        "n": int(n_rows[i]), "estimator": estimator, "raw_min": float(er.min()),
                        "raw_q10": float(np.quantile(er, 0.1)), "raw_median": float(np.median(er))}
        hyper_collapsed[key] = bool(summary[key]["q10"] < threshold)
        collapsed[key] = bool(hyper_collapsed[key] or summary[key]["raw_q10"] < threshold)
        if collapsed[key]:
            msgs.append(explain(key, summary[key], hyper_collapsed[key]))
            warnings.warn(msgs[-1], RuntimeWarning, stacklevel=stacklevel + 1)
    return summary, collapsed, hyper_collapsed, msgs


def evidence_parts(tmcmc_log_z: float, tmcmc_se: float, ess: np.ndarray, log_n: np.ndarray, log_z: np.ndarray,
                   log_z_se: np.ndarray) -> tuple[float, float, dict]:
    """Hyper-evidence log p(all data | family) = TMCMC log-evidence over ψ + Σ_i log Z_i, its SE and parts.

    The SE combines in quadrature the TMCMC SE, the stage-1 SEs and the importance-sampling noise,
    Var[log mean r] ≈ 1/ESS − 1/N per specimen (delta method), summed over specimens, median over
    the draws ``ess`` (n_draws, n_specimens).
    """
    is_var = np.sum(np.maximum(1.0 / np.maximum(ess, 1e-300) - 1.0 / np.exp(log_n), 0.0), axis=1)
    se_tm = float(tmcmc_se or 0.0)
    se_is = float(np.sqrt(np.median(is_var)))
    se_st1 = float(np.sqrt(np.sum(log_z_se**2)))
    parts = {"tmcmc": float(tmcmc_log_z), "tmcmc_se": se_tm, "sum_log_Z": float(log_z.sum()),
             "stage1_se": se_st1, "importance_se": se_is}
    return float(tmcmc_log_z) + float(log_z.sum()), float(np.sqrt(se_tm**2 + se_is**2 + se_st1**2)), parts


def _diag_rows(n: int, n_draws: int) -> np.ndarray:
    """Evenly spaced hyper-draw indices (deterministic: the diagnostic consumes no random numbers)."""
    return np.unique(np.linspace(0, n - 1, min(n, int(n_draws))).round().astype(int))


def reuse_diagnostics(
    model: HierarchicalModel,
    theta: np.ndarray,
    raw: np.ndarray,
    *,
    log_prior: np.ndarray | None = None,
    log_weights: np.ndarray | None = None,
    n_stage1: int | None = None,
    log_likelihood: np.ndarray | None = None,
    updated_weights: np.ndarray | None = None,
    edge: float = 0.02,
    cover: float = 0.0,
    slope_bin: float = 0.1,
    outer: float = 0.005,
    n_draws: int = 200,
) -> dict:
    """How well one specimen's reused samples represent p(θ_i | d_i, ψ) over the hyper-posterior.

    The importance ESS measures how unevenly the existing samples are weighted; it cannot see
    mass where the samples never went.  Diagnostics that can:

    * **PSIS k̂** (:func:`hbm.samplers.hierarchical.psis.pareto_khat`) of the ratios r_ij(ψ) at ``n_draws``
      evenly spaced hyper-posterior draws: a heavy ratio tail (k̂ > 0.7) means the target has
      mass where the samples are too sparse for the estimate to converge.
    * **uncovered mass** (``uncovered``): per pooled coordinate z_k, the share of the
      conditional posterior p(z | d_i, ψ) ∝ L_i(z) p(z|ψ) beyond the range [min z_k, max z_k]
      of the stage-1 samples, with the likelihood extrapolated as flat beyond the range at its
      value in the edge bin (the samples below the ``edge`` quantile, resp. above 1 − ``edge``):

          U_k,lo(ψ) = W_lo(ψ) · P_ψ(z_k < min) / P_ψ(min ≤ z_k ≤ q_edge),

      W_lo the share of the normalised ratios in the edge bin, P_ψ the population marginal of
      z_k.  Flat extrapolation is exact where the data bound a parameter from one side only (the
      likelihood no longer changes beyond the samples) and conservative where it decays.
      U = Σ_k (U_k,lo + U_k,hi); uncovered = U/(1 + U), averaged over the draws.
    * **measured outside mass** (``outside_measured``, only with reference draws appended to
      the stage-1 samples, ``n_stage1`` < N): the share of the normalised ratios carried by the
      rows outside the stage-1 samples' range in some pooled coordinate, with their real
      likelihoods; averaged over the draws.
    * ``population_outside``: the population-predictive probability of a pooled coordinate
      outside the stage-1 samples' [``outer``, 1 − ``outer``] quantile range (likelihood
      ignored: large for every informed specimen whose posterior is narrower than the
      population, so it is information, not a trigger).

    Parameters
    ----------
    model : HierarchicalModel
    theta : ndarray (N, len(model.all_names))
        The specimen's samples as used by the layer (stage-1 rows first).
    raw : ndarray (n, 2d+q)
        Hyper-posterior draws in sampler coordinates (``result.raw_samples``).
    log_prior, log_weights : ndarray (N,), optional
        As passed to :func:`hierarchical`.
    n_stage1 : int, optional
        Number of leading rows that are stage-1 posterior samples (default all).
    updated_weights : ndarray (N,), optional
        The updated individual's weights (``result.updated_weights[key]``); adds ``khat_updated``.
    edge, outer : float
        Quantile of the edge bins, and of the range for ``population_outside``.
    n_draws : int
        Hyper-posterior draws used (evenly spaced).

    Returns
    -------
    dict
        ``khat_median``, ``khat_q90``, ``khat_frac`` (share of draws with k̂ > 0.7),
        ``khat_updated`` (if weights given), ``uncovered``, ``uncovered_by`` (name -> value),
        ``outside_measured`` (NaN without reference rows), ``population_outside``, ``n_draws``,
        ``likelihood_slope`` (whether the extrapolation used the log-likelihoods; without them it
        is flat, an upper bound that :func:`reuse_unreliable` does not act on).
    """
    if not (0 < edge < 0.5 and 0 < outer < 0.5 and 0 <= cover < edge):
        raise HbmError(f"reuse_diagnostics: need 0 <= cover < edge < 0.5 and 0 < outer < 0.5, got {cover}, {edge}, "
                       f"{outer}")
    theta = np.asarray(theta, float)
    n1 = theta.shape[0] if n_stage1 is None else int(n_stage1)
    F, c = model.features(theta, log_prior)
    if log_weights is not None:
        c = c + np.asarray(log_weights, float)
    ll1 = None if log_likelihood is None else np.asarray(log_likelihood, float)[:n1]
    if ll1 is not None and (ll1.shape != (n1,) or not np.all(np.isfinite(ll1))):
        raise HbmError(f"reuse_diagnostics: log_likelihood must be {n1} finite values (the stage-1 rows)")
    rows = _diag_rows(raw.shape[0], n_draws)
    coef, cconst = model.coefficients(raw[rows])
    lr = coef @ F.T + cconst[:, None] + c[None, :]  # (n_draws, N) log ratios
    khat = pareto_khat(np.where(np.isfinite(lr), lr, -np.inf))
    w = np.exp(lr - lr.max(axis=1, keepdims=True))
    w /= w.sum(axis=1, keepdims=True)
    z, _ = model.to_z(theta)
    z1 = z[:n1]
    nat = model.natural(raw[rows])
    mu, sd = nat[:, : model.d], nat[:, model.d : 2 * model.d]

    def lmass(a, b, k, tilt=0.0):
        # log ∫_a^b e^{tilt·z} N(z; mu, sd) dz up to factors that cancel in the ratios below:
        # an exponential tilt of a normal is the normal shifted by tilt·sd²
        m = mu[:, k] + tilt * sd[:, k] ** 2
        with np.errstate(divide="ignore", invalid="ignore"):
            return log_mass((a - m) / sd[:, k], (b - m) / sd[:, k])

    U = np.zeros(len(rows))
    by = {}
    log_keep = np.zeros(len(rows))  # log P(all coordinates inside the outer range)
    outside_rows = np.zeros(theta.shape[0], bool)
    log_cov_beyond = np.zeros(len(rows))  # log P(every coordinate inside), likelihood-tilted beyond
    for k, name in enumerate(model.names):  # loop over the pooled parameters, vectorised over draws
        zk = z1[:, k]
        zmin, zmax = np.quantile(zk, [cover, 1.0 - cover])
        outside_rows |= (z[:, k] < zmin) | (z[:, k] > zmax)
        qlo, qhi = np.quantile(zk, [edge, 1.0 - edge])
        Uk = np.zeros(len(rows))
        for side, beyond, binm, sel in ((-1, (model.zlo[k], zmin), (zmin, qlo), z[:, k] <= qlo),
                                        (1, (zmax, model.zhi[k]), (qhi, zmax), z[:, k] >= qhi)):
            if not beyond[1] > beyond[0]:
                continue  # the samples reach the box edge: nothing beyond them
            sel = sel.copy()
            sel[n1:] = False  # the extrapolation is of the stage-1 samples' edge bin
            wb = w[:, sel].sum(axis=1)
            tilt = 0.0 if ll1 is None else _edge_slope(zk, ll1, side, slope_bin)
            with np.errstate(divide="ignore", invalid="ignore"):
                lu = np.log(wb) + lmass(*beyond, k, tilt) - lmass(*binm, k, tilt)
            Uk += np.where(wb > 0, np.exp(np.minimum(np.nan_to_num(lu, nan=-np.inf), 700.0)), 0.0)
        U += Uk
        by[name] = float(np.mean(Uk / (1.0 + Uk)))
        o_lo, o_hi = np.quantile(zk, [outer, 1.0 - outer])
        log_keep += lmass(o_lo, o_hi, k) - lmass(model.zlo[k], model.zhi[k], k)
        # population mass beyond the samples' [outer, 1 − outer] range, the likelihood modelled as
        # flat inside and as e^{s (z − edge)} beyond (s: its log-slope at that edge of the samples)
        log_in = lmass(o_lo, o_hi, k)
        parts = [log_in]
        for side, (a, b), e in ((-1, (model.zlo[k], o_lo), o_lo), (1, (o_hi, model.zhi[k]), o_hi)):
            if not b > a:
                continue
            t = 0.0 if ll1 is None else _edge_slope(zk, ll1, side, slope_bin)
            # ∫_a^b e^{t(z−e)} N(z; mu, sd) dz = e^{t(mu−e) + t² sd²/2} · mass of N(mu + t sd², sd)
            parts.append(t * (mu[:, k] - e) + 0.5 * t * t * sd[:, k] ** 2 + lmass(a, b, k, t))
        tot = np.logaddexp.reduce(np.array(parts), axis=0)
        log_cov_beyond += log_in - tot
    out = {
        "khat_median": float(np.median(khat)), "khat_q90": float(np.quantile(khat, 0.9)),
        "khat_frac": float(np.mean(khat > K_HAT_THRESHOLD)),
        "uncovered": float(np.mean(U / (1.0 + U))), "uncovered_by": by,
        "outside_measured": float(np.mean(w[:, outside_rows].sum(axis=1))) if n1 < theta.shape[0] else float("nan"),
        "population_outside": float(np.mean(-np.expm1(log_keep))),
        "population_beyond": float(np.mean(-np.expm1(log_cov_beyond))), "n_draws": int(len(rows)),
        "likelihood_slope": ll1 is not None,
    }
    if updated_weights is not None:
        with np.errstate(divide="ignore"):
            out["khat_updated"] = float(pareto_khat(np.log(np.asarray(updated_weights, float))))
    return out


def _edge_slope(z: np.ndarray, ll: np.ndarray, side: int, frac: float) -> float:
    """d log L / dz of the likelihood at one edge of the samples, from the ``frac`` outermost samples.

    Least-squares slope of the samples' log-likelihoods on z, clipped so that the likelihood can
    only fall beyond the edge (never rise: then flat extrapolation, the conservative choice).  A
    likelihood that is flat at the edge (data bounding the parameter from the other side only)
    gives ≈ 0; a decaying one gives its local log-slope, which the extrapolation uses.
    """
    q = np.quantile(z, frac if side < 0 else 1.0 - frac)
    sel = z <= q if side < 0 else z >= q
    if sel.sum() < 5 or np.ptp(z[sel]) <= 0:
        return 0.0
    x = z[sel] - z[sel].mean()
    slope = float(np.dot(x, ll[sel] - ll[sel].mean()) / np.dot(x, x))
    return max(slope, 0.0) if side < 0 else min(slope, 0.0)


def reuse_unreliable(
    reuse: Mapping[str, Mapping],
    *,
    ess_threshold: float = 50.0,
    khat_max: float = K_HAT_THRESHOLD,
    beyond_max: float = 0.35,
) -> dict[str, tuple[bool, list[str]]]:
    """Decide per specimen whether reusing its samples is unreliable (then refine it).

    Parameters
    ----------
    reuse : mapping specimen -> dict
        ``result.reuse`` (entries of :func:`reuse_diagnostics` plus ``ess_q10`` / ``ess_raw_q10``).
    ess_threshold : float
        10 % quantile of the importance ESS over hyper draws below which the reuse collapsed.
    khat_max : float
        Hyper-posterior median PSIS k̂ (or k̂ of the updated weights) above which the ratios
        have too heavy a tail.
    beyond_max : float
        ``population_beyond`` (population-predictive mass beyond the samples' 0.5–99.5 % range,
        the likelihood extrapolated with its edge slope) above which the samples miss the
        tails.  Calibrated on the gold benchmark (workflows/benchmarks/hierarchical_gold.py):
        the specimens whose reweighted individuals were 1.2–2.2 NUTS sd off had 0.44–0.67, the
        ones within 0.64 sd 0.22–0.26.  Without stored log-likelihoods (flat extrapolation, an
        upper bound) it is reported but not acted on.

    Returns
    -------
    dict specimen -> (unreliable, reasons)
    """
    out = {}
    for key, r in reuse.items():
        why = []
        for name in ("ess_q10", "ess_raw_q10"):
            if name in r and r[name] < ess_threshold:
                why.append(f"{name} {r[name]:.1f} < {ess_threshold:g}")
        for name in ("khat_median", "khat_updated"):
            if name in r and r[name] > khat_max:
                why.append(f"{name} {r[name]:.2f} > {khat_max:g}")
        # flat extrapolation (no stored log-likelihoods) is only an upper bound: reported, not a trigger
        if r.get("likelihood_slope", True) and r.get("population_beyond", 0.0) > beyond_max:
            why.append(f"population mass beyond the samples {r['population_beyond']:.2f} > {beyond_max:g}")
        out[key] = (bool(why), why)
    return out

