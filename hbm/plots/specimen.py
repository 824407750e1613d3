"""Per-specimen figures: corner plot, posterior predictive (+ extrapolation), Sobol bars."""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import numpy as np

from ..model import spyrou_model
from ..model.spec import spec_of
from . import RELEVANCE_COLORS, plt, save

__all__ = ["corner_plot", "predictive_plot", "sobol_plot", "specimen_figures", "model_theta"]


def _thin(n: int, m: int, seed: int = 0) -> np.ndarray:
    if n <= m:
        return np.arange(n)
    return np.sort(np.random.default_rng(seed).choice(n, m, replace=False))


def corner_plot(result, *, max_points: int = 1500, color_by: str | None = None, path=None):
    """Corner plot: marginals on the diagonal, 2-D densities below, samples above coloured by
    ``color_by`` (default: the fraction of the model's manifold, VOLF for the Spyrou base), CMA-ES
    optima overlaid (stars: restarts, diamonds: sweep optima)."""
    if color_by is None:
        man = spec_of(result).manifold
        color_by = man.x if man is not None else ""
    names = list(result.names)
    x = result.samples
    d = len(names)
    idx = _thin(x.shape[0], max_points)
    cvals = result.column(color_by)[idx] if (color_by in names or color_by in result.fixed) else None
    opt = result.optima or []
    fig, axes = plt.subplots(d, d, figsize=(1.55 * d + 1, 1.55 * d), squeeze=False)
    sc = None
    for i in range(d):
        for j in range(d):
            ax = axes[i, j]
            xi, xj = x[:, i], x[:, j]
            if i == j:
                ax.hist(xi, bins=40, color="#4d4d4d", histtype="stepfilled", alpha=0.6, density=True)
                lo, hi = np.quantile(xi, [0.05, 0.95])
                for v in (lo, hi):
                    ax.axvline(v, color="k", lw=0.6, ls=":")
                ax.set_yticks([])
            elif i > j:  # lower: 2-D density of (x_j, x_i)
                ax.hist2d(xj, xi, bins=25, cmap="Greys", cmin=1, rasterized=True)
                for o in opt:
                    p = o["params"]
                    if names[j] in p and names[i] in p:
                        sweep = o.get("kind") == "sweep"
                        ax.plot(p[names[j]], p[names[i]], marker="D" if sweep else "*",
                                ms=3.5 if sweep else 7, color="#e41a1c" if not sweep else "#ff7f00",
                                mec="k", mew=0.3, ls="none")
            else:  # upper: samples coloured by VOLF
                sc = ax.scatter(xj[idx], xi[idx], c=cvals, s=2, cmap="viridis", rasterized=True,
                                lw=0) if cvals is not None else ax.scatter(xj[idx], xi[idx], s=2, lw=0)
            if i < d - 1:
                ax.set_xticklabels([])
            else:
                ax.set_xlabel(names[j], fontsize=9)
                ax.tick_params(axis="x", labelrotation=45, labelsize=6)
            if j > 0 or i == 0:
                if i != j:
                    ax.set_yticklabels([])
            else:
                ax.set_ylabel(names[i], fontsize=9)
                ax.tick_params(axis="y", labelsize=6)
            ax.locator_params(nbins=3)
            if i != j:
                ax.set_xlim(np.quantile(xj, [0.0, 1.0]))
                ax.set_ylim(np.quantile(xi, [0.0, 1.0]))
    if sc is not None and cvals is not None:
        cax = fig.add_axes([0.92, 0.55, 0.015, 0.3])
        fig.colorbar(sc, cax=cax, label=f"{color_by} (upper panels)")
    from matplotlib.lines import Line2D

    handles = [Line2D([], [], marker="*", color="#e41a1c", mec="k", ls="none", ms=8, label="CMA-ES restart optimum"),
               Line2D([], [], marker="D", color="#ff7f00", mec="k", ls="none", ms=4, label="CMA-ES sweep optimum"),
               Line2D([], [], color="k", ls=":", label="90% interval")]
    fig.subplots_adjust(top=0.93, wspace=0.08, hspace=0.08)
    fig.legend(handles=handles, loc="lower right", bbox_to_anchor=(0.9, 0.94), fontsize=8, frameon=False, ncol=3)
    fig.suptitle(f"{result.specimen_id}: posterior ({result.n_samples} TMCMC samples; below: density, "
                 f"above: samples coloured by {color_by})", x=0.1, y=0.985, ha="left", fontsize=11)
    return save(fig, path, dpi=90, tight=False) if path is not None else fig


