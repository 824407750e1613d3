"""The population layer by joint sampling: every specimen with its real likelihood, batched (issue 37).

:func:`sample_layer` samples the joint posterior of the population and the specimens
(:func:`hbm.samplers.hierarchical.batched_gibbs`) in the pooling strategy's coordinates
(:mod:`.pooling`: y = (log G, log c·P1, log (1−c)·T1, the other stage-1 columns) for
``--pool combinations``, the stage-1 columns otherwise), with the specimens' likelihoods batched a
shard at a time (:class:`.batch.SpecimenLikelihoods`).  In the default case (the base model with
``iid`` or ``weighted`` noise) a specimen's amplitudes move with the population at no model
evaluation and each of its chains costs two model evaluations per round; its stage-1 samples serve
only for its proposal (a Gaussian mixture), its random-walk covariance and its starting points.

Shards: at most :data:`SHARD_SIZE` specimens each, fixed by the number of specimens alone.  With a
dask client of at least two workers and at least two shards, the shards run as actors on the workers;
otherwise in this process.  Seeds (:mod:`hbm.runtime.seeds`): ``layer`` for the population, ``layer_specimen`` k for
specimen k (k in sorted id order), so the draws are bitwise the same on any number of workers.

Length: 6 chains × 3000 kept draws by default; chains short of the targets (:func:`converged`: hyper R-hat
≤ :data:`RHAT_TARGET`, bulk ESS ≥ :data:`ESS_TARGET`, specimens' R-hat ≤ :data:`RHAT_SPECIMEN`) go on, half
that at a time, up to ``layer_extend`` times it; the run says when it extended and still warns at the cap.

Output: the chains' kept draws — hyper-parameters (chain-major, ``chains`` chains), the updated
individuals (VOLF, P1, T1, GF, GM drawn from the box prior given their combinations), a new
specimen's pooled columns — and a summary of the run (R-hat, ESS, acceptance, evaluations).
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass
from typing import Mapping, Sequence

import numpy as np

from ..runtime import seeds
from ..errors import HbmError
from ..samplers.hierarchical import HierarchicalModel, draw_population
from ..samplers.hierarchical.batched import PooledFeatures, ShardSpec, batched_gibbs, one_population
from ..runtime.progress import log_progress as _log
from .batch import SpecimenLikelihoods, amplitude_columns
from .config import PopulationConfig
from .fallbacks import specimen_likelihood

__all__ = ["SHARD_SIZE", "LayerDraws", "sample_layer", "at_floor", "converged", "shards_on_workers"]

#: most specimens per shard (the shards, hence the draws, depend on the number of specimens only): 96
#: specimens make four shards, two per worker of a two-worker cluster
SHARD_SIZE = 24
#: most updated-individual draws stored per specimen (96 specimens × 4000 draws × 9 columns: 28 MB)
UPDATED_DRAWS = 4000
#: R-hat and bulk ESS every hyper-parameter should reach (the run warns otherwise)
RHAT_TARGET, ESS_TARGET = 1.01, 400.0
#: R-hat above which a specimen column is reported as not converged
RHAT_SPECIMEN = 1.05
#: a population sd whose draws lie within FLOOR_BAND × the hyperprior's lower end in more than FLOOR_MASS of
#: the draws is reported: its spread is set by the prior's floor, not by the data
FLOOR_BAND, FLOOR_MASS = 1.1, 0.05


@dataclass
class LayerDraws:
    """What :func:`sample_layer` returns.

    ``model``: the population model; ``raw`` (n, 2d+q) hyper draws in its raw coordinates and
    ``hyper`` their natural values (chain-major, ``chains`` chains); ``specimens``: ids in order;
    ``updated``: specimen -> (n, len(stage-1 columns)) θ draws; ``predictive`` (n, d) a new specimen's
    pooled columns; ``names``: the pooled columns; ``info``: JSON-able summary.
    """

    model: HierarchicalModel
    raw: np.ndarray
    hyper: np.ndarray
    chains: int
    specimens: list
    updated: dict
    predictive: np.ndarray
    names: list
    info: dict

    @property
    def hyper_names(self) -> list:
        return list(self.model.hyper_names)


class _Valid:
    """Rows y (..., dy) inside the box and the prior support (the coordinates' fibre point exists)."""

    def __init__(self, coords) -> None:
        self.coords, self.box = coords, np.asarray(coords.box, float)

    def __call__(self, y: np.ndarray) -> np.ndarray:
        with np.errstate(invalid="ignore"):
            inside = np.all((y >= self.box[:, 0]) & (y <= self.box[:, 1]), axis=-1)
        _, ok = self.coords.theta_of(np.where(inside[..., None], y, self.box[:, 0]).reshape(-1, y.shape[-1]))
        return inside & ok.reshape(y.shape[:-1])


def _workers(client) -> int:
    """The cluster's number of workers (0 if the scheduler does not say)."""
    try:
        return len(client.scheduler_info().get("workers", {}))
    except Exception:  # a scheduler that does not answer: run in this process
        return 0


def shards_on_workers(n_specimens: int, client) -> bool:
    """Whether the joint sampler of ``n_specimens`` runs its shards as actors on ``client``'s workers: two
    shards (more than :data:`SHARD_SIZE` specimens) and two workers at least; in this process otherwise."""
    return client is not None and math.ceil(n_specimens / SHARD_SIZE) >= 2 and _workers(client) >= 2


def _start(model: HierarchicalModel, features, rows: Sequence[np.ndarray], chains: int, rng: np.random.Generator,
           spec_rngs: Sequence[np.random.Generator]) -> tuple[np.ndarray, np.ndarray]:
    """Starting points: hyper coordinates (C, n_free) around the spread of the specimens' stage-1 means
    (jittered per chain, inside the box), and per chain and specimen a stage-1 row drawn with weight
    ∝ the chain's starting population at it (rows the population finds plausible: a shorter burn-in).
    Returns (x0, row indices (S, C))."""
    S, d = len(rows), model.d
    zs = [model.to_z(features.full(r))[0] for r in rows]
    m = np.stack([z.mean(axis=0) for z in zs])                 # (S, d) specimen means
    spread = np.sqrt(m.var(axis=0) + np.mean([z.var(axis=0) for z in zs], axis=0) / S)
    mu = m.mean(axis=0) + rng.standard_normal((chains, d)) * spread / np.sqrt(S)
    sd = spread * np.exp(0.3 * rng.standard_normal((chains, d)))
    raw = np.tile(model._fixed_raw, (chains, 1))
    raw[:, :d] = mu
    raw[:, d:2 * d] = np.log(np.maximum(sd, 1e-300)) if model.sd_prior == "loguniform" else sd
    width = model.box[:, 1] - model.box[:, 0]
    x0 = np.clip(raw[:, model.free], model.box[:, 0] + 1e-3 * width, model.box[:, 1] - 1e-3 * width)
    coef, cc = model.coefficients(model.expand(x0))
    init = np.empty((S, chains), int)
    for i, (r, g) in enumerate(zip(rows, spec_rngs)):
        F, c = features(r)
        lw = F @ coef.T + cc[None, :] + c[:, None]  # (N, C)
        w = np.exp(lw - lw.max(axis=0))
        cw = np.cumsum(w, axis=0)
        init[i] = np.minimum(np.sum(cw < g.random(chains) * cw[-1], axis=0), len(r) - 1)
    return x0, init


def schedule(cfg: PopulationConfig) -> tuple[int, int, int, int]:
    """(chains, burn-in rounds, kept draws per chain, rounds per kept draw) of ``cfg`` (at least
    ``cfg.samples`` draws in all)."""
    chains = int(cfg.layer_chains)
    keep = max(int(cfg.layer_keep), -(-int(cfg.samples) // chains))
    return chains, int(cfg.layer_burn), keep, int(cfg.layer_thin)


def converged(rhat: Mapping[str, float], ess: Mapping[str, float]) -> bool:
    """Whether the joint sampler's diagnostics meet the layer's targets: every hyper-parameter (``hyper:``
    keys) R-hat <= :data:`RHAT_TARGET` and bulk ESS >= :data:`ESS_TARGET`, every specimen column R-hat <=
    :data:`RHAT_SPECIMEN` (a NaN -- a constant column -- does not count against)."""
    bad, specimen_bad = _short({k: (r, ess[k]) for k, r in rhat.items() if k.startswith("hyper:")},
                               [r for k, r in rhat.items() if not k.startswith("hyper:")])
    return not bad and not specimen_bad


def _short(hyper: Mapping[str, tuple[float, float]], specimen_rhat) -> tuple[list[str], bool]:
    """The one convergence rule (the sampler's extension and the run's warning): the hyper-parameters short of
    R-hat <= RHAT_TARGET or bulk ESS >= ESS_TARGET (name -> (R-hat, ESS)), and whether a specimen column's R-hat
    exceeds RHAT_SPECIMEN; NaN counts against neither."""
    bad = [k for k, (r, e) in hyper.items() if r > RHAT_TARGET or e < ESS_TARGET]
    return bad, any(r > RHAT_SPECIMEN for r in specimen_rhat)


def sample_layer(cfg: PopulationConfig, results: Mapping, datasets: Mapping, model, layout, strategy,
                 client=None) -> LayerDraws:
    """The joint posterior of the population and the specimens (module docstring).

    Parameters
    ----------
    cfg : PopulationConfig
    results, datasets : mappings specimen -> SpecimenResult / Dataset
    model : Model
    layout : Layout
        The pooling strategy's layout (names, box, pooled columns and transforms).
    strategy : pooling strategy
        Its ``coords`` are the sampler's coordinates.
    client : distributed.Client, optional
        Shards as dask actors when there are at least two.

    Returns
    -------
    LayerDraws
    """
    c0 = time.process_time()
    ids = sorted(results)
    missing = [sid for sid in ids if datasets is None or sid not in datasets]
    if missing:
        raise HbmError(f"the population layer needs the datasets of {', '.join(missing)} (pass datasets=...)")
    coords = strategy.coords
    hm = HierarchicalModel(layout.names, layout.bounds, pooled=layout.pooled, transforms=layout.transforms,
                           sd_range=cfg.sd_bounds(joint=True))
    names_y = list(coords.names_y)
    pool_y = [names_y.index(p) for p in hm.names]
    features = PooledFeatures(hm, pool_y, getattr(coords, "log_u", None))
    valid = _Valid(coords)
    liks = [specimen_likelihood(cfg, results, sid, datasets, model) for sid in ids]
    rows = [coords.y_of(np.asarray(results[sid].samples, float)) for sid in ids]
    amp, why = amplitude_columns(model, names_y, liks[0].noise_model)
    amp = [] if amp is None else amp
    amp_pool = [hm.names.index(names_y[j]) if names_y[j] in hm.names else -1 for j in amp]
    S = len(ids)
    chains, burn, keep, thin = schedule(cfg)
    root = seeds.stream(int(cfg.seed), "layer")
    spec_seeds = [seeds.stream(int(cfg.seed), "layer_specimen", k) for k in range(S)]
    x0, init = _start(hm, features, rows, chains, np.random.default_rng(seeds.child(root, 0)),
                      [np.random.default_rng(seeds.child(s, 2)) for s in spec_seeds])
    n_shards = max(1, math.ceil(S / SHARD_SIZE))
    parts = np.array_split(np.arange(S), n_shards)
    # the shards go to the workers when there are two of each at least (the draws are the same either way)
    use_dask = shards_on_workers(S, client)
    mode = (f"amplitudes {', '.join(names_y[j] for j in amp)} moved with the population at no evaluation"
            if amp else f"every model parameter evaluated ({why})")
    _log(f"population layer: joint sampling of the population and {S} specimens, {chains} chains, "
         f"{n_shards} shard(s) {'on dask' if use_dask else 'in this process'}; {mode}", cfg.progress)
    shards = []
    for idx in parts:
        batch = SpecimenLikelihoods([liks[i] for i in idx], coords, amplitude=bool(amp))
        batch.check([rows[i] for i in idx])
        shards.append(ShardSpec(batch=batch, rows=[rows[i] for i in idx], init=init[idx], seeds=[spec_seeds[i] for i in idx],
                                index=idx))
    res = batched_gibbs(one_population(hm, S), shards, x0, features=features, valid=valid,
                        constraints=shards[0].batch.amplitude_constraints, amp_cols=amp, amp_pool=amp_pool,
                        box=coords.box, seed=root, n_burn=burn, n_keep=keep, thin=thin, client=client if use_dask else None,
                        log=(lambda m: _log(m, cfg.progress)), converged=converged,
                        max_keep=int(math.floor(keep * float(cfg.layer_extend))))
    cpu = time.process_time() - c0 + float(res.timings.get("shard_cpu", 0.0))  # + the workers' CPU
    x = res.x.reshape(-1, res.x.shape[-1])
    raw = hm.expand(x)
    rng_out = np.random.default_rng(seeds.child(root, 4))
    # the updated individuals: every chain's draws, thinned to at most UPDATED_DRAWS per specimen (the
    # hyper-parameters keep all: their chains are what R-hat reads)
    step = max(1, math.ceil(res.y.shape[0] * res.y.shape[1] / UPDATED_DRAWS))
    y = res.y[:, ::step].reshape(-1, S, res.y.shape[-1])
    updated = {sid: coords.draw_theta(y[:, i], rng_out) for i, sid in enumerate(ids)}
    predictive = draw_population(hm, raw, raw.shape[0], np.random.default_rng(seeds.child(root, 5)))
    info = _summary(res, ids, names_y, hm, chains, cpu, use_dask)
    info["sd_at_floor"] = at_floor(hm, raw)
    info["warnings"] = _report(info, names_y, cfg)
    return LayerDraws(model=hm, raw=raw, hyper=hm.natural(raw), chains=chains, specimens=ids, updated=updated,
                      predictive=predictive, names=list(hm.names), info=info)


def at_floor(hm: HierarchicalModel, raw: np.ndarray) -> dict:
    """Pooled columns whose population sd piles up at the hyperprior's lower end: name -> (fraction of the
    draws below ``FLOOR_BAND`` × the floor, the floor), for those above ``FLOOR_MASS``.

    Parameters
    ----------
    hm : HierarchicalModel
    raw : ndarray (n, 2d+q)
        Hyper draws in the model's raw coordinates.
    """
    sd = hm.natural(raw)[:, hm.d:2 * hm.d]
    out = {}
    for k, p in enumerate(hm.names):
        if f"sd_{p}" in hm.fix:
            continue
        frac = float(np.mean(sd[:, k] < FLOOR_BAND * hm.sd_lo[k]))
        if frac > FLOOR_MASS:
            out[f"sd_{p}"] = (frac, float(hm.sd_lo[k]))
    return out


def _summary(res, ids, names_y, hm, chains, cpu, use_dask) -> dict:
    """JSON-able record of the run (``hierarchical.nc`` attribute ``layer``)."""
    hyper = {k.split(":", 1)[1]: (float(v), float(res.ess[k])) for k, v in res.rhat.items() if k.startswith("hyper:")}
    spec = {}
    for key, v in res.rhat.items():
        if key.startswith("hyper:"):
            continue
        s, col = key.split(":")
        spec[f"{ids[int(s)]}:{names_y[int(col)]}"] = (float(v), float(res.ess[key]))
    worst_s = max(spec, key=lambda k: spec[k][0]) if spec else None
    return {"method": "batched Metropolis-within-Gibbs", "chains": int(chains), **res.options,
            "evaluations": int(res.evaluations.sum()),
            "evaluations_per_specimen": {sid: int(e) for sid, e in zip(ids, res.evaluations)},
            "rhat_hyper_max": max(v[0] for v in hyper.values()), "ess_hyper_min": min(v[1] for v in hyper.values()),
            "rhat_specimen_max": spec[worst_s][0] if worst_s else float("nan"),
            "rhat_specimen_worst": worst_s,
            "hyper": {k: {"rhat": v[0], "ess": v[1]} for k, v in hyper.items()},
            "specimens": {k: {"rhat": v[0], "ess": v[1]} for k, v in spec.items()},
            "acceptance": res.acceptance, "wall_s": float(res.timings["total"]), "cpu_s": float(cpu),
            "dask": bool(use_dask)}


def _report(info: dict, names_y, cfg: PopulationConfig) -> list[str]:
    """The run's line, and a warning if the chains have not converged (returned: ``hierarchical.nc`` and the
    report keep it)."""
    _log(f"population layer: {info['evaluations']:,} model evaluations, {info['wall_s']:.1f} s; max R-hat "
         f"{info['rhat_hyper_max']:.3f} (hyper-parameters), {info['rhat_specimen_max']:.3f} (specimens), "
         f"min bulk ESS {info['ess_hyper_min']:.0f} (hyper-parameters)", cfg.progress)
    extended = info.get("n_keep", 0) > info.get("n_keep_planned", info.get("n_keep", 0))
    if extended:
        _log(f"population layer: chains extended from {info['n_keep_planned']} to {info['n_keep']} draws per chain "
             f"to converge (at most {info['max_keep']})", cfg.progress)
    bad, spec_bad = _short({k: (v["rhat"], v["ess"]) for k, v in info["hyper"].items()}, [info["rhat_specimen_max"]])
    if bad or spec_bad:
        what = ", ".join(f"{k} (R-hat {info['hyper'][k]['rhat']:.3f}, ESS {info['hyper'][k]['ess']:.0f})" for k in bad)
        if spec_bad:
            what += ("; " if what else "") + f"{info['rhat_specimen_worst']} (R-hat {info['rhat_specimen_max']:.3f})"
        planned = info.get("n_keep_planned", info["n_keep"])
        doubled = f"--hier-samples {2 * info['chains'] * planned} doubles the planned draws"
        # chains that could not go on are told how to let them; chains that went on to the cap, how to raise it
        advice = (f"{doubled} and with them the cap" if info.get("max_keep", planned) > planned else
                  f"--hier-extend 3 lets them go on until converged (up to 3 x), or {doubled}")
        msg = (f"population layer not converged: {what}"
               + (f" after extending its chains to {info['n_keep']} draws each" if extended else "")
               + f"; longer chains help: {advice}")
        _log(f"WARNING: {msg}", True)
        out = [msg]
    else:
        out = []
    if info.get("sd_at_floor"):
        msg = ("population spread at the hyperprior's lower end: " + ", ".join(
            f"{k} ({100 * f:.0f} % of the draws below {FLOOR_BAND:g} x its floor {lo:.3g})"
            for k, (f, lo) in info["sd_at_floor"].items())
            + "; the data allow a narrower population than the prior (sd_range setting, a fraction of mu's range)")
        _log(f"WARNING: {msg}", True)
        out.append(msg)
    return out
