"""Dense records at the cost of their information: consecutive readings averaged into bins.

A 50 Hz machine export holds thousands of rows whose neighbours differ by noise: the fit's cost
grows with the rows, what they tell about the parameters does not.  :func:`reduce_record`
replaces each run of neighbouring rows of one test by its mean (strain, time, stress) and
keeps how many readings it holds, so the likelihood can give each mean its variance
(:class:`hbm.likelihood.binned.BinnedNoise`: σ²/c for c readings).  The mean of c readings
carries their information about the curve as long as the curve is straight over the bin, so:

* **where the bins are cut.**  Each test is split into *pieces* at the corners of its strain path
  (where the strain starts or stops moving, reverses or changes its rate: the rows depart from a
  straight line by more than ``CORNER`` of the strain span); the stress changes fastest right
  after a corner (a relaxation, the start of a ramp), so bins grow geometrically away from each
  corner (1, 2, 2, 2, 3, 4, 4, 5 ... readings, ratio ``GROWTH``: constant resolution in the
  logarithm of the time since the corner, where relaxation is resolved) up to
  ``ceil(n / TARGET_BINS)`` readings.  The corner rows are bins of
  their own, so every loading history starts and ends where it did.
* **checked on the data.**  A bin whose readings curve -- the bias of its mean, from a quadratic
  fit over the bin, exceeds ``BIAS`` times the noise sd of the mean by two standard errors --
  is split in two, again and again.
* **the noise.**  The raw readings' sd and lag-1 correlation ρ come from the residuals of
  straight lines fitted within the bins; a bin of c readings of AR(1) noise holds
  c / (1 + 2 Σ_{k<c} (1 − k/c) ρ^k) independent readings' worth of information, and that
  *effective* count is what the likelihood uses (:func:`bin_counts`; the specimen's
  ``reduction`` attribute keeps it as ``count`` and the raw count as ``readings``).

A record above ``DENSE_POINTS`` rows is reduced by ``hbm fit``, ``diagnose`` and ``extend``
unless ``--reduce off``; the first output line says so.  ``workflows/benchmarks/dense_records.py``
compares the reduced with the full record's posterior and verdict.
"""

from __future__ import annotations

import json
import math

import numpy as np

from ..errors import HbmError
from .artefacts import segments
from .specimen import Series, Specimen

__all__ = ["DENSE_POINTS", "TARGET_BINS", "reduce_record", "is_reduced", "bin_counts", "reduction_summary",
           "effective_count"]

#: records with more rows than this are reduced ("auto")
DENSE_POINTS = 1000
#: the largest bin holds ceil(rows / TARGET_BINS) readings
TARGET_BINS = 250
#: geometric growth of the bins away from a corner of the strain path
GROWTH = 1.2
#: a bin's mean may differ from the curve at its centre by this share of the mean's noise sd
BIAS = 0.2
#: a corner of the strain path: rows depart from a straight line by more than this share of the span
CORNER = 2e-3


def effective_count(c: np.ndarray, rho: float) -> np.ndarray:
    """Independent readings' worth of the mean of ``c`` consecutive readings of AR(1) noise."""
    c = np.asarray(c, dtype=float)
    if rho <= 0:
        return c
    out = np.empty_like(c)
    for i, m in enumerate(c.astype(int)):
        k = np.arange(1, m)
        out[i] = m / (1.0 + 2.0 * float(np.sum((1.0 - k / m) * rho ** k)))
    return out


