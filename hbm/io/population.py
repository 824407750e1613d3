"""The hierarchical layer's file (hyper-posterior, updated individuals, new-specimen predictive, groups, reuse diagnostics) and the population summary."""

from __future__ import annotations

import json
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Mapping, Sequence

import numpy as np
import xarray as xr

from .conventions import annotate, hyper_attrs
from .._version import __version__
from ..errors import HbmError
from ..samplers.types import StageInfo

from .common import (
    G_COMBOS, G_DIAG, G_GROUPS, G_MANIFOLD, G_NEW, G_POSTERIOR, G_STATS, G_UPDATED, _ds, _dumps, _open_tree,
    _write_tree)
from .specimen import _add_stage_stats, _read_stage_stats


# ----------------------------------------------------------------------------- hierarchical
@dataclass
class HierarchicalFile:
    """Contents of ``hierarchical.nc``.

    Attributes
    ----------
    param_names : list of str
        Stage-1 columns (columns of ``updated``).
    hyper_names : list of str
    hyper_samples : ndarray (n, k)
    specimen_ids : list of str
    updated : ndarray (n, S, d) or None
        Updated individual posteriors (shrunk toward the population), columns ``param_names``.
    new_specimen : ndarray (n, k) or None
        Pooled parameters (``pooled_names``) of a new, unseen specimen drawn from the
        hyper-posterior predictive.
    pooled_names : list of str
        Parameters with a population distribution (hyper-parameters ``mu_P``, ``sd_P``).
    log_evidence, log_evidence_se : float
        Hyper-evidence log p(all data | hyperprior family).
    stages : list of StageInfo (or mappings with a subset of its fields)
        Per stage of the hyper-level TMCMC; read back as :class:`StageInfo`.
    ess : ndarray (S,) or None
        Minimum per-specimen importance ESS over the hyper-posterior population.
    attrs : dict
        Extra metadata (JSON-able), e.g. transform, hyperprior, warnings.
    groups : dict or None
        The group level of a grouped layer: ``key`` (metadata key), ``names`` (groups),
        ``specimen_group`` ({specimen: group}), ``pooled`` (parameters), ``means`` and
        ``predictive`` (n, G, len(pooled)) and any JSON-able extras; None without groups.
    reuse : dict specimen -> dict
        Per-specimen reuse diagnostics of the stage-1 samples
        (:func:`hbm.samplers.hierarchical.reuse_diagnostics`): the numbers of :data:`REUSE_VARS`
        are stored as variables ``reuse_<name>`` over ``specimen`` in the diagnostics group,
        the flag as ``reuse_unreliable`` (0/1), the reasons in the attributes.
    chains : int
        The rows of ``hyper_samples`` and ``updated`` are this many chains, chain-major (stored over
        ``(chain, draw)``, so that ArviZ's R-hat and ESS of the file are those of the sampler's chains);
        1 for the reuse layer's TMCMC population and for files written before issue 37.
    evaluations : int or None
        Model evaluations of the layer (root attribute ``evaluations``); None when not recorded.
    """

    param_names: list[str]
    hyper_names: list[str]
    hyper_samples: np.ndarray
    specimen_ids: list[str]
    updated: np.ndarray | None = None
    new_specimen: np.ndarray | None = None
    log_evidence: float = float("nan")
    log_evidence_se: float = float("nan")
    stages: list[StageInfo | Mapping[str, Any]] = field(default_factory=list)
    ess: np.ndarray | None = None
    attrs: dict = field(default_factory=dict)
    complete: bool = True
    pooled_names: list[str] = field(default_factory=list)
    groups: dict | None = None
    reuse: dict = field(default_factory=dict)
    chains: int = 1
    evaluations: int | None = None

    def hyper(self, name: str) -> np.ndarray:
        return self.hyper_samples[:, self.hyper_names.index(name)]


