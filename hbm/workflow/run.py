"""The six-rat workflow (``hbm run``): per-specimen fits on dask, hierarchical layer, manifolds, report.

Phases
------
1. **Specimens** (parallel, one dask task each, :func:`hbm.fit.fit_specimen`): CMA-ES optima with
   a VOLF bound sweep (the manifold), TMCMC posterior with evidence, posterior predictive, Sobol.
   Results go to ``<out>/specimens/<id>.nc``; a re-run skips complete files made with the same
   settings and resumes interrupted ones from ``<out>/checkpoints/``.
2. **Population layer** (:func:`hbm.population.run_population`, the hierarchical model over the
   fitted specimens, reusing the stage-1 samples) -> ``<out>/hierarchical.nc``.  ``hier_pooled``:
   "combinations" (the default for the base model: a population over what a uniaxial curve
   identifies), "informed", "all", a list of names, or "auto" (see :mod:`hbm.population`).
   Specimens with ``# group:`` lines, or grouped by ``group_by`` (any metadata key), get a
   population → group → specimen layer (:func:`hbm.data.specimen_groups`).
3. **Identifiability and manifolds** (:mod:`hbm.identifiability.views`): identifiable combinations, VOLF–T1
   manifold splines -> ``<out>/manifolds.nc``.
4. **Figures** (``<out>/figures/``) and the Markdown report (``<out>/report.md``); the run's
   settings and timings also go to ``<out>/run.json``.

Reproducibility: every stream comes from the seed table :mod:`hbm.runtime.seeds` (specimen ``k`` in sorted
id order, its phases, the population layer, refits).  Nothing depends on the
number of workers or on the order tasks finish.
"""

from __future__ import annotations

import contextlib
import dataclasses
import json
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Mapping, Sequence

import numpy as np

from ..io import identity
from .. import io
from ..runtime.blas import single_thread_env
from .._version import __version__
from ..data import GROUP_KEY, load_specimens, specimen_groups
from ..errors import DataError, HbmError
from ..fit.specimen import fit_specimen
from ..model import spyrou_model
from ..runtime.parallel import dask_client, map_specimens, spawn_specimen_seeds
from ..population import DEFAULT_SD_RANGE, PopulationConfig, run_population
from .report import write_report
from ..runtime.files import atomic_write_text, file_lock
from ..runtime.progress import log_progress as _log
from ..identifiability.views import identified_directions, manifold_spline

#: default output folder of hbm run and hbm fit: untracked (.gitignore), so that a run never replaces
#: the shipped reference results in results/
DEFAULT_OUT = "hbm-results"

__all__ = ["DEFAULT_OUT", "RunConfig", "WorkflowResult", "run_workflow", "fit_task"]



@dataclass
class RunConfig:
    """Settings of ``hbm run`` (see the CLI help for their meaning)."""

    data: str = "data/specimens"
    out: str = DEFAULT_OUT
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
    #: exact fallback of the population layer for flagged specimens ("gibbs") or None (reuse + TMCMC refinement)
    hier_exact: str | None = "gibbs"
    figures: bool = True
    progress: bool = True
    retries: int = 1
    quick: bool = False
    tmcmc_options: dict | None = None
    #: likelihood tier of every specimen's fit ("auto": collapsed where the model allows, or "full")
    likelihood: str = "auto"
    #: user prior (:meth:`hbm.likelihood.prior.Prior.to_dict`), or None for the model's box (uniform)
    prior: dict | None = None
    #: reference sarcomere length (µm) for files with a sarcomere_length_um column (``--sl0``)
    sl0: float | None = None
    #: metadata key whose values group the specimens (``--group-by``); None: ``# group:`` lines, if any
    group_by: str | None = None

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

    def fit_options(self, sigma_bounds: tuple[float, float]) -> dict:
        """The keyword arguments of every specimen's :func:`hbm.fit.fit_specimen` (all but data,
        seed and paths) -- the ONE settings record: the same dict runs the fits and keys their
        results and checkpoints (:func:`hbm.io.identity.fit_key`), so no setting can be forgotten."""
        return {"samples": self.samples, "kernel": self.kernel, "noise": self.noise, "fix": self.fix,
                "bounds": self.bounds, "restarts": self.restarts, "sweep": self.sweep,
                "sobol_n": self.sobol_n if self.sobol else None, "tmcmc_options": self.tmcmc_options,
                "optimize_options": {"maxfevals": self.maxfevals}, "sigma_bounds": tuple(sigma_bounds),
                "likelihood": self.likelihood,
                **({"prior": self.prior, "bounds": None} if self.prior else {})}

    def population_config(self) -> PopulationConfig:
        """The settings of the population layer (:func:`hbm.population.run_population`)."""
        return PopulationConfig(seed=self.seed, pooled=self.hier_pooled, samples=self.hier_samples,
                                max_steps=self.hier_max_steps, estimator=self.hier_estimator,
                                transforms=self.hier_transforms, sd_range=self.hier_sd_range,
                                stage1_samples=self.samples, noise=self.noise, fix=self.fix, bounds=self.bounds,
                                retries=self.retries, progress=self.progress, exact=self.hier_exact,
                                # a smoke run: the fallback's chains shorter too (a tenth of the draws kept)
                                **({"exact_burn": 200, "exact_keep": 12} if self.quick else {}))


