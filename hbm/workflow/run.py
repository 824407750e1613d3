"""The six-rat workflow (``hbm run``): per-specimen fits on dask, hierarchical layer, manifolds, report.

Phases
------
1. **Specimens** (parallel, one dask task each, :func:`hbm.fit.fit_specimen`): CMA-ES optima with
   a VOLF bound sweep (the manifold), TMCMC posterior with evidence, posterior predictive, Sobol.
   Results go to ``<out>/specimens/<id>.nc``; a re-run skips complete files made with the same
   settings and resumes interrupted ones from ``<out>/checkpoints/``.  When the population layer runs in
   this process (it needs the posteriors only), each fit is two tasks: the TMCMC posterior first
   (:func:`hbm.fit.specimen.fit_posterior`), then, beside the layer and at a lower priority on the embedded
   cluster, the optima, sweep, Sobol indices, file and figures (:func:`hbm.fit.specimen.complete_fit`; the
   same file).
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
import json
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Mapping, Sequence

import numpy as np

from ..io import identity
from .. import io, plots  # plots.population/.specimen (matplotlib) load when figures are drawn
from ..runtime.blas import single_thread_env
from .._version import __version__
from ..data import GROUP_KEY, load_specimens, specimen_groups
from ..data.modes import check_along_fibre
from ..errors import DataError
from ..fit.specimen import complete_fit, fit_posterior, fit_specimen
from ..model import spyrou_model
from ..model.spec import sweep_parameter
from ..runtime.parallel import (background_priority, beside_this_process, dask_client, map_specimens,
                                spawn_specimen_seeds, submit_specimens)
from ..population import layer_rules, run_population, shards_on_workers
from ..settings import DEFAULT_OUT, FitRecord, FitSettings, PopulationSettings, RunSettings
from .report import write_report
from ..runtime.files import atomic_write_text, file_lock
from ..runtime.progress import log_progress as _log
from ..identifiability.views import identified_directions, manifold_spline

__all__ = ["DEFAULT_OUT", "RunConfig", "RunSettings", "WorkflowResult", "run_workflow", "fit_task"]

#: the settings of a run (:class:`hbm.settings.RunSettings`; ``RunConfig`` is its older name)
RunConfig = RunSettings


def fit_task(data, *, out_path: str, checkpoint: str, settings_hash: str, settings: FitSettings, model=None,
             identity_parts: Mapping[str, str] | None = None) -> str:
    """One dask task: fit one specimen and write ``out_path``; returns the path.

    ``settings`` are the specimen's (its own seed included), ``settings_hash`` its content key
    (:mod:`hbm.io.identity`), stored with the result together with its components
    ``identity_parts``.  A retried task (worker lost) resumes from the TMCMC checkpoint.  A file
    that is already complete with the same key is returned untouched (idempotent).
    """
    single_thread_env()
    # the checkpoint folder carries the settings hash; fit_specimen names the file <dir>/<id>.npz
    _write_once(out_path, settings_hash, lambda: fit_specimen(
        data, model=model, settings=settings, out=out_path, checkpoint_dir=Path(checkpoint).parent, progress=False,
        config_extra={"settings_hash": settings_hash, "identity": dict(identity_parts or {})}))
    return out_path


def _write_once(out_path: str, key: str, write: Callable[[], Any]) -> None:
    """Run ``write`` (which writes ``out_path``) unless the file is complete with content key ``key`` (a task
    is idempotent), under the one writer rule: a concurrent 'hbm fit --out' of this file makes this specimen
    fail, not both."""
    if io.is_complete(out_path) and _stored_hash(out_path) == key:
        return
    with file_lock(out_path, "specimen result"):
        write()


def _drop_checkpoint(ckpt: Path) -> None:
    """Remove the checkpoint of a specimen whose result is complete (stale: never resumed)."""
    with contextlib.suppress(OSError):
        ckpt.unlink()
    with contextlib.suppress(OSError):
        ckpt.parent.rmdir()  # only if empty


def _stored_hash(path) -> str | None:
    """The content key a finished specimen file was computed under (None for older files)."""
    return FitRecord.from_attrs(io.read_attrs(path).get("config")).settings_hash


def _stored_identity(path) -> dict | None:
    """The key's components stored with a finished specimen file (None for older files)."""
    return FitRecord.from_attrs(io.read_attrs(path).get("config")).identity


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
    smax = max(float(np.max(np.abs(spec.stress))) for spec in datasets.values())
    return (1e-4, max(0.05, 0.5 * smax))