def write_hierarchical(h: HierarchicalFile, path: str | os.PathLike) -> Path:
    """Write the hierarchical layer's results atomically."""
    path = Path(path)
    n, nc = h.hyper_samples.shape[0], int(h.chains)
    if nc < 1 or n % nc:
        raise HbmError(f"hierarchical result: {n} hyper draws do not split into {nc} chains")
    draws = {"chain": np.arange(nc), "draw": np.arange(n // nc)}
    transforms = dict(h.attrs.get("transforms") or {})
    hyper = h.hyper_samples.reshape(nc, n // nc, -1)
    post = xr.Dataset({nm: (("chain", "draw"), hyper[:, :, i], hyper_attrs(nm, transforms))
                       for i, nm in enumerate(h.hyper_names)}, coords=draws)
    groups: dict[str, xr.Dataset] = {G_POSTERIOR: annotate(post, "other")}
    stats: dict[str, Any] = {"log_marginal_likelihood": (("chain",), [float(h.log_evidence)]),
                             "log_marginal_likelihood_se": (("chain",), [float(h.log_evidence_se)])}
    coords: dict[str, Any] = {"chain": [0]}
    _add_stage_stats(stats, coords, h.stages)
    groups[G_STATS] = xr.Dataset(stats, coords=coords)
    if h.updated is not None:
        m = h.updated.shape[0]
        uc = nc if m == n else 1  # the updated individuals of the joint sampler are its chains' draws
        up = h.updated.reshape((uc, m // uc) + h.updated.shape[1:])
        groups[G_UPDATED] = xr.Dataset(
            {nm: (("chain", "draw", "specimen"), up[..., i]) for i, nm in enumerate(h.param_names)},
            coords={"chain": np.arange(uc), "draw": np.arange(m // uc), "specimen": list(h.specimen_ids)})
    if h.new_specimen is not None:
        m = h.new_specimen.shape[0]
        groups[G_NEW] = annotate(xr.Dataset({nm: (("chain", "draw"), h.new_specimen[None, :, i])
                                                         for i, nm in enumerate(h.pooled_names or h.param_names)},
                                                        coords={"chain": [0], "draw": np.arange(m)}), "parameters")
    diag_vars = _reuse_vars(h)
    if h.ess is not None:
        diag_vars["importance_ess"] = ("specimen", np.asarray(h.ess, float))
    if diag_vars:
        groups[G_DIAG] = xr.Dataset(diag_vars, coords={"specimen": list(h.specimen_ids)},
                                    attrs={"reuse_reasons": _dumps({k: list(v.get("reasons") or [])
                                                                    for k, v in h.reuse.items()})})
    if h.groups is not None:
        groups[G_GROUPS] = _groups_dataset(h.groups, h.specimen_ids)
    root_attrs = {"param_names": _dumps(list(h.param_names)), "pooled_names": _dumps(list(h.pooled_names or h.param_names)),
                  "specimen_ids": _dumps(list(h.specimen_ids)), "extra": _dumps(h.attrs), "hbm_version": __version__,
                  "complete": 0}
    if h.evaluations is not None:
        root_attrs["evaluations"] = int(h.evaluations)
    root = xr.Dataset(attrs=root_attrs)
    tree = xr.DataTree.from_dict({"/": root, **groups})
    return _write_tree(tree, path, h.complete)


def read_hierarchical(path: str | os.PathLike) -> HierarchicalFile:
    """Read ``hierarchical.nc``."""
    tree = _open_tree(path)
    post = _ds(tree, G_POSTERIOR)
    if post is None:
        raise HbmError(f"{path}: no '{G_POSTERIOR}' group; not an hbm hierarchical result")
    hn = [str(v) for v in post.data_vars]
    params = json.loads(tree.attrs.get("param_names", "[]"))
    ids = json.loads(tree.attrs.get("specimen_ids", "[]"))
    h = HierarchicalFile(param_names=params, hyper_names=hn,
                         hyper_samples=np.stack([post[v].values.reshape(-1) for v in hn], axis=1),
                         specimen_ids=ids, attrs=json.loads(tree.attrs.get("extra", "{}")),
                         complete=int(tree.attrs.get("complete", 0)) == 1,
                         pooled_names=json.loads(tree.attrs.get("pooled_names", "[]")) or list(params),
                         chains=int(post.sizes.get("chain", 1)),
                         evaluations=int(tree.attrs["evaluations"]) if "evaluations" in tree.attrs else None)
    stats = _ds(tree, G_STATS)
    if stats is not None:
        h.log_evidence = float(stats["log_marginal_likelihood"].values[0])
        h.log_evidence_se = float(stats["log_marginal_likelihood_se"].values[0])
        h.stages = _read_stage_stats(stats)
    up = _ds(tree, G_UPDATED)
    if up is not None:
        h.updated = np.stack([up[nm].values.reshape(-1, len(ids)) for nm in params], axis=-1)
    new = _ds(tree, G_NEW)
    if new is not None:
        h.new_specimen = np.stack([new[nm].values.reshape(-1) for nm in h.pooled_names], axis=-1)
    diag = _ds(tree, G_DIAG)
    if diag is not None:
        if "importance_ess" in diag:
            h.ess = diag["importance_ess"].values
        h.reuse = _read_reuse(diag, ids)
    grp = _ds(tree, G_GROUPS)
    if grp is not None:
        h.groups = _read_groups(grp)
    return h


_GROUP_ARRAYS = {"means": "mean", "predictive": "new_specimen"}


def _groups_dataset(g: Mapping[str, Any], specimen_ids: Sequence[str]) -> xr.Dataset:
    """The ``groups`` group of hierarchical.nc from :attr:`HierarchicalFile.groups`."""
    names, pooled = list(g["names"]), list(g["pooled"])
    data: dict[str, Any] = {}
    for key, prefix in _GROUP_ARRAYS.items():
        a = np.asarray(g[key], float)  # (n, G, d)
        data.update({f"{prefix}_{p}": (("chain", "draw", "group"), a[None, :, :, k]) for k, p in enumerate(pooled)})
    sg = dict(g["specimen_group"])
    data["specimen_group"] = ("specimen", [str(sg[s]) for s in specimen_ids])
    extra = {k: v for k, v in g.items() if k not in (*_GROUP_ARRAYS, "names", "pooled", "specimen_group", "key")}
    n = np.asarray(g["means"]).shape[0]
    return xr.Dataset(data, coords={"chain": [0], "draw": np.arange(n), "group": names, "specimen": list(specimen_ids)},
                      attrs={"key": str(g.get("key", "group")), "pooled": _dumps(pooled), "extra": _dumps(extra)})


def _read_groups(ds: xr.Dataset) -> dict:
    """:attr:`HierarchicalFile.groups` back from the ``groups`` group."""
    pooled = json.loads(ds.attrs.get("pooled", "[]"))
    out = {"key": str(ds.attrs.get("key", "group")), "names": [str(v) for v in ds["group"].values],
           "pooled": pooled,
           "specimen_group": dict(zip(map(str, ds["specimen"].values), map(str, ds["specimen_group"].values))),
           **json.loads(ds.attrs.get("extra", "{}"))}
    for key, prefix in _GROUP_ARRAYS.items():
        out[key] = np.stack([ds[f"{prefix}_{p}"].values[0] for p in pooled], axis=-1)
    return out


#: per-specimen reuse diagnostics stored as variables ``reuse_<name>`` of the diagnostics group
REUSE_VARS = ("khat_median", "khat_q90", "khat_frac", "khat_updated", "uncovered", "outside_measured",
              "population_outside", "population_beyond", "ess_q10", "ess_raw_q10")


def _reuse_vars(h: HierarchicalFile) -> dict[str, Any]:
    """The diagnostics-group variables of ``h.reuse`` (empty without diagnostics)."""
    if not h.reuse:
        return {}
    ids = list(h.specimen_ids)
    out = {f"reuse_{k}": ("specimen", np.array([float(h.reuse.get(s, {}).get(k, np.nan)) for s in ids]))
           for k in REUSE_VARS}
    out["reuse_unreliable"] = ("specimen", np.array([int(bool(h.reuse.get(s, {}).get("unreliable"))) for s in ids]))
    return out


def _read_reuse(diag: xr.Dataset, ids: Sequence[str]) -> dict:
    """``HierarchicalFile.reuse`` back from the diagnostics group ({} for files without it)."""
    if "reuse_unreliable" not in diag:
        return {}
    reasons = json.loads(diag.attrs.get("reuse_reasons", "{}"))
    out = {}
    for j, sid in enumerate(ids):
        r = {k: float(diag[f"reuse_{k}"].values[j]) for k in REUSE_VARS if f"reuse_{k}" in diag}
        r["unreliable"] = bool(diag["reuse_unreliable"].values[j])
        r["reasons"] = list(reasons.get(sid, []))
        out[sid] = r
    return out


# ----------------------------------------------------------------------------- population summary
def write_population_summary(path: str | os.PathLike, *, specimen_ids: Sequence[str],
                             manifolds: Mapping[str, Mapping[str, np.ndarray]] | None = None,
                             combinations: Mapping[str, Mapping[str, Sequence[float]]] | None = None,
                             attrs: Mapping[str, Any] | None = None) -> Path:
    """Write cross-specimen tables (``<out>/manifolds.nc``).

    Parameters
    ----------
    specimen_ids : sequence of str
    manifolds : {specimen: {"x": (g,), "y": (g,), "x_name": str, "y_name": str}}, optional
        Spline-evaluated manifold curves (e.g. VOLF -> T1), stored over (specimen, grid); curves
        of different length are NaN-padded.
    combinations : {quantity: {"mean": [...], "lower": [...], "upper": [...]}} per specimen, optional
    """
    groups: dict[str, xr.Dataset] = {}
    ids = list(specimen_ids)
    if manifolds:
        g = max(len(np.asarray(m["x"])) for m in manifolds.values())
        x = np.full((len(ids), g), np.nan)
        y = np.full((len(ids), g), np.nan)
        for i, sid in enumerate(ids):
            if sid in manifolds:
                mx, my = np.asarray(manifolds[sid]["x"], float), np.asarray(manifolds[sid]["y"], float)
                x[i, :mx.size], y[i, :my.size] = mx, my
        first = next(iter(manifolds.values()))
        groups[G_MANIFOLD] = xr.Dataset({"x": (("specimen", "grid"), x), "y": (("specimen", "grid"), y)},
                                        coords={"specimen": ids},
                                        attrs={"x_name": str(first.get("x_name", "x")),
                                               "y_name": str(first.get("y_name", "y"))})
    if combinations:
        cv = {}
        for q, stats in combinations.items():
            safe = q.replace("*", "_x_").replace("(", "").replace(")", "").replace("-", "m")
            for k, vals in stats.items():
                cv[f"{safe}__{k}"] = ("specimen", np.asarray(vals, float))
        groups[G_COMBOS] = xr.Dataset(cv, coords={"specimen": ids},
                                      attrs={"quantities": _dumps(list(combinations))})
    root = xr.Dataset(attrs={"specimen_ids": _dumps(ids), "extra": _dumps(dict(attrs or {})),
                             "hbm_version": __version__})
    tree = xr.DataTree.from_dict({"/": root, **groups})
    return _write_tree(tree, path, None)


def read_population_summary(path: str | os.PathLike) -> dict:
    """Read ``manifolds.nc`` back into ``{"manifolds": {...}, "specimen_ids": [...]}``."""
    tree = _open_tree(path)
    out: dict[str, Any] = {"specimen_ids": json.loads(tree.attrs.get("specimen_ids", "[]")), "manifolds": {}}
    man = _ds(tree, G_MANIFOLD)
    if man is not None:
        for i, sid in enumerate(out["specimen_ids"]):
            x, y = man["x"].values[i], man["y"].values[i]
            ok = np.isfinite(x) & np.isfinite(y)
            out["manifolds"][sid] = {"x": x[ok], "y": y[ok], "x_name": man.attrs.get("x_name"),
                                     "y_name": man.attrs.get("y_name")}
    return out
