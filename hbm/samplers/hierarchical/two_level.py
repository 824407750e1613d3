"""The two-level driver: one population over all specimens (:func:`hierarchical`).

This module is sampler-layer code: it knows nothing about muscles.
"""

from __future__ import annotations

import time
from typing import Any, Callable, Mapping, Sequence

import numpy as np

from .model import HierarchicalModel, draw_population
from .posterior import fit_layer
from .result import HierarchicalResult
from .reuse import ReuseEstimator, pack_stage1

__all__ = ["hierarchical"]


def _explain(key: str, s: dict, hyper: bool, threshold: float) -> str:
    """The warning of a collapsed ESS (p(d|ψ) and the updated posterior, or the latter only)."""
    if hyper:
        return (f"hierarchical: importance ESS of specimen {key!r} collapsed (10% quantile {s['q10']:.1f}, median "
                f"{s['median']:.1f} of {s['n']} stage-1 samples < {threshold:g}, estimator {s['estimator']!r}); "
                f"its updated posterior and p(d|psi) are unreliable: run "
                f"hbm.samplers.hierarchical.refine_individual for it")
    return (f"hierarchical: importance ESS of specimen {key!r} collapsed for its updated posterior (raw ratios: 10% "
            f"quantile {s['raw_q10']:.1f} < {threshold:g}); p(d|psi) is fine ({s['estimator']} ESS 10% quantile "
            f"{s['q10']:.1f}): run hbm.samplers.hierarchical.refine_individual for its updated posterior")


