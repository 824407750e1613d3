"""The six-rat workflow (``hbm run``): per-specimen fits on dask, hierarchical layer, manifolds, report.

Phases
------
1. **Specimens** (parallel, one dask task each, :func:`hbm.fit.fit_specimen`): CMA-ES optima with
   a VOLF bound sweep (the manifold), TMCMC posterior with evidence, posterior predictive, Sobol.
   Results go to ``<out>/specimens/<id>.nc``; a re-run skips complete files made with the same
   settings and resumes interrupted ones from ``<out>/checkpoints/``.
2. **Hierarchical layer** (:func:`hbm.samplers.hierarchical.hierarchical`) on the model
   parameters, reusing the stage-1 samples -> ``<out>/hierarchical.nc``.  ``hier_pooled``:
   "combinations" (a population over log G, log c·P1, log (1−c)·T1, T2, THETA — what a uniaxial
   curve identifies — with the exact stage-1 prior density of the combinations,
   :mod:`hbm.combinations`), "informed" (the model parameters that the posteriors inform,
   :func:`~hbm.samplers.hierarchical.auto_pool`), "all", a list of names, or "auto" (default:
   "combinations" when VOLF, P1, T1, GF, GM, T2, THETA are free, otherwise "informed").
3. **Identifiability and manifolds**: identifiable combinations, VOLF–T1 manifold splines ->
   ``<out>/manifolds.nc``.
4. **Figures** (``<out>/figures/``) and the Markdown report (``<out>/report.md``); the run's
   settings and timings also go to ``<out>/run.json``.

Reproducibility: specimen ``k`` (in sorted id order) gets child ``k`` of ``SeedSequence(seed)``;
the hierarchical layer gets ``SeedSequence(seed, spawn_key=(10000,))``.  Nothing depends on the
number of workers or on the order tasks finish.
"""

from __future__ import annotations

import contextlib
import dataclasses
import hashlib
import json
import os
import sys
import time
import warnings
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Mapping, Sequence

import numpy as np

from . import io
from ._version import __version__
from .errors import HbmError
from .utils import atomic_write_text

__all__ = ["RunConfig", "WorkflowResult", "run_workflow", "fit_task", "DEFAULT_TRANSFORMS",
           "manifold_spline", "identified_directions", "specimen_variability", "population_table"]

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
_HIER_SPAWN = 10_000


@dataclass
class RunConfig:
    """Settings of ``hbm run`` (see the CLI help for their meaning)."""

    data: str = "data/specimens"
    out: str = "results"
    samples: int = 2000
    kernel: str = "rw"
    noise: str = "iid"
    workers: int | None = None
    scheduler: str | None = None
    seed: int = 0
    sobol: bool = True
    sobol_n: int = 1024
    restarts: int = 3
    sweep: str | None = "VOLF:0.07"
    maxfevals: int = 3000
    fix: dict | None = None
    bounds: dict | None = None
    hierarchical: bool = True
    hier_samples: int = 1000
    hier_max_steps: int = 25
    hier_pooled: list | str | None = "auto"
    hier_estimator: str = "raw"
    hier_transforms: dict | None = None
    hier_sd_range: tuple = DEFAULT_SD_RANGE
    figures: bool = True
    progress: bool = True
    retries: int = 1
    quick: bool = False
    tmcmc_options: dict | None = None

    def __post_init__(self) -> None:
        if self.quick:  # a smoke run: every phase, small budgets
            self.samples = min(self.samples, 500)
            self.restarts = min(self.restarts, 2)
            self.maxfevals = min(self.maxfevals, 2000)
            self.sweep = "VOLF:0.1" if self.sweep else None
            self.sobol_n = min(self.sobol_n, 128)
            self.hier_samples = min(self.hier_samples, 500)
        if self.kernel not in ("rw", "manifold"):
            raise HbmError(f"--kernel must be rw or manifold, got {self.kernel!r}")
        if int(self.samples) < 10:
            raise HbmError(f"--samples must be >= 10, got {self.samples}")

    def fit_settings(self) -> dict:
        """The settings that change a specimen's result (used to decide whether to re-fit)."""
        return {"samples": int(self.samples), "kernel": self.kernel, "noise": self.noise,
                "seed": int(self.seed), "sobol_n": int(self.sobol_n) if self.sobol else 0,
                "restarts": int(self.restarts), "sweep": self.sweep, "maxfevals": int(self.maxfevals),
                "fix": self.fix or None, "bounds": {k: list(map(float, v)) for k, v in (self.bounds or {}).items()}
                or None, "tmcmc_options": self.tmcmc_options or None, "version": __version__}