def run_workflow(config: RunConfig | None = None, *, client=None, model=None,
                 extra_sections: Sequence[Callable[..., str]] | None = None, **kwargs) -> WorkflowResult:
    """Run the whole workflow (``hbm run``).

    Parameters
    ----------
    config : RunSettings, optional
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
    cfg = config.replace(**kwargs) if config is not None else RunSettings(**kwargs)
    model = model if model is not None else spyrou_model()
    swept = sweep_parameter(model)  # the default sweep: the model's manifold fraction, unless it is fixed
    cfg = cfg.with_sweep(swept if swept not in (cfg.fix or {}) else None,
                         model.spec.manifold.sweep_width if swept is not None else 0.07)
    t_all = time.perf_counter()
    out = Path(cfg.out)
    datasets = load_specimens(cfg.data, sl0=cfg.sl0)
    check_along_fibre(datasets, cfg.data)  # checked by the CLI already; here for the Python entry
    (out / "specimens").mkdir(parents=True, exist_ok=True)
    if cfg.hierarchical:  # a specimen without its group fails before any fit
        specimen_groups(datasets, cfg.group_by)
    ids = sorted(datasets)
    sigma_box = _common_sigma_box(datasets)
    # the one settings record of every specimen's fit: it runs the fit and keys its result and checkpoint
    # (hbm.io.identity: the data, the model, the settings with the specimen's own seed)
    specimen_seeds = spawn_specimen_seeds(cfg.seed, ids)
    fit_settings = {sid: cfg.fit_settings(sigma_box, seed=specimen_seeds[sid]) for sid in ids}
    keyed = {sid: identity.fit_key(datasets[sid], model, fit_settings[sid]) for sid in ids}
    keys = {sid: keyed[sid][0] for sid in ids}
    parts = {sid: keyed[sid][1] for sid in ids}
    settings = cfg.fit_settings(sigma_box).record()  # for run.json
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
    timings: dict[str, float] = {}
    if client is not None:
        ctx = contextlib.nullcontext(client)
    elif cfg.workers == 0 or not todo and not cfg.figures:
        ctx = contextlib.nullcontext(None)
    else:
        ctx = dask_client(cfg.workers, cfg.scheduler)
    with ctx as cl:
        wres = _phases(cfg, cl, datasets, ids, todo, skipped, paths, ckpts, (keys, parts), fit_settings, out, model,
                       timings)

    # ---- report
    t = time.perf_counter()
    timings["total_before_report"] = time.perf_counter() - t_all
    wres.report_path = write_report(wres, out / "report.md", extra_sections=extra_sections)
    timings["report"] = time.perf_counter() - t
    timings["total"] = time.perf_counter() - t_all
    run_info = {"settings": settings, "config": cfg.to_attrs(), "specimens": ids, "skipped": skipped,
                "errors": wres.errors, "timings": timings, "hbm_version": __version__}
    atomic_write_text(out / "run.json", json.dumps(run_info, indent=2, default=io.json_default))
    _log(f"done in {timings['total']:.1f} s -> {wres.report_path}", cfg.progress)
    return wres


def _phases(cfg, cl, datasets, ids, todo, skipped, paths, ckpts, identities, fit_settings, out, model, timings):
    """Fits (dask), hierarchical layer, identifiability, figures (dask) -> WorkflowResult."""
    t = time.perf_counter()
    errors: dict[str, str] = {}
    task_times: dict[str, float] = {}
    keys, parts = identities
    fig_dir = out / "figures"
    # the layer needs the specimens' posteriors only: with the layer in this process, their optima, sweep,
    # Sobol indices and figures run on the workers beside it (the TMCMC phase first, on every worker)
    split = (bool(todo) and cl is not None and cfg.hierarchical and len(ids) >= 2
             and not shards_on_workers(len(ids), cl))
    pending = None
    posteriors: dict[str, io.SpecimenResult] = {}
    if todo and split:
        mres = map_specimens(_posterior_one, {sid: (todo[sid], str(ckpts[sid]), keys[sid], parts[sid],
                                                    fit_settings[sid]) for sid in todo},
                             seed=cfg.seed, client=cl, kwargs={"model": model}, prefix="posterior",
                             retries=cfg.retries, progress=cfg.progress, checkpoints={sid: ckpts[sid] for sid in todo},
                             all_ids=ids)
        errors, task_times, posteriors = dict(mres.errors), dict(mres.task_times), dict(mres.values)
        pending = submit_specimens(
            _complete_one, {sid: (posteriors[sid], todo[sid], str(paths[sid]), str(ckpts[sid]), keys[sid], parts[sid],
                                  fit_settings[sid], str(fig_dir) if cfg.figures else None) for sid in sorted(posteriors)},
            seed=cfg.seed, client=cl, kwargs={"model": model, "background": beside_this_process(cl)}, prefix="fit",
            retries=cfg.retries, all_ids=ids)
    elif todo:
        mres = map_specimens(_fit_one, {sid: (todo[sid], str(paths[sid]), str(ckpts[sid]), keys[sid], parts[sid],
                                              fit_settings[sid]) for sid in todo},
                             seed=cfg.seed, client=cl, kwargs={"model": model},
                             prefix="fit", retries=cfg.retries, progress=cfg.progress,
                             checkpoints={sid: ckpts[sid] for sid in todo}, all_ids=ids)
        errors, task_times = mres.errors, mres.task_times
    timings["specimens_wall"] = time.perf_counter() - t
    for sid, msg in errors.items():  # (hbm run ends with one 'hbm: error:' line naming them)
        _log(f"specimen {sid} FAILED: {msg}", cfg.progress)

    # in a split run a specimen being fitted has no result yet (an older file of it is being replaced)
    results = {sid: io.read_specimen_result(paths[sid]) for sid in ids
               if io.is_complete(paths[sid]) and not (pending is not None and sid in todo)}
    # what the layer pools: the finished results and, in a split run, the new posteriors
    pooled = {sid: posteriors[sid] if sid in posteriors else results[sid] for sid in ids
              if sid in posteriors or sid in results}
    wres = WorkflowResult(config=cfg, out=out, specimen_paths={s: paths[s] for s in results},
                          results=results, skipped=skipped, errors=errors, timings=timings)

    # ---- per-specimen figures run on the workers while the client does the hierarchical layer -- after it when
    # the layer's shards run on those workers (they would share the cores: 96 specimens, 582 s against 415 s);
    # in a split run the specimens fitted now draw theirs in their completing task
    fig_futures: dict = {}

    def submit_figures() -> None:
        if cfg.figures and results and cl is not None:
            fig_futures.update({sid: cl.submit(_figures_task, str(paths[sid]), str(fig_dir), model,
                                               key=f"figures-{sid}", pure=False, retries=cfg.retries)
                                for sid in sorted(results)})

    layer_on_workers = cfg.hierarchical and len(pooled) >= 2 and shards_on_workers(len(pooled), cl)
    if not layer_on_workers:
        submit_figures()

    # ---- hierarchical layer
    if cfg.hierarchical and len(pooled) >= 2:
        t = time.perf_counter()
        hpath = out / "hierarchical.nc"
        # keyed over the specimen results it pools (the content key each carries) and its own settings: reused
        # when none changed
        pop_cfg = _with_groups(cfg.population_settings(), cfg, {sid: datasets[sid] for sid in pooled})
        hkey = identity.content_key({
            "specimens": identity.settings_key({sid: _fit_key(pooled[sid]) for sid in sorted(pooled)}),
            "population": identity.settings_key(pop_cfg.record()), "rules": layer_rules(),
            "model": identity.model_key(model), "version": __version__})
        stored = io.read_hierarchical(hpath) if io.is_complete(hpath) else None
        if stored is not None and stored.attrs.get("content_key") == hkey:
            _log("hierarchical layer: reused (unchanged specimens and settings)", cfg.progress)
            wres.hierarchical, wres.hierarchical_path = stored, hpath
            timings["hierarchical_reused"] = True   # the report must not present 0.2 s as the layer's cost
        else:
            _log(f"hierarchical layer over {len(pooled)} specimens"
                 + (" (their optima, sweep and Sobol indices beside it on the workers)" if pending is not None
                    else ""), cfg.progress)
            wres.hierarchical, wres.hierarchical_path = run_population(pooled, datasets, model, config=pop_cfg,
                                                                       out=out, client=cl)
            if wres.hierarchical is not None and wres.hierarchical.evaluations is not None:
                timings["hierarchical_evaluations"] = int(wres.hierarchical.evaluations)  # type: ignore[assignment]
            if wres.hierarchical is not None and wres.hierarchical_path is not None:
                wres.hierarchical.attrs["content_key"] = hkey
                io.write_hierarchical(wres.hierarchical, wres.hierarchical_path)
        timings["hierarchical"] = time.perf_counter() - t
    if layer_on_workers:
        submit_figures()
    split_figures: list[Path] = []
    if pending is not None:
        t = time.perf_counter()
        split_figures = _complete_beside_layer(pending, cfg, errors, task_times, pooled_layer=wres.hierarchical)
        timings["specimens_extras_wait"] = time.perf_counter() - t
        timings["specimens_extras_beside_layer"] = True  # type: ignore[assignment]
        # the run's results as an unsplit run defines them: every complete file
        results = {sid: io.read_specimen_result(paths[sid]) for sid in ids if io.is_complete(paths[sid])}
        wres.results, wres.specimen_paths = results, {s: paths[s] for s in results}
    for phase in ("cmaes", "tmcmc", "predictive", "sobol"):
        timings[f"{phase}_cpu"] = float(sum(r.timings.get(phase, 0.0) for r in results.values()))
    timings["task_times"] = task_times  # type: ignore[assignment]

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
        wres.figures += split_figures
        if cl is not None:  # drawn by tasks: submit_figures' and, in a split run, the completing ones
            for sid in sorted(fig_futures):
                try:
                    wres.figures += [Path(p) for p in fig_futures[sid].result()]
                except Exception as exc:  # a figure must not sink the run
                    _log(f"figures of {sid} failed: {type(exc).__name__}: {exc}", True)
        else:
            for sid in sorted(results):
                wres.figures += [Path(p) for p in _figures_task(str(paths[sid]), str(fig_dir), model)]
        try:
            wres.figures += plots.population.population_figures(results, wres.hierarchical, wres.manifolds, fig_dir)
        except Exception as exc:  # a figure must not sink the run
            _log(f"population figures failed: {type(exc).__name__}: {exc}", True)
        timings["figures"] = time.perf_counter() - t
    return wres


def _with_groups(pop_cfg: PopulationSettings, cfg: RunSettings, datasets: Mapping) -> PopulationSettings:
    """The population settings with the fitted specimens' groups (``group_by`` / ``# group:``), if any."""
    try:
        groups = specimen_groups(datasets, cfg.group_by)
    except DataError as exc:  # checked on every specimen before the fits: failed fits left one group
        _log(f"WARNING: {exc} among the fitted specimens; one population without groups", True)
        return pop_cfg
    if groups is None:
        return pop_cfg
    return pop_cfg.replace(groups=groups, group_by=cfg.group_by or GROUP_KEY)


