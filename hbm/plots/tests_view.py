"""Drawing multi-test data test by test, with the model as a dense curve (shared by the fit,
diagnosis and extension figures).

* :func:`dense_path` -- each test's loading path with ``factor`` − 1 points inserted between
  neighbours (strain and time interpolated linearly), kept in one piece where the time
  continues, so that history effects (viscoelastic memory, damage) see the same history;
* :func:`model_curve` -- a likelihood's model evaluated along that path at one parameter row;
* :func:`draw_tests` -- markers (and optionally lines) per test, one colour each, never a line
  from one test's end to the next test's start;
* :func:`toe_axes` -- an inset with log stress over the lower part of the strain range.
"""

from __future__ import annotations

import textwrap

import numpy as np

from ..data.specimen import Specimen
from ..model.core import Loading
from . import plt

__all__ = ["TEST_COLORS", "test_ids", "dense_path", "model_curve", "draw_tests", "draw_curve", "toe_axes", "wrapped"]

TEST_COLORS = plt.get_cmap("tab10").colors


def test_ids(spec: Specimen) -> np.ndarray:
    """The test id of each point of a specimen (zeros without a test column)."""
    return np.zeros(spec.n_points, int) if spec.test is None else spec.test


def dense_path(spec: Specimen, factor: int = 8) -> dict:
    """The specimen's loading path with ``factor`` − 1 interpolated points between neighbours of one history.

    A history (time continuing, or one test without time) is densified as a whole; the inserted
    points belong to the test of the point they follow.  Returns ``strain``, ``time`` (or None)
    and ``test`` arrays of the dense path.
    """
    strain, time, test = spec.strain, spec.time, test_ids(spec)
    hist = spec.loading.history
    xs, ts, ks = [], [], []
    for h in np.unique(hist):
        idx = np.flatnonzero(hist == h)
        u = np.arange((idx.size - 1) * factor + 1) / factor
        base = np.arange(idx.size)
        xs.append(np.interp(u, base, strain[idx]))
        if time is not None:
            ts.append(np.interp(u, base, np.asarray(time, float)[idx]))
        ks.append(np.asarray(test)[idx][np.minimum(np.floor(u).astype(int), idx.size - 1)])
    k = np.concatenate(ks)
    hd = np.concatenate([np.full(x.size, j) for j, x in enumerate(xs)])
    # one drawable piece per run of one test within one history
    piece = np.cumsum(np.r_[True, (k[1:] != k[:-1]) | (hd[1:] != hd[:-1])]) - 1
    return {"strain": np.concatenate(xs), "time": np.concatenate(ts) if time is not None else None,
            "test": k, "piece": piece}


def model_curve(lik, x, spec: Specimen, factor: int = 8) -> dict:
    """``lik``'s model stress at free vector ``x`` along the specimen's dense path (:func:`dense_path`).

    Returns the dense path with ``stress``; ``None`` when the model cannot be evaluated off the
    data points (the caller then draws the prediction at the data points).
    """
    path = dense_path(spec, factor)
    try:
        theta = np.asarray(lik.model_theta(np.asarray(x, float)[None, :]))[0]
        with np.errstate(all="ignore"):
            s = np.asarray(lik.model.stress(Loading(path["strain"], path["time"], path["test"]), theta), float)
    except Exception:    # noqa: BLE001 -- a model tied to its data points (e.g. a user effect): no dense curve
        return None
    return {**path, "stress": s.reshape(-1)}


def draw_tests(ax, x: np.ndarray, y: np.ndarray, tests: np.ndarray, *, style: str = "o", label: bool = True,
               **kw) -> None:
    """Draw ``y`` against ``x`` one test at a time (colour per test, nothing joins two tests)."""
    for k, t in enumerate(np.unique(tests)):
        m = tests == t
        ax.plot(x[m], y[m], style, color=TEST_COLORS[k % len(TEST_COLORS)],
                label=(f"test {t}" if label else None), **kw)


def draw_curve(ax, curve: dict, axis: str, tests: np.ndarray, **kw) -> None:
    """The dense model curve against ``axis`` ("strain" or "time"), a line per piece (one test
    within one history), in its test's colour."""
    order = {t: k for k, t in enumerate(np.unique(tests))}
    for p in np.unique(curve["piece"]):
        m = curve["piece"] == p
        t = curve["test"][m][0]
        ax.plot(curve[axis][m], curve["stress"][m], color=TEST_COLORS[order.get(t, 0) % len(TEST_COLORS)],
                **{"ls": "-", **kw})


def toe_axes(ax, strain: np.ndarray, stress: np.ndarray, tests: np.ndarray, curve: dict | None,
             pred: np.ndarray | None = None):
    """An inset with log stress over the lower 40 % of the strain range (where the relative
    error of a fit is largest); None when no positive stress is there."""
    strain, stress = np.asarray(strain, float), np.asarray(stress, float)
    cut = float(np.min(strain) + 0.4 * np.ptp(strain))
    m = (strain <= cut) & (stress > 0)
    if m.sum() < 3:
        return None
    ins = ax.inset_axes([0.17, 0.55, 0.33, 0.40])
    for k, t in enumerate(np.unique(tests)):
        col = TEST_COLORS[k % len(TEST_COLORS)]
        mt = m & (tests == t)
        ins.plot(strain[mt], stress[mt], "o", ms=2, color=col, alpha=0.8)
        if curve is not None:
            for p in np.unique(curve["piece"][curve["test"] == t]):
                mc = (curve["piece"] == p) & (curve["strain"] <= cut) & (curve["stress"] > 0)
                ins.plot(curve["strain"][mc], curve["stress"][mc], "-", lw=0.9, color=col)
        elif pred is not None:
            mp = mt & (pred > 0)
            ins.plot(strain[mp], pred[mp], "-", lw=1, color=col)
    ins.set_yscale("log")
    ins.yaxis.set_minor_formatter(plt.NullFormatter())   # decades only: minor labels crowd the inset
    ins.set_title("toe (log stress)", fontsize=7)
    ins.tick_params(labelsize=6)
    return ins


def wrapped(text: str, width: int = 120, max_lines: int = 8) -> str:
    """``text`` wrapped for a figure title (and shortened beyond ``max_lines``)."""
    lines = textwrap.wrap(text, width)
    if len(lines) > max_lines:
        lines = lines[:max_lines - 1] + [lines[max_lines - 1][: width - 20] + " … (see the text report)"]
    return "\n".join(lines)
