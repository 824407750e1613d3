"""Across-specimen figures: VOLF–T1 manifolds, forest plot, hyper-posterior densities."""

from __future__ import annotations

import os
from pathlib import Path
from typing import Mapping

import numpy as np
from matplotlib.lines import Line2D
from matplotlib.patches import Patch

from ..identifiability.views import pooled_view, quantity_samples
from ..model.spec import ModelSpec, spec_of
from . import plt, save

__all__ = ["manifold_plot", "forest_plot", "hyper_plot", "population_figures", "FOREST_QUANTITIES"]



def forest_quantities(spec: ModelSpec) -> tuple[str, ...]:
    """Quantities shown in the forest plot: the spec's combinations (identified ones first), its shape parameters."""
    return spec.combination_names + spec.shape_parameters


def _label(spec: ModelSpec, name: str) -> str:
    """A panel title: the quantity's prose form and unit."""
    units = spec.units()
    text = next((c.text for c in spec.combinations if c.name == name), name)
    return f"{text} ({units[name]})" if name in units else text


#: the default base's forest quantities
FOREST_QUANTITIES = forest_quantities(spec_of())


def _colors(n):
    cmap = plt.get_cmap("tab10")
    return [cmap(i % 10) for i in range(n)]


def manifold_plot(manifolds: Mapping[str, dict], results=None, *, path=None):
    """VOLF–T1 manifolds of all specimens (spline + points), and (1−VOLF)·T1 along them."""
    ids = sorted(manifolds)
    fig, (a1, a2) = plt.subplots(1, 2, figsize=(12, 4.8))
    for sid, c in zip(ids, _colors(len(ids))):
        m = manifolds[sid]
        x, y = np.asarray(m["x"]), np.asarray(m["y"])
        a1.plot(x, y, color=c, lw=1.8, label=sid)
        a1.plot(m["points_x"], m["points_y"], "o", color=c, ms=3.5, mec="k", mew=0.3)
        a2.plot(x, (1 - x) * y, color=c, lw=1.8, label=sid)
        a2.plot(m["points_x"], (1 - np.asarray(m["points_x"])) * np.asarray(m["points_y"]), "o", color=c, ms=3.5,
                mec="k", mew=0.3)
    # limits from the fitted points: an interpolating spline may overshoot between sparse knots
    py_all = np.concatenate([np.asarray(manifolds[s]["points_y"], float) for s in ids]) if ids else np.ones(1)
    pp_all = np.concatenate([(1 - np.asarray(manifolds[s]["points_x"], float)) * np.asarray(manifolds[s]["points_y"])
                             for s in ids]) if ids else np.ones(1)
    py_all, pp_all = py_all[py_all > 0], pp_all[pp_all > 0]
    if py_all.size:
        a1.set_ylim(py_all.min() / 2, py_all.max() * 2)
    if pp_all.size:
        a2.set_ylim(pp_all.min() / 2, pp_all.max() * 2)
    a1.set_yscale("log")
    a1.set_xlabel("VOLF c (-)")
    a1.set_ylabel("T1 (MPa, log scale)")
    src = manifolds[ids[0]].get("source", "") if ids else ""
    a1.set_title(f"VOLF–T1 manifolds (dots: {src}; lines: shape-preserving cubic spline)", fontsize=9)
    a1.legend(fontsize=8)
    a2.set_yscale("log")
    a2.set_xlabel("VOLF c (-)")
    a2.set_ylabel("(1−c)·T1 (MPa, log scale)")
    a2.set_title("(1−c)·T1 along each manifold (flat: the product is what the data identify)", fontsize=9)
    fig.tight_layout()
    return save(fig, path) if path is not None else fig


