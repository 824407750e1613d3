"""The population layer's one driver: pool → sample (joint, or reuse + refinements) → new-specimen draw → write."""

from __future__ import annotations

import warnings
from pathlib import Path
from typing import Mapping, Sequence

import numpy as np

from .. import io
from ..runtime import seeds
from ..data.specimen import as_specimen
from ..errors import HbmError
from ..model import spyrou_model
from ..samplers.hierarchical import GroupedResult, grouped_hierarchical, hierarchical
from ..runtime.progress import log_progress as _log
from .config import PopulationConfig
from .fallbacks import refine_collapsed, to_refine
from .layer import sample_layer
from .pooling import Layout, pack_results, pooling_strategy

__all__ = ["run_population"]


def run_population(results: Mapping[str, io.SpecimenResult], datasets: Mapping | None = None, model=None, *,
                   config: PopulationConfig | None = None, out: str | Path | None = None, client=None,
                   **kwargs) -> tuple[io.HierarchicalFile, Path | None]:
    """Hierarchical layer over fitted specimens: hyper-posterior, updated individuals, a new specimen.

    Parameters
    ----------
    results : mapping of specimen id -> SpecimenResult
        Stage-1 results, all fitted with the same parameters and prior boxes.
    datasets : mapping of specimen id -> Specimen (or xarray.Dataset), optional
        The specimens' data (Datasets are converted once): the joint sampler (the default) needs them;
        without them the layer reuses the stage-1 samples (:func:`joint_applies`).
    model : Model, optional
        The stage-1 model; default :func:`hbm.spyrou_model`.
    config : PopulationConfig, optional
        Settings; keyword arguments override/construct it.
    out : path, optional
        Folder of ``hierarchical.nc``; None: nothing is written.
    client : distributed.Client, optional
        Run the joint sampler's shards as dask actors (when there are at least two) or the refinements
        of collapsed specimens as dask tasks; None: in this process.  The draws do not depend on it.

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
    cfg = config.replace(**kwargs) if config is not None else PopulationConfig(**kwargs)
    if len(results) < 2:
        raise HbmError(f"the population layer needs at least two specimens, got {len(results)}")
    model = spyrou_model() if model is None else model
    if datasets is not None:  # converted once (a Dataset of older code or a notebook becomes a Specimen)
        datasets = {sid: d if d is None else as_specimen(d) for sid, d in datasets.items()}
    data = pack_results(results, model, cfg)
    strategy = pooling_strategy(cfg.pooled, data)
    joint = joint_applies(cfg, datasets, results)
    layout = strategy.layout(data, cfg, joint=joint)
    out = None if out is None else Path(out)
    if joint:
        draws = sample_layer(cfg, data.results, datasets, model, layout, strategy, client)
        new, new_names, new_attrs = strategy.new_specimen(draws, cfg)
        return _write_joint(cfg, draws, out, data.names, new, new_names, {**layout.attrs, **new_attrs},
                            _bounds(layout))
    h, warn_msgs = _fit(cfg, layout.with_prior(), data.log_likelihood)
    updated = strategy.updated(h)
    to_fix = to_refine(h, datasets)
    updated.update(refine_collapsed(cfg, h, to_fix, datasets, model, results, client, augment=strategy.augment))
    new, new_names, new_attrs = strategy.new_specimen(h, cfg)
    attrs = {**layout.attrs, **new_attrs, "bounds": _bounds(layout)}
    return _write(cfg, h, out, data.names, updated, new, new_names, warn_msgs, to_fix, attrs)


def joint_applies(cfg: PopulationConfig, datasets, specimens) -> bool:
    """Whether the joint sampler runs (``exact="gibbs"``, a two-level layer, every dataset at hand); the
    reuse layer otherwise (a warning says why when the datasets are missing)."""
    if cfg.exact != "gibbs" or cfg.groups:
        return False
    missing = [sid for sid in specimens if datasets is None or sid not in datasets]
    if missing:
        _log(f"population layer: no dataset for {', '.join(sorted(missing))}: TMCMC over the population reusing "
             "the stage-1 samples instead of the joint sampler (pass datasets=...)", cfg.progress)
        return False
    return True


def _bounds(layout: Layout) -> dict:
    return {n: list(map(float, layout.bounds[layout.names.index(n)])) for n in layout.pooled}


def _write_joint(cfg: PopulationConfig, draws, out: Path | None, names: Sequence[str], new_specimen: np.ndarray,
                 pooled_names: Sequence[str], attrs: dict, bounds: dict):
    """The HierarchicalFile of the joint sampler, written to ``<out>/hierarchical.nc`` unless ``out`` is None."""
    info = draws.info
    attrs.update({"bounds": bounds, "layer": info, "warnings": list(info.get("warnings", [])),
                  "evaluations": int(info["evaluations"]), "refined": [],
                  "hyperprior": {"mu": "uniform on transformed box",
                                 "sd": f"loguniform on {cfg.sd_bounds(joint=True)} x mu range"}})
    hf = io.HierarchicalFile(param_names=list(names), hyper_names=list(draws.hyper_names),
                             hyper_samples=np.asarray(draws.hyper), specimen_ids=list(draws.specimens),
                             updated=np.stack([draws.updated[s] for s in draws.specimens], axis=1),
                             new_specimen=np.asarray(new_specimen), attrs=attrs, pooled_names=list(pooled_names),
                             chains=int(draws.chains), evaluations=int(info["evaluations"]))
    return hf, (io.write_hierarchical(hf, out / "hierarchical.nc") if out is not None else None)


def _unique(msgs: Sequence[str]) -> list[str]:
    """Messages in order without repeats (a warning is both raised and kept in the result)."""
    return list(dict.fromkeys(msgs))


def _fit(cfg: PopulationConfig, layout: Layout, log_likelihood: Mapping | None):
    """The two-level layer (stream ``hierarchical``) or, with groups, the grouped one (stream ``grouped``),
    with the run's settings; the stored stage-1 log-likelihoods feed the reuse diagnostics.

    Returns the result and its warnings (raised and kept ones, without repeats).
    """
    options = dict(transforms=layout.transforms, pooled=layout.pooled, n_samples=int(cfg.samples),
                   progress=cfg.progress, sd_range=cfg.sd_bounds(joint=False), estimator=cfg.estimator,
                   log_prior=layout.log_prior, tmcmc_options=cfg.tmcmc_options(), log_likelihood=log_likelihood)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        if cfg.groups:
            groups = {sid: cfg.groups.get(sid) for sid in layout.stage1}
            _log("groups" + (f" ({cfg.group_by})" if cfg.group_by else "") + ": " + ", ".join(
                f"{g} ({sum(v == g for v in groups.values())})" for g in sorted(set(groups.values()), key=str)),
                cfg.progress)
            h = grouped_hierarchical(layout.stage1, layout.names, layout.bounds, groups,
                                     seed=seeds.seed_int(seeds.stream(int(cfg.seed), "grouped")), **options)
        else:
            # an int seed for the hierarchical layer, independent of the specimen streams
            h = hierarchical(layout.stage1, layout.names, layout.bounds,
                             seed=seeds.seed_int(seeds.stream(int(cfg.seed), "hierarchical")), **options)
    return h, _unique([str(w.message) for w in caught] + list(h.warnings))


def _group_payload(cfg: PopulationConfig, h) -> dict | None:
    """The group level of a grouped result for :class:`hbm.io.HierarchicalFile` (None if ungrouped)."""
    if not isinstance(h, GroupedResult):
        return None
    return {"key": cfg.group_by or "group", "names": list(h.groups), "specimen_group": dict(h.specimen_group),
            "pooled": list(h.names), "means": np.asarray(h.group_means), "predictive": np.asarray(h.group_predictive),
            "hyperprior": {"group means": "normal(mu, sd_between) truncated to the range of mu",
                           "sd_between, sd_within": f"each loguniform on {cfg.sd_bounds(joint=False)} x mu range"}}


def _reuse_attrs(h) -> dict:
    """Per-specimen reuse diagnostics, JSON-able (hierarchical.nc stores them; the report shows them)."""
    return {sid: {k: v for k, v in r.items() if k != "uncovered_by"} for sid, r in (getattr(h, "reuse", None) or {}).items()}


def _write(cfg: PopulationConfig, h, out: Path | None, names: Sequence[str], updated: Mapping[str, np.ndarray],
           new_specimen: np.ndarray, pooled_names: Sequence[str], warn_msgs: Sequence[str], refined: Sequence[str],
           attrs: dict):
    """The HierarchicalFile of a hierarchical result, written to ``<out>/hierarchical.nc`` unless ``out`` is
    None; ``attrs``: the pooling strategy's own attributes."""
    attrs.update({"method": "reuse", "estimator": cfg.estimator, "log_evidence_parts": h.log_evidence_parts,
                  "warnings": list(warn_msgs), "refined": list(refined), "ess_summary": h.ess_summary,
                  "hyperprior": {"mu": "uniform on transformed box",
                                 "sd": f"loguniform on {cfg.sd_bounds(joint=False)} x mu range"}})
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
