"""The population layer's fallbacks for specimens whose reused stage-1 samples are unreliable.

* :func:`exact_gibbs` (``PopulationConfig.exact="gibbs"``, default, issue 15): the joint posterior
  of (population, specimens) by Metropolis-within-Gibbs
  (:func:`hbm.samplers.hierarchical.joint_gibbs`): flagged specimens (with ``exact_all``: every
  specimen) with their real likelihoods in the pooling strategy's coordinates, the others by their
  stage-1 samples; its hyper draws and updated individuals replace the reuse ones.
* :func:`refine_collapsed` (``exact=None``, or the grouped layer): a fresh TMCMC run of each flagged
  specimen's updated posterior p(θ_i | all data) under the population, one dask task each.
"""

from __future__ import annotations

import dataclasses
import time
from typing import Mapping, Sequence

import numpy as np

from .. import io
from ..runtime import seeds
from ..errors import HbmError
from ..likelihood.core import make_likelihood
from ..samplers.hierarchical import ExactSpecimen, GroupedResult, ReuseSpecimen, joint_gibbs, refine_individual
from ..samplers.resampling import resample
from ..runtime.progress import log_progress as _log
from .blocks import amplitude_block
from .config import PopulationConfig

__all__ = ["to_refine", "refine_collapsed", "exact_applies", "exact_gibbs", "specimen_likelihood"]


def specimen_likelihood(cfg: PopulationConfig, results: Mapping[str, io.SpecimenResult], sid: str, datasets, model):
    """The stage-1 log-likelihood of one specimen, on the box its stage-1 fit used: a recorded user
    prior (possibly wider than the thesis box), otherwise the run's --bounds."""
    first = next(iter(results.values()))
    names = list(first.names)
    noise_col = len([n for n in names if n in model.parameter_names])  # first noise column (common box)
    sigma_bounds = tuple(first.bounds[noise_col]) if noise_col < len(names) else None
    recorded = getattr(results[sid], "prior", None)
    return make_likelihood(model, datasets[sid], noise=cfg.noise, fix=cfg.fix,
                           bounds=None if recorded else cfg.bounds, sigma_bounds=sigma_bounds,
                           prior=results[sid].prior_dict() if recorded else None)


def to_refine(h, datasets) -> list[str]:
    """Specimens whose reused samples are unreliable: ESS collapse, or the reuse diagnostics
    (PSIS k̂, uncovered mass; :func:`hbm.samplers.hierarchical.reuse_unreliable`).  Without a
    specimen's dataset a diagnostic flag only warns (an ESS collapse still needs the data)."""
    reuse = getattr(h, "reuse", None) or {}
    flagged = [sid for sid in h.specimens if reuse.get(sid, {}).get("unreliable")]
    missing = [sid for sid in flagged if datasets is None or sid not in datasets]
    if missing:
        _log(f"WARNING: reused stage-1 samples unreliable for {', '.join(missing)} (see the reuse diagnostics); "
             "no dataset to refine them", True)
    return sorted(sid for sid in h.specimens if h.ess_collapsed.get(sid) or (sid in flagged and sid not in missing))


def _refine_task(h, sid: str, lik, n_samples: int, seed: int, n_out: int, tmcmc_options: Mapping,
                 n_hyper: int = 200, augment=None) -> np.ndarray:
    """Fresh TMCMC of one specimen's updated posterior; returns ``n_out`` equal-weight draws.

    The population prior is a mixture over ``n_hyper`` hyper-posterior draws (its cost is linear
    in n_hyper per particle); ``tmcmc_options`` (the layer's, :meth:`PopulationConfig.tmcmc_options`)
    go to the TMCMC driver.  ``augment``: the map to pooled derived columns (``--pool combinations``),
    run over the likelihood's own box.
    """
    extra = {} if augment is None else {"augment": augment, "bounds": lik.bounds}
    h = h.view(sid) if isinstance(h, GroupedResult) else h  # the specimen's own (group mean, sd_within)
    tr = refine_individual(h, sid, lik, n_samples=n_samples, seed=seed, progress=False, n_hyper=n_hyper,
                           **extra, **dict(tmcmc_options))
    rng = np.random.default_rng(seed)
    sel = rng.choice(tr.samples.shape[0], n_out, replace=tr.samples.shape[0] < n_out)
    return np.asarray(tr.samples)[sel]


