"""The population layer of a multi-specimen fit: the hierarchical model over fitted specimens.

:func:`run_population` takes the specimens' stage-1 results (:class:`hbm.io.SpecimenResult`,
from :func:`hbm.fit.fit_specimen` or ``<out>/specimens/*.nc``), their datasets and the model,
and fits :func:`hbm.samplers.hierarchical.hierarchical` on the model parameters, reusing the
stage-1 samples; the result goes to ``<out>/hierarchical.nc``.  It is phase 2 of ``hbm run``
(:mod:`hbm.workflow`) and runs without dask; a dask client, when given, only runs the fresh
TMCMC refinements of collapsed specimens in parallel.

Pooling (``PopulationConfig.pooled``): "combinations" (a population over log G, log c·P1,
log (1−c)·T1, T2, THETA — what a uniaxial curve identifies — with the exact stage-1 prior
density of the combinations, :mod:`hbm.combinations`), "informed" (the model parameters that
the posteriors inform, :func:`~hbm.samplers.hierarchical.auto_pool`), "all", a list of names,
or "auto" (default: "combinations" when VOLF, P1, T1, GF, GM, T2, THETA are free, otherwise
"informed").

Groups (``PopulationConfig.groups``, from ``# group:`` lines or ``hbm run --group-by KEY``): a
population → group → specimen layer (:func:`hbm.samplers.grouped.grouped_hierarchical`) in the same
transformed coordinates and with every pooling mode; its group-level draws go to
``hierarchical.nc`` too.  Without groups the two-level code path runs unchanged.

Reuse diagnostics (issue 15): per specimen PSIS k̂ and the mass beyond the stage-1 samples
(:func:`~hbm.samplers.hierarchical.reuse_diagnostics`, in ``hierarchical.nc`` and the report); a
specimen flagged unreliable, or whose ESS collapsed, gets its updated posterior from a fresh
TMCMC run under the population.  ``PopulationConfig.reference`` > 0 appends defensive reference
draws to each specimen's samples (``--pool combinations``, :func:`_reference_rows`).

Exact fallback (``PopulationConfig.exact="gibbs"``, issue 15): when the diagnostics flag a
specimen, the joint posterior of (population, specimens) is sampled by Metropolis-within-Gibbs
(:func:`hbm.samplers.joint_gibbs.joint_gibbs`, :func:`_exact_gibbs`): flagged specimens with their real
likelihoods (``--pool combinations``: in the coordinates y = (φ, the other parameters), where the
stage-1 density p0(φ) cancels), the others by their stage-1 samples; its hyper draws and updated
individuals replace the reuse ones and no fresh TMCMC refinement runs.

Seeds: the streams ``hierarchical`` (``grouped`` with groups), ``new_specimen``, ``refine`` k, ``reference`` k
and ``joint`` of :mod:`hbm.seeds`.
"""

from __future__ import annotations

import dataclasses
import time
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Mapping, Sequence

import numpy as np
from scipy.special import gammaln

from . import io, seeds
from .combinations import (COMBINATION_PARAMS, combination_features, fibre_point, log_density,
                           sample_conditional, support_hull, to_features)
from .errors import HbmError
from .likelihood import make_likelihood
from .model import COMBINATIONS, spyrou_model
from .samplers.hierarchical import (ExactSpecimen, GroupedResult, ReuseSpecimen, auto_pool, defensive_log_weights,
                                    grouped_hierarchical, hierarchical, joint_gibbs, mixture_log_weights,
                                    refine_individual, systematic_resample)
from .utils import log_progress as _log

__all__ = ["PopulationConfig", "run_population", "DEFAULT_TRANSFORMS", "DEFAULT_SD_RANGE", "POOL_COMBINATIONS",
           "POOL_INFORMED", "COMBINATION_COLUMNS", "COMBINATION_NEEDS"]

#: transform of each base-model parameter in the population model (see hbm.samplers.hierarchical):
#: log for strictly positive moduli spanning decades (P1, GF, GM: a log-normal population, sd
#: reads as a relative spread); logit on the box for bounded fractions/scales (VOLF, EOPT, T1,
#: T2: no truncation needed); identity (truncated normal) for THETA, whose posteriors pile up
#: against the 60° edge: logit would stretch that pile-up into a tail many units wide, far wider
#: than the population, and the importance ESS collapses (measured: 10% ESS 2-3 of 500 vs 9-190).
DEFAULT_TRANSFORMS = {"VOLF": "logit", "EOPT": "logit", "P1": "log", "T1": "logit", "T2": "logit",
                      "THETA": "identity", "GF": "log", "GM": "log"}
#: sd_k in [0.05, 1] x the width of mu_k's range.  The lower end keeps the unidentified directions
#: (VOLF, P1, T1, GF, GM individually) from drawing populations far narrower than every
#: individual posterior -- the log-uniform sd prior would otherwise put mass there, where the
#: stage-1 samples cannot represent the population (importance ESS ~ 1).
DEFAULT_SD_RANGE = (0.05, 1.0)

#: ``--pool combinations``: pool the identifiable combinations instead of the raw parameters
POOL_COMBINATIONS = "combinations"
#: ``--pool informed``: pool the model parameters that the posteriors inform (auto_pool)
POOL_INFORMED = "informed"
#: pooled coordinates of ``--pool combinations`` (identity transform: they are logs already)
COMBINATION_COLUMNS = tuple(f"log_{c}" for c in COMBINATIONS)
#: model parameters ``--pool combinations`` needs free
COMBINATION_NEEDS = COMBINATION_PARAMS + ("T2", "THETA")