def model_theta(result, model) -> np.ndarray:
    """Full model parameter rows (n, model.n_params) from a result (fixed values filled in)."""
    cols = result.as_dict()
    missing = [n for n in model.parameter_names if n not in cols]
    if missing:
        raise KeyError(f"result lacks model parameters {missing}")
    return np.column_stack([cols[n] for n in model.parameter_names])


def predictive_plot(result, *, model=None, extrapolate: float = 1.5, max_draws: int = 2000, path=None):
    """Data with posterior-predictive bands (model-only and with noise), and the prediction beyond
    the tested strain up to ``extrapolate`` × the maximum."""
    model = spyrou_model() if model is None else model
    strain, stress = result.data.strain, result.data.stress
    fig, (a1, a2) = plt.subplots(1, 2, figsize=(12, 4.6))
    q = [0.05, 0.5, 0.95]
    order = np.argsort(strain, kind="stable") if result.data.time is None else np.arange(strain.size)
    if result.predictive is not None:
        lo, med, hi = np.quantile(result.predictive, q, axis=0)
        a1.fill_between(strain[order], lo[order], hi[order], color="#9ecae1", alpha=0.6,
                        label="90% predictive (model + noise)")
    if result.predictive_model is not None:
        lo, med, hi = np.quantile(result.predictive_model, q, axis=0)
        a1.fill_between(strain[order], lo[order], hi[order], color="#08519c", alpha=0.6,
                        label="90% model (parameter uncertainty)")
        a1.plot(strain[order], med[order], color="#08306b", lw=1, label="posterior median")
    a1.plot(strain, stress, "o", ms=3, color="#d62728", label="data", zorder=5)
    a1.set_xlabel("strain ε (-)")
    a1.set_ylabel("stress σ (MPa)")
    a1.set_title(f"{result.specimen_id}: posterior predictive on the tested range")
    a1.legend(fontsize=8, loc="upper left")

    # extrapolation: evaluate the model on a monotonic grid to extrapolate x max strain
    emax = float(np.max(strain))
    grid = np.linspace(0.0, extrapolate * emax, 120)
    idx = _thin(result.n_samples, max_draws, 1)
    try:
        th = model_theta(result, model)[idx]
        with np.errstate(all="ignore"):
            s = model.stress(grid, th)
        ok = np.all(np.isfinite(s), axis=1)
        s = s[ok]
        sig = result.column("sigma")[idx][ok] if "sigma" in result.names else None
        if sig is not None:
            noisy = s + sig[:, None] * np.random.default_rng(2).standard_normal(s.shape)
            lo, hi = np.quantile(noisy, [0.05, 0.95], axis=0)
            a2.fill_between(grid, lo, hi, color="#9ecae1", alpha=0.6, label="90% predictive (model + noise)")
        lo, med, hi = np.quantile(s, q, axis=0)
        a2.fill_between(grid, lo, hi, color="#08519c", alpha=0.6, label="90% model")
        a2.plot(grid, med, color="#08306b", lw=1, label="posterior median")
        lin = max(1e-4, float(np.max(np.abs(stress))) / 20)
        a2.set_yscale("symlog", linthresh=lin)
        a2.set_ylim(bottom=-lin)
    except (KeyError, ValueError) as exc:  # a model without these parameters: leave a note
        a2.text(0.5, 0.5, f"no extrapolation: {exc}", transform=a2.transAxes, ha="center")
    a2.plot(strain, stress, "o", ms=3, color="#d62728", label="data", zorder=5)
    a2.axvspan(emax, extrapolate * emax, color="#fee0d2", alpha=0.5, zorder=0, label="beyond tested strain")
    a2.set_xlabel("strain ε (-)")
    a2.set_ylabel("stress σ (MPa, symlog scale)")
    a2.set_title(f"prediction to {extrapolate:g}× the maximum tested strain")
    a2.legend(fontsize=8, loc="upper left")
    fig.tight_layout()
    return save(fig, path) if path is not None else fig


