"""The figure of a fit across loading modes: one panel per test, in the test's own axes."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from ..model.loadcases import get_load_case
from . import plt, save

__all__ = ["modes_plot"]


def modes_plot(fit, *, path: str | os.PathLike | None = None, prob: float = 0.9):
    """One panel per (test, observable): the data, the posterior-mean prediction and the central ``prob``
    posterior-predictive band, against the test's control (engineering strain along its load, or γ).

    Parameters
    ----------
    fit : ModesFit
        From :func:`hbm.fit.modes.fit_modes`.
    path : path, optional
        Save the figure there (PNG or PDF by suffix).
    prob : float
        Band level.

    Returns
    -------
    matplotlib.figure.Figure
    """
    series = fit.likelihood.series
    spec = fit.likelihood.data
    n = len(series)
    cols = min(3, n)
    rows = -(-n // cols)
    fig, axes = plt.subplots(rows, cols, figsize=(4.2 * cols, 3.4 * rows), squeeze=False)
    a = (1 - prob) / 2
    for ax, s, m, r in zip(axes.ravel(), series, fit.predictions, fit.replicates):
        case = get_load_case(s.test.load_case)
        x = spec.strain[s.rows]
        order = np.argsort(x, kind="stable")
        lo, hi = np.quantile(r, [a, 1 - a], axis=0)
        unit = "MPa" if s.is_stress else "-"
        ax.fill_between(x[order], lo[order], hi[order], alpha=0.3, label=f"{prob:.0%} predictive")
        ax.plot(x[order], m.mean(axis=0)[order], "-", label="posterior mean")
        ax.plot(x, s.observed, "o", ms=3, color="k", label="data")
        ax.set_xlabel("shear γ" if case.control == "shear" else "engineering strain along the load")
        ax.set_ylabel(f"{s.observable} [{unit}]")
        ax.set_title(f"{s.name} · {case.name}", fontsize=9)
    for ax in axes.ravel()[n:]:
        ax.set_visible(False)
    axes.ravel()[0].legend(fontsize=7)
    fig.suptitle(f"{spec.id}: {fit.likelihood.energy.label}", fontsize=10)
    fig.tight_layout()
    if path is not None:
        save(fig, Path(path))
    return fig
