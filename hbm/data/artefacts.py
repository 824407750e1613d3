"""Rows a testing machine wrote that are not the tissue: found before any fit, named, dropped on request.

A robust, model-free screen of each test's path (its rows in order, against time where the test
has it).  Every row is compared with three robust straight lines through its neighbours (not
through itself): one through the ``K`` rows before it, one through the ``K`` rows after it, one
through both.  The lines are *repeated-median* fits (Siegel 1982), which ignore up to half of
their points, so a neighbouring artefact does not hide a row.  A row is flagged when

* it misses the two-sided line by more than ``THRESHOLD`` times the local scale -- the robust
  spread (1.4826 × median absolute deviation) of the same statistic over the ``SCALE_WINDOW``
  rows on each side, so that a strongly curved or coarsely sampled stretch raises its own bar;
* and both one-sided lines miss it in the same direction by at least half as much.  At a true
  corner of the path -- the peak where a ramp turns into a relaxation hold, a load reversal --
  the line from the side that leads into the corner predicts the row, so corners are not flagged.

The first row of a test is judged by the line after it alone, at ``EDGE_FACTOR`` times the bar,
and named a *pre-test reading* when it sits at (near) zero strain with a stress far from where
the test starts; the last row by the line before it, at the same bar.  Two rules need no line:

* a *post-failure tail*: the stress falls from at least half its running peak to below
  ``TAIL_LEVEL`` of it within ``TAIL_ROWS`` rows while the strain keeps growing, and stays there to
  the end of the test (a relaxation never falls that far: the library's relaxing fraction is ≤ 0.9);
* flagged rows whose stress is near zero between loaded neighbours are *dropouts*, and rows below
  their neighbours at constant strain are *dips during a hold*; the rest are *spikes*.

The thresholds were set on the shipped specimens, synthetic clean records (ramps, holds, cycles,
iid and AR(1) noise, 40-8000 rows; none flagged) and the measured raw record of
``tests/data`` (its pre-test reading flagged); ``tests/test_artefacts.py`` checks both.
"""

from __future__ import annotations

import json
import warnings
from dataclasses import dataclass

import numpy as np

__all__ = ["Artefact", "segments", "screen_artefacts", "artefact_rows", "drop_rows", "describe_artefacts", "data_lines",
           "THRESHOLD"]

#: rows on each side of a row that its robust lines go through
K = 5
#: bar of the two-sided miss, in local scales (the one-sided misses need half of it)
THRESHOLD = 10.0
#: a test's first or last row (one line only) needs this many times the bar
EDGE_FACTOR = 2.0
#: rows on each side over which the local scale is the median absolute miss
SCALE_WINDOW = 15
#: a pre-test reading sits within this fraction of the test's largest |strain| from zero strain
PRETEST_STRAIN = 0.05
#: post-failure tail: the stress stays below this fraction of its running peak ...
TAIL_LEVEL = 0.05
#: ... after falling from half of it within this many rows
TAIL_ROWS = 3


@dataclass(frozen=True)
class Artefact:
    """Rows of one artefact: ``kind``, the 0-based ``rows`` (points of the dataset) and what was seen."""

    kind: str
    rows: tuple[int, ...]
    detail: str

    def to_dict(self, lines=None) -> dict:
        """JSON-ready: kind, rows (0-based points), the file's lines where known, detail."""
        out = {"kind": self.kind, "rows": list(self.rows), "detail": self.detail}
        if lines is not None:
            out["lines"] = [int(lines[r]) for r in self.rows]
        return out