def _figures_task(path: str, fig_dir: str, model=None) -> list[str]:
    """Per-specimen figures from a result file (a dask task: matplotlib runs on the worker)."""
    r = io.read_specimen_result(path)
    return [str(p) for p in plots.specimen.specimen_figures(r, fig_dir, model=model)]


def _fit_one(item, *, seed, model) -> str:
    """map_specimens adapter: item = (specimen, out_path, checkpoint_path, content key, its parts, its settings);
    ``seed`` (the specimen's stream of the seed table) is already the settings' seed."""
    data, out_path, ckpt, key, parts, settings = item
    return fit_task(data, out_path=out_path, checkpoint=ckpt, settings_hash=key, settings=settings, model=model,
                    identity_parts=parts)


def _complete_beside_layer(pending, cfg, errors: dict, task_times: dict, pooled_layer) -> list[Path]:
    """Wait for a split run's completing tasks: their errors and times join the run's; returns their figures."""
    _log("specimens: optima, sweep and Sobol indices", cfg.progress)
    done = pending.wait(progress=cfg.progress)
    for sid, msg in done.errors.items():
        _log(f"specimen {sid} FAILED: {msg}" + (" (its posterior is in the population layer)"
                                                if pooled_layer is not None else ""), cfg.progress)
    errors.update(done.errors)
    figures: list[Path] = []
    for sid in sorted(done.values):
        task_times[sid] = task_times.get(sid, 0.0) + done.task_times[sid]
        figures += [Path(f) for f in done.values[sid]["figures"]]
        if done.values[sid]["figure_error"]:
            _log(f"figures of {sid} failed: {done.values[sid]['figure_error']}", True)
    return figures