def sobol_plot(result, *, path=None):
    """S1 and ST bars (bootstrap CIs) of the Sobol QoI, bars coloured by relevance class, with the
    class thresholds of thesis Table 2.1."""
    s = result.sobol
    names = list(s["ST"])
    x = np.arange(len(names))
    fig, ax = plt.subplots(figsize=(1.0 * len(names) + 3, 4))
    st = np.array([s["ST"][n] for n in names], float)
    s1 = np.array([s["S1"][n] for n in names], float)
    stc = np.array([s.get("ST_conf", {}).get(n, 0.0) for n in names], float)
    s1c = np.array([s.get("S1_conf", {}).get(n, 0.0) for n in names], float)
    cols = [RELEVANCE_COLORS.get(s.get("relevance", {}).get(n, ""), "#999999") for n in names]
    ax.bar(x - 0.2, np.nan_to_num(s1), 0.4, yerr=np.nan_to_num(s1c), color="white", edgecolor=cols, hatch="//",
           lw=1.5, capsize=2, label="first order S1")
    ax.bar(x + 0.2, np.nan_to_num(st), 0.4, yerr=np.nan_to_num(stc), color=cols, capsize=2, label="total ST")
    for thr, lab in ((0.8, "very important"), (0.5, "important"), (0.3, "unimportant")):
        ax.axhline(thr, color=RELEVANCE_COLORS[lab], ls="--", lw=0.8)
        ax.text(len(names) - 0.45, thr + 0.01, f"≥{thr}: {lab}", fontsize=7, ha="right", va="bottom",
                color=RELEVANCE_COLORS[lab])
    ax.set_xticks(x, names)
    top = 1.2  # indices live in [0, 1]; estimates beyond (heavy-tailed QoI, small N) are annotated, not drawn
    ax.set_ylim(0, top)
    for xi, v, c in zip(x, st, stc):
        if np.isfinite(v) and v + c > top:
            ax.annotate(f"ST={v:.2g}±{c:.2g}", (xi + 0.2, top), xytext=(0, -12), textcoords="offset points",
                        ha="center", fontsize=7, color="k", bbox=dict(fc="white", ec="none", alpha=0.85))
    ax.set_ylabel("Sobol index")
    qoi = s.get("qoi", "")
    ax.set_title(f"{result.specimen_id}: Sobol indices of '{qoi}' over the prior box, N={s.get('n', '?')} "
                 f"(bar colour = relevance class from ST; whiskers: bootstrap CI)", fontsize=9)
    ax.legend(fontsize=8, loc="upper left")
    fig.tight_layout()
    return save(fig, path) if path is not None else fig


def specimen_figures(result, fig_dir: str | os.PathLike, *, model=None, manifold: Any = None) -> list[Path]:
    """All per-specimen figures into ``fig_dir``; returns their paths."""
    fig_dir = Path(fig_dir)
    sid = result.specimen_id
    out = [corner_plot(result, path=fig_dir / f"{sid}_corner.png"),
           predictive_plot(result, model=model, path=fig_dir / f"{sid}_predictive.png")]
    if result.sobol:
        out.append(sobol_plot(result, path=fig_dir / f"{sid}_sobol.png"))
    return out