def _repeated_median(x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Repeated-median lines of many small point sets at once: ``x``, ``y`` (m, k) with NaN for
    absent points; returns (slope, intercept), each (m,), NaN where fewer than two points."""
    dx = x[:, :, None] - x[:, None, :]
    dy = y[:, :, None] - y[:, None, :]
    with np.errstate(invalid="ignore", divide="ignore"):
        s = dy / dx
    k = x.shape[1]
    s[:, np.arange(k), np.arange(k)] = np.nan
    s[~np.isfinite(s)] = np.nan
    with np.errstate(all="ignore"):
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)   # all-NaN rows: fewer than two points
            slope = np.nanmedian(np.nanmedian(s, axis=2), axis=1)
            intercept = np.nanmedian(y - slope[:, None] * x, axis=1)
    return slope, intercept


def _windows(n: int, offsets: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Indices i + offsets for every row i, and which of them exist (0 <= index < n)."""
    idx = np.arange(n)[:, None] + offsets[None, :]
    ok = (idx >= 0) & (idx < n)
    return np.clip(idx, 0, n - 1), ok


def _predict(x: np.ndarray, y: np.ndarray, offsets: np.ndarray) -> np.ndarray:
    """Each row's value on the repeated-median line through its neighbours at ``offsets`` (NaN:
    fewer than two of them)."""
    idx, ok = _windows(x.size, offsets)
    xs, ys = np.where(ok, x[idx], np.nan), np.where(ok, y[idx], np.nan)
    xc = x[:, None]
    slope, intercept = _repeated_median(xs - xc, ys)       # centred on the row: intercept is the value
    enough = ok.sum(axis=1) >= 2
    return np.where(enough, intercept, np.nan)


def _local_scale(e: np.ndarray, floor: float) -> np.ndarray:
    """1.4826 × the median |e| of the ``SCALE_WINDOW`` rows on each side (the row itself left out),
    at least that of the whole test (a local median of a few rows is itself noisy: the bar may rise
    where the path curves, never fall below the test's own spread) and ``floor``."""
    offsets = np.concatenate([np.arange(-SCALE_WINDOW, 0), np.arange(1, SCALE_WINDOW + 1)])
    idx, ok = _windows(e.size, offsets)
    a = np.where(ok, np.abs(e[idx]), np.nan)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        s = 1.4826 * np.nanmedian(a, axis=1)
    whole = 1.4826 * float(np.median(np.abs(e)))
    return np.maximum(np.where(np.isfinite(s), s, floor), max(floor, whole))


def _floor(y: np.ndarray, span: float) -> float:
    """The smallest scale a row is judged on: half the reading's resolution -- the 5th percentile of
    the steps between rows, counting only steps above a twentieth of the median step (a Cauchy
    factor makes equal machine readings differ by far less than the resolution) -- or 1e-9 of the span."""
    steps = np.abs(np.diff(y))
    steps = steps[steps > 1e-12 * span]
    if steps.size:
        steps = steps[steps > 0.05 * float(np.median(steps))]
    return max(0.5 * float(np.quantile(steps, 0.05)) if steps.size else 0.0, 1e-9 * span)


def segments(n: int, time: np.ndarray | None, test: np.ndarray | None) -> list[tuple[int, int]]:
    """Row ranges [a, b) of a record's tests (contiguous rows of one test id), split where time restarts."""
    starts = np.zeros(n, bool)
    starts[0] = True
    if test is not None:
        starts[1:] |= test[1:] != test[:-1]
    if time is not None:
        starts[1:] |= np.diff(time) < 0
    bounds = np.append(np.flatnonzero(starts), n)
    return list(zip(bounds[:-1].tolist(), bounds[1:].tolist()))


def _fmt(strain, stress, time, i) -> str:
    t = f"t = {time[i]:.4g} s, " if time is not None else ""
    return f"{t}strain {strain[i]:.4g}, stress {stress[i]:.4g} MPa"


def _screen_segment(idx: np.ndarray, strain, stress, time) -> list[Artefact]:
    y = stress[idx]
    n = y.size
    if n < 2 * K + 1:
        return []
    tseg = None if time is None else time[idx]
    x = tseg.astype(float) if tseg is not None and np.all(np.diff(tseg) > 0) else np.arange(n, dtype=float)
    span = float(np.max(np.abs(y))) or 1.0
    # the scale floor: the reading's resolution (smallest step between rows) or a tiny share of the span
    floor = _floor(y, span)
    left = _predict(x, y, np.arange(-K, 0))
    right = _predict(x, y, np.arange(1, K + 1))
    both = _predict(x, y, np.concatenate([np.arange(-K, 0), np.arange(1, K + 1)]))
    e_c, e_l, e_r = y - both, y - left, y - right
    scale = _local_scale(np.where(np.isfinite(e_c), e_c, 0.0), floor)
    bar = THRESHOLD * scale
    sign = np.sign(e_c)
    inner = (np.abs(e_c) > bar) & (sign * e_l > 0.5 * bar) & (sign * e_r > 0.5 * bar)
    inner[[0, n - 1]] = False
    flagged = set(np.flatnonzero(inner).tolist())
    out: list[Artefact] = []
    eps = strain[idx]
    reach = float(np.max(np.abs(eps))) or 1.0
    # the first rows: a pre-test reading (zero strain, stress far from where the test starts)
    j = 0
    while j < K and n - j > 2 * K:
        rest = y[j + 1:]
        pred = _predict(x[j:], y[j:], np.arange(1, K + 1))[0]
        miss = y[j] - pred
        if not (abs(miss) > EDGE_FACTOR * bar[j] and abs(eps[j]) <= PRETEST_STRAIN * reach
                and abs(y[j]) > 0.5 * float(np.max(np.abs(rest[:K])))):
            break
        out.append(Artefact("pre-test reading", (int(idx[j]),),
                            f"{_fmt(strain, stress, time, idx[j])} at the start of the test, where the rows after it "
                            f"start from {pred:.4g} MPa ({abs(miss) / scale[j]:.0f} local scales away)"))
        j += 1
    last = n - 1
    if np.isfinite(e_l[last]) and abs(e_l[last]) > EDGE_FACTOR * bar[last] and last not in flagged:
        flagged.add(last)
    tail = _tail(y, eps)
    for i in sorted(flagged):
        if tail is not None and i >= tail:
            continue
        out.append(_classify(i, idx, y, eps, both if i < last else left, strain, stress, time, scale))
    if tail is not None:
        rows = tuple(int(r) for r in idx[tail:])
        out.append(Artefact("post-failure tail", rows,
                            f"the stress falls to below {TAIL_LEVEL:.0%} of its peak at "
                            f"{_fmt(strain, stress, time, idx[tail])} "
                            f"while the strain keeps growing, and stays there for the {len(rows)} rows to the end of "
                            "the test (the specimen failed)"))
    return _merge(out)


def _classify(i, idx, y, eps, pred, strain, stress, time, scale) -> Artefact:
    """A flagged row: dropout (a reading near zero), dip during a hold (constant strain, towards
    zero) or spike."""
    p = pred[i]
    lo, hi = max(0, i - K), min(y.size, i + K + 1)
    held = np.ptp(eps[lo:hi]) <= 1e-3 * max(float(np.max(np.abs(eps))), 1e-12)
    what = f"{_fmt(strain, stress, time, idx[i])}, where its neighbours give {p:.4g} MPa " \
           f"({abs(y[i] - p) / scale[i]:.0f} local scales away)"
    if abs(y[i]) < 0.1 * abs(p):
        return Artefact("dropout", (int(idx[i]),), what + ": a reading near zero between loaded rows")
    if held and abs(y[i]) < abs(p):
        return Artefact("dip during a hold", (int(idx[i]),), what + ": the load dips at constant strain")
    return Artefact("spike", (int(idx[i]),), what)


def _merge(found: list[Artefact]) -> list[Artefact]:
    """Neighbouring rows of the same kind (a two-row dip) as one artefact."""
    found = sorted(found, key=lambda a: a.rows[0])
    out: list[Artefact] = []
    for a in found:
        if out and out[-1].kind == a.kind and a.kind != "post-failure tail" and a.rows[0] - out[-1].rows[-1] == 1:
            prev = out[-1]
            out[-1] = Artefact(prev.kind, prev.rows + a.rows, prev.detail + "; " + a.detail)
        else:
            out.append(a)
    return out


def _tail(y: np.ndarray, eps: np.ndarray) -> int | None:
    """First row of a post-failure tail (module docstring), or None."""
    peak = np.maximum.accumulate(np.abs(y))
    n = y.size
    for f in range(1, n - 1):
        if abs(y[f]) >= TAIL_LEVEL * peak[f - 1] or peak[f - 1] <= 0:
            continue
        before = max(0, f - TAIL_ROWS)
        if not np.any(np.abs(y[before:f]) >= 0.5 * peak[f - 1]):
            continue
        if np.all(np.abs(y[f:]) < TAIL_LEVEL * peak[f - 1]) and abs(eps[-1]) > abs(eps[f - 1]) and n - f >= 2:
            return f
        return None
    return None


def screen_artefacts(strain, stress, time=None, test=None) -> list[Artefact]:
    """Find the rows that are not the tissue (module docstring), before any fit.

    Parameters
    ----------
    strain, stress : array (n,)
        Engineering strain and Cauchy stress (MPa) as loaded.
    time, test : array (n,), optional
        The tests' time and ids (the screen runs test by test, against time where there is).

    Returns
    -------
    list of Artefact
        In row order; empty for a clean record.
    """
    strain, stress = np.asarray(strain, float), np.asarray(stress, float)
    time = None if time is None else np.asarray(time, float)
    test = None if test is None else np.asarray(test)
    out: list[Artefact] = []
    for a, b in segments(stress.size, time, test):
        out += _screen_segment(np.arange(a, b), strain, stress, time)
    return out


def artefact_rows(found) -> list[int]:
    """The flagged rows (0-based points), sorted."""
    return sorted({r for a in found for r in a.rows})


def data_lines(path) -> list[int] | None:
    """The line number of every data row of a specimen file (after the header), or None when the
    file cannot be read: the loader's rules (comment lines before the header, blank lines skipped)."""
    try:
        text = open(path, encoding="utf-8-sig").read()
    except (OSError, UnicodeDecodeError, TypeError):
        return None
    lines, header = [], False
    for k, line in enumerate(text.replace("\r\n", "\n").replace("\r", "\n").split("\n"), start=1):
        if not line.strip() or (not header and line.lstrip().startswith("#")):
            continue
        if not header:
            header = True
            continue
        lines.append(k)
    return lines


def describe_artefacts(found, lines=None) -> str:
    """One clause per artefact, naming its rows (the file's lines where known)."""
    parts = []
    for a in found:
        where = (f"line{'s' if len(a.rows) > 1 else ''} {_ranges([lines[r] for r in a.rows])}" if lines is not None
                 else f"row{'s' if len(a.rows) > 1 else ''} {_ranges([r + 1 for r in a.rows])}")
        parts.append(f"{where}: {a.kind} ({a.detail})")
    return "; ".join(parts)


def _ranges(values: list[int]) -> str:
    out, start, prev = [], None, None
    for v in values:
        if start is None:
            start = prev = v
        elif v == prev + 1:
            prev = v
        else:
            out.append(f"{start}" if start == prev else f"{start}-{prev}")
            start = prev = v
    if start is not None:
        out.append(f"{start}" if start == prev else f"{start}-{prev}")
    return ", ".join(out)


def drop_rows(spec, found, lines=None):
    """The specimen without the artefacts' rows, the drop recorded in its attributes
    (``dropped_rows``: JSON list of {kind, rows, lines, detail}).

    Parameters
    ----------
    spec : Specimen
        A loaded specimen.
    found : list of Artefact
        :func:`screen_artefacts`'s result.
    lines : list of int, optional
        The file's line of every row (:func:`data_lines`), named in the record.
    """
    rows = artefact_rows(found)
    if not rows:
        return spec
    keep = np.setdiff1d(np.arange(spec.n_points), rows)
    return spec.select(keep).with_attrs(dropped_rows=json.dumps([a.to_dict(lines) for a in found]))
