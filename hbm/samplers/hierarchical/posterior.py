"""The shared core of both drivers: TMCMC over ψ on the reuse estimator, then the five post-sampling steps.

:func:`fit_layer` samples the hyper-posterior with TMCMC on Σ_i log p̂(d_i | ψ) (plus the
hyperprior's correction) and then, for the draws: the per-specimen estimates and ESS of the
estimator and of the raw ratios, the ESS summary and flags, the hyper-evidence and its parts, the
updated individuals, and the reuse diagnostics with their verdict.  A driver supplies its sampler
coordinates (``box``), the map from them to each group's population (``raws_of``; the two-level
layer has one group) and its own products (predictive, result class).

This module is sampler-layer code: it knows nothing about muscles.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Any, Callable, Mapping, Sequence

import numpy as np

from ..tmcmc import tmcmc as _tmcmc
from .diagnostics import ess_checks, evidence_parts, reuse_diagnostics, reuse_unreliable
from .result import LayerProducts
from .reuse import ReuseEstimator

__all__ = ["LayerFit", "fit_layer"]


@dataclass(kw_only=True)
class LayerFit(LayerProducts):
    """What :func:`fit_layer` computed: the :class:`~hbm.samplers.hierarchical.result.LayerProducts`, and

    ``x``: the TMCMC draws in the driver's sampler coordinates; ``raws``: each group's population
    at those draws (the model's raw coordinates); ``timings``: ``tmcmc``, ``updated``, ``diagnostics``.
    """

    x: np.ndarray
    raws: list
    timings: dict

    def result_fields(self, setup: float, predictive: float) -> dict:
        """The keyword arguments of a result that both drivers fill alike (``setup``, ``predictive``: seconds)."""
        timings = {"setup": setup, **self.timings, "predictive": predictive,
                   "total": setup + sum(self.timings.values()) + predictive, "likelihood_calls": len(self.ess_trace)}
        return {**self.layer_fields(), "timings": timings}


def fit_layer(
    est: ReuseEstimator,
    box: np.ndarray,
    raws_of: Callable[[np.ndarray], Sequence[np.ndarray]],
    log_prior_correction: Callable[[np.ndarray], np.ndarray],
    groups: np.ndarray,
    seeds: tuple,
    *,
    n_samples: int,
    progress: bool,
    sampler: Callable | None,
    tmcmc_options: Mapping[str, Any] | None,
    ess_threshold: float,
    n_updated: int | None,
    n_hyper_updated: int,
    explain: Callable[[str, dict, bool], str],
) -> LayerFit:
    """Hyper-posterior draws and the five post-sampling steps shared by both drivers.

    Parameters
    ----------
    est : ReuseEstimator
        The estimator of p(d_i | ψ) over the packed stage-1 data.
    box : ndarray (n_x, 2)
        The sampler box (uniform TMCMC reference).
    raws_of : callable x (n, n_x) -> list of (n, 2d+q)
        Each group's population in the model's raw coordinates.
    log_prior_correction : callable x -> (n,)
        log hyperprior minus the log uniform density on ``box``.
    groups : ndarray of int (n_specimens,)
        Each specimen's group (all 0 for the two-level layer).
    seeds : (SeedSequence, SeedSequence)
        Of the TMCMC run and of the updated individuals' draws.
    n_samples, progress, sampler, tmcmc_options, ess_threshold, n_updated, n_hyper_updated
        As :func:`hbm.samplers.hierarchical.hierarchical`.
    explain : callable (specimen, ess summary, hyper_collapsed) -> str
        The driver's warning for a collapsed ESS.

    Returns
    -------
    LayerFit
    """
    data, trace = est.data, []

    def target(x: np.ndarray) -> np.ndarray:
        x = np.atleast_2d(np.asarray(x, float))
        lm, ess = est.log_marginals(raws_of(x), groups)
        trace.append(ess.min(axis=0))
        out = lm.sum(axis=1) + log_prior_correction(x)
        return np.where(np.isfinite(out), out, -np.inf)

    s_tmcmc, s_upd = seeds
    sampler = _tmcmc if sampler is None else sampler
    t1 = time.perf_counter()
    res = sampler(target, box, int(n_samples), seed=int(s_tmcmc.generate_state(1)[0]), progress=progress,
                  **dict(tmcmc_options or {}))
    t2 = time.perf_counter()
    x = np.asarray(res.samples, float)
    raws = list(raws_of(x))
    lm, ess = est.log_marginals(raws, groups)
    # the updated individuals reweight the stage-1 samples with the raw ratios: their ESS
    lm_raw, ess_raw = (lm, ess) if est.estimator == "raw" else est.log_marginals(raws, groups, kernel=False)
    summary, collapsed, hyper_collapsed, msgs = ess_checks(
        data.specimens, [s.shape[0] for s in data.samples], ess, ess_raw, est.estimator, ess_threshold, explain,
        stacklevel=3)
    log_ev, se, parts = evidence_parts(res.log_evidence, getattr(res, "log_evidence_se", 0.0), ess, est.log_n,
                                       data.log_z, data.log_z_se)

    # updated individuals: per-draw normalised weights averaged over (a subset of) the draws
    t3 = time.perf_counter()
    rng_u = np.random.default_rng(s_upd)
    sub = np.arange(x.shape[0]) if x.shape[0] <= n_hyper_updated else np.sort(
        rng_u.choice(x.shape[0], n_hyper_updated, replace=False))
    updated, upd_w, upd_ess = est.updated(raws_of(x[sub]), groups, lm_raw[sub], int(n_updated or n_samples), rng_u)
    t4 = time.perf_counter()

    # what the reused samples cannot represent (no random numbers), each specimen against its group's population
    reuse = {}
    for i, key in enumerate(data.specimens):
        reuse[key] = reuse_diagnostics(est.model, data.samples[i], raws[groups[i]], log_prior=data.log_prior[i],
                                       updated_weights=upd_w[key], log_weights=data.log_weights[i],
                                       n_stage1=data.n_stage1[i], log_likelihood=data.log_likelihood[i])
        reuse[key].update(ess_q10=summary[key]["q10"], ess_raw_q10=summary[key]["raw_q10"])
    for key, (bad, why) in reuse_unreliable(reuse, ess_threshold=ess_threshold).items():
        reuse[key].update(unreliable=bad, reasons=why)
    t5 = time.perf_counter()
    return LayerFit(x=x, raws=raws, sampler_result=res, log_marginal=lm + data.log_z[None, :], ess=ess,
                    ess_raw=ess_raw, ess_summary=summary, ess_collapsed=collapsed, hyper_ess_collapsed=hyper_collapsed,
                    warnings=msgs, log_evidence=log_ev, log_evidence_se=se, log_evidence_parts=parts, updated=updated,
                    updated_weights=upd_w, updated_ess=upd_ess, reuse=reuse, ess_trace=trace,
                    timings={"tmcmc": t2 - t1, "updated": t4 - t3, "diagnostics": t5 - t4})