def refine_collapsed(cfg: PopulationConfig, h, collapsed: Sequence[str], datasets, model,
                     results: Mapping[str, io.SpecimenResult], cl=None, augment=None) -> dict[str, np.ndarray]:
    """Fresh TMCMC of p(θ_i | all data) for every specimen whose reused samples are unreliable.

    One dask task per specimen when a client is given; seeds spawned per specimen from the run
    seed (stream ``refine`` k), so the draws do not depend on the number of workers.
    """
    if not collapsed:
        return {}
    if datasets is None or any(sid not in datasets for sid in collapsed):
        raise HbmError(f"importance ESS collapsed for {', '.join(collapsed)}: their fresh TMCMC runs need "
                       "their datasets (pass datasets=...)")
    why = {sid: "; ".join((getattr(h, "reuse", None) or {}).get(sid, {}).get("reasons") or ["ESS collapsed"])
           for sid in collapsed}
    _log(f"WARNING: reused stage-1 samples unreliable for {', '.join(f'{s} ({why[s]})' for s in collapsed)}: "
         "fresh TMCMC runs of their updated posteriors p(θ_i | all data)" + (" on dask" if cl is not None else ""),
         True)
    n_up = next(iter(h.updated.values())).shape[0]
    jobs = {}
    h_ref = cl.scatter(h) if cl is not None else h
    for k, sid in enumerate(h.specimens):
        if sid not in collapsed:
            continue
        lik = specimen_likelihood(cfg, results, sid, datasets, model)
        rs = seeds.seed_int(seeds.stream(int(cfg.seed), "refine", k))
        args = (h_ref, sid, lik, min(int(cfg.samples), int(cfg.stage1_samples)), rs, n_up, cfg.tmcmc_options())
        kw = {"augment": augment} if augment is not None else {}
        jobs[sid] = (cl.submit(_refine_task, *args, key=f"refine-{sid}", pure=False, retries=cfg.retries, **kw)
                     if cl is not None else _refine_task(*args, **kw))
    return {sid: (job.result() if cl is not None else job) for sid, job in jobs.items()}


def exact_applies(cfg: PopulationConfig, to_fix: Sequence[str], datasets=None, specimens=()) -> list[str]:
    """The specimens the exact fallback gives real likelihoods ([]: it does not run).

    It runs when asked for, with something to fix, on a two-level layer (the grouped layer keeps its
    refinements), and with the datasets of what it fixes; ``exact_all``: then every specimen whose
    dataset is at hand.
    """
    if (cfg.exact != "gibbs" or not to_fix or cfg.groups or datasets is None
            or any(sid not in datasets for sid in to_fix)):
        return []
    return sorted(sid for sid in specimens if sid in datasets) if cfg.exact_all else sorted(to_fix)


class _OnFibre:
    """The stage-1 log-likelihood of θ as a function of the exact fallback's coordinates y (−inf off the support)."""

    def __init__(self, lik, coords) -> None:
        self.lik, self.coords = lik, coords

    def __call__(self, y: np.ndarray) -> np.ndarray:
        theta, ok = self.coords.theta_of(np.asarray(y, float))
        out = np.full(theta.shape[0], -np.inf)
        if ok.any():
            out[ok] = np.asarray(self.lik(theta[ok]), float)
        return out