def _pieces(eps: np.ndarray, x: np.ndarray) -> list[tuple[int, int]]:
    """Smooth pieces of one test's strain path: row ranges [a, b) whose ends are its corners.

    Douglas–Peucker on (x, strain): a piece whose rows depart from the straight line between its
    end rows by more than ``CORNER`` of the strain span is cut at the row that departs most.
    Independent of the sampling rate, and a quantised position reading (a few quanta of noise)
    does not cut a ramp or a hold."""
    n = eps.size
    tol = CORNER * (float(np.ptp(eps)) or 1.0)
    cuts, todo = {0, n - 1}, [(0, n - 1)]
    while todo:
        a, b = todo.pop()
        if b - a < 2:
            continue
        xa, xb = x[a], x[b]
        t = (x[a:b + 1] - xa) / (xb - xa) if xb > xa else np.linspace(0.0, 1.0, b - a + 1)
        dev = np.abs(eps[a:b + 1] - (eps[a] + t * (eps[b] - eps[a])))
        k = int(np.argmax(dev))
        if dev[k] > tol:
            cuts.add(a + k)
            todo += [(a, a + k), (a + k, b)]
    c = sorted(cuts)
    # a corner row is a bin of its own: pieces [c_i, c_{i+1}) and the last row alone
    out = [(a, b) for a, b in zip(c[:-1], c[1:]) if b > a]
    return out + [(n - 1, n)] if n > 1 else [(0, n)]


