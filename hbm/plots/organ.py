"""Organ-scale prediction figures (thesis Figs. 3.64–3.66) from :class:`hbm.io.OrganFile` curves.

* :func:`specimen_organ_plot`: one specimen's force–elongation bands (posterior, hierarchical
  updated individual) with the extrapolated part hatched/dashed, and the largest fiber strain
  against the tested strain (Fig. 3.64 style);
* :func:`overlay_plot`: all specimens (and the new-specimen predictive) overlaid (Fig. 3.66);
* :func:`optima_plot`: one specimen's near-optimal CMA-ES sets overlaid, with their relative
  differences (Fig. 3.65).

Force is on the vertical axis, elongation on the horizontal one (a force–elongation test plot).
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Mapping

import numpy as np

from ..model.spec import spec_of
from . import plt, save

__all__ = ["specimen_organ_plot", "overlay_plot", "optima_plot", "organ_figures"]

SOURCE_STYLE = {"posterior": ("#08519c", "specimen posterior"),
                "updated": ("#d95f02", "hierarchical: updated individual"),
                "population": ("#636363", "new specimen (population predictive)")}
_EXT_COLOR = "#fcbba1"


def _split_at(share: np.ndarray) -> int:
    """First force index where at least half of the draws are extrapolated (len if none)."""
    hit = np.flatnonzero(share >= 0.5)
    return int(hit[0]) if hit.size else share.size


def _band(ax, ds, color, label, *, alpha=0.35, lw=1.6, band=True):
    """Median (solid in the tested range, dashed beyond) and 90% band (hatched beyond)."""
    F = ds["force"].values
    lo, med, hi = ds["elongation"].values
    k = _split_at(ds["extrapolated_share"].values)
    kk = min(k + 1, F.size)  # overlap one point so the two pieces join
    if band:
        ax.fill_betweenx(F[:kk], lo[:kk], hi[:kk], color=color, alpha=alpha, lw=0)
        if k < F.size:
            ax.fill_betweenx(F[k:], lo[k:], hi[k:], color=color, alpha=alpha * 0.4, lw=0)
            ax.fill_betweenx(F[k:], lo[k:], hi[k:], facecolor="none", edgecolor=color, hatch="//",
                             alpha=0.35, lw=0)
    ax.plot(med[:kk], F[:kk], color=color, lw=lw, label=label)
    if k < F.size:
        ax.plot(med[k:], F[k:], color=color, lw=lw, ls="--")
    return k


def specimen_organ_plot(sid: str, curves: dict, *, geometry_name: str = "", path=None):
    """Force–elongation bands of one specimen and its largest fiber strain vs the tested strain.

    Parameters
    ----------
    sid : str
    curves : {source: Dataset}
        Band datasets of :mod:`hbm.workflow.organ` (``"posterior"``, optionally ``"updated"``).
    geometry_name : str
    path : path, optional
        Save there (PNG) and return the path; else return the figure.
    """
    fig, (a1, a2) = plt.subplots(1, 2, figsize=(11.5, 4.6), sharey=True,
                                 gridspec_kw={"width_ratios": [1.5, 1]})
    post = curves["posterior"]
    F = post["force"].values
    tested = float(post.attrs["tested_max_strain"])
    k = _split_at(post["extrapolated_share"].values)
    for src in ("posterior", "updated"):
        if src in curves:
            col, lab = SOURCE_STYLE[src]
            _band(a1, curves[src], col, f"{lab}: median, 90% band", alpha=0.35 if src == "posterior" else 0.25)
            lo, med, hi = curves[src]["max_strain"].values
            a2.fill_betweenx(F, lo, hi, color=col, alpha=0.3 if src == "posterior" else 0.2, lw=0)
            a2.plot(med, F, color=col, lw=1.4, label=f"largest fiber strain ({src})")
    fr = float(post.attrs.get("ref_force", np.nan))
    q = post["elongation_at_ref"].values
    if np.isfinite(fr) and np.isfinite(q).all() and fr <= F[-1]:
        a1.errorbar([q[1]], [fr], xerr=[[q[1] - q[0]], [q[2] - q[1]]], fmt="o", ms=4, color="k", capsize=3,
                    lw=1, zorder=6,
                    label=f"at F_ref = {fr:.3g} N: δ = {q[1]:.3g} [{q[0]:.3g}, {q[2]:.3g}] mm (90%)")
    mid = post["mid_strain"].values[1]
    a2.plot(mid, F, color="#08519c", lw=1, ls=":", label="mid-belly fiber strain (posterior median)")
    a2.axvline(tested, color="#cb181d", lw=1.2, label=f"largest strain tested on {sid} ({tested:.3g})")
    if k < F.size:
        for ax in (a1, a2):
            ax.axhspan(F[k], F[-1], color=_EXT_COLOR, alpha=0.35, lw=0, zorder=0)
        a1.axhline(F[k], color="#cb181d", lw=0.8, ls=":")
        a1.text(0.98, F[k], f"F = {F[k]:.3g} N: organ strain leaves the tested range\n"
                            "(≥ 50% of draws) — extrapolation above (dashed, hatched)",
                ha="right", va="bottom", fontsize=7.5, color="#99000d", transform=a1.get_yaxis_transform())
    a1.set_xlabel("organ elongation δ (mm)")
    a1.set_ylabel("axial force F (N)")
    a1.set_xlim(left=0)
    a1.set_ylim(0, F[-1])
    a1.legend(fontsize=7.5, loc="upper left")
    a1.set_title(f"{sid}: force–elongation of the {geometry_name or 'fusiform muscle'}", fontsize=10)
    a2.set_xlabel("fiber strain λ − 1 (-)")
    a2.set_xlim(left=0)
    a2.legend(fontsize=7.5, loc="upper left")
    a2.set_title("largest fiber strain (thinnest section) vs tested strain", fontsize=10)
    fig.tight_layout()
    return save(fig, path) if path is not None else fig


def overlay_plot(curves: dict, population=None, *, extrapolate: float | None = None, path=None):
    """All specimens' posterior medians and 90% bands overlaid (thesis Fig. 3.66).

    Parameters
    ----------
    curves : {specimen: {source: Dataset}}
    population : Dataset, optional
        New-specimen predictive band (grey).
    extrapolate : float, optional
        Force multiple of the grids (for the title).
    """
    fig, ax = plt.subplots(figsize=(12, 5.6))
    cmap = plt.get_cmap("tab10")
    fmax, xmax = 0.0, 0.0
    for i, sid in enumerate(sorted(curves)):
        ds = curves[sid]["posterior"]
        _band(ax, ds, cmap(i % 10), sid, alpha=0.2)
        fmax = max(fmax, float(ds["force"].values[-1]))
        xmax = max(xmax, float(np.nanmax(ds["elongation"].values[1])))
    if population is not None:
        F = population["force"].values
        lo, med, hi = population["elongation"].values
        right = 1.25 * max(xmax, float(np.nanmax(med)) if np.isfinite(med).any() else 0.0)
        # NaN 95% quantile: >= 5% of the draws need a stretch beyond the solver's limit (softer than
        # anything computable), so the band reaches past the right edge
        open_hi = ~np.isfinite(hi) & np.isfinite(lo)
        ax.fill_betweenx(F, lo, np.where(open_hi, 10 * right, hi), color="#bdbdbd", alpha=0.35, lw=0, zorder=0)
        for b in (lo, hi):
            ax.plot(b, F, color="#969696", lw=0.7, zorder=0)
        ax.plot(med, F, color="#252525", lw=1.2, ls="-.",
                label=SOURCE_STYLE["population"][1] + ":\nmedian (dash-dot) and 90% band (grey)"
                + ("; the band's soft edge leaves\nthe plot where >= 5% of draws exceed the solver's stretch limit"
                   if open_hi.any() else ""))
        xmax = max(xmax, float(np.nanmax(med)) if np.isfinite(med).any() else 0.0)
    ax.plot([], [], color="k", ls="--", label="dashed / hatched: extrapolated (≥ 50% of draws beyond tested strain)")
    ax.set_xlim(0, 1.25 * xmax if xmax > 0 else None)
    ax.set_ylim(0, fmax)
    ax.set_xlabel("organ elongation δ (mm)")
    ax.set_ylabel("axial force F (N)")
    mult = f"{extrapolate:g}×" if extrapolate else "a multiple of"
    ax.set_title("Organ response per specimen: posterior median and 90% band\n(each specimen's force axis ends at "
                 f"{mult} the force where its organ leaves its tested strain range)", fontsize=10)
    ax.legend(fontsize=8, loc="upper left", bbox_to_anchor=(1.01, 1.0), borderaxespad=0)
    fig.tight_layout()
    return save(fig, path) if path is not None else fig


def optima_plot(sid: str, optima, posterior=None, *, difference, spread, path=None):
    """Near-optimal CMA-ES sets of one specimen pushed through the organ model (thesis Fig. 3.65).

    Left: each set's force–elongation curve (distinct styles, widest first so coinciding curves
    stay visible), on the posterior band; legend with VOLF, T1 and Δ(−log L).  Right: relative
    difference of each curve from the best set's, in %.

    ``difference`` (optimum × force) and ``spread`` ``(within, beyond)`` are the relative differences
    from the best set and their largest magnitudes inside/beyond the tested range
    (:func:`hbm.workflow.organ.optima_difference`, :func:`hbm.workflow.organ.optima_spread`).
    """
    F = optima["force"].values
    E = optima["elongation"].values
    pn = [str(p) for p in optima["parameter"].values]
    P = optima["parameters"].values
    dobj = optima["delta_objective"].values
    kind = [str(x) for x in optima["kind"].values]
    n = E.shape[0]
    fig, (a1, a2) = plt.subplots(1, 2, figsize=(12.5, 4.8), gridspec_kw={"width_ratios": [1.3, 1]})
    if posterior is not None:
        lo, _, hi = posterior["elongation"].values
        a1.fill_betweenx(posterior["force"].values, lo, hi, color="#d9d9d9", lw=0, label="posterior 90% band")
    cmap = plt.get_cmap("viridis")
    styles = ["-", "--", "-.", ":"]
    widths = np.linspace(4.0, 1.0, n) if n > 1 else [2.0]
    man = spec_of().manifold   # the optima's labels: the base's manifold coordinates (VOLF, T1)
    xn, yn = (man.x, man.y) if man is not None else ("", "")
    xs = P[:, pn.index(xn)] if xn in pn else None
    ys = P[:, pn.index(yn)] if yn in pn else None
    rel = 100.0 * np.asarray(difference, float)
    for i in range(n):
        col = cmap(i / max(n - 1, 1) * 0.9)
        lab = ", ".join(x for x in (f"{xn}={xs[i]:.3f}" if xs is not None else "",
                                    f"{yn}={ys[i]:.3g}" if ys is not None else "",
                                    f"Δ(−log L)={dobj[i]:.2f}", kind[i]) if x)
        ext = optima["extrapolated"].values[i].astype(bool)
        k = int(np.argmax(ext)) if ext.any() else F.size
        a1.plot(E[i, :min(k + 1, F.size)], F[:min(k + 1, F.size)], color=col, lw=widths[i], ls=styles[i % 4],
                label=lab, alpha=0.9)
        if k < F.size:
            a1.plot(E[i, k:], F[k:], color=col, lw=min(widths[i], 1.5), ls=(0, (1, 1)), alpha=0.9)
        a2.plot(F, rel[i], color=col, lw=1.3, ls=styles[i % 4])
    ext_any = optima["extrapolated"].values.astype(bool)
    if ext_any.any():
        kf = int(np.argmax(ext_any.any(axis=0)))
        a1.axhspan(F[kf], F[-1], color=_EXT_COLOR, alpha=0.35, lw=0, zorder=0,
                   label="beyond the tested strain (thin dotted curves)")
    a1.set_xlabel("organ elongation δ (mm)")
    a1.set_ylabel("axial force F (N)")
    a1.set_xlim(left=0)
    a1.set_ylim(0, F[-1])
    a1.legend(fontsize=7, loc="upper left", title=f"{n} near-optimal sets (best: Δ=0)", title_fontsize=7.5)
    a1.set_title(f"{sid}: organ curves of near-optimal CMA-ES parameter sets", fontsize=10)
    within, beyond = spread
    a2.axhline(0, color="k", lw=0.6)
    if ext_any.any():
        a2.axvspan(F[kf], F[-1], color=_EXT_COLOR, alpha=0.35, lw=0, zorder=0)
        a2.text(F[kf], 0.02, " extrapolated", transform=a2.get_xaxis_transform(), fontsize=8, color="#99000d")
    a2.set_xlabel("axial force F (N)")
    a2.set_ylabel("(δ_i − δ_best) / δ_best  (%, symlog)")
    finite = rel[np.isfinite(rel)]
    span = float(np.max(np.abs(finite))) if finite.size else 0.0
    # symlog: sets that agree to 1e-4 % and a distinct local optimum 50 % away both stay readable
    a2.set_yscale("symlog", linthresh=1e-2)
    top = 10 ** np.ceil(np.log10(max(span, 1e-2) * 1.5))
    a2.set_ylim(-top, top)
    a2.set_xlim(0, F[-1])
    a2.set_title(f"difference from the best set: largest {100 * within:.2g}% in the tested range"
                 + (f", {100 * beyond:.2g}% beyond" if np.isfinite(beyond) else "")
                 + "\n(below the tested range's end, δ_best is taken at least as its value there)", fontsize=9)
    fig.tight_layout()
    return save(fig, path) if path is not None else fig


def organ_figures(organ, fig_dir: str | os.PathLike, *, optima_specimen: str | None = None,
                  optima_comparison: Mapping[str, tuple] | None = None) -> list[Path]:
    """All organ figures of an :class:`hbm.io.OrganFile` into ``fig_dir``; returns their paths.

    ``organ_overlay.png``, ``organ_optima_<id>.png`` (the specimen with most near-optimal sets,
    or ``optima_specimen``; drawn when ``optima_comparison`` maps it to its ``(difference,
    spread)``, see :func:`optima_plot`) and ``organ_<id>.png`` per specimen.
    """
    fig_dir = Path(fig_dir)
    name = organ.attrs.get("geometry", {}).get("name", "") if isinstance(organ.attrs.get("geometry"), dict) else ""
    out = [overlay_plot(organ.curves, organ.population, extrapolate=organ.attrs.get("extrapolate"),
                        path=fig_dir / "organ_overlay.png")]
    with_opt = {sid: c["optima"] for sid, c in organ.curves.items()
                if "optima" in c and c["optima"].sizes["optimum"] >= 1}
    if with_opt:
        if optima_specimen is None or optima_specimen not in with_opt:
            optima_specimen = max(sorted(with_opt), key=lambda s: with_opt[s].sizes["optimum"])
        if optima_specimen in (optima_comparison or {}):
            difference, spread = optima_comparison[optima_specimen]
            out.append(optima_plot(optima_specimen, with_opt[optima_specimen],
                                   organ.curves[optima_specimen].get("posterior"), difference=difference,
                                   spread=spread, path=fig_dir / f"organ_optima_{optima_specimen}.png"))
    for sid in sorted(organ.curves):
        out.append(specimen_organ_plot(sid, organ.curves[sid], geometry_name=name, path=fig_dir / f"organ_{sid}.png"))
    return out