def _settings_hash(settings: Mapping) -> str:
    return hashlib.sha256(json.dumps(settings, sort_keys=True, default=str).encode()).hexdigest()[:12]


def fit_task(data, *, seed, out_path: str, checkpoint: str, settings_hash: str, options: Mapping) -> str:
    """One dask task: fit one specimen and write ``out_path``; returns the path.

    A retried task (worker lost) resumes from the TMCMC checkpoint.  A file that is already
    complete with the same settings is returned untouched (idempotent).
    """
    for k, v in (("OMP_NUM_THREADS", "1"), ("OPENBLAS_NUM_THREADS", "1"), ("MKL_NUM_THREADS", "1")):
        os.environ.setdefault(k, v)
    from .fit import fit_specimen

    if io.is_complete(out_path) and _stored_hash(out_path) == settings_hash:
        return out_path
    ck = Path(checkpoint)
    opts = dict(options)
    opts.setdefault("tmcmc_options", None)
    # the checkpoint folder carries the settings hash; fit_specimen names the file <dir>/<id>.npz
    fit_specimen(data, seed=seed, out=out_path, checkpoint_dir=ck.parent, progress=False,
                 config_extra={"settings_hash": settings_hash}, **opts)
    return out_path


def _stored_hash(path) -> str | None:
    return io.read_attrs(path).get("config", {}).get("settings_hash")


# ----------------------------------------------------------------------------- identifiability
def identified_directions(result: io.SpecimenResult) -> list[dict]:
    """Combinations of parameters that the specimen's posterior pins down (:func:`hbm.identify.identifiable_directions`).

    Returns
    -------
    list of dict
        ``{"expression", "ratio" (posterior/prior sd of the rounded combination), "median", "lo", "hi"}``,
        a sparse basis of the identified subspace, best first; empty when the samples are too few.
    """
    from .identify import identifiable_directions

    try:
        rep = identifiable_directions(result.samples, result.names, bounds=result.bounds)
    except HbmError:
        return []
    return [{"expression": d["label"], "ratio": float(d["sd_ratio_rounded"]), "median": float(d["median"]),
             "lo": float(d["lo"]), "hi": float(d["hi"])} for d in rep.directions]


def manifold_spline(result: io.SpecimenResult, n_grid: int = 60) -> dict | None:
    """The specimen's VOLF–T1 manifold (:func:`hbm.identify.volf_t1_manifold`) on a grid.

    Points: the CMA-ES sweep optima (one per VOLF window) when there are at least four distinct
    VOLF values, otherwise binned medians of the posterior samples.

    Returns
    -------
    dict or None
        ``{"x", "y" (grid), "points_x", "points_y", "x_name", "y_name", "source",
        "combination_rel_spread" (flatness of (1−VOLF)·T1 along the curve), "level", "object"}``;
        None when VOLF or T1 is fixed or the fit is impossible.
    """
    from .identify import volf_t1_manifold

    pts = [(o["params"]["VOLF"], o["params"]["T1"]) for o in (result.optima or [])
           if o.get("kind") == "sweep" and "VOLF" in o["params"] and "T1" in o["params"]]
    try:
        if len({round(p[0], 9) for p in pts}) >= 4:
            px, py = np.array(pts).T
            man = volf_t1_manifold(px, py, source="points")
            src = "CMA-ES sweep optima"
        elif "VOLF" in result.names and "T1" in result.names:
            man = volf_t1_manifold(result.column("VOLF"), result.column("T1"), source="samples")
            src = "posterior samples (binned medians)"
            px, py = man.knots_volf, np.exp(man.knots_log_t1)
        else:
            return None
    except HbmError:
        return None
    g = man.grid(n_grid)
    return {"x": g, "y": man(g), "points_x": np.asarray(px), "points_y": np.asarray(py), "x_name": "VOLF",
            "y_name": "T1", "source": src, "combination_rel_spread": float(man.flatness), "level":
            np.asarray(man.level, float), "object": man}


