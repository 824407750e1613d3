"""Figures of the detective: where the model fails (diagnosis) and the error fall (extend).

The functions take the detective's results duck-typed (their attributes are read, nothing is
imported from :mod:`hbm.detective`), so the detective never depends on matplotlib.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from . import plt, save
from .tests_view import TEST_COLORS, draw_curve, draw_tests, model_curve, test_ids, toe_axes, wrapped

__all__ = ["plot_diagnosis", "plot_extension"]

_TEST_COLORS = TEST_COLORS


def _tests(d):
    return test_ids(d.ds)


def _data_panels(fig, gs_row, d, curve: dict | None, pred: np.ndarray, band: tuple | None = None,
                 title: str = ""):
    """Stress against strain (with a toe inset) and, where the data have time, against time:
    data per test, the model as a dense curve (or at the data points when it cannot be
    evaluated elsewhere), the predictive band as a shaded strip per test."""
    tests = _tests(d)
    has_time = d.time is not None
    axes = [fig.add_subplot(gs_row[0])] + ([fig.add_subplot(gs_row[1])] if has_time else [])
    for ax, axis, xd in zip(axes, ("strain", "time"), (d.strain, d.time)):
        if band is not None:
            for k, t in enumerate(np.unique(tests)):
                m = tests == t
                ax.fill_between(xd[m], band[0][m], band[1][m], color=_TEST_COLORS[k % 10], alpha=0.15, lw=0)
        draw_tests(ax, xd, d.stress, tests, ms=2.6, alpha=0.75, label=axis == "strain")
        if curve is not None:
            draw_curve(ax, curve, axis, tests, lw=1.3)
        else:
            draw_tests(ax, xd, pred, tests, style="-", label=False, lw=1.3)
        ax.set_xlabel("strain ε (−)" if axis == "strain" else "time t (s)")
        ax.set_ylabel("stress (MPa)")
    axes[0].legend(fontsize=7, ncol=2, loc="lower right")
    toe_axes(axes[0], d.strain, d.stress, tests, curve, pred)
    if title:
        axes[0].set_title(wrapped(title, 70 if has_time else 130), fontsize=8, loc="left")
    return axes


def plot_diagnosis(dg, path: str | os.PathLike, *, evidence_threshold: float) -> Path:
    """Data and model per test (against strain, and time where the data have it; a toe view),
    standardised residuals with the misfit windows shaded, candidate evidence gains, the verdict.

    Parameters
    ----------
    dg : hbm.detective.Diagnosis
        Read: ``data`` (strain, stress, time, test, name), ``residual_curve``, ``base``
        (likelihood, theta_max: the model is drawn as a dense curve along each test's path),
        ``coverage``, ``window_detail``, ``candidates``, ``selected``, ``group``, ``verdict``,
        ``message``.
    path : path of the image (format from the suffix)
    evidence_threshold : float
        Δlog Z needed to name an effect (a dashed line on the evidence bars).
    """
    d = dg.data
    rc = dg.residual_curve
    tests = _tests(d)
    has_time = d.time is not None
    fig = plt.figure(figsize=(11.5, 14))
    gs = fig.add_gridspec(4, 2 if has_time else 1, height_ratios=[3, 2, 2.4, 1.5], hspace=0.42, wspace=0.22)
    curve = None
    if dg.base.likelihood is not None:
        curve = model_curve(dg.base.likelihood, dg.base.theta_max, d.ds)
    band = (rc["lower"], rc["upper"]) if "lower" in rc else None
    title = (f"{d.name}: {' + '.join(dg.base.effects) or 'base model'} — noise {dg.base.noise}, RMSE "
             f"{dg.base.rmse:.3g} MPa, {int(100 * dg.coverage.get('band', 0.9))}% band covers "
             f"{dg.coverage.get('overall', float('nan')):.0%} (lines: the model along each test's path)")
    _data_panels(fig, [gs[0, 0], gs[0, 1]] if has_time else [gs[0, 0]], d, curve, rc["pred"], band, title)
    # residuals with misfit windows, against time where the data have it (a drift, a slip, a ripple show there)
    ax = fig.add_subplot(gs[1, :])
    x = d.time if has_time else d.strain
    for w in dg.window_detail:
        lo, hi = (x[w["i0"]], x[w["i1"]]) if has_time and "i0" in w else (w["eps_lo"], w["eps_hi"])
        ax.axvspan(lo, hi, color="#d6604d" if w["sign"] > 0 else "#4393c3", alpha=0.25, lw=0)
    draw_tests(ax, x, rc["z"], tests, style=".", label=False, ms=2.5, alpha=0.5)
    draw_tests(ax, x, rc["smoothed"], tests, style="-", label=False, lw=1.6)
    ax.axhline(0, color="k", lw=0.8)
    for s in (-2, 2):
        ax.axhline(s, color="grey", lw=0.6, ls=":")
    ax.set_ylabel("standardised residual")
    ax.set_xlabel("time t (s)" if has_time else "strain ε (−)")
    txt = ("shaded: misfit windows (red: data above model, blue: below; family-wise 5 %, "
           f"noise rho {rc.get('rho_window', 0):.2f})" if dg.window_detail else "no significant misfit window")
    ax.set_title(txt + "; lines: smoothed residual per test", fontsize=8, loc="left")
    # candidates
    ax = fig.add_subplot(gs[2, :])
    cands = dg.candidates
    names = [c.effect for c in cands]
    y = np.arange(len(cands))
    z = [c.score for c in cands]
    ax.barh(y - 0.2, z, height=0.38, color="#bababa", label="screen score z")
    dz = [c.delta_log_evidence if c.refit else np.nan for c in cands]
    se = [c.delta_log_evidence_se if c.refit else 0 for c in cands]
    colors = ["#1b7837" if c.effect in dg.selected else ("#762a83" if c.effect in dg.group else "#2166ac")
              for c in cands]
    ax.barh(y + 0.2, np.nan_to_num(dz, nan=0.0), xerr=se, height=0.38, color=colors, label="Δlog Z (refit)")
    ax.axvline(evidence_threshold, color="k", ls="--", lw=0.8)
    ax.axvline(0, color="k", lw=0.6)
    ax.set_yticks(y)
    ax.set_yticklabels(names, fontsize=8)
    ax.invert_yaxis()
    ax.legend(fontsize=7, loc="lower right")
    ax.set_title("candidates: screen score and evidence gain against the best base (dashed: the threshold)",
                 fontsize=8, loc="left")
    # the verdict in full (wrapped) in its own row: a title would be cut off
    ax = fig.add_subplot(gs[3, :])
    ax.axis("off")
    ax.text(0.0, 1.0, wrapped(f"verdict: {dg.verdict} — {dg.message}", 160, 11), fontsize=7.5, va="top",
            ha="left", transform=ax.transAxes)
    return save(fig, path)


def plot_extension(ext, path: str | os.PathLike, *, noise_sd: float | None = None) -> Path:
    """Error fall: data per test with each step's model as a dense curve (against strain, and
    time where the data have it; a toe view), the residuals of the first and last step, and
    RMSE, log-evidence ± SE and coverage per step.

    Parameters
    ----------
    ext : hbm.detective.Extension
        Read: ``data`` (strain, stress, time, test, name) and ``steps`` (effects, likelihood,
        theta_max, rmse, log_evidence, log_evidence_se, coverage, noise).
    path : path of the image
    noise_sd : float, optional
        Noise sd of the data, drawn as the level the RMSE should fall to.
    """
    d = ext.data
    steps = ext.steps
    labels = ["base" if not steps[0].effects else "+".join(steps[0].effects)] + \
        ["+" + s.effects[-1] if s.effects else "base" for s in steps[1:]]
    tests = _tests(d)
    has_time = d.time is not None
    fig = plt.figure(figsize=(11.5, 11))
    gs = fig.add_gridspec(3, 3, height_ratios=[3, 1.8, 2], hspace=0.5, wspace=0.35)
    top = [gs[0, :2], gs[0, 2]] if has_time else [gs[0, :]]
    styles = [":", "--", "-.", "-"]
    preds = [np.asarray(s.likelihood.predict(np.asarray(s.theta_max)[None, :]))[0] for s in steps]
    axes = _data_panels(fig, top, d, None, preds[-1], None,
                        f"{d.name}: error fall as effects are added (colour: test; line style: step)")
    for ax, axis in zip(axes, ("strain", "time")):
        for ln in list(ax.lines)[len(np.unique(tests)):]:
            ln.remove()         # the last step is drawn below with the others, as dense curves
        for i, s in enumerate(steps):
            ls = styles[-1] if i == len(steps) - 1 else styles[i % (len(styles) - 1)]
            curve = model_curve(s.likelihood, s.theta_max, d.ds)
            if curve is not None:
                draw_curve(ax, curve, axis, tests, lw=1.2, ls=ls)
            else:
                draw_tests(ax, d.strain if axis == "strain" else d.time, preds[i], tests, style=ls, label=False)
            ax.plot([], [], ls=ls, color="k", label=labels[i])
        ax.legend(fontsize=7, ncol=2, loc="lower right")
    # residuals of the first and the last step
    ax = fig.add_subplot(gs[1, :])
    x = d.time if has_time else d.strain
    for i in sorted({0, len(steps) - 1}):
        r = d.stress - preds[i]
        draw_tests(ax, x, r, tests, style="o" if i == 0 else ".", label=False, ms=2.5 if i == 0 else 3,
                   alpha=0.35 if i == 0 else 0.9, mfc="none" if i == 0 else None)
        ax.plot([], [], "o" if i == 0 else ".", color="k", mfc="none" if i == 0 else None,
                label=f"{labels[i]} (RMSE {steps[i].rmse:.3g} MPa)")
    ax.axhline(0, color="k", lw=0.8)
    if noise_sd is not None and np.isfinite(noise_sd):
        for sgn in (-1, 1):
            ax.axhline(sgn * 2 * noise_sd, color="grey", ls=":", lw=0.8)
    ax.set_xlabel("time t (s)" if has_time else "strain ε (−)")
    ax.set_ylabel("residual (MPa)")
    ax.legend(fontsize=7, loc="upper right")
    ax.set_title("residuals (dotted: ± 2 model-free noise sd)", fontsize=8, loc="left")
    xs = np.arange(len(steps))
    ax = fig.add_subplot(gs[2, 0])
    ax.plot(xs, [s.rmse for s in steps], "o-", color="#b2182b")
    if noise_sd is not None and np.isfinite(noise_sd):
        ax.axhline(noise_sd, color="grey", ls="--", lw=0.8, label="model-free noise sd")
        ax.legend(fontsize=7)
    ax.set_ylabel("RMSE (MPa)")
    ax = fig.add_subplot(gs[2, 1])
    ax.errorbar(xs, [s.log_evidence for s in steps], yerr=[s.log_evidence_se for s in steps], fmt="o-",
                color="#2166ac", capsize=3)
    ax.set_ylabel("log evidence")
    ax.set_title("noise: " + ", ".join(sorted({s.noise for s in steps})), fontsize=8)
    ax3 = fig.add_subplot(gs[2, 2])
    ax3.plot(xs, [s.coverage for s in steps], "o-", color="#1b7837")
    ax3.axhline(0.9, color="grey", ls="--", lw=0.8)
    ax3.set_ylim(0, 1.02)
    ax3.set_ylabel("90% predictive coverage")
    for a in fig.axes[-3:]:
        a.set_xticks(xs)
        a.set_xticklabels(labels, rotation=30, fontsize=7)
    return save(fig, path)
