"""Figures of the detective: where the model fails (diagnosis) and the error fall (extend).

The functions take the detective's results duck-typed (their attributes are read, nothing is
imported from :mod:`hbm.detective`), so the detective never depends on matplotlib.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from . import plt, save

__all__ = ["plot_diagnosis", "plot_extension"]

_TEST_COLORS = plt.get_cmap("tab10").colors


def _tests(d):
    return d.test if d.test is not None else np.zeros(d.stress.size, int)


def plot_diagnosis(dg, path: str | os.PathLike, *, evidence_threshold: float) -> Path:
    """Data, fit and predictive band; standardised residuals with the misfit windows shaded;
    candidate evidence gains.

    Parameters
    ----------
    dg : hbm.detective.Diagnosis
        Read: ``data`` (strain, stress, test, name), ``residual_curve``, ``base``, ``coverage``,
        ``window_detail``, ``candidates``, ``selected``, ``group``, ``verdict``, ``message``.
    path : path of the image (format from the suffix)
    evidence_threshold : float
        Δlog Z needed to name an effect (a dashed line on the evidence bars).
    """
    d = dg.data
    rc = dg.residual_curve
    tests = _tests(d)
    fig, axes = plt.subplots(3, 1, figsize=(8.5, 10.5), gridspec_kw={"height_ratios": [3, 2, 2]})
    ax = axes[0]
    for k, t in enumerate(np.unique(tests)):
        m = tests == t
        col = _TEST_COLORS[k % len(_TEST_COLORS)]
        ax.fill_between(d.strain[m], rc["lower"][m], rc["upper"][m], color=col, alpha=0.18, lw=0,
                        step=None)
        ax.plot(d.strain[m], d.stress[m], "o", ms=2.8, color=col, alpha=0.8, label=f"test {t}")
        ax.plot(d.strain[m], rc["pred"][m], "-", color=col, lw=1.4)
    ax.set_ylabel("stress (MPa)")
    ax.set_title(f"{d.name}: {' + '.join(dg.base.effects) or 'base model'} — noise {dg.base.noise}, "
                 f"RMSE {dg.base.rmse:.3g} MPa, {int(100 * dg.coverage.get('band', 0.9))}% band covers "
                 f"{dg.coverage.get('overall', float('nan')):.0%}", fontsize=9)
    ax.legend(fontsize=7, ncol=4, loc="upper left")
    # residuals with misfit windows
    ax = axes[1]
    for w in dg.window_detail:
        ax.axvspan(w["eps_lo"], w["eps_hi"], color="#d6604d" if w["sign"] > 0 else "#4393c3", alpha=0.25, lw=0)
    for k, t in enumerate(np.unique(tests)):
        m = tests == t
        col = _TEST_COLORS[k % len(_TEST_COLORS)]
        ax.plot(d.strain[m], rc["z"][m], ".", ms=2.5, color=col, alpha=0.5)
        ax.plot(d.strain[m], rc["smoothed"][m], "-", color=col, lw=1.6)
    ax.axhline(0, color="k", lw=0.8)
    for s in (-2, 2):
        ax.axhline(s, color="grey", lw=0.6, ls=":")
    ax.set_ylabel("standardised residual")
    ax.set_xlabel("strain ε (−)")
    txt = ("shaded: misfit windows (red: data above model, blue: below; family-wise 5 %, "
           f"noise rho {rc.get('rho_window', 0):.2f})" if dg.window_detail else "no significant misfit window")
    ax.set_title(txt, fontsize=8)
    # candidates
    ax = axes[2]
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
    ax.set_title(f"verdict: {dg.verdict} — {dg.message}"[:150], fontsize=8)
    fig.tight_layout()
    return save(fig, path)


def plot_extension(ext, path: str | os.PathLike, *, noise_sd: float | None = None) -> Path:
    """Error fall: fits of each step over the data; RMSE, log-evidence ± SE and coverage per step.

    Parameters
    ----------
    ext : hbm.detective.Extension
        Read: ``data`` (strain, stress, test, name) and ``steps`` (effects, likelihood,
        theta_max, rmse, log_evidence, log_evidence_se, coverage).
    path : path of the image
    noise_sd : float, optional
        Noise sd of the data, drawn as the level the RMSE should fall to.
    """
    d = ext.data
    steps = ext.steps
    labels = ["base"] + ["+" + s.effects[-1] if s.effects else "base" for s in steps[1:]]
    fig = plt.figure(figsize=(10, 7.5))
    gs = fig.add_gridspec(2, 3, height_ratios=[3, 2])
    ax = fig.add_subplot(gs[0, :])
    tests = _tests(d)
    ax.plot(d.strain, d.stress, "o", ms=2.5, color="#4d4d4d", alpha=0.6, label="data")
    cmap = plt.get_cmap("viridis")
    for i, s in enumerate(steps):
        pred = np.asarray(s.likelihood.predict(np.asarray(s.theta_max)[None, :]))[0]
        col = cmap(i / max(1, len(steps) - 1))
        for k, t in enumerate(np.unique(tests)):
            m = tests == t
            ax.plot(d.strain[m], pred[m], "-", color=col, lw=1.3, label=labels[i] if k == 0 else None)
    ax.set_xlabel("strain ε (−)")
    ax.set_ylabel("stress (MPa)")
    ax.legend(fontsize=8)
    ax.set_title(f"{d.name}: error fall as effects are added", fontsize=10)
    x = np.arange(len(steps))
    ax = fig.add_subplot(gs[1, 0])
    ax.plot(x, [s.rmse for s in steps], "o-", color="#b2182b")
    if noise_sd is not None and np.isfinite(noise_sd):
        ax.axhline(noise_sd, color="grey", ls="--", lw=0.8, label="model-free noise sd")
        ax.legend(fontsize=7)
    ax.set_xticks(x)
    ax.set_xticklabels(labels, rotation=30, fontsize=7)
    ax.set_ylabel("RMSE (MPa)")
    ax = fig.add_subplot(gs[1, 1])
    ax.errorbar(x, [s.log_evidence for s in steps], yerr=[s.log_evidence_se for s in steps], fmt="o-",
                color="#2166ac", capsize=3)
    ax.set_xticks(x)
    ax.set_xticklabels(labels, rotation=30, fontsize=7)
    ax.set_ylabel("log evidence")
    ax = fig.add_subplot(gs[1, 2])
    ax.plot(x, [s.coverage for s in steps], "o-", color="#1b7837")
    ax.axhline(0.9, color="grey", ls="--", lw=0.8)
    ax.set_ylim(0, 1.02)
    ax.set_xticks(x)
    ax.set_xticklabels(labels, rotation=30, fontsize=7)
    ax.set_ylabel("90% predictive coverage")
    fig.tight_layout()
    return save(fig, path)