def forest_plot(results: Mapping, hier=None, *, prob: float = 0.9, path=None):
    """Per quantity: each specimen's individual (stage-1) and updated (hierarchical) 90 % intervals,
    and the population (predictive of a new specimen) at the bottom."""
    ids = sorted(results)
    q = [(1 - prob) / 2, 0.5, (1 + prob) / 2]
    spec = spec_of(results[ids[0]]) if ids else spec_of()
    indiv = {sid: quantity_samples(list(results[sid].as_dict()),
                                   np.column_stack(list(results[sid].as_dict().values())), spec) for sid in ids}
    quantities = [k for k in forest_quantities(spec) if all(k in indiv[s] for s in ids)]
    upd, pop = {}, None
    if hier is not None and hier.updated is not None:
        for k, sid in enumerate(hier.specimen_ids):
            upd[sid] = quantity_samples(hier.param_names, hier.updated[:, k, :], spec)
        if hier.new_specimen is not None:
            pop = quantity_samples(hier.pooled_names, hier.new_specimen, spec)
    ncol = 3
    nrow = int(np.ceil(len(quantities) / ncol))
    fig, axes = plt.subplots(nrow, ncol, figsize=(4.3 * ncol, 0.45 * (len(ids) + 2) * nrow + 1.2), squeeze=False)
    for ax, k in zip(axes.ravel(), quantities):
        for r, sid in enumerate(ids):
            y = len(ids) - r
            lo, med, hi = np.quantile(indiv[sid][k], q)
            ax.plot([lo, hi], [y + 0.15] * 2, color="#636363", lw=2)
            ax.plot(med, y + 0.15, "o", color="#636363", ms=4)
            if sid in upd and k in upd[sid]:
                lo, med, hi = np.quantile(upd[sid][k], q)
                ax.plot([lo, hi], [y - 0.15] * 2, color="#d95f02", lw=2)
                ax.plot(med, y - 0.15, "s", color="#d95f02", ms=4)
        if pop is not None and k in pop:
            lo, med, hi = np.quantile(pop[k], q)
            ax.plot([lo, hi], [0, 0], color="#1b9e77", lw=3)
            ax.plot(med, 0, "D", color="#1b9e77", ms=5)
            ax.axvspan(lo, hi, color="#1b9e77", alpha=0.08)
        ax.set_yticks(list(range(len(ids), 0, -1)) + ([0] if pop is not None else []),
                      ids + (["population (new specimen)"] if pop is not None else []), fontsize=7)
        vals = np.concatenate([indiv[s][k] for s in ids])
        if np.all(vals > 0) and np.quantile(vals, 0.99) / max(np.quantile(vals, 0.01), 1e-300) > 30:
            ax.set_xscale("log")
        ax.set_title(_label(spec, k), fontsize=9)
        ax.grid(axis="x", alpha=0.3)
    for ax in axes.ravel()[len(quantities):]:
        ax.axis("off")
    handles = [Line2D([], [], color="#636363", marker="o", lw=2, label="individual posterior (own data)"),
               Line2D([], [], color="#d95f02", marker="s", lw=2, label="updated (hierarchical, all data)"),
               Line2D([], [], color="#1b9e77", marker="D", lw=3, label="population: new specimen")]
    fig.legend(handles=handles, loc="upper center", ncol=3, fontsize=8, frameon=False, bbox_to_anchor=(0.5, 1.0))
    fig.suptitle(f"{int(prob * 100)}% intervals per specimen", y=1.04, fontsize=10)
    fig.tight_layout(rect=(0, 0, 1, 0.96))
    return save(fig, path) if path is not None else fig


def hyper_plot(hier, results=None, *, path=None):
    """Hyper-posterior: density of each pooled quantity's population median g⁻¹(mu) (natural
    units) and of a new specimen's value; lines: the specimens' posterior means."""
    view = pooled_view(hier)
    ncol = max(1, min(4, len(view)))  # no empty panels when few quantities are pooled
    nrow = int(np.ceil(len(view) / ncol))
    fig, axes = plt.subplots(nrow, ncol, figsize=(3.6 * ncol, 2.7 * nrow), squeeze=False)
    means = {}
    spec = spec_of(next(iter(results.values()))) if results else spec_of()
    if results:
        means = {sid: {k: float(np.mean(v)) for k, v in quantity_samples(
            list(results[sid].as_dict()), np.column_stack(list(results[sid].as_dict().values())),
            spec_of(results[sid])).items()} for sid in sorted(results)}
    for ax, v in zip(axes.ravel(), view):
        med, new = v["median"], v["new"]
        allv = np.concatenate([med] + ([new] if new is not None else []))
        if v["log_scale"]:
            bins = np.geomspace(max(allv.min(), 1e-300), allv.max(), 50)
            ax.set_xscale("log")
        else:
            bins = np.linspace(allv.min(), allv.max(), 50)
        # probability per bin (bins equal in log on a log axis): density=True would be per linear unit
        # and inflate the narrow low bins of a log axis
        ax.hist(med, bins=bins, weights=np.full(med.size, 1.0 / med.size), color="#1b9e77", alpha=0.7)
        if new is not None:
            ax.hist(new, bins=bins, weights=np.full(new.size, 1.0 / new.size), histtype="step", color="k", lw=1.2)
        for sid, m in means.items():
            if v["display"] in m:
                ax.axvline(m[v["display"]], color="#d95f02", lw=0.8, alpha=0.8)
        ax.set_title(f"{_label(spec, v['display'])}\n({v['transform']}; median population sd "
                     f"{v['sd']:.2g})", fontsize=8.5)
        ax.set_yticks([])
    for ax in axes.ravel()[len(view):]:
        ax.axis("off")
    handles = [Patch(color="#1b9e77", alpha=0.7, label="hyper-posterior of the population median g⁻¹(mu)"),
               Line2D([], [], color="k", label="predictive of a new specimen"),
               Line2D([], [], color="#d95f02", label="specimens' posterior means")]
    ev = f"hyper-evidence log Z = {hier.log_evidence:.2f} ± {hier.log_evidence_se:.2f}"
    fig.suptitle(f"Hierarchical layer ({ev})", y=0.995, fontsize=11)
    fig.legend(handles=handles, loc="upper center", ncol=3, fontsize=8, frameon=False, bbox_to_anchor=(0.5, 0.955))
    fig.tight_layout(rect=(0, 0, 1, 0.9))
    return save(fig, path) if path is not None else fig


def population_figures(results: Mapping, hier, manifolds: Mapping, fig_dir: str | os.PathLike) -> list[Path]:
    """All across-specimen figures into ``fig_dir``."""
    fig_dir = Path(fig_dir)
    out = []
    if manifolds:
        out.append(manifold_plot(manifolds, results, path=fig_dir / "manifolds_volf_t1.png"))
    if results:
        out.append(forest_plot(results, hier, path=fig_dir / "forest.png"))
    if hier is not None:
        out.append(hyper_plot(hier, results, path=fig_dir / "hyperposterior.png"))
    return out