def fit_task(data, *, seed, out_path: str, checkpoint: str, settings_hash: str, options: Mapping,
             identity_parts: Mapping[str, str] | None = None) -> str:
    """One dask task: fit one specimen and write ``out_path``; returns the path.

    ``settings_hash`` is the specimen's content key (:mod:`hbm.io.identity`), stored with the
    result together with its components ``identity_parts``.  A retried task (worker lost)
    resumes from the TMCMC checkpoint.  A file that is already complete with the same key is
    returned untouched (idempotent).
    """
    single_thread_env()
    if io.is_complete(out_path) and _stored_hash(out_path) == settings_hash:
        return out_path
    ck = Path(checkpoint)
    opts = dict(options)
    opts.setdefault("tmcmc_options", None)
    # the one writer rule: a concurrent 'hbm fit --out' of this file makes this specimen fail, not both
    with file_lock(out_path, "specimen result"):
        # the checkpoint folder carries the settings hash; fit_specimen names the file <dir>/<id>.npz
        fit_specimen(data, seed=seed, out=out_path, checkpoint_dir=ck.parent, progress=False,
                     config_extra={"settings_hash": settings_hash, "identity": dict(identity_parts or {})}, **opts)
    return out_path


def _drop_checkpoint(ckpt: Path) -> None:
    """Remove the checkpoint of a specimen whose result is complete (stale: never resumed)."""
    with contextlib.suppress(OSError):
        ckpt.unlink()
    with contextlib.suppress(OSError):
        ckpt.parent.rmdir()  # only if empty


def _stored_hash(path) -> str | None:
    """The content key a finished specimen file was computed under (None for older files)."""
    return io.read_attrs(path).get("config", {}).get("settings_hash")


def _stored_identity(path) -> dict | None:
    """The key's components stored with a finished specimen file (None for older files)."""
    return io.read_attrs(path).get("config", {}).get("identity")


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
    cfg = dataclasses.replace(config, **kwargs) if config is not None else RunConfig(**kwargs)
    t_all = time.perf_counter()
    out = Path(cfg.out)
    (out / "specimens").mkdir(parents=True, exist_ok=True)
    datasets = load_specimens(cfg.data, sl0=cfg.sl0)
    if cfg.hierarchical:  # a specimen without its group fails before any fit
        specimen_groups(datasets, cfg.group_by)
    ids = sorted(datasets)
    model = model if model is not None else spyrou_model()
    sigma_box = _common_sigma_box(datasets)
    options = cfg.fit_options(sigma_box)  # the one settings record (RunConfig.fit_options)
    # one content key per specimen (hbm.io.identity): its data, the model, the settings with its own seed
    specimen_seeds = spawn_specimen_seeds(cfg.seed, ids)
    keyed = {sid: identity.fit_key(datasets[sid], model, {**options, "seed": specimen_seeds[sid]}) for sid in ids}
    keys = {sid: keyed[sid][0] for sid in ids}
    parts = {sid: keyed[sid][1] for sid in ids}
    settings = identity.fit_record({**options, "seed": cfg.seed})  # for run.json
    paths = {sid: io.specimen_path(out, sid) for sid in ids}
    # a checkpoint is keyed by the content key: one made on other data or another model is never resumed
    ckpts = {sid: identity.checkpoint_dir(out / "checkpoints", sid, keys[sid]) / f"{sid}.npz" for sid in ids}
    other = identity.set_aside_checkpoints(out / "checkpoints", {sid: ckpts[sid].parent for sid in ids})
    if other:
        _log(f"{len(other)} checkpoint(s) of other data, model or settings set aside (not resumed): "
             f"{', '.join(str(p.relative_to(out)) for p in other)}", cfg.progress)
    todo, skipped = {}, []
    for sid in ids:
        complete = io.is_complete(paths[sid])
        if complete and _stored_hash(paths[sid]) == keys[sid]:
            skipped.append(sid)
            _drop_checkpoint(ckpts[sid])  # of a finished result (its removal failed or was interrupted)
            continue
        todo[sid] = datasets[sid]
        if complete:  # say why a finished result is not reused
            what = identity.changed(_stored_identity(paths[sid]), parts[sid])
            _log(f"{sid}: {', '.join(what) if what else 'result'} changed -- refitting", cfg.progress)
    _log(f"{len(ids)} specimens in {cfg.data}: {len(skipped)} complete (skipped), {len(todo)} to fit"
         + (f" ({sum(c.exists() for c in ckpts.values())} resuming from checkpoints)"
            if any(ckpts[s].exists() for s in todo) else ""), cfg.progress)
    options = {"model": model, **options}
    timings: dict[str, float] = {}
    if client is not None:
        ctx = contextlib.nullcontext(client)
    elif cfg.workers == 0 or not todo and not cfg.figures:
        ctx = contextlib.nullcontext(None)
    else:
        ctx = dask_client(cfg.workers, cfg.scheduler)
    with ctx as cl:
        wres = _phases(cfg, cl, datasets, ids, todo, skipped, paths, ckpts, (keys, parts), options, out, model,
                       timings)

    # ---- report
    t = time.perf_counter()
    timings["total_before_report"] = time.perf_counter() - t_all
    wres.report_path = write_report(wres, out / "report.md", extra_sections=extra_sections)
    timings["report"] = time.perf_counter() - t
    timings["total"] = time.perf_counter() - t_all
    run_info = {"settings": settings, "config": dataclasses.asdict(cfg), "specimens": ids, "skipped": skipped,
                "errors": wres.errors, "timings": timings, "hbm_version": __version__}
    atomic_write_text(out / "run.json", json.dumps(run_info, indent=2, default=io.json_default))
    _log(f"done in {timings['total']:.1f} s -> {wres.report_path}", cfg.progress)
    return wres