def hierarchical(
    stage1: Mapping[str, tuple], names: Sequence[str], bounds, *, transforms: Mapping[str, str] | None = None,
    pooled: Sequence[str] | None = None, n_samples: int = 2000, seed=None, full_cov: Sequence[str] | None = None,
    sd_prior: str = "loguniform", sd_range: tuple[float, float] = (1e-3, 1.0),
    mu_bounds: Mapping[str, tuple[float, float]] | None = None, logit_range: float = 8.0,
    fix: Mapping[str, float] | None = None, ess_threshold: float = 50.0, thin: int | None = None,
    n_updated: int | None = None, n_hyper_updated: int = 1000, chunk_bytes: float = 4e6, progress: bool = True,
    sampler: Callable | None = None, tmcmc_options: Mapping[str, Any] | None = None, estimator: str = "raw",
    bandwidth: str | float = "silverman", log_prior: Mapping[str, np.ndarray] | None = None,
    log_weights: Mapping[str, np.ndarray] | None = None, stage1_rows: Mapping[str, int] | None = None,
    log_likelihood: Mapping[str, np.ndarray] | None = None,
) -> HierarchicalResult:
    """Hyper-posterior, hyper-evidence, updated individuals and population predictive.

    Parameters
    ----------
    stage1 : mapping specimen -> (samples (N_i, d), log_Z_i[, log_Z_se_i])
        Equal-weight stage-1 posterior samples drawn under the uniform prior on ``bounds``, and their
        log-evidence.
    names, bounds : sequence of str, array_like (d, 2)
        Column names of the samples and the stage-1 uniform prior box.
    transforms, pooled, full_cov, sd_prior, sd_range, mu_bounds, logit_range, fix
        The population model and hyperprior, see :class:`HierarchicalModel` (``pooled`` default all).
    n_samples, seed : int, int or SeedSequence or Generator
        TMCMC population over ψ (= hyper-posterior draws); everything random derives from ``seed``.
    ess_threshold : float
        10 % quantile of the importance ESS below which a specimen is flagged as collapsed.
    thin : int, optional
        Use at most this many stage-1 samples per specimen (a seeded random subset); default all.
    n_updated, n_hyper_updated : int
        Draws per updated individual (default ``n_samples``); hyper draws that average its weights.
    chunk_bytes, progress
        Memory bound of one block of log-ratios; progress of the TMCMC driver.
    sampler, tmcmc_options : callable, mapping, optional
        Replacement for :func:`hbm.samplers.tmcmc.tmcmc` (same signature), and its extra keywords.
    estimator, bandwidth : {"raw", "kernel"}, {"silverman", "scott"} or float
        Estimator of p(d_i|ψ) (:mod:`~hbm.samplers.hierarchical.reuse`); the updated individuals
        always use the raw ratios.
    log_prior : mapping specimen -> ndarray (N_i,), optional
        Stage-1 prior log density of each row's pooled columns (derived features; default the box).
    log_weights, stage1_rows : mappings, optional
        Log importance weights of the rows (rows from a defensive mixture,
        :mod:`~hbm.samplers.hierarchical.reuse`) and the number of leading
        rows that are stage-1 samples (for the coverage diagnostic).
    log_likelihood : mapping specimen -> ndarray, optional
        Log-likelihoods of the stage-1 rows: the coverage diagnostic extrapolates the likelihood
        beyond the samples with its log-slope at the edge (flat without them).

    Returns
    -------
    HierarchicalResult
    """
    t0 = time.perf_counter()
    names = [str(n) for n in names]
    model = HierarchicalModel(names, bounds, pooled=pooled, transforms=transforms, full_cov=full_cov,
                              sd_prior=sd_prior, sd_range=sd_range, mu_bounds=mu_bounds, logit_range=logit_range,
                              fix=fix)
    ss = np.random.SeedSequence(seed if not isinstance(seed, np.random.Generator) else seed.integers(2**63))
    s_tmcmc, s_upd, s_pred, s_thin = ss.spawn(4)
    data = pack_stage1(stage1, names, model.all_bounds, log_prior=log_prior, log_weights=log_weights,
                       stage1_rows=stage1_rows, log_likelihood=log_likelihood, thin=thin, thin_seed=s_thin)
    est = ReuseEstimator(model, data, estimator=estimator, bandwidth=bandwidth, chunk_bytes=chunk_bytes)
    t1 = time.perf_counter()
    fit = fit_layer(est, model.box, lambda x: [model.expand(x)],
                    lambda x: model.log_hyperprior_correction(model.expand(x)), np.zeros(len(data.specimens), int),
                    (s_tmcmc, s_upd), n_samples=n_samples, progress=progress, sampler=sampler,
                    tmcmc_options=tmcmc_options, ess_threshold=ess_threshold, n_updated=n_updated,
                    n_hyper_updated=n_hyper_updated, explain=lambda k, s, h: _explain(k, s, h, ess_threshold))
    raw = fit.raws[0]
    t2 = time.perf_counter()
    predictive = draw_population(model, raw, raw.shape[0], np.random.default_rng(s_pred))
    t3 = time.perf_counter()
    specs, kvar = data.specimens, est.kernel_var
    return HierarchicalResult(
        hyper_samples=model.natural(raw), hyper_names=list(model.hyper_names), names=list(model.names),
        all_names=list(names), bounds=model.all_bounds.copy(), transforms=dict(model.transforms), specimens=specs,
        predictive=predictive, model=model, raw_samples=raw, **fit.result_fields(t1 - t0, t3 - t2),
        options={"n_samples": int(n_samples), "sd_prior": sd_prior, "sd_range": list(sd_range),
                 "full_cov": list(model.full_cov), "fix": dict(model.fix), "ess_threshold": ess_threshold,
                 "logit_range": logit_range, "mu_lo": model.mu_lo.tolist(), "mu_hi": model.mu_hi.tolist(),
                 "estimator": estimator, "log_prior": log_prior is not None,
                 "bandwidth": bandwidth if isinstance(bandwidth, str) else float(bandwidth),
                 "kernel_h": est.kernel_h, "kernel_sd": {k: np.sqrt(v).tolist() for k, v in zip(specs, kvar)
                                                        if v is not None}},
    )