@dataclass
class PopulationConfig:
    """Settings of the population layer (``hbm run``: ``--hier-*``, ``--pool`` and the stage-1
    settings that a fresh TMCMC run of a collapsed specimen repeats).

    Attributes
    ----------
    seed : int
        Run seed; the layer's streams are spawned from it (module docstring).
    pooled : str, list of str or None
        "auto", "combinations", "informed", "all" or parameter names (module docstring).
    samples : int
        Hyper-posterior draws (TMCMC population of the layer).  When the exact fallback runs,
        the layer's draws are all its chains × kept draws, at least ``samples``.
    max_steps : int
        MH steps per TMCMC stage of the layer and of the refinements.
    estimator : str
        Importance estimator of :func:`~hbm.samplers.hierarchical.hierarchical`.
    transforms : dict, optional
        Per-parameter transforms overriding :data:`DEFAULT_TRANSFORMS`.
    sd_range : tuple of float
        Population sd range as a fraction of mu's range.
    stage1_samples : int
        The specimens' TMCMC N (caps a refinement's N).
    noise, fix, bounds
        Stage-1 likelihood settings (:func:`hbm.likelihood.make_likelihood`), for refinements.
    retries : int
        dask retries of a refinement task.
    progress : bool
        Progress lines and bars on stderr.
    groups : dict, optional
        Specimen id -> group name (:func:`hbm.data.specimen_groups`): the three-level layer.
        None: the two-level layer.
    group_by : str, optional
        The metadata key the groups come from (``group``, ``species`` ...), for the report's words.
    second_pass : bool
        ``--pool combinations``: refit the layer with draws of the flagged specimens' posteriors
        under a reference population flat in the pooled coordinates appended
        (:func:`_mixture_pass`; needs the datasets).  Off by default: on the gold benchmark it
        fixed the tails for one layer seed of three and costs ~13x the layer's CPU
        (results/benchmarks/hierarchical_gold.md).
    reference : float
        ``--pool combinations``: defensive reference draws per stage-1 sample appended to each
        specimen's samples (:func:`_reference_rows`; needs the datasets); 0 = plain reuse.
    exact : str or None
        "gibbs" (default): when a specimen's reuse is flagged unreliable (or its ESS collapsed),
        sample the joint posterior of (population, specimens) by Metropolis-within-Gibbs
        (:func:`hbm.samplers.joint_gibbs.joint_gibbs`): flagged specimens with their real
        likelihoods, the others by their reweighted stage-1 samples; its hyper-posterior and
        updated individuals replace the reuse ones (:func:`_exact_gibbs`; needs the datasets;
        two-level layer without reference draws or second pass, otherwise not applied).  On the
        gold benchmark it brings every hyper-parameter median within 0.14 and every 5/95 % quantile
        within 0.40 NUTS sd (reuse: 0.41 / 1.21) for ~1.8x the layer's CPU on the shipped six
        (results/benchmarks/hierarchical_gold.md).
        None: reuse (+ fresh TMCMC refinement of flagged specimens).
    exact_all : bool
        With ``exact="gibbs"``, once some specimen is flagged: real likelihoods for every specimen
        (default; on the gold the unflagged ones' reweighted samples left the medians 0.21 NUTS sd
        off, real likelihoods 0.19, for +30 % CPU); False: only for the flagged ones.
    exact_chains, exact_burn, exact_keep, exact_thin : int
        Chains, adaptive burn-in sweeps, kept draws per chain and sweeps between kept draws.
    """

    seed: int = 0
    pooled: list | str | None = "auto"
    samples: int = 1000
    max_steps: int = 25
    estimator: str = "raw"
    transforms: dict | None = None
    sd_range: tuple = DEFAULT_SD_RANGE
    stage1_samples: int = 2000
    noise: str = "iid"
    fix: dict | None = None
    bounds: dict | None = None
    retries: int = 1
    progress: bool = True
    groups: dict | None = None
    group_by: str | None = None
    reference: float = 0.0
    second_pass: bool = False
    exact: str | None = "gibbs"
    exact_all: bool = True
    exact_chains: int = 128
    # gold benchmark: 400 + 120 x 10 sweeps gave worst median 0.14 / tail 0.40 NUTS sd (R-hat <= 1.39),
    # 600 + 60 x 10 gave 0.19 / 0.34 (R-hat <= 1.57) for 25 % less CPU
    exact_burn: int = 400
    exact_keep: int = 120
    exact_thin: int = 10


def run_population(results: Mapping[str, io.SpecimenResult], datasets: Mapping | None = None, model=None, *,
                   config: PopulationConfig | None = None, out: str | Path | None = None, client=None,
                   **kwargs) -> tuple[io.HierarchicalFile, Path | None]:
    """Hierarchical layer over fitted specimens: hyper-posterior, updated individuals, a new specimen.

    Parameters
    ----------
    results : mapping of specimen id -> SpecimenResult
        Stage-1 results, all fitted with the same parameters and prior boxes.
    datasets : mapping of specimen id -> xarray.Dataset, optional
        The specimens' data; needed only when a specimen's importance ESS collapses (its updated
        posterior then comes from a fresh TMCMC run of p(θ_i | all data)).
    model : Model, optional
        The stage-1 model; default :func:`hbm.spyrou_model`.
    config : PopulationConfig, optional
        Settings; keyword arguments override/construct it.
    out : path, optional
        Folder of ``hierarchical.nc``; None: nothing is written.
    client : distributed.Client, optional
        Run the refinements of collapsed specimens as dask tasks; None: in this process.

    Returns
    -------
    (HierarchicalFile, Path or None)
        The result and the path of ``hierarchical.nc``.

    Raises
    ------
    HbmError
        Fewer than two specimens, specimens fitted with different parameters/boxes, a bad
        ``pooled``, or refinements needed without ``datasets``.
    """
    cfg = dataclasses.replace(config, **kwargs) if config is not None else PopulationConfig(**kwargs)
    _check_exact(cfg)
    if len(results) < 2:
        raise HbmError(f"the population layer needs at least two specimens, got {len(results)}")
    return _run_hierarchical(cfg, results, datasets, None if out is None else Path(out), model, client)


def _refine_task(h, sid: str, lik, n_samples: int, seed: int, n_out: int, max_steps: int = 25,
                 n_hyper: int = 200, augment=None) -> np.ndarray:
    """Fresh TMCMC of one specimen's updated posterior; returns ``n_out`` equal-weight draws.

    The population prior is a mixture over ``n_hyper`` hyper-posterior draws (its cost is linear
    in n_hyper per particle); ``max_steps`` caps the MH steps per stage.  ``augment``: the map
    to pooled derived columns (``--pool combinations``), run over the likelihood's own box.
    """
    extra = {} if augment is None else {"augment": augment, "bounds": lik.bounds}
    h = h.view(sid) if isinstance(h, GroupedResult) else h  # the specimen's own (group mean, sd_within)
    tr = refine_individual(h, sid, lik, n_samples=n_samples, seed=seed, progress=False, n_hyper=n_hyper,
                           max_steps=max_steps, **extra)
    rng = np.random.default_rng(seed)
    sel = rng.choice(tr.samples.shape[0], n_out, replace=tr.samples.shape[0] < n_out)
    return np.asarray(tr.samples)[sel]