def _fit_key(result: io.SpecimenResult) -> str | None:
    """The content key a specimen result was computed under (stored with it; None for older files)."""
    return FitRecord.from_attrs(result.config).settings_hash


def _posterior_one(item, *, seed, model) -> io.SpecimenResult:
    """map_specimens adapter of a split run's first task: item = (specimen, checkpoint, content key, its parts,
    its settings) -> the posterior (:func:`hbm.fit.specimen.fit_posterior`; nothing written but the checkpoint)."""
    single_thread_env()
    data, ckpt, key, parts, settings = item
    return fit_posterior(data, model=model, settings=settings, checkpoint_dir=Path(ckpt).parent,
                         config_extra={"settings_hash": key, "identity": dict(parts or {})})


def _complete_one(item, *, seed, model, background: bool = False) -> dict:
    """map_specimens adapter of a split run's second task: the posterior's optima, sweep and Sobol indices,
    written as the one result file (:func:`hbm.fit.specimen.complete_fit`), then its figures.  Returns
    ``{"path", "figures", "figure_error"}`` (a figure must not sink the specimen).  ``background``: the
    worker shares the machine with the layer, which gets the priority
    (:func:`hbm.runtime.parallel.background_priority`)."""
    single_thread_env()
    if background:
        background_priority()
    posterior, data, out_path, ckpt, key, parts, settings, fig_dir = item
    _write_once(out_path, key, lambda: complete_fit(posterior, data, model=model, settings=settings,
                                                    checkpoint_dir=Path(ckpt).parent, out=out_path))
    figures, error = [], None
    if fig_dir is not None:
        try:
            figures = _figures_task(out_path, fig_dir, model)
        except Exception as exc:  # noqa: BLE001 -- reported by the run, the result stands
            error = f"{type(exc).__name__}: {exc}"
    return {"path": out_path, "figures": figures, "figure_error": error}
