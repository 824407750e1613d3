"""The fit figure: data, MAP curve and the 90 % posterior-predictive band (+ stress against time)."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from ..fit import FitResult, fit_quality, map_prediction
from . import plt, save

__all__ = ["fit_plot"]


def _band(ax, x, lo, hi, label):
    """Shaded band where x is monotone; its two edges as lines along a loading path otherwise."""
    if np.all(np.diff(x) >= 0):
        ax.fill_between(x, lo, hi, color="#9ecae1", alpha=0.6, lw=0, label=label)
    else:
        ax.plot(x, lo, color="#6baed6", lw=0.8, ls="--", label=label)
        ax.plot(x, hi, color="#6baed6", lw=0.8, ls="--")


def fit_plot(result, data=None, *, likelihood=None, prob: float = 0.9,
             path: str | os.PathLike | None = None):
    """Data, MAP curve and central ``prob`` posterior-predictive band; stress against time too.

    Parameters
    ----------
    result : FitResult or SpecimenResult
        A :class:`~hbm.fit.FitResult` evaluates the MAP curve with its likelihood; a stored
        result uses the best posterior sample's prediction.
    data : xarray.Dataset, optional
        Observed curve (``strain``, ``stress``, optional ``time``); default the stored data.
    likelihood : Likelihood, optional
    prob : float
        Mass of the predictive band (0.9).
    path : path, optional
        Write the figure there (format from the suffix) and return the path; else return the figure.

    Returns
    -------
    Path or matplotlib.figure.Figure
    """
    r = result.result if isinstance(result, FitResult) else result
    if data is not None:
        strain = np.asarray(data["strain"].values, float)
        stress = np.asarray(data["stress"].values, float)
        tm = np.asarray(data["time"].values, float) if "time" in data else None
    else:
        strain, stress, tm = np.asarray(r.strain, float), np.asarray(r.stress, float), r.time
        tm = None if tm is None else np.asarray(tm, float)
    curve = map_prediction(result, likelihood)
    band = None
    if r.predictive is not None:
        band = np.quantile(np.asarray(r.predictive, float), [(1 - prob) / 2, (1 + prob) / 2], axis=0)
    q = fit_quality(result, data, likelihood=likelihood, prob=prob)
    ncol = 2 if tm is not None else 1
    fig, axes = plt.subplots(1, ncol, figsize=(5.2 * ncol, 4.0), squeeze=False)
    label = f"{int(round(100 * prob))}% predictive band"
    for ax, x, xl in zip(axes[0], (strain, tm), ("strain", "time (s)")):
        if band is not None:
            _band(ax, x, band[0], band[1], label)
        if curve is not None:
            ax.plot(x, curve, color="#b2182b", lw=1.5, label="MAP")
        ax.plot(x, stress, "o", ms=3.5, color="k", label="data")
        ax.set_xlabel(xl)
        ax.set_ylabel("stress (MPa)")
    axes[0, 0].legend(fontsize=8, frameon=False)
    cov = "n/a" if q["coverage90"] is None else f"{100 * q['coverage90']:.0f}%"
    fig.suptitle(f"{r.specimen_id}: RMSE {q['rmse']:.3g} MPa ({100 * q['rmse_rel']:.1f}% of peak), "
                 f"coverage {cov}, log Z {q['log_evidence']:.2f} ± {q['log_evidence_se']:.2f}", fontsize=9)
    if path is None:
        return fig
    return save(fig, Path(path))