def exact_gibbs(cfg: PopulationConfig, h, exact_ids: Sequence[str], results: Mapping[str, io.SpecimenResult],
                 datasets, model, rows: Mapping[str, np.ndarray], log_prior: Mapping | None, coords):
    """The exact fallback (``PopulationConfig.exact="gibbs"``): joint Metropolis-within-Gibbs.

    ``exact_ids`` get their real likelihoods (in ``coords``), the others their stage-1 ``rows``
    (:class:`~hbm.samplers.hierarchical.ReuseSpecimen`).  Chains start from the layer's hyper draws
    and reweighted individuals.  Seeds: stream ``joint`` (child 0 starting points, 1 the sampler,
    2 the output θ given φ).

    Returns (the layer's result with the Gibbs hyper draws and predictive, updated individuals
    {specimen: θ draws}, a JSON-able summary for ``hierarchical.nc``).
    """
    missing = [sid for sid in exact_ids if datasets is None or sid not in datasets]
    if missing:
        raise HbmError(f"exact='gibbs' needs the datasets of {', '.join(missing)} (pass datasets=...)")
    root = seeds.stream(int(cfg.seed), "joint")  # children: 0 starts, 1 sampler, 2 θ given φ of the output
    rng = np.random.default_rng(seeds.child(root, 0))
    nc = int(cfg.exact_chains)
    n_h = h.raw_samples.shape[0]
    raw0 = h.raw_samples[rng.choice(n_h, nc, replace=n_h < nc)]
    # y columns that are pooled columns (the sampler uses those with the identity transform)
    pooled_cols = {j: h.model.names.index(n) for j, n in enumerate(coords.names_y) if n in h.model.names}
    specs, no_block = {}, {}
    for sid in h.specimens:
        idx = resample(np.asarray(h.updated_weights[sid], float), nc, rng)
        idx = rng.permutation(idx)  # systematic resampling sorts: pair rows with hyper draws at random
        if sid in exact_ids:
            y = coords.y_of(results[sid].samples)
            lik = specimen_likelihood(cfg, results, sid, datasets, model)
            block = None
            if cfg.exact_block_rounds > 0:  # the amplitudes moved given φ at one evaluation per sweep
                block, no_block[sid] = amplitude_block(lik, coords, coords.names_y, y[:16], rng)
            specs[sid] = ExactSpecimen(log_likelihood=_OnFibre(lik, coords), columns=coords.columns, box=coords.box,
                                       init=y[idx], scale_rows=y, pooled_cols=pooled_cols, block=block)
        else:
            specs[sid] = ReuseSpecimen(rows=rows[sid], log_prior=None if log_prior is None else log_prior[sid],
                                       init=idx)
    _log(f"exact fallback: joint Metropolis-within-Gibbs, {nc} chains, real likelihoods for "
         f"{', '.join(exact_ids)}", cfg.progress)
    c0 = time.process_time()
    # every kept draw is output (a subsample would only add Monte Carlo error); at least cfg.samples
    n_keep = max(int(cfg.exact_keep), -(-int(cfg.samples) // nc))
    reasons = sorted({why for why in no_block.values() if why})
    if reasons:
        _log(f"exact fallback: no amplitude block for {', '.join(s for s, w in no_block.items() if w)} "
             f"({'; '.join(reasons)}): their amplitudes move with the other parameters", cfg.progress)
    # with amplitude blocks the non-centred moves of log amplitudes are cheap (block rounds); one full
    # one per sweep for the other pooled columns (THETA) instead of two
    blocks = any(sp.block is not None for sp in specs.values() if isinstance(sp, ExactSpecimen))
    g = joint_gibbs(h.model, raw0, specs, n_keep=n_keep, n_burn=int(cfg.exact_burn), thin=int(cfg.exact_thin),
                    nc_steps=1 if blocks else 2, block_rounds=int(cfg.exact_block_rounds), seed=seeds.child(root, 1),
                    progress=cfg.progress, log=lambda m: _log(m, cfg.progress))
    cpu = time.process_time() - c0
    rng_out = np.random.default_rng(seeds.child(root, 2))
    # all chains x kept draws, joint (row k of ψ goes with row k of every specimen); on the gold a
    # random subset of 1000 of the 7680 moved the worst median 0.19 -> 0.29 NUTS sd
    flat = g.flat_raw()
    updated = {sid: (coords.draw_theta(g.flat_state(sid), rng_out) if sid in exact_ids
                     else np.asarray(results[sid].samples)[g.flat_state(sid)]) for sid in h.specimens}
    h = dataclasses.replace(h, hyper_samples=h.model.natural(flat), raw_samples=flat, predictive=g.predictive)
    worst_rhat = max(g.rhat.values())
    min_ess = min(g.ess.values())
    info = {"method": "gibbs", "exact": list(exact_ids), "reuse": [s for s in h.specimens if s not in exact_ids],
            **g.options, "rhat_max": float(worst_rhat), "ess_min": float(min_ess),
            "rhat": {k: float(v) for k, v in g.rhat.items()}, "ess": {k: float(v) for k, v in g.ess.items()},
            "acceptance": g.acceptance, "evaluations": g.evaluations, "wall_s": float(g.timings["total"]),
            "cpu_s": float(cpu), "columns": list(coords.names_y)}  # the y columns behind "<specimen>:<k>"
    _log(f"exact fallback: {sum(g.evaluations.values())} likelihood evaluations, {g.timings['total']:.1f} s; "
         f"max R-hat {worst_rhat:.3f}, min bulk ESS {min_ess:.0f}", cfg.progress)
    if worst_rhat > 1.05:
        key = max(g.rhat, key=g.rhat.get)
        sid, _, col = key.rpartition(":")
        where = key if sid == "hyper" or not col.isdigit() else f"{sid} {coords.names_y[int(col)]}"
        _log(f"WARNING: exact fallback not converged (max R-hat {worst_rhat:.3f} > 1.05, at {where}): its chains "
             f"have not mixed in every direction; longer chains help (--hier-samples {2 * nc * n_keep} doubles the "
             "kept sweeps); read the population's tails with the report's gold-benchmark accuracy", True)
    return h, updated, info