def _phases(cfg, cl, datasets, ids, todo, skipped, paths, ckpts, identities, options, out, model, timings):
    """Fits (dask), hierarchical layer, identifiability, figures (dask) -> WorkflowResult."""
    t = time.perf_counter()
    errors: dict[str, str] = {}
    task_times: dict[str, float] = {}
    if todo:
        keys, parts = identities
        mres = map_specimens(_fit_one, {sid: (todo[sid], str(paths[sid]), str(ckpts[sid]), keys[sid], parts[sid])
                                        for sid in todo},
                             seed=cfg.seed, client=cl, kwargs={"options": options},
                             prefix="fit", retries=cfg.retries, progress=cfg.progress,
                             checkpoints={sid: ckpts[sid] for sid in todo}, all_ids=ids)
        errors, task_times = mres.errors, mres.task_times
    timings["specimens_wall"] = time.perf_counter() - t
    for sid, msg in errors.items():  # (hbm run ends with one 'hbm: error:' line naming them)
        _log(f"specimen {sid} FAILED: {msg}", cfg.progress)

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
        hpath = out / "hierarchical.nc"
        # keyed over the specimen results it pools and its own settings: reused when none changed
        pop_cfg = _with_groups(cfg.population_config(), cfg, {sid: datasets[sid] for sid in results})
        hkey = identity.content_key({
            "specimens": identity.settings_key({sid: _stored_hash(paths[sid]) for sid in sorted(results)}),
            "population": identity.settings_key(pop_cfg.key_settings()),
            "model": identity.model_key(model), "version": __version__})
        stored = io.read_hierarchical(hpath) if io.is_complete(hpath) else None
        if stored is not None and stored.attrs.get("content_key") == hkey:
            _log("hierarchical layer: reused (unchanged specimens and settings)", cfg.progress)
            wres.hierarchical, wres.hierarchical_path = stored, hpath
            timings["hierarchical_reused"] = True   # the report must not present 0.2 s as the layer's cost
        else:
            _log(f"hierarchical layer over {len(results)} specimens", cfg.progress)
            wres.hierarchical, wres.hierarchical_path = run_population(results, datasets, model, config=pop_cfg,
                                                                       out=out, client=cl)
            if wres.hierarchical is not None and wres.hierarchical_path is not None:
                wres.hierarchical.attrs["content_key"] = hkey
                io.write_hierarchical(wres.hierarchical, wres.hierarchical_path)
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
        from ..plots import population as ppop  # matplotlib: loaded only when figures are drawn

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


def _with_groups(pop_cfg: PopulationConfig, cfg: RunConfig, datasets: Mapping) -> PopulationConfig:
    """The population settings with the fitted specimens' groups (``group_by`` / ``# group:``), if any."""
    try:
        groups = specimen_groups(datasets, cfg.group_by)
    except DataError as exc:  # checked on every specimen before the fits: failed fits left one group
        _log(f"WARNING: {exc} among the fitted specimens; one population without groups", True)
        return pop_cfg
    if groups is None:
        return pop_cfg
    return dataclasses.replace(pop_cfg, groups=groups, group_by=cfg.group_by or GROUP_KEY)


def _figures_task(path: str, fig_dir: str, model=None) -> list[str]:
    """Per-specimen figures from a result file (a dask task: matplotlib runs on the worker)."""
    from ..plots import specimen as pspec  # matplotlib, on the worker that draws

    r = io.read_specimen_result(path)
    return [str(p) for p in pspec.specimen_figures(r, fig_dir, model=model)]


def _fit_one(item, *, seed, options: Mapping) -> str:
    """map_specimens adapter: item = (dataset, out_path, checkpoint_path, content key, its parts)."""
    data, out_path, ckpt, key, parts = item
    return fit_task(data, seed=seed, out_path=out_path, checkpoint=ckpt, settings_hash=key, options=options,
                    identity_parts=parts)