def specimen_variability(samples: Mapping[str, np.ndarray], *, log: bool = True) -> dict:
    """Do specimens differ in a quantity beyond their posterior uncertainty?

    Cochran's Q heterogeneity statistic on the posterior means (in log space for positive
    quantities) with the posterior sds as standard errors: Q = Σ (m_i − m̄_w)² / s_i² ~ χ²(S−1)
    under "all specimens share one value".  Also the pairs whose posterior difference excludes
    zero with 95 % probability.

    Returns
    -------
    dict
        ``{"Q", "df", "p_value", "separated_pairs": [(a, b), ...], "n_pairs"}``
    """
    from scipy.stats import chi2

    ids = sorted(samples)
    vals = {k: np.asarray(samples[k], float) for k in ids}
    if log and all(np.all(v > 0) for v in vals.values()):
        vals = {k: np.log(v) for k, v in vals.items()}
    m = np.array([v.mean() for v in vals.values()])
    s = np.array([v.std(ddof=1) for v in vals.values()])
    s = np.maximum(s, 1e-12 * (np.abs(m) + 1e-300))
    w = 1 / s ** 2
    mw = float((w * m).sum() / w.sum())
    q = float((w * (m - mw) ** 2).sum())
    df = len(ids) - 1
    pairs = []
    rng = np.random.default_rng(0)  # pairing of draws only; any fixed seed gives the same answer up to MC error
    for i in range(len(ids)):
        for j in range(i + 1, len(ids)):
            a, b = vals[ids[i]], vals[ids[j]]
            n = min(a.size, b.size)
            diff = rng.permutation(a)[:n] - rng.permutation(b)[:n]
            p = float((diff > 0).mean())
            if p > 0.975 or p < 0.025:
                pairs.append((ids[i], ids[j]))
    return {"Q": q, "df": df, "p_value": float(chi2.sf(q, df)) if df > 0 else float("nan"),
            "separated_pairs": pairs, "n_pairs": len(ids) * (len(ids) - 1) // 2}


def quantity_samples(names, theta) -> dict[str, np.ndarray]:
    """Identifiable combinations (G, VOLF*P1, (1-VOLF)*T1) plus T2, THETA, EOPT from rows of named parameters."""
    from .model import identifiable_combinations

    theta = np.asarray(theta, float)
    col = {n: theta[:, i] for i, n in enumerate(names)}
    out = {}
    if all(k in col for k in ("VOLF", "P1", "T1", "GF", "GM")):
        out.update({k: np.asarray(v) for k, v in identifiable_combinations(list(names), theta).items()})
    for k in ("T2", "THETA", "EOPT"):
        if k in col:
            out[k] = col[k]
    return out


def pooled_view(h) -> list[dict]:
    """The pooled columns of a hierarchical result in natural units, for tables and figures.

    A column ``log_X`` with the identity transform (``--pool combinations``) is shown as X with
    a log-normal population; log/logit columns are mapped back with g⁻¹.

    Returns
    -------
    list of dict
        Per pooled column with hyperparameters: ``name`` (column), ``display`` (quantity name),
        ``transform`` (of the displayed quantity: log, logit or identity), ``median`` (draws of
        the population median g⁻¹(mu) over the hyper-posterior), ``new`` (a new specimen's draws
        or None), ``sd`` (median population sd in transformed units), ``log_scale`` (bool).
    """
    from scipy.special import expit

    transforms = dict(h.attrs.get("transforms", {}))
    bounds = dict(h.attrs.get("bounds", {}))
    out = []
    for j, nm in enumerate(h.pooled_names):
        if f"mu_{nm}" not in h.hyper_names:  # derived column of the new specimen (--pool combinations)
            continue
        mu = np.asarray(h.hyper(f"mu_{nm}"), float)
        t = transforms.get(nm, "identity")
        new = None if h.new_specimen is None else np.asarray(h.new_specimen[:, j], float)
        display = nm
        if t == "identity" and nm.startswith("log_"):  # a pooled log-combination
            display, t = nm[4:], "log"
            mu_nat, new = np.exp(mu), (None if new is None else np.exp(new))
        elif t == "log":
            mu_nat = np.exp(mu)
        elif t == "logit":
            lo, hi = bounds.get(nm, (0.0, 1.0))
            mu_nat = lo + (hi - lo) * expit(mu)
        else:
            mu_nat = mu
        out.append({"name": nm, "display": display, "transform": t, "median": mu_nat, "new": new,
                    "sd": float(np.median(h.hyper(f"sd_{nm}"))), "log_scale": t == "log"})
    return out


def population_table(h, *, prob: float = 0.9) -> dict[str, dict[str, float]]:
    """Population estimates in natural units from the hierarchical result, keyed by quantity.

    ``median``: g⁻¹(mu) (the population median for logit/log/identity populations without
    active truncation), with its ``prob`` interval over the hyper-posterior; ``new_*``: the
    predictive distribution of a new specimen's value; ``sd_transformed``: the population sd
    in transformed units (log units for log-normal populations).
    """
    q = [(1 - prob) / 2, 0.5, (1 + prob) / 2]
    out = {}
    for v in pooled_view(h):
        a, b, c = np.quantile(v["median"], q)
        row = {"median": float(b), "median_lower": float(a), "median_upper": float(c),
               "sd_transformed": v["sd"], "transform": v["transform"]}
        if v["new"] is not None:
            na, nb, nc = np.quantile(v["new"], q)
            row.update(new_lower=float(na), new_median=float(nb), new_upper=float(nc))
        out[v["display"]] = row
    return out


# ----------------------------------------------------------------------------- the run
@dataclass
class WorkflowResult:
    """What :func:`run_workflow` produced (paths, in-memory results and timings)."""

    config: RunConfig
    out: Path
    specimen_paths: dict[str, Path]
    results: dict[str, io.SpecimenResult]
    skipped: list[str] = field(default_factory=list)
    errors: dict[str, str] = field(default_factory=dict)
    hierarchical_path: Path | None = None
    hierarchical: Any = None
    manifolds: dict = field(default_factory=dict)
    directions: dict = field(default_factory=dict)
    figures: list[Path] = field(default_factory=list)
    report_path: Path | None = None
    timings: dict = field(default_factory=dict)


def _log(msg: str, progress: bool) -> None:
    if progress:
        print(f"[hbm run] {msg}", file=sys.stderr, flush=True)


def _common_sigma_box(datasets: Mapping[str, Any]) -> tuple[float, float]:
    """One noise box for every specimen: the hierarchical layer needs a common stage-1 prior."""
    smax = max(float(np.max(np.abs(ds["stress"].values))) for ds in datasets.values())
    return (1e-4, max(0.05, 0.5 * smax))


def run_workflow(config: RunConfig | None = None, *, client=None, model=None,
                 extra_sections: Sequence[Callable[..., str]] | None = None, **kwargs) -> WorkflowResult:
    """Run the whole workflow (``hbm run``).

    Parameters
    ----------
    config : RunConfig, optional
        Settings; keyword arguments override/construct it (``run_workflow(data=..., out=...)``).
    client : distributed.Client, optional
        Use this client instead of creating one (``workers``/``scheduler`` are then ignored);
        ``config.workers == 0`` runs in-process without dask.
    model : Model, optional
        Default :func:`hbm.spyrou_model`.
    extra_sections : sequence of callables, optional
        Report hooks ``f(workflow_result) -> markdown str`` appended to the report (e.g. the
        organ-prediction section).

    Returns
    -------
    WorkflowResult
    """
    from .data import load_specimens
    from .parallel import dask_client

    cfg = dataclasses.replace(config, **kwargs) if config is not None else RunConfig(**kwargs)
    t_all = time.perf_counter()
    out = Path(cfg.out)
    (out / "specimens").mkdir(parents=True, exist_ok=True)
    datasets = load_specimens(cfg.data)
    ids = sorted(datasets)
    settings = cfg.fit_settings()
    sigma_box = _common_sigma_box(datasets)
    settings["sigma_bounds"] = list(sigma_box)
    shash = _settings_hash(settings)
    paths = {sid: io.specimen_path(out, sid) for sid in ids}
    ckpts = {sid: out / "checkpoints" / f"{sid}-{shash}" / f"{sid}.npz" for sid in ids}
    todo, skipped = {}, []
    for sid in ids:
        if io.is_complete(paths[sid]) and _stored_hash(paths[sid]) == shash:
            skipped.append(sid)
        else:
            todo[sid] = datasets[sid]
    _log(f"{len(ids)} specimens in {cfg.data}: {len(skipped)} complete (skipped), {len(todo)} to fit"
         + (f" ({sum(c.exists() for c in ckpts.values())} resuming from checkpoints)"
            if any(ckpts[s].exists() for s in todo) else ""), cfg.progress)
    options = {"model": model, "samples": cfg.samples, "kernel": cfg.kernel, "noise": cfg.noise,
               "fix": cfg.fix, "bounds": cfg.bounds, "restarts": cfg.restarts, "sweep": cfg.sweep,
               "sobol_n": cfg.sobol_n if cfg.sobol else None, "tmcmc_options": cfg.tmcmc_options,
               "optimize_options": {"maxfevals": cfg.maxfevals}, "sigma_bounds": sigma_box}
    timings: dict[str, float] = {}
    if client is not None:
        ctx = contextlib.nullcontext(client)
    elif cfg.workers == 0 or not todo and not cfg.figures:
        ctx = contextlib.nullcontext(None)
    else:
        ctx = dask_client(cfg.workers, cfg.scheduler)
    with ctx as cl:
        wres = _phases(cfg, cl, datasets, ids, todo, skipped, paths, ckpts, shash, options, out, model, timings)

    # ---- report
    t = time.perf_counter()
    from .report import write_report

    timings["total_before_report"] = time.perf_counter() - t_all
    wres.report_path = write_report(wres, out / "report.md", extra_sections=extra_sections)
    timings["report"] = time.perf_counter() - t
    timings["total"] = time.perf_counter() - t_all
    run_info = {"settings": settings, "config": dataclasses.asdict(cfg), "specimens": ids, "skipped": skipped,
                "errors": wres.errors, "timings": timings, "hbm_version": __version__}
    atomic_write_text(out / "run.json", json.dumps(run_info, indent=2, default=io.json_default))
    _log(f"done in {timings['total']:.1f} s -> {wres.report_path}", cfg.progress)
    return wres


def _phases(cfg, cl, datasets, ids, todo, skipped, paths, ckpts, shash, options, out, model, timings):
    """Fits (dask), hierarchical layer, identifiability, figures (dask) -> WorkflowResult."""
    from .parallel import map_specimens

    t = time.perf_counter()
    errors: dict[str, str] = {}
    task_times: dict[str, float] = {}
    if todo:
        mres = map_specimens(_fit_one, {sid: (todo[sid], str(paths[sid]), str(ckpts[sid])) for sid in todo},
                             seed=cfg.seed, client=cl, kwargs={"settings_hash": shash, "options": options},
                             prefix="fit", retries=cfg.retries, progress=cfg.progress,
                             checkpoints={sid: ckpts[sid] for sid in todo}, all_ids=ids)
        errors, task_times = mres.errors, mres.task_times
    timings["specimens_wall"] = time.perf_counter() - t
    for sid, msg in errors.items():
        _log(f"specimen {sid} FAILED: {msg}", True)

    results = {sid: io.read_specimen_result(paths[sid]) for sid in ids if io.is_complete(paths[sid])}
    for phase in ("cmaes", "tmcmc", "predictive", "sobol"):
        timings[f"{phase}_cpu"] = float(sum(r.timings.get(phase, 0.0) for r in results.values()))
    wres = WorkflowResult(config=cfg, out=out, specimen_paths={s: paths[s] for s in results},
                          results=results, skipped=skipped, errors=errors, timings=timings)
    timings["task_times"] = task_times  # type: ignore[assignment]

    # ---- per-specimen figures run on the workers while the client does the hierarchical layer
    fig_dir = out / "figures"
    fig_futures = {}
    if cfg.figures and results and cl is not None:
        fig_futures = {sid: cl.submit(_figures_task, str(paths[sid]), str(fig_dir), model,
                                      key=f"figures-{sid}", pure=False, retries=cfg.retries)
                       for sid in sorted(results)}

    # ---- hierarchical layer
    if cfg.hierarchical and len(results) >= 2:
        t = time.perf_counter()
        _log(f"hierarchical layer over {len(results)} specimens", cfg.progress)
        wres.hierarchical, wres.hierarchical_path = _run_hierarchical(cfg, results, datasets, out, model, cl)
        timings["hierarchical"] = time.perf_counter() - t

    # ---- identifiability and manifolds
    t = time.perf_counter()
    for sid, r in results.items():
        wres.directions[sid] = identified_directions(r)
        m = manifold_spline(r)
        if m is not None:
            wres.manifolds[sid] = m
    if wres.manifolds:
        io.write_population_summary(out / "manifolds.nc", specimen_ids=list(wres.manifolds),
                                    manifolds=wres.manifolds)
    timings["identify"] = time.perf_counter() - t

    # ---- figures
    if cfg.figures and results:
        t = time.perf_counter()
        _log("figures", cfg.progress)
        from .plots import population as ppop

        if fig_futures:
            for sid in sorted(fig_futures):
                try:
                    wres.figures += [Path(p) for p in fig_futures[sid].result()]
                except Exception as exc:  # a figure must not sink the run
                    _log(f"figures of {sid} failed: {type(exc).__name__}: {exc}", True)
        else:
            for sid in sorted(results):
                wres.figures += [Path(p) for p in _figures_task(str(paths[sid]), str(fig_dir), model)]
        try:
            wres.figures += ppop.population_figures(results, wres.hierarchical, wres.manifolds, fig_dir)
        except Exception as exc:  # a figure must not sink the run
            _log(f"population figures failed: {type(exc).__name__}: {exc}", True)
        timings["figures"] = time.perf_counter() - t
    return wres


def _figures_task(path: str, fig_dir: str, model=None) -> list[str]:
    """Per-specimen figures from a result file (a dask task: matplotlib runs on the worker)."""
    from .plots import specimen as pspec

    r = io.read_specimen_result(path)
    return [str(p) for p in pspec.specimen_figures(r, fig_dir, model=model)]


def _fit_one(item, *, seed, settings_hash: str, options: Mapping) -> str:
    """map_specimens adapter: item = (dataset, out_path, checkpoint_path)."""
    data, out_path, ckpt = item
    return fit_task(data, seed=seed, out_path=out_path, checkpoint=ckpt, settings_hash=settings_hash,
                    options=options)


def _refine_task(h, sid: str, lik, n_samples: int, seed: int, n_out: int, max_steps: int = 25,
                 n_hyper: int = 200, augment=None) -> np.ndarray:
    """Fresh TMCMC of one specimen's updated posterior; returns ``n_out`` equal-weight draws.

    The population prior is a mixture over ``n_hyper`` hyper-posterior draws (its cost is linear
    in n_hyper per particle); ``max_steps`` caps the MH steps per stage.  ``augment``: the map
    to pooled derived columns (``--pool combinations``), run over the likelihood's own box.
    """
    from .samplers.hierarchical import refine_individual

    extra = {} if augment is None else {"augment": augment, "bounds": lik.bounds}
    tr = refine_individual(h, sid, lik, n_samples=n_samples, seed=seed, progress=False, n_hyper=n_hyper,
                           max_steps=max_steps, **extra)
    rng = np.random.default_rng(seed)
    sel = rng.choice(tr.samples.shape[0], n_out, replace=tr.samples.shape[0] < n_out)
    return np.asarray(tr.samples)[sel]


#: ``--pool combinations``: pool the identifiable combinations instead of the raw parameters
COMBINATIONS = "combinations"
#: ``--pool informed``: pool the model parameters that the posteriors inform (auto_pool)
INFORMED = "informed"
#: pooled coordinates of ``--pool combinations`` (identity transform: they are logs already)
COMBINATION_COLUMNS = ("log_G", "log_VOLF*P1", "log_(1-VOLF)*T1")
#: model parameters ``--pool combinations`` needs free
COMBINATION_NEEDS = ("VOLF", "P1", "T1", "GF", "GM", "T2", "THETA")


def _pool_mode(pooled, model_names: Sequence[str]):
    """Resolve ``RunConfig.hier_pooled`` to "combinations", "informed", "all" or a list of names."""
    if isinstance(pooled, (list, tuple)) and len(pooled) == 1 and pooled[0] in ("auto", COMBINATIONS, INFORMED, "all"):
        pooled = pooled[0]  # the CLI splits --pool on commas
    if pooled in (None, "auto"):
        return COMBINATIONS if all(n in model_names for n in COMBINATION_NEEDS) else INFORMED
    return pooled


class _CombinationAugment:
    """θ (stage-1 columns) -> (θ + φ columns, stage-1 prior log density of the pooled columns).

    The map behind ``--pool combinations``, for the fresh-TMCMC fallback of collapsed specimens
    (:func:`hbm.samplers.hierarchical.refine_individual`); a class so that dask can ship it.
    """

    def __init__(self, names: Sequence[str], bounds: np.ndarray, log_u: float) -> None:
        self.names, self.bounds, self.log_u = list(names), np.asarray(bounds, float), float(log_u)

    def __call__(self, theta: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        from .combinations import log_density, to_features

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


def _refine_collapsed(cfg: RunConfig, h, collapsed: Sequence[str], datasets, model,
                      results: Mapping[str, io.SpecimenResult], cl=None, augment=None) -> dict[str, np.ndarray]:
    """Fresh TMCMC of p(θ_i | all data) for every specimen whose importance ESS collapsed.

    One dask task per specimen when a client is given; seeds spawned per specimen from the run
    seed, so the draws do not depend on the number of workers.
    """
    from .likelihood import make_likelihood

    if not collapsed:
        return {}
    _log(f"WARNING: importance ESS collapsed for {', '.join(collapsed)}: fresh TMCMC runs of their "
         "updated posteriors p(θ_i | all data)" + (" on dask" if cl is not None else ""), True)
    first = next(iter(results.values()))
    names = list(first.names)
    noise_col = len([n for n in names if n in model.parameter_names])  # first noise column (common box)
    sigma_bounds = tuple(first.bounds[noise_col]) if noise_col < len(names) else None
    n_up = next(iter(h.updated.values())).shape[0]
    jobs = {}
    h_ref = cl.scatter(h) if cl is not None else h
    for k, sid in enumerate(h.specimens):
        if sid not in collapsed:
            continue
        lik = make_likelihood(model, datasets[sid], noise=cfg.noise, fix=cfg.fix, bounds=cfg.bounds,
                              sigma_bounds=sigma_bounds)
        rs = int(np.random.SeedSequence(int(cfg.seed), spawn_key=(_HIER_SPAWN, 1 + k)).generate_state(
            1, np.uint64)[0] >> 1)
        args = (h_ref, sid, lik, min(int(cfg.hier_samples), int(cfg.samples)), rs, n_up, int(cfg.hier_max_steps))
        kw = {"augment": augment} if augment is not None else {}
        jobs[sid] = (cl.submit(_refine_task, *args, key=f"refine-{sid}", pure=False, retries=cfg.retries, **kw)
                     if cl is not None else _refine_task(*args, **kw))
    return {sid: (job.result() if cl is not None else job) for sid, job in jobs.items()}


def _fit_population(cfg: RunConfig, stage1: Mapping, names: Sequence[str], bounds, transforms: Mapping,
                    pooled: Sequence[str], log_prior: Mapping | None = None):
    """:func:`~hbm.samplers.hierarchical.hierarchical` with the run's settings and its own seed.

    Returns the result and its warnings (raised and kept ones, without repeats).
    """
    from .samplers.hierarchical import hierarchical

    # an int seed for the hierarchical layer, independent of the specimen streams
    seed = int(np.random.SeedSequence(int(cfg.seed), spawn_key=(_HIER_SPAWN,)).generate_state(1, np.uint64)[0] >> 1)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        h = hierarchical(stage1, names, bounds, transforms=transforms, pooled=pooled,
                         n_samples=int(cfg.hier_samples), seed=seed, progress=cfg.progress,
                         sd_range=tuple(cfg.hier_sd_range), estimator=cfg.hier_estimator, log_prior=log_prior,
                         # each ψ evaluation is a (n_ψ × 2d) @ (2d × Σ N_i) product: cap the MH steps per
                         # stage so the layer stays at tens of seconds for six specimens
                         tmcmc_options={"max_steps": int(cfg.hier_max_steps)})
    return h, _unique([str(w.message) for w in caught] + list(h.warnings))


def _write_population(cfg: RunConfig, h, out: Path, names: Sequence[str], updated: Mapping[str, np.ndarray],
                      new_specimen: np.ndarray, pooled_names: Sequence[str], warn_msgs: Sequence[str],
                      refined: Sequence[str], **attrs):
    """``<out>/hierarchical.nc`` from a hierarchical result; ``attrs``: the pooling mode's own attributes."""
    attrs.update({"estimator": cfg.hier_estimator, "log_evidence_parts": h.log_evidence_parts,
                  "warnings": list(warn_msgs), "refined": list(refined), "ess_summary": h.ess_summary,
                  "hyperprior": {"mu": "uniform on transformed box",
                                 "sd": f"loguniform on {tuple(cfg.hier_sd_range)} x mu range"}})
    hf = io.HierarchicalFile(param_names=list(names), hyper_names=list(h.hyper_names),
                             hyper_samples=np.asarray(h.hyper_samples), specimen_ids=list(h.specimens),
                             updated=np.stack([updated[s] for s in h.specimens], axis=1),
                             new_specimen=np.asarray(new_specimen), log_evidence=float(h.log_evidence),
                             log_evidence_se=float(h.log_evidence_se),
                             stages=list(getattr(h.sampler_result, "stages", [])),
                             ess=np.array([float(h.ess_summary[s]["min"]) for s in h.specimens]), attrs=attrs,
                             pooled_names=list(pooled_names))
    return hf, io.write_hierarchical(hf, out / "hierarchical.nc")


def _run_hierarchical_combinations(cfg: RunConfig, results: Mapping[str, io.SpecimenResult], datasets, out: Path,
                                   model, names: list, model_names: list, transforms: dict, cl=None):
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
    from .combinations import (COMBINATION_PARAMS, combination_features, log_density, sample_conditional,
                               support_hull)
    from .samplers.hierarchical import auto_pool

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
    reasons["combinations"] = ("--pool combinations: population over log G, log VOLF*P1, log (1-VOLF)*T1 "
                               f"(exact stage-1 prior density) and {', '.join(extra)}")
    _log(f"pooled (combinations): {', '.join(pooled)}", cfg.progress)
    h, warn_msgs = _fit_population(cfg, stage1, aug_names, aug_bounds, tr, pooled, log_prior)
    n_par = len(names)
    updated = {s: np.asarray(h.updated[s])[:, :n_par] for s in h.specimens}
    collapsed = sorted(sid for sid in h.specimens if h.ess_collapsed.get(sid))
    augment = _CombinationAugment(names, bounds, log_u)
    updated.update(_refine_collapsed(cfg, h, collapsed, datasets, model, results, cl, augment=augment))
    # new specimen: pooled columns from the predictive, (VOLF, P1, T1, GF, GM) | φ from the box
    # prior, unpooled model parameters from their uniform stage-1 prior
    rng = np.random.default_rng(np.random.SeedSequence(int(cfg.seed), spawn_key=(_HIER_SPAWN, 0)))
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
                             transforms=tr, pooled=pooled, pool_reasons=reasons, mode=COMBINATIONS,
                             derived=derived, outside_support_fraction=outside_fraction,
                             bounds={n: list(map(float, aug_bounds[aug_names.index(n)])) for n in pooled})


def _run_hierarchical(cfg: RunConfig, results: Mapping[str, io.SpecimenResult], datasets, out: Path, model,
                      cl=None):
    """Hyper-posterior, ESS check (+ fresh TMCMC fallback), updated individuals -> hierarchical.nc."""
    from .model import spyrou_model
    from .samplers.hierarchical import auto_pool

    model = spyrou_model() if model is None else model
    first = next(iter(results.values()))
    names = list(first.names)
    for sid, r in results.items():
        if list(r.names) != names or not np.allclose(r.bounds, first.bounds):
            raise HbmError(f"hierarchical: specimen {sid} was fitted with other parameters/boxes than "
                           f"{first.specimen_id}; re-run all specimens with the same settings")
    model_names = [n for n in names if n in model.parameter_names]
    transforms = {n: DEFAULT_TRANSFORMS.get(n, "logit") for n in model_names}
    transforms.update({k: v for k, v in dict(cfg.hier_transforms or {}).items() if k in model_names})
    for n in model_names:  # log needs a positive box
        if transforms[n] == "log" and first.bounds[names.index(n), 0] <= 0:
            transforms[n] = "logit"
    pool_reasons = None
    mode = _pool_mode(cfg.hier_pooled, model_names)
    if mode == COMBINATIONS:
        return _run_hierarchical_combinations(cfg, results, datasets, out, model, names, model_names, transforms,
                                              cl=cl)
    if mode == INFORMED:  # parameters informed in at least half of the specimens
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
    h, warn_msgs = _fit_population(cfg, stage1, names, first.bounds, transforms, model_names)
    updated = {sid: np.asarray(h.updated[sid]) for sid in h.specimens}
    collapsed = sorted(sid for sid in h.specimens if h.ess_collapsed.get(sid))
    updated.update(_refine_collapsed(cfg, h, collapsed, datasets, model, results, cl))
    return _write_population(cfg, h, out, names, updated, h.predictive, h.names, warn_msgs, collapsed,
                             transforms=transforms, pooled=model_names, pool_reasons=pool_reasons,
                             mode=mode if isinstance(mode, str) else "list",
                             bounds={n: list(map(float, first.bounds[names.index(n)])) for n in model_names})