def _pool_mode(pooled, model_names: Sequence[str]):
    """Resolve ``PopulationConfig.pooled`` to "combinations", "informed", "all" or a list of names."""
    if (isinstance(pooled, (list, tuple)) and len(pooled) == 1
            and pooled[0] in ("auto", POOL_COMBINATIONS, POOL_INFORMED, "all")):
        pooled = pooled[0]  # the CLI splits --pool on commas
    if pooled in (None, "auto"):
        return POOL_COMBINATIONS if all(n in model_names for n in COMBINATION_NEEDS) else POOL_INFORMED
    return pooled


class _CombinationAugment:
    """θ (stage-1 columns) -> (θ + φ columns, stage-1 prior log density of the pooled columns).

    The map behind ``--pool combinations``, for the fresh-TMCMC fallback of collapsed specimens
    (:func:`hbm.samplers.hierarchical.refine_individual`); a class so that dask can ship it.
    """

    def __init__(self, names: Sequence[str], bounds: np.ndarray, log_u: float) -> None:
        self.names, self.bounds, self.log_u = list(names), np.asarray(bounds, float), float(log_u)

    def __call__(self, theta: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        f = to_features(self.names, theta)
        ok = np.all(f > 0, axis=1)  # T1 = 0 exactly has no log feature (prior mass 0)
        phi = np.log(np.where(ok[:, None], f, 1.0))
        lp = np.full(theta.shape[0], -np.inf)
        if ok.any():
            lp[ok] = log_density(phi[ok], self.bounds, self.names) + self.log_u
        return np.hstack([theta, phi]), lp


def _unique(msgs: Sequence[str]) -> list[str]:
    """Messages in order without repeats (a warning is both raised and kept in the result)."""
    return list(dict.fromkeys(msgs))


def _specimen_likelihood(cfg: PopulationConfig, results: Mapping[str, io.SpecimenResult], sid: str, datasets, model):
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


def _to_refine(h, datasets) -> list[str]:
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


def _refine_collapsed(cfg: PopulationConfig, h, collapsed: Sequence[str], datasets, model,
                      results: Mapping[str, io.SpecimenResult], cl=None, augment=None) -> dict[str, np.ndarray]:
    """Fresh TMCMC of p(θ_i | all data) for every specimen whose importance ESS collapsed.

    One dask task per specimen when a client is given; seeds spawned per specimen from the run
    seed, so the draws do not depend on the number of workers.
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
        lik = _specimen_likelihood(cfg, results, sid, datasets, model)
        rs = seeds.seed_int(seeds.stream(int(cfg.seed), "refine", k))
        args = (h_ref, sid, lik, min(int(cfg.samples), int(cfg.stage1_samples)), rs, n_up, int(cfg.max_steps))
        kw = {"augment": augment} if augment is not None else {}
        jobs[sid] = (cl.submit(_refine_task, *args, key=f"refine-{sid}", pure=False, retries=cfg.retries, **kw)
                     if cl is not None else _refine_task(*args, **kw))
    return {sid: (job.result() if cl is not None else job) for sid, job in jobs.items()}


def _fit_population(cfg: PopulationConfig, stage1: Mapping, names: Sequence[str], bounds, transforms: Mapping,
                    pooled: Sequence[str], log_prior: Mapping | None = None, extra: Mapping | None = None):
    """:func:`~hbm.samplers.hierarchical.hierarchical` with the run's settings and its own seed.

    Returns the result and its warnings (raised and kept ones, without repeats).
    """
    if cfg.groups:
        return _fit_grouped(cfg, stage1, names, bounds, transforms, pooled, log_prior, extra)
    # an int seed for the hierarchical layer, independent of the specimen streams
    seed = seeds.seed_int(seeds.stream(int(cfg.seed), "hierarchical"))
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        h = hierarchical(stage1, names, bounds, transforms=transforms, pooled=pooled,
                         n_samples=int(cfg.samples), seed=seed, progress=cfg.progress,
                         sd_range=tuple(cfg.sd_range), estimator=cfg.estimator, log_prior=log_prior,
                         # each ψ evaluation is a (n_ψ × 2d) @ (2d × Σ N_i) product: cap the MH steps per
                         # stage so the layer stays at tens of seconds for six specimens
                         tmcmc_options={"max_steps": int(cfg.max_steps)}, **(extra or {}))
    return h, _unique([str(w.message) for w in caught] + list(h.warnings))


def _fit_grouped(cfg: PopulationConfig, stage1: Mapping, names: Sequence[str], bounds, transforms: Mapping,
                 pooled: Sequence[str], log_prior: Mapping | None = None, extra: Mapping | None = None):
    """:func:`~hbm.samplers.grouped.grouped_hierarchical` with the run's settings (stream ``grouped``).

    ``extra``: the stored stage-1 log-likelihoods for the reuse diagnostics (reference rows and
    other two-level-only options are not used by the grouped layer).  Returns the result and its
    warnings, as :func:`_fit_population`.
    """
    groups = {sid: cfg.groups.get(sid) for sid in stage1}
    _log("groups" + (f" ({cfg.group_by})" if cfg.group_by else "") + ": " + ", ".join(
        f"{g} ({sum(v == g for v in groups.values())})" for g in sorted(set(groups.values()), key=str)), cfg.progress)
    options = dict(transforms=transforms, pooled=pooled, log_prior=log_prior, n_samples=int(cfg.samples),
                   seed=seeds.seed_int(seeds.stream(int(cfg.seed), "grouped")), progress=cfg.progress,
                   sd_range=tuple(cfg.sd_range), estimator=cfg.estimator,
                   tmcmc_options={"max_steps": int(cfg.max_steps)},
                   log_likelihood=(extra or {}).get("log_likelihood"))
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        h = grouped_hierarchical(stage1, names, bounds, groups, **options)
    return h, _unique([str(w.message) for w in caught] + list(h.warnings))


def _group_payload(cfg: PopulationConfig, h) -> dict | None:
    """The group level of a grouped result for :class:`hbm.io.HierarchicalFile` (None if ungrouped)."""
    if not isinstance(h, GroupedResult):
        return None
    return {"key": cfg.group_by or "group", "names": list(h.groups), "specimen_group": dict(h.specimen_group),
            "pooled": list(h.names), "means": np.asarray(h.group_means), "predictive": np.asarray(h.group_predictive),
            "hyperprior": {"group means": "normal(mu, sd_between) truncated to the range of mu",
                           "sd_between, sd_within": f"each loguniform on {tuple(cfg.sd_range)} x mu range"}}


def _write_population(cfg: PopulationConfig, h, out: Path | None, names: Sequence[str],
                      updated: Mapping[str, np.ndarray], new_specimen: np.ndarray, pooled_names: Sequence[str],
                      warn_msgs: Sequence[str], refined: Sequence[str], **attrs):
    """The HierarchicalFile of a hierarchical result, written to ``<out>/hierarchical.nc`` unless ``out`` is
    None; ``attrs``: the pooling mode's own attributes."""
    attrs.update({"estimator": cfg.estimator, "log_evidence_parts": h.log_evidence_parts,
                  "warnings": list(warn_msgs), "refined": list(refined), "ess_summary": h.ess_summary,
                  "hyperprior": {"mu": "uniform on transformed box",
                                 "sd": f"loguniform on {tuple(cfg.sd_range)} x mu range"}})
    hf = io.HierarchicalFile(param_names=list(names), hyper_names=list(h.hyper_names),
                             hyper_samples=np.asarray(h.hyper_samples), specimen_ids=list(h.specimens),
                             updated=np.stack([updated[s] for s in h.specimens], axis=1),
                             new_specimen=np.asarray(new_specimen), log_evidence=float(h.log_evidence),
                             log_evidence_se=float(h.log_evidence_se),
                             stages=list(getattr(h.sampler_result, "stages", [])),
                             ess=np.array([float(h.ess_summary[s]["min"]) for s in h.specimens]), attrs=attrs,
                             pooled_names=list(pooled_names), reuse=_reuse_attrs(h))
    hf.groups = _group_payload(cfg, h)
    return hf, (io.write_hierarchical(hf, out / "hierarchical.nc") if out is not None else None)


#: reference of the defensive draws: multivariate Student-t with these degrees of freedom, scaled
#: by this factor over the stage-1 posterior covariance of u = (φ, other parameters)
REFERENCE_DF = 4.0
REFERENCE_SCALE = 2.0


def _mvt(u: np.ndarray, n: int, rng: np.random.Generator) -> tuple[np.ndarray, callable]:
    """n draws from the Student-t reference fitted to rows ``u`` and its log density function."""
    mean = u.mean(axis=0)
    cov = np.cov(u, rowvar=False) * REFERENCE_SCALE**2
    cov += np.diag(1e-12 * np.maximum(np.diag(cov), 1e-300))  # a constant column (fixed value) stays PD
    L = np.linalg.cholesky(cov)
    d, nu = u.shape[1], REFERENCE_DF
    x = mean + (rng.standard_normal((n, d)) @ L.T) / np.sqrt(rng.chisquare(nu, n) / nu)[:, None]
    logdet = 2.0 * np.sum(np.log(np.diag(L)))
    norm = gammaln((nu + d) / 2) - gammaln(nu / 2) - 0.5 * d * np.log(nu * np.pi) - 0.5 * logdet

    def logpdf(v: np.ndarray) -> np.ndarray:
        m = np.linalg.solve(L, (v - mean).T)
        return norm - 0.5 * (nu + d) * np.log1p(np.sum(m * m, axis=0) / nu)

    return x, logpdf


def _reference_rows(cfg: PopulationConfig, results: Mapping[str, io.SpecimenResult], datasets, model,
                    names: Sequence[str], bounds: np.ndarray, hull: np.ndarray,
                    feats: Mapping[str, tuple]) -> dict[str, tuple]:
    """Defensive reference draws per specimen for ``--pool combinations`` (issue 15: the tails).

    Under the uniform stage-1 prior the density of log c·P1 falls off as e^y, and where the data
    bound c·P1 only from above the stage-1 samples barely reach the small values a population
    puts mass on: reuse then under-estimates p(d_i|ψ) for those populations and the updated
    individuals' tails.  Here every specimen gets ``cfg.reference × N`` extra draws from a
    reference q that covers those tails by construction: u = (φ, the other parameters) from a
    Student-t (``REFERENCE_DF``) with ``REFERENCE_SCALE``² × the stage-1 covariance of u, and
    (VOLF, P1, T1, GF, GM) given φ from the stage-1 prior (:func:`hbm.combinations.sample_conditional`),
    so q(θ)/p0(θ) = t(u)/p0(u).  Their real log-likelihoods are evaluated, and the stage-1 samples
    plus the draws are weighted as a deterministic mixture
    (:func:`hbm.samplers.hierarchical.defensive_log_weights`): p(d_i|ψ) stays unbiased and the
    stage-1 results, log Z_i included, are untouched.  Draws outside the box, the φ hull or the
    support of the combinations are dropped (counted as zeros).

    Returns
    -------
    dict specimen -> (rows (M, len(names) + 3), log p0 of the pooled φ (M,), log ω of all N + M rows)
        Empty without datasets or with ``cfg.reference`` = 0.
    """
    if not cfg.reference or datasets is None or any(sid not in datasets for sid in results):
        return {}
    names = list(names)
    comb = [names.index(p) for p in COMBINATION_PARAMS]
    other = [j for j, n in enumerate(names) if n not in COMBINATION_PARAMS]
    log_p0_other = -float(np.sum(np.log(np.ptp(bounds[other], axis=1))))
    out = {}
    for k, (sid, r) in enumerate(results.items()):
        phi, lp_phi = feats[sid]
        u = np.column_stack([phi, r.samples[:, other]])
        n_post = u.shape[0]
        n_drawn = int(round(float(cfg.reference) * n_post))
        rng = seeds.rng(int(cfg.seed), "reference", k)
        x, logpdf = _mvt(u, n_drawn, rng)
        ok = (np.all((x[:, :3] >= hull[:, 0]) & (x[:, :3] <= hull[:, 1]), axis=1)
              & np.all((x[:, 3:] >= bounds[other, 0]) & (x[:, 3:] <= bounds[other, 1]), axis=1))
        x = x[ok]
        lp_x = log_density(x[:, :3], bounds, names)
        x, lp_x = x[np.isfinite(lp_x)], lp_x[np.isfinite(lp_x)]
        theta = np.empty((x.shape[0], len(names)))
        theta[:, comb] = sample_conditional(x[:, :3], bounds, rng, names)
        theta[:, other] = x[:, 3:]
        lik = _specimen_likelihood(cfg, results, sid, datasets, model)
        ll_x = np.asarray(lik(theta), float)
        keep = np.isfinite(ll_x)
        theta, x, lp_x, ll_x = theta[keep], x[keep], lp_x[keep], ll_x[keep]
        ll_post = np.asarray(lik(r.samples), float)
        log_rho = np.concatenate([logpdf(u) - lp_phi, logpdf(x) - lp_x]) - log_p0_other
        lw = defensive_log_weights(np.concatenate([ll_post, ll_x]), log_rho, float(r.log_evidence), n_post,
                                   n_drawn)
        out[sid] = (np.hstack([theta, x[:, :3]]), lp_x, lw)
    return out


def _mixture_pass(cfg: PopulationConfig, h, flagged: Sequence[str], results: Mapping[str, io.SpecimenResult],
                  datasets, model, stage1: dict, log_prior: dict, augment, more: dict) -> tuple[dict, dict, dict]:
    """Second pass for specimens whose reuse is unreliable: add draws of their posterior under a flat reference.

    For each flagged specimen a fresh TMCMC run samples q = p(d_i|θ)·p_ref(θ)/Z_q, p_ref the
    population model with mu mid-range and sd at the top of the hyperprior range, i.e. nearly flat
    in the pooled (log-)coordinates (:func:`hbm.samplers.hierarchical.refine_individual`, real
    likelihood).  (A mixture over the first pass's hyper-posterior draws was tried first: its
    draws stayed where the first pass's too narrow populations were and changed nothing.)  The
    draws go where the populations may put mass, which the stage-1 samples drawn under the uniform
    prior may never reach (the e^y tail of log c·P1 bounded from above); they are appended to
    the stage-1 samples with the deterministic-mixture weights of
    :func:`hbm.samplers.hierarchical.mixture_log_weights` (unbiased p(d_i|ψ), stage-1 results
    and log Z_i untouched) and the layer is fitted again on them.

    Returns the new (stage1, log_prior, extra keyword arguments of the layer).
    """
    stage1, log_prior, more = dict(stage1), dict(log_prior), dict(more)
    lws, n1 = dict(more.get("log_weights") or {}), dict(more.get("stage1_rows") or {})
    # reference "population": mu mid-range, sd at the top of the hyperprior range, i.e. nearly flat in the
    # pooled (log-)coordinates over their box -- the reference prior of the issue, where p0 is not flat
    hm = h.model
    flat = np.zeros((1, h.raw_samples.shape[1]))
    flat[0, : hm.d] = 0.5 * (hm.mu_lo + hm.mu_hi)
    flat[0, hm.d : 2 * hm.d] = np.log(hm.sd_hi) if hm.sd_prior == "loguniform" else hm.sd_hi
    h_ref = dataclasses.replace(h, raw_samples=flat)
    for k, sid in enumerate(h.specimens):
        if sid not in flagged:
            continue
        if sid in lws:  # already carries reference rows: keep them as they are
            continue
        lik = _specimen_likelihood(cfg, results, sid, datasets, model)
        rs = seeds.seed_int(seeds.stream(int(cfg.seed), "refine", k))
        tr, raw, w = refine_individual(h_ref, sid, lik, n_samples=min(int(cfg.samples), int(cfg.stage1_samples)),
                                       seed=rs, progress=False, n_hyper=1, weighting="plain",
                                       max_steps=int(cfg.max_steps), augment=augment, bounds=lik.bounds,
                                       return_mixture=True)
        cols_q, lp_q = augment(np.asarray(tr.samples, float))
        ok = np.isfinite(lp_q)
        cols_q, lp_q = cols_q[ok], lp_q[ok]
        rows1 = np.asarray(stage1[sid][0], float)
        rows = np.vstack([rows1, cols_q])
        lp = np.concatenate([log_prior[sid], lp_q])
        ratio = h.model.log_density(rows, raw, w) - lp  # log p_mix/p0 of the pooled columns
        lws[sid] = mixture_log_weights(ratio, rows1.shape[0])
        # the union is the specimen's sample set from now on (coverage, likelihood slopes)
        n1[sid] = rows.shape[0]
        if sid in (more.get("log_likelihood") or {}):
            ll_q = np.asarray(lik(np.asarray(tr.samples, float)[ok]), float)
            more["log_likelihood"] = {**more["log_likelihood"],
                                      sid: np.concatenate([more["log_likelihood"][sid][: rows1.shape[0]], ll_q])}
        stage1[sid] = (rows,) + tuple(stage1[sid][1:])
        log_prior[sid] = lp
    if lws:
        for sid in h.specimens:  # rows without extra draws: weight 1
            lws.setdefault(sid, np.zeros(len(stage1[sid][0])))
        more.update(log_weights=lws, stage1_rows=n1)
    return stage1, log_prior, more


def _diagnostic_inputs(results: Mapping[str, io.SpecimenResult]) -> dict:
    """Stage-1 log-likelihoods for the coverage diagnostic (its likelihood extrapolation), when stored."""
    ll = {sid: np.asarray(r.log_likelihood, float) for sid, r in results.items()
          if getattr(r, "log_likelihood", None) is not None and len(r.log_likelihood) == len(r.samples)}
    return {"log_likelihood": ll} if len(ll) == len(results) else {}


def _reuse_attrs(h) -> dict:
    """Per-specimen reuse diagnostics, JSON-able (hierarchical.nc stores them; the report shows them)."""
    return {sid: {k: v for k, v in r.items() if k != "uncovered_by"} for sid, r in (getattr(h, "reuse", None) or {}).items()}


class _PlainCoordinates:
    """Coordinates of the exact fallback when the pooled columns are stage-1 columns: y = θ."""

    def __init__(self, bounds: np.ndarray, names: Sequence[str]) -> None:
        self.box, self.names_y = np.asarray(bounds, float), list(names)

    def y_of(self, theta: np.ndarray) -> np.ndarray:
        return np.asarray(theta, float)

    def theta_of(self, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        return y, np.ones(y.shape[0], bool)

    def columns(self, y: np.ndarray) -> tuple[np.ndarray, None]:
        return y, None  # the model's uniform box prior of the pooled columns

    def draw_theta(self, y: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        return y


class _PhiCoordinates:
    """Coordinates of the exact fallback for ``--pool combinations``: y = (φ, the other stage-1 columns).

    The likelihood depends on (VOLF, P1, T1, GF, GM) only through φ = (log G, log c·P1,
    log (1−c)·T1), so the joint posterior is sampled in y: with p(θ|ψ) = p_pop(x|ψ)·p0(θ)/p0(x)
    the fibre of θ over y integrates to p(y|ψ) ∝ p_pop(x(y)|ψ) on the support of p0(φ), i.e. the
    stage-1 density p0(φ) cancels and is never evaluated (it costs 10× the likelihood).  The
    likelihood is evaluated at one deterministic point of the fibre (:meth:`theta_of`); the
    output θ are drawn from the box prior given φ (:func:`hbm.combinations.sample_conditional`),
    which is the joint posterior's own conditional.
    """

    def __init__(self, names: Sequence[str], bounds: np.ndarray, hull: np.ndarray, log_u: float) -> None:
        self.names, self.bounds, self.log_u = list(names), np.asarray(bounds, float), float(log_u)
        self.comb = [self.names.index(p) for p in COMBINATION_PARAMS]
        self.other = [j for j, n in enumerate(self.names) if n not in COMBINATION_PARAMS]
        self.box = np.vstack([np.asarray(hull, float), self.bounds[self.other]])
        self.names_y = list(COMBINATION_COLUMNS) + [self.names[j] for j in self.other]

    def y_of(self, theta: np.ndarray) -> np.ndarray:
        theta = np.asarray(theta, float)
        return np.column_stack([np.log(to_features(self.names, theta)), theta[:, self.other]])

    def theta_of(self, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """A θ with combinations φ = y[:, :3] (:func:`hbm.combinations.fibre_point`) and whether one exists."""
        parts, ok = fibre_point(y[:, :3], self.bounds, self.names)
        theta = np.empty((y.shape[0], len(self.names)))
        theta[:, self.comb] = parts
        theta[:, self.other] = y[:, 3:]
        return theta, ok

    def columns(self, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        # log_prior: the uniform densities of the other pooled columns only -- p0(φ) cancels (class docstring)
        return np.hstack([self.theta_of(y)[0], y[:, :3]]), np.full(y.shape[0], self.log_u)

    def draw_theta(self, y: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        theta = np.empty((y.shape[0], len(self.names)))
        theta[:, self.comb] = sample_conditional(y[:, :3], self.bounds, rng, self.names)
        theta[:, self.other] = y[:, 3:]
        return theta


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


def _exact_gibbs(cfg: PopulationConfig, h, exact_ids: Sequence[str], results: Mapping[str, io.SpecimenResult],
                 datasets, model, rows: Mapping[str, np.ndarray], log_prior: Mapping | None, coords):
    """The exact fallback (``PopulationConfig.exact="gibbs"``): joint Metropolis-within-Gibbs.

    ``exact_ids`` get their real likelihoods (in ``coords``), the others their stage-1 ``rows``
    (:class:`~hbm.samplers.joint_gibbs.ReuseSpecimen`).  Chains start from the layer's hyper draws
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
    specs = {}
    for sid in h.specimens:
        idx = systematic_resample(np.asarray(h.updated_weights[sid], float), nc, rng)
        idx = rng.permutation(idx)  # systematic resampling sorts: pair rows with hyper draws at random
        if sid in exact_ids:
            y = coords.y_of(results[sid].samples)
            lik = _specimen_likelihood(cfg, results, sid, datasets, model)
            specs[sid] = ExactSpecimen(log_likelihood=_OnFibre(lik, coords), columns=coords.columns, box=coords.box,
                                       init=y[idx], scale_rows=y, pooled_cols=pooled_cols)
        else:
            specs[sid] = ReuseSpecimen(rows=rows[sid], log_prior=None if log_prior is None else log_prior[sid],
                                       init=idx)
    _log(f"exact fallback: joint Metropolis-within-Gibbs, {nc} chains, real likelihoods for "
         f"{', '.join(exact_ids)}", cfg.progress)
    c0 = time.process_time()
    # every kept draw is output (a subsample would only add Monte Carlo error); at least cfg.samples
    n_keep = max(int(cfg.exact_keep), -(-int(cfg.samples) // nc))
    g = joint_gibbs(h.model, raw0, specs, n_keep=n_keep, n_burn=int(cfg.exact_burn),
                    thin=int(cfg.exact_thin), seed=seeds.child(root, 1), progress=cfg.progress,
                    log=lambda m: _log(m, cfg.progress))
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
            "cpu_s": float(cpu)}
    _log(f"exact fallback: {sum(g.evaluations.values())} likelihood evaluations, {g.timings['total']:.1f} s; "
         f"max R-hat {worst_rhat:.3f}, min bulk ESS {min_ess:.0f}", cfg.progress)
    if worst_rhat > 1.05:
        # measured on the shipped six (600 kept sweeps): R-hat 1.22 after 600 burn-in sweeps, 1.27 after
        # 2000 -- slow mixing along the one-sided tails, not a short burn-in; so no "raise the burn-in"
        # advice (more kept sweeps do help: 400 + 1200 gave 1.16)
        _log(f"WARNING: exact fallback not converged (max R-hat {worst_rhat:.3f} > 1.05): its chains mix slowly "
             "along one-sided tails; read the population's tails with the report's gold-benchmark accuracy", True)
    return h, updated, info


def _check_exact(cfg: PopulationConfig) -> None:
    """Bad settings of the exact fallback and the tail options (HbmError)."""
    if cfg.groups and (cfg.reference or cfg.second_pass):
        # the grouped layer has no deterministic-mixture weights: reference rows would count as posterior draws
        raise HbmError("reference draws and the second pass are options of the two-level layer; not with groups")
    if cfg.exact is None:
        return
    if cfg.exact != "gibbs":
        raise HbmError(f"exact must be 'gibbs' or None, got {cfg.exact!r}")
    if min(int(cfg.exact_chains), int(cfg.exact_keep)) < 4 or int(cfg.exact_thin) < 1 or int(cfg.exact_burn) < 0:
        raise HbmError("exact='gibbs' needs exact_chains >= 4, exact_keep >= 4, exact_thin >= 1, exact_burn >= 0")


def _exact_applies(cfg: PopulationConfig, to_fix: Sequence[str], datasets=None, specimens=()) -> list[str]:
    """The specimens the exact fallback gives real likelihoods ([]: it does not run).

    It runs when asked for, with something to fix, on a two-level layer (the grouped layer keeps its
    refinements) without reference draws or second pass, and with the datasets of what it fixes;
    ``exact_all``: then every specimen whose dataset is at hand.
    """
    if (cfg.exact != "gibbs" or not to_fix or cfg.groups or cfg.reference or cfg.second_pass or datasets is None
            or any(sid not in datasets for sid in to_fix)):
        return []
    return sorted(sid for sid in specimens if sid in datasets) if cfg.exact_all else sorted(to_fix)


def _run_hierarchical_combinations(cfg: PopulationConfig, results: Mapping[str, io.SpecimenResult], datasets,
                                   out: Path | None, model, names: list, model_names: list, transforms: dict, cl=None):
    """``--pool combinations``: a population over φ = (log G, log c·P1, log (1−c)·T1), T2, THETA
    (+ EOPT when ``auto_pool`` would pool it), with the exact stage-1 prior density of φ.

    The φ columns are appended to the stage-1 samples (the other columns ride along), their
    stage-1 prior log density goes in as ``log_prior`` (see :mod:`hbm.combinations`), and a new
    specimen's (VOLF, P1, T1, GF, GM) are drawn from the box prior conditioned on its φ; its
    unpooled model parameters (EOPT if not pooled) from their stage-1 (uniform) prior, as the
    population model leaves them.  A specimen whose importance ESS collapses gets a fresh TMCMC
    run of p(θ_i | all data) over its own parameters, with the population density of φ(θ)
    divided by the stage-1 prior density of φ (:class:`_CombinationAugment`).
    """
    first = next(iter(results.values()))
    bounds = np.asarray(first.bounds, float)
    missing = [p for p in COMBINATION_NEEDS if p not in model_names]
    if missing:
        raise HbmError(f"--pool combinations needs free parameters {', '.join(missing)} (fixed or absent); "
                       f"use --pool informed")
    choice = auto_pool({sid: r.samples for sid, r in results.items()}, names, bounds, transforms,
                       candidates=model_names)
    extra = [n for n in model_names if n in ("EOPT", "T2", "THETA")
             and (n != "EOPT" or n in choice.pooled)]
    feats = {sid: combination_features(names, r.samples, bounds) for sid, r in results.items()}
    # box of the φ columns: the support hull of the combinations (a zero lower end, T1 from 0, is
    # floored; widened if a sample lies below the floor so every sample is inside)
    hull = np.log(support_hull(bounds, names))
    allphi = np.concatenate([f[0] for f in feats.values()])
    hull[:, 0] = np.minimum(hull[:, 0], allphi.min(axis=0) - 1e-9)
    hull[:, 1] = np.maximum(hull[:, 1], allphi.max(axis=0) + 1e-9)
    aug_names = list(names) + list(COMBINATION_COLUMNS)
    aug_bounds = np.vstack([bounds, hull])
    pooled = list(COMBINATION_COLUMNS) + extra
    tr = {**{c: "identity" for c in COMBINATION_COLUMNS}, **{n: transforms[n] for n in extra}}
    # stage-1 prior of the pooled columns: p0(φ) × uniform densities of the other pooled columns
    log_u = -float(sum(np.log(np.ptp(bounds[names.index(n)])) for n in extra))
    stage1 = {sid: (np.hstack([r.samples, feats[sid][0]]), r.log_evidence, r.log_evidence_se)
              for sid, r in results.items()}
    log_prior = {sid: feats[sid][1] + log_u for sid in results}
    reasons = {k: v["reason"] for k, v in choice.reasons.items()}
    reasons["combinations"] = ("--pool combinations: population over " + ", ".join(f"log {c}" for c in COMBINATIONS)
                               + f" (exact stage-1 prior density) and {', '.join(extra)}")
    _log(f"pooled (combinations): {', '.join(pooled)}", cfg.progress)
    more = _diagnostic_inputs(results)
    ref = _reference_rows(cfg, results, datasets, model, names, bounds, hull, feats)
    if ref:  # stage-1 samples + defensive reference draws, weighted as a deterministic mixture
        more.update(stage1_rows={sid: len(r.samples) for sid, r in results.items()},
                    log_weights={sid: ref[sid][2] for sid in results})
        stage1 = {sid: (np.vstack([v[0], ref[sid][0]]),) + tuple(v[1:]) for sid, v in stage1.items()}
        log_prior = {sid: np.concatenate([log_prior[sid], ref[sid][1] + log_u]) for sid in results}
        reasons["reference"] = (f"defensive reference draws: {cfg.reference:g} per stage-1 sample (Student-t "
                                f"{REFERENCE_DF:g} dof, {REFERENCE_SCALE:g} x the stage-1 sd); kept "
                                + ", ".join(f"{sid} {len(ref[sid][1])}" for sid in results))
    h, warn_msgs = _fit_population(cfg, stage1, aug_names, aug_bounds, tr, pooled, log_prior, extra=more)
    n_par = len(names)
    augment = _CombinationAugment(names, bounds, log_u)
    flagged = [sid for sid in h.specimens if (h.reuse.get(sid) or {}).get("unreliable")]
    if cfg.second_pass and flagged and datasets is not None and all(sid in datasets for sid in flagged):
        _log(f"reuse unreliable for {', '.join(flagged)}: second pass with draws of their posteriors under the "
             "population", cfg.progress)
        first_reuse = h.reuse
        stage1, log_prior, more = _mixture_pass(cfg, h, flagged, results, datasets, model, stage1, log_prior,
                                                augment, more)
        h, warn_more = _fit_population(cfg, stage1, aug_names, aug_bounds, tr, pooled, log_prior, extra=more)
        warn_msgs = _unique(list(warn_msgs) + list(warn_more))
        reasons["second_pass"] = ("second pass (posterior draws under the population appended) for "
                                  + ", ".join(f"{s} ({'; '.join(first_reuse[s].get('reasons') or [])})" for s in flagged))
        # the second pass's own diagnostics decide about refinement; the first pass's flags are kept
        for sid in flagged:
            h.reuse[sid]["reasons"] = ([f"first pass: {'; '.join(first_reuse[sid].get('reasons') or [])} -> "
                                        "posterior draws under the population added"]
                                       + list(h.reuse[sid].get("reasons") or []))
    updated = {s: np.asarray(h.updated[s])[:, :n_par] for s in h.specimens}
    collapsed = _to_refine(h, datasets)
    exact = None
    exact_ids = _exact_applies(cfg, collapsed, datasets, h.specimens)
    if exact_ids:
        coords = _PhiCoordinates(names, bounds, hull, log_u)
        h, exact_updated, exact = _exact_gibbs(cfg, h, exact_ids,
                                               results, datasets, model, {s: v[0] for s, v in stage1.items()},
                                               log_prior, coords)
        updated, collapsed = exact_updated, []
    else:
        updated.update(_refine_collapsed(cfg, h, collapsed, datasets, model, results, cl, augment=augment))
    # new specimen: pooled columns from the predictive, (VOLF, P1, T1, GF, GM) | φ from the box
    # prior, unpooled model parameters from their uniform stage-1 prior
    rng = seeds.rng(int(cfg.seed), "new_specimen")
    pred = np.asarray(h.predictive)
    # The normal population lives on the hull box of φ, but p0 (hence a real specimen) lives on a
    # smaller region (e.g. c·P1/P1_hi + (1−c)·T1/T1_hi ≤ 1): predictive draws outside it have no
    # parameters and are rejected (rejection sampling of the population restricted to the support).
    # The likelihood ignores that truncation mass Z_S(ψ); the rejected fraction, E_ψ[1 − Z_S(ψ)],
    # bounds its effect and goes into the attributes.
    inside = np.isfinite(log_density(pred[:, : len(COMBINATION_COLUMNS)], bounds, names))
    outside_fraction = float(1.0 - inside.mean())
    if not inside.any():
        raise HbmError("--pool combinations: every new-specimen draw lies outside the prior support of the "
                       "combinations; the population is not usable")
    pred = pred[inside]
    parts = sample_conditional(pred[:, : len(COMBINATION_COLUMNS)], bounds, rng, names)
    derived_cols = {p: parts[:, k] for k, p in enumerate(COMBINATION_PARAMS)}
    for n in model_names:
        if n not in derived_cols and n not in extra:
            lo, hi = bounds[names.index(n)]
            derived_cols[n] = rng.uniform(lo, hi, pred.shape[0])
    derived = [n for n in model_names if n in derived_cols]
    new = np.column_stack([pred] + [derived_cols[n] for n in derived])
    return _write_population(cfg, h, out, names, updated, new, list(h.names) + derived, warn_msgs, collapsed,
                             transforms=tr, pooled=pooled, pool_reasons=reasons, mode=POOL_COMBINATIONS,
                             derived=derived, outside_support_fraction=outside_fraction,
                             bounds={n: list(map(float, aug_bounds[aug_names.index(n)])) for n in pooled},
                             **({"exact": exact} if exact else {}))


def _run_hierarchical(cfg: PopulationConfig, results: Mapping[str, io.SpecimenResult], datasets,
                      out: Path | None, model, cl=None):
    """Hyper-posterior, ESS check (+ fresh TMCMC fallback), updated individuals -> hierarchical.nc."""
    model = spyrou_model() if model is None else model
    first = next(iter(results.values()))
    names = list(first.names)
    for sid, r in results.items():
        if list(r.names) != names or not np.allclose(r.bounds, first.bounds):
            raise HbmError(f"hierarchical: specimen {sid} was fitted with other parameters/boxes than "
                           f"{first.specimen_id}; re-run all specimens with the same settings")
        # stage-1 posteriors are reweighted by their prior, taken as uniform on the box
        logu = [n for n, p in (getattr(r, "prior", None) or {}).items() if p.get("form", "uniform") != "uniform"]
        if logu:
            raise HbmError(f"hierarchical: specimen {sid} was fitted with a non-uniform prior on "
                           f"{', '.join(logu)}; the population layer needs uniform stage-1 priors")
    model_names = [n for n in names if n in model.parameter_names]
    transforms = {n: DEFAULT_TRANSFORMS.get(n, "logit") for n in model_names}
    transforms.update({k: v for k, v in dict(cfg.transforms or {}).items() if k in model_names})
    for n in model_names:  # log needs a positive box
        if transforms[n] == "log" and first.bounds[names.index(n), 0] <= 0:
            transforms[n] = "logit"
    pool_reasons = None
    mode = _pool_mode(cfg.pooled, model_names)
    if mode == POOL_COMBINATIONS:
        return _run_hierarchical_combinations(cfg, results, datasets, out, model, names, model_names, transforms,
                                              cl=cl)
    if mode == POOL_INFORMED:  # parameters informed in at least half of the specimens
        choice = auto_pool({sid: r.samples for sid, r in results.items()}, names, first.bounds, transforms,
                           candidates=model_names)
        pool_reasons = {k: v["reason"] for k, v in choice.reasons.items()}
        model_names = choice.pooled
        _log(f"pooled (informed): {', '.join(model_names)}", cfg.progress)
    elif mode and mode != "all":
        if isinstance(mode, str):
            mode = [mode]
        bad = [p for p in mode if p not in model_names]
        if bad:
            raise HbmError(f"--pool: {', '.join(bad)} not among the free model parameters {', '.join(model_names)} "
                           f"(or auto, combinations, informed, all)")
        model_names = [n for n in model_names if n in mode]
    transforms = {n: transforms[n] for n in model_names}
    stage1 = {sid: (r.samples, r.log_evidence, r.log_evidence_se) for sid, r in results.items()}
    h, warn_msgs = _fit_population(cfg, stage1, names, first.bounds, transforms, model_names,
                                   extra=_diagnostic_inputs(results))
    updated = {sid: np.asarray(h.updated[sid]) for sid in h.specimens}
    collapsed = _to_refine(h, datasets)
    exact = None
    exact_ids = _exact_applies(cfg, collapsed, datasets, h.specimens)
    if exact_ids:
        h, updated, exact = _exact_gibbs(cfg, h, exact_ids, results,
                                         datasets, model, {s: v[0] for s, v in stage1.items()}, None,
                                         _PlainCoordinates(first.bounds, names))
        collapsed = []
    else:
        updated.update(_refine_collapsed(cfg, h, collapsed, datasets, model, results, cl))
    return _write_population(cfg, h, out, names, updated, h.predictive, h.names, warn_msgs, collapsed,
                             transforms=transforms, pooled=model_names, pool_reasons=pool_reasons,
                             mode=mode if isinstance(mode, str) else "list",
                             bounds={n: list(map(float, first.bounds[names.index(n)])) for n in model_names},
                             **({"exact": exact} if exact else {}))