def _geometric(length: int, largest: int) -> list[int]:
    """Bin sizes of one piece: growing by ``GROWTH`` from both ends, ``largest`` in between."""
    if length <= 2:
        return [1] * length
    sizes, size = [], 1.0
    total = 0
    while True:
        s = min(int(size), largest)
        if 2 * (total + s) > length or s >= largest:
            break
        sizes.append(s)
        total += s
        size = max(size * GROWTH, size + (1 if size < 2 else 0))
    middle = length - 2 * total
    k = max(1, math.ceil(middle / largest)) if middle > 0 else 0
    mids = [middle // k + (1 if i < middle % k else 0) for i in range(k)] if k else []
    return sizes + mids + sizes[::-1]


def _bias_splits(x: np.ndarray, y: np.ndarray, bins: list[tuple[int, int]], sigma: float) -> list[tuple[int, int]]:
    """Split every bin whose mean is biased beyond ``BIAS`` × its noise sd (module docstring)."""
    out, todo = [], list(bins)
    while todo:
        a, b = todo.pop(0)
        m = b - a
        if m >= 6 and sigma > 0:
            xs = x[a:b] - x[a:b].mean()
            v = float(np.mean(xs * xs))
            if v > 0:
                A = np.column_stack([np.ones(m), xs, xs * xs - v])
                coef, *_ = np.linalg.lstsq(A, y[a:b], rcond=None)
                cov = np.linalg.pinv(A.T @ A) * sigma * sigma
                # the mean minus the curve at the bin's centre: c·(mean of xs² ) = c·v
                bias, se = abs(coef[2]) * v, math.sqrt(max(cov[2, 2], 0.0)) * v
                if bias - 2.0 * se > BIAS * sigma / math.sqrt(m):
                    h = m // 2
                    todo[:0] = [(a, a + h), (a + h, b)]
                    continue
        out.append((a, b))
    return sorted(out)


def _line_residuals(x: np.ndarray, y: np.ndarray, bins: list[tuple[int, int]]) -> list[np.ndarray]:
    res = []
    for a, b in bins:
        if b - a >= 5:
            xs = x[a:b] - x[a:b].mean()
            slope = float(xs @ (y[a:b] - y[a:b].mean()) / max(float(xs @ xs), 1e-300))
            res.append(y[a:b] - y[a:b].mean() - slope * xs)
    return res


def _noise(res: list[np.ndarray]) -> tuple[float, float]:
    """Raw readings' sd and lag-1 correlation from residuals of straight lines within bins."""
    if not res:
        return float("nan"), 0.0
    ss = sum(float(r @ r) for r in res)
    dof = sum(r.size - 2 for r in res)
    lag = sum(float(r[1:] @ r[:-1]) for r in res)
    n1 = sum(r.size - 1 for r in res)
    sigma = math.sqrt(ss / max(dof, 1))
    rho = (lag / max(n1, 1)) / max(ss / max(sum(r.size for r in res), 1), 1e-300)
    return sigma, float(np.clip(rho, 0.0, 0.95))


def reduce_record(spec: Specimen) -> Specimen:
    """The record with each bin of neighbouring readings replaced by its mean (module docstring).

    Parameters
    ----------
    spec : Specimen
        A loaded specimen with its stress series (optional time and tests).

    Returns
    -------
    Specimen
        The bin means (every series averaged, a test's id kept), with the attribute ``reduction``
        (JSON: rows, bins, largest bin, raw noise sd and ρ, rules, and per point ``count`` -- the
        effective independent readings, what the likelihood uses, :func:`bin_counts` -- and
        ``readings`` -- the readings averaged).
    """
    if is_reduced(spec):
        raise HbmError(f"{spec.id}: the record is reduced already")
    strain, stress, time, test = spec.strain, spec.stress, spec.time, spec.test
    n = stress.size
    largest = max(1, math.ceil(n / TARGET_BINS))
    bins: list[tuple[int, int]] = []
    for s0, s1 in segments(n, time, test):
        x = time[s0:s1] if time is not None else np.arange(s1 - s0, dtype=float)
        for a, b in _pieces(strain[s0:s1], x):
            k = s0 + a
            for size in _geometric(b - a, largest):
                bins.append((k, k + size))
                k += size
    xs = time if time is not None else np.arange(n, dtype=float)
    sigma, rho = _noise(_line_residuals(xs, stress, bins))
    bins = _bias_splits(xs, stress, bins, sigma)
    sigma, rho = _noise(_line_residuals(xs, stress, bins))
    starts = np.array([a for a, _ in bins])
    rows = np.array([b - a for a, b in bins])
    mean = lambda v: np.add.reduceat(v, starts) / rows  # noqa: E731
    new_time = None
    if time is not None:
        new_time = mean(time)
        # a history that restarts at time 0 still starts at exactly 0 (its first row is a bin of its own)
        new_time[time[starts] == 0.0] = 0.0
    count = effective_count(rows, rho)
    attrs = dict(spec.attrs)
    attrs["reduction"] = json.dumps({
        "method": "bin means", "rows": int(n), "bins": int(rows.size), "largest_bin": int(rows.max()),
        "growth": GROWTH, "bias_limit": BIAS, "raw_noise_sd": sigma, "raw_noise_rho": rho,
        "effective_readings": float(np.sum(count)), "count": count.tolist(), "readings": rows.tolist()})
    observed = {k: Series(k, mean(s.values), s.unit, s.long_name) for k, s in spec.observed.items()}
    return Specimen(spec.id, mean(strain), new_time, None if test is None else test[starts], observed, attrs)


def _reduction(attrs) -> dict | None:
    text = attrs.get("reduction") if hasattr(attrs, "get") else None
    if not text:
        return None
    try:
        return json.loads(text)
    except (TypeError, ValueError):
        return None


def is_reduced(spec) -> bool:
    """Does ``spec`` hold bin means of a dense record?"""
    return _reduction(getattr(spec, "attrs", {})) is not None


def bin_counts(spec) -> np.ndarray | None:
    """The effective independent readings of each bin mean of a reduced record (None for another).

    Raises
    ------
    HbmError
        When the record's points no longer match its bins (rows selected after the reduction).
    """
    r = _reduction(getattr(spec, "attrs", {}))
    if r is None or "count" not in r:
        return None
    counts = np.asarray(r["count"], dtype=float)
    n = getattr(spec, "n_points", counts.size)
    if counts.size != n:
        raise HbmError(f"{getattr(spec, 'id', 'specimen')}: {n} points but {counts.size} bin counts: rows were "
                       "selected after the reduction (reduce the selected record instead)")
    return counts


def reduction_summary(attrs) -> str:
    """``"7993 rows reduced to 312 bin means (...)"`` from the ``reduction`` attribute ("" if none)."""
    r = _reduction(attrs)
    if r is None:
        return ""
    rho = f", raw noise correlation {r['raw_noise_rho']:.2f} accounted for" if r.get("raw_noise_rho") else ""
    return (f"dense record: {r['rows']} rows reduced to {r['bins']} bin means (at most {r['largest_bin']} readings "
            f"each, cut at the corners of the strain path and where the curve bends{rho}; --reduce off keeps every "
            "row)")
