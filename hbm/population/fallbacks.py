"""The reuse layer's fallback for specimens whose reused stage-1 samples are unreliable, and the specimens'
likelihoods as the layer rebuilds them.

* :func:`refine_collapsed` (the reuse layer: ``exact=None``, the grouped layer, or no datasets for the
  joint sampler): a fresh TMCMC run of each flagged specimen's updated posterior p(θ_i | all data)
  under the population, one dask task each.  (The exact Gibbs fallback of issues 15 and 27 left with
  issue 37: the joint sampler, :mod:`hbm.population.layer`, supersedes it; its code is at commit 68827b1.)
* :func:`specimen_likelihood`: a specimen's stage-1 likelihood on the box its fit used.
"""

from __future__ import annotations

from typing import Mapping, Sequence

import numpy as np

from .. import io
from ..runtime import seeds
from ..errors import HbmError
from ..likelihood.core import make_likelihood
from ..samplers.hierarchical import GroupedResult, refine_individual
from ..runtime.progress import log_progress as _log
from .config import PopulationConfig

__all__ = ["to_refine", "refine_collapsed", "specimen_likelihood"]


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
