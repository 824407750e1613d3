"""The VOLF–T1 manifold of a specimen (thesis Appendix B) and its comparison across specimens.

* :func:`volf_t1_manifold` — cubic spline of T1 against VOLF (in the coordinates
  (−log(1 − VOLF), log T1), because T1 ∝ 1/(1 − VOLF) on the structural manifold rises
  steeply as VOLF → 1; see :class:`VolfT1Manifold`) through CMA-ES sweep optima or through
  binned medians of posterior samples; reports the implied (1 − VOLF)·T1 along the curve
  (constant ⇔ the structural manifold).
* :func:`compare_manifolds` — levels of (1 − VOLF)·T1 per specimen with intervals, and which
  specimens differ beyond their uncertainty (non-overlapping intervals).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Mapping

import numpy as np
from scipy.interpolate import PchipInterpolator, make_smoothing_spline

from ..errors import HbmError

__all__ = ["VolfT1Manifold", "volf_t1_manifold", "ManifoldComparison", "compare_manifolds"]


# --------------------------------------------------------------------------------------
# (b) the VOLF–T1 manifold
# --------------------------------------------------------------------------------------
@dataclass
class VolfT1Manifold:
    """A fitted VOLF–T1 curve: T1(VOLF) = exp(S(−log(1 − VOLF))), S a shape-preserving cubic spline.

    S is the piecewise-cubic Hermite interpolant of Fritsch–Carlson (scipy PchipInterpolator):
    C¹, cubic on every interval, and it never overshoots the knots.  A natural (C²) cubic spline
    through CMA-ES sweep optima that wander (a specimen whose T1 the data do not fix, so
    neighbouring windows land on different T1–T2 trade-offs) oscillated between knots by a
    factor of 5 on the shipped data, which drew a manifold that no optimum supports.

    The abscissa −log(1 − VOLF) and the ordinate log T1 make a constant (1 − VOLF)·T1 a
    straight line, which the spline reproduces exactly; in plain (VOLF, T1) or
    (VOLF, log T1) coordinates the 1/(1 − VOLF) rise near VOLF → 1 put a 6 % interpolation
    error into (1 − VOLF)·T1 between equally spaced sweep optima (measured), which would be
    mistaken for a departure from the structural manifold.  Any other monotone or
    non-monotone relation is still representable.

    Attributes
    ----------
    knots_volf, knots_log_t1 : ndarray
        Nodes of the spline (CMA-ES optima, or bin centres of samples with smoothed values).
    level : ndarray [median, lo, hi]
        (1 − VOLF)·T1 of the input points/samples: median and interval.
    level_interval : (float, float)
        Quantiles used for ``level``.
    source : str
        "points" (interpolating spline through optima) or "samples" (smoothing spline
        through binned medians).
    n_input : int
    """

    knots_volf: np.ndarray
    knots_log_t1: np.ndarray
    level: np.ndarray
    level_interval: tuple
    source: str
    n_input: int

    def __post_init__(self):
        self.knots_volf = np.asarray(self.knots_volf, float)
        self.knots_log_t1 = np.asarray(self.knots_log_t1, float)
        self._spline = PchipInterpolator(-np.log1p(-self.knots_volf), self.knots_log_t1, extrapolate=False)

    @property
    def volf_range(self) -> tuple[float, float]:
        return float(self.knots_volf[0]), float(self.knots_volf[-1])

    def __call__(self, volf) -> np.ndarray:
        """T1 on the curve at ``volf`` (NaN outside the fitted VOLF range)."""
        v = np.asarray(volf, float)
        with np.errstate(divide="ignore", invalid="ignore"):
            return np.exp(self._spline(-np.log1p(-v)))

    def product(self, volf) -> np.ndarray:
        """(1 − VOLF)·T1(VOLF) along the curve."""
        volf = np.asarray(volf, float)
        return (1.0 - volf) * self(volf)

    def grid(self, n: int = 50) -> np.ndarray:
        return np.linspace(*self.volf_range, n)

    @property
    def flatness(self) -> float:
        """(max − min)/median of (1 − VOLF)·T1 along the curve: ≈ 0 on the structural manifold."""
        p = self.product(self.grid(200))
        return float((p.max() - p.min()) / np.median(p))

    def to_arrays(self, n_grid: int = 50) -> dict[str, np.ndarray]:
        """Plain arrays (for netCDF): knots, level, and the curve on a grid."""
        g = self.grid(n_grid)
        return {
            "knots_volf": self.knots_volf.copy(), "knots_log_t1": self.knots_log_t1.copy(),
            "level": np.asarray(self.level, float).copy(), "level_interval": np.asarray(self.level_interval, float),
            "grid_volf": g, "grid_t1": self(g), "grid_product": self.product(g),
            "n_input": np.asarray(self.n_input), "source": np.asarray(self.source),
        }

    @classmethod
    def from_arrays(cls, arrays: Mapping[str, np.ndarray]) -> "VolfT1Manifold":
        """Inverse of :meth:`to_arrays`."""
        try:
            return cls(knots_volf=np.asarray(arrays["knots_volf"]), knots_log_t1=np.asarray(arrays["knots_log_t1"]),
                       level=np.asarray(arrays["level"]), level_interval=tuple(np.asarray(arrays["level_interval"]).tolist()),
                       source=str(np.asarray(arrays["source"])), n_input=int(np.asarray(arrays["n_input"])))
        except KeyError as exc:
            raise HbmError(f"VolfT1Manifold.from_arrays: missing field {exc.args[0]!r}") from None


def volf_t1_manifold(
    volf,
    t1,
    *,
    source: str = "auto",
    n_bins: int = 15,
    smooth: bool | None = None,
    interval: tuple[float, float] = (0.05, 0.95),
    min_points: int = 4,
) -> VolfT1Manifold:
    """Fit the VOLF–T1 curve (thesis Appendix B, automated).

    Parameters
    ----------
    volf, t1 : array_like (n,)
        CMA-ES sweep optima (one per VOLF sub-range) and/or posterior samples.
    source : {"auto", "points", "samples"}
        "points": sort by VOLF, average duplicates, shape-preserving cubic spline through them
        (interpolating, as in the thesis; ``smooth=True`` uses a GCV smoothing spline
        instead).  "samples": split VOLF into ``n_bins`` equal-count bins, take the median
        VOLF and median log T1 of each bin (medians commute with the monotone VOLF ↦ T1 of a
        manifold, so the knots lie on it) and interpolate them (``smooth=True``: GCV smoothing
        spline weighted by bin counts, whose values at the bin medians become the knots; it
        bends the steep end near VOLF → 1, so it is not the default).
        "auto": "samples" if n > 10·n_bins.
    n_bins : int
    smooth : bool, optional
        GCV smoothing instead of interpolation (default False).
    interval : (float, float)
        Quantiles of the (1 − VOLF)·T1 level interval.
    min_points : int
        Fewer distinct VOLF values than this is an error.

    Returns
    -------
    VolfT1Manifold
    """
    v = np.asarray(volf, float).ravel()
    t = np.asarray(t1, float).ravel()
    if v.shape != t.shape:
        raise HbmError(f"volf_t1_manifold: volf and t1 must have the same length, got {v.size} and {t.size}")
    ok = np.isfinite(v) & np.isfinite(t) & (t > 0) & (v < 1)
    v, t = v[ok], t[ok]
    if source == "auto":
        source = "samples" if v.size > 10 * n_bins else "points"
    if source not in ("points", "samples"):
        raise HbmError(f"volf_t1_manifold: source must be 'auto', 'points' or 'samples', got {source!r}")
    prod = (1.0 - v) * t
    if prod.size == 0:
        raise HbmError("volf_t1_manifold: no finite points with T1 > 0 and VOLF < 1")
    level = np.quantile(prod, [0.5, interval[0], interval[1]])
    lt = np.log(t)
    if source == "points":
        order = np.argsort(v)
        xs, inv = np.unique(np.round(v[order], 12), return_inverse=True)
        ys = np.bincount(inv, weights=lt[order]) / np.bincount(inv)
        if xs.size < min_points:
            raise HbmError(f"volf_t1_manifold: need at least {min_points} distinct VOLF values, got {xs.size}")
        if smooth and xs.size >= 5:
            ys = make_smoothing_spline(xs, ys)(xs)
        knots_x, knots_y = xs, ys
    else:
        if v.size < max(min_points, 5) * 2:
            raise HbmError(f"volf_t1_manifold: too few samples ({v.size}) for {n_bins} bins")
        nb = int(min(n_bins, v.size // 10))
        edges = np.quantile(v, np.linspace(0, 1, nb + 1))
        idx = np.clip(np.searchsorted(edges, v, side="right") - 1, 0, nb - 1)
        xs, ys, ws = [], [], []
        for b in range(nb):  # loop over bins (few), vectorised within
            m = idx == b
            if m.sum() >= 3:
                xs.append(np.median(v[m]))
                ys.append(np.median(lt[m]))
                ws.append(m.sum())
        xs, ys, ws = np.array(xs), np.array(ys), np.array(ws, float)
        keep = np.concatenate([[True], np.diff(xs) > 1e-12])
        xs, ys, ws = xs[keep], ys[keep], ws[keep]
        if xs.size < min_points:
            raise HbmError(f"volf_t1_manifold: samples span fewer than {min_points} distinct VOLF bins")
        if smooth and xs.size >= 5:
            ys = make_smoothing_spline(xs, ys, w=ws / ws.mean())(xs)
        knots_x, knots_y = xs, ys
    return VolfT1Manifold(knots_volf=knots_x, knots_log_t1=knots_y, level=level, level_interval=tuple(interval),
                          source=source, n_input=int(v.size))


# --------------------------------------------------------------------------------------
# (c) comparison across specimens
# --------------------------------------------------------------------------------------
@dataclass
class ManifoldComparison:
    """Differences between specimens' VOLF–T1 manifolds.

    Attributes
    ----------
    specimens : list of str
    level : ndarray (n, 3)
        (1 − VOLF)·T1 median, lo, hi per specimen.
    flatness : ndarray (n,)
    overlap : ndarray (n, n) bool
        Whether the level intervals of two specimens overlap.
    differ : list of (str, str)
        Pairs whose intervals do not overlap (they differ beyond their uncertainty).
    grid_volf : ndarray (g,)
        Common VOLF grid (intersection of the fitted ranges; empty if they do not intersect).
    grid_t1 : ndarray (n, g)
    spread : float
        max/min ratio of the specimen medians of (1 − VOLF)·T1.
    """

    specimens: list
    level: np.ndarray
    flatness: np.ndarray
    overlap: np.ndarray
    differ: list
    grid_volf: np.ndarray
    grid_t1: np.ndarray
    spread: float

    def table(self) -> str:
        """Markdown table of the levels per specimen."""
        lines = ["| specimen | (1-VOLF)·T1 median | interval | flatness along curve |", "|---|---|---|---|"]
        for s, (m, a, b), f in zip(self.specimens, self.level, self.flatness):
            lines.append(f"| {s} | {m:.4g} | [{a:.4g}, {b:.4g}] | {f:.3g} |")
        if self.differ:
            lines.append("")
            lines.append("Differ beyond their uncertainty: " + ", ".join(f"{a}–{b}" for a, b in self.differ))
        return "\n".join(lines)


def compare_manifolds(manifolds: Mapping[str, VolfT1Manifold], *, n_grid: int = 50) -> ManifoldComparison:
    """Compare the VOLF–T1 manifolds of several specimens.

    Parameters
    ----------
    manifolds : mapping specimen -> VolfT1Manifold
    n_grid : int
        Points of the common VOLF grid.

    Returns
    -------
    ManifoldComparison
    """
    if not manifolds:
        raise HbmError("compare_manifolds: no manifolds given")
    specs = list(manifolds)
    lev = np.array([np.asarray(manifolds[s].level, float) for s in specs])
    flat = np.array([manifolds[s].flatness for s in specs])
    lo, hi = lev[:, 1], lev[:, 2]
    overlap = (lo[:, None] <= hi[None, :]) & (lo[None, :] <= hi[:, None])
    differ = [(specs[i], specs[j]) for i in range(len(specs)) for j in range(i + 1, len(specs)) if not overlap[i, j]]
    a = max(manifolds[s].volf_range[0] for s in specs)
    b = min(manifolds[s].volf_range[1] for s in specs)
    g = np.linspace(a, b, n_grid) if b > a else np.empty(0)
    curves = np.array([manifolds[s](g) for s in specs]) if g.size else np.empty((len(specs), 0))
    spread = float(lev[:, 0].max() / lev[:, 0].min()) if lev[:, 0].min() > 0 else float("inf")
    return ManifoldComparison(specimens=specs, level=lev, flatness=flat, overlap=overlap, differ=differ,
                              grid_volf=g, grid_t1=curves, spread=spread)
