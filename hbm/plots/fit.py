"""The fit figure: data per test, the MAP model as a dense curve, the 90 % posterior-predictive band, a toe
view and residuals (+ stress against time)."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from ..data.specimen import as_specimen
from ..fit.specimen import FitResult, fit_quality, map_estimate, map_prediction
from ..model.core import Loading
from . import plt, save
from .tests_view import TEST_COLORS, dense_path, draw_curve, draw_tests, test_ids, toe_axes, wrapped

__all__ = ["fit_plot"]


def _dense_map_curve(likelihood, estimate: dict, spec):
    """The MAP model along each test's dense path (None without a likelihood to evaluate)."""
    if likelihood is None:
        return None
    model = likelihood.model
    try:
        theta = np.array([estimate[n] for n in model.parameter_names], float)
        path = dense_path(spec)
        with np.errstate(all="ignore"):
            s = np.asarray(model.stress(Loading(path["strain"], path["time"], path["test"]), theta), float)
    except Exception:    # noqa: BLE001 -- a parameter missing from the estimate: draw at the data points
        return None
    return {**path, "stress": s.reshape(-1)}


def fit_plot(result, data=None, *, likelihood=None, prob: float = 0.9,
             path: str | os.PathLike | None = None):
    """Data per test, the MAP model as a dense curve, the ``prob`` posterior-predictive band,
    a toe view (log stress) and a residual panel; stress against time too where the data have it.

    Parameters
    ----------
    result : FitResult or SpecimenResult
        A :class:`~hbm.fit.FitResult` evaluates the MAP curve with its likelihood (densely along
        each test's path); a stored result uses the best posterior sample's prediction at the
        data points.
    data : Specimen or xarray.Dataset, optional
        The observed specimen; default the one stored in the result.
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
    spec = as_specimen(data) if data is not None else r.data
    strain, stress, tm = spec.strain, spec.stress, spec.time
    tests = test_ids(spec)
    if likelihood is None and isinstance(result, FitResult):
        likelihood = result.likelihood
    curve_pts = map_prediction(result, likelihood)
    curve = _dense_map_curve(likelihood, map_estimate(result), spec)
    band = None
    if r.predictive is not None:
        band = np.quantile(np.asarray(r.predictive, float), [(1 - prob) / 2, (1 + prob) / 2], axis=0)
    q = fit_quality(result, data, likelihood=likelihood, prob=prob)
    ncol = 2 if tm is not None else 1
    fig = plt.figure(figsize=(5.6 * ncol, 6.6))
    gs = fig.add_gridspec(2, ncol, height_ratios=[3, 1.4], hspace=0.35, wspace=0.25)
    for j, (x, xl, axis) in enumerate(zip((strain, tm), ("strain ε (−)", "time t (s)"), ("strain", "time"))):
        if x is None:
            continue
        ax = fig.add_subplot(gs[0, j])
        if band is not None:
            for k, t in enumerate(np.unique(tests)):
                m = tests == t
                ax.fill_between(x[m], band[0][m], band[1][m], color=TEST_COLORS[k % 10], alpha=0.15, lw=0)
        draw_tests(ax, x, stress, tests, ms=3, alpha=0.8, label=j == 0)
        if curve is not None:
            draw_curve(ax, curve, axis, tests, lw=1.4)
        elif curve_pts is not None:
            draw_tests(ax, x, curve_pts, tests, style="-", label=False, lw=1.4)
        ax.set_xlabel(xl)
        ax.set_ylabel("stress (MPa)")
        if j == 0:
            ax.plot([], [], "-", color="k", label="MAP model")
            if band is not None:
                ax.fill_between([], [], [], color="grey", alpha=0.2, label=f"{int(round(100 * prob))}% predictive band")
            ax.legend(fontsize=7, frameon=False, loc="lower right")
            toe_axes(ax, strain, stress, tests, curve, curve_pts)
        # residuals below, on the same axis
        ax = fig.add_subplot(gs[1, j])
        if curve_pts is not None:
            draw_tests(ax, x, stress - curve_pts, tests, style=".", label=False, ms=4)
            ax.axhline(0, color="k", lw=0.8)
        ax.set_xlabel(xl)
        ax.set_ylabel("data − MAP (MPa)")
    cov = "n/a" if q["coverage90"] is None else f"{100 * q['coverage90']:.0f}%"
    fig.suptitle(wrapped(f"{r.specimen_id}: RMSE {q['rmse']:.3g} MPa ({100 * q['rmse_rel']:.1f}% of peak), "
                         f"coverage {cov}, log Z {q['log_evidence']:.2f} ± {q['log_evidence_se']:.2f}", 90), fontsize=9)
    if path is None:
        return fig
    return save(fig, Path(path))
