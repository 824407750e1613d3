"""The prior an amplitude column inherits from the box priors of the parameters it carries.

A column amplitude is ``A = offset + Σ_i w_i·a_i`` with each original parameter ``a_i`` carrying an
independent box prior, uniform or log-uniform on ``[lo_i, hi_i]``, the weights ``w_i > 0`` given
by the nonlinear parameters (e.g. G = c·GF + (1−c)·GM, AF = c·P1) and ``offset`` the part of
parameters held fixed.  The density of ``A`` is derived, never assumed (a flat prior on G instead
of the trapezoid below moves the benchmark's log Z by +0.33 nats):

=====================  ====================================================================
terms                  density of A (u = w_1·a_1 ∈ [a1, b1], v = w_2·a_2 ∈ [a2, b2])
=====================  ====================================================================
1 uniform              1/(b1 − a1) on [a1, b1]
1 log-uniform          1/(A·L1) on [a1, b1], L1 = log(hi_1/lo_1)
2 uniform              trapezoid: the convolution of U[a1, b1] and U[a2, b2]; knots
                       a1+a2, a1+a2+min(ℓ1, ℓ2), a1+a2+max(ℓ1, ℓ2), b1+b2 (ℓ = b − a),
                       plateau 1/max(ℓ1, ℓ2)
2 log-uniform          [log(u/(A − u))]_{u0}^{u1} / (L1·L2·A)
uniform u + log v      log((A − u0)/(A − u1)) / (ℓ1·L2)
log u + uniform v      log((A − v0)/(A − v1)) / (ℓ2·L1)
=====================  ====================================================================

with ``u0 = max(a1, A − b2)``, ``u1 = min(b1, A − a2)`` (the feasible part of the segment
u + v = A) and ``v0, v1`` likewise.  Columns with three or more free terms are refused
(:class:`CollapseError`): their density is a piecewise polynomial of higher degree (uniform) or
has no closed form here (log-uniform).

Given A, the original parameters follow from the same convolution (:meth:`ColumnPrior.split`):
``u`` given ``A`` has the density ∝ f_u(u)·f_v(A − u) on ``[u0, u1]`` -- uniform for two uniform
terms, uniform in ``log(u/(A − u))`` for two log-uniform terms, uniform in ``log(A − u)`` (resp.
``log(A − v)``) for the mixed ones.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ...errors import HbmError
from ..prior import ParameterPrior

__all__ = ["CollapseError", "Term", "ColumnPrior"]


class CollapseError(HbmError):
    """The collapsed (amplitude-integrated) likelihood cannot be used; the message says why."""


@dataclass(frozen=True)
class Term(ParameterPrior):
    """One original parameter feeding a column: its box and prior form, and its name."""

    name: str = ""

    @classmethod
    def of(cls, name: str, lo: float, hi: float, form: str = "uniform") -> "Term":
        return cls(float(lo), float(hi), form, str(name))

    @property
    def log_width(self) -> float:
        return float(np.log(self.hi / self.lo))


def _pwlin(x: np.ndarray, knots: np.ndarray, values: np.ndarray) -> np.ndarray:
    """Piecewise-linear interpolation row by row (knots (n, K) sorted, values (n, K)); 0 outside.

    ``x`` has shape (n, ...); knots may repeat (zero-width pieces are skipped).
    """
    extra = (1,) * (x.ndim - 1)
    out = np.zeros(x.shape)
    for i in range(knots.shape[1] - 1):  # loop over the ≤ 3 pieces, not over samples
        k0, k1 = knots[:, i].reshape((-1,) + extra), knots[:, i + 1].reshape((-1,) + extra)
        v0, v1 = values[:, i].reshape((-1,) + extra), values[:, i + 1].reshape((-1,) + extra)
        width = k1 - k0
        inside = (x >= k0) & (x <= k1) & (width > 0)
        t = np.where(width > 0, (x - k0) / np.where(width > 0, width, 1.0), 0.0)
        out = np.where(inside, v0 + (v1 - v0) * t, out)
    return out


class ColumnPrior:
    """Density of one column amplitude A = offset + Σ w_i·a_i for a population of weights.

    Parameters
    ----------
    name : str
        Column name (for messages).
    terms : sequence of Term
        The free original parameters of the column (0, 1 or 2).
    weights : array (n, len(terms))
        Their positive weights per population row.
    offset : array (n,), optional
        Contribution of parameters of this column held fixed (default 0).

    Attributes
    ----------
    knots : ndarray (n, K)
        Sorted break points of the density, first and last = the support.
    linear : bool
        The density is piecewise linear between the knots (uniform terms only): the innermost
        Gaussian integral then has a closed form.
    log_coords : bool
        Integrate in log A (every term log-uniform, so the support is positive and the density
        behaves like 1/A).
    knot_values : ndarray (n, K) or None
        Density at the knots when ``linear``.

    Raises
    ------
    CollapseError
        Three or more free terms, a non-positive weight or a log-uniform term with lo <= 0.
    """

    def __init__(self, name: str, terms, weights, offset=None) -> None:
        self.name = str(name)
        self.terms = tuple(terms)
        w = np.asarray(weights, dtype=float)
        n = w.shape[0]
        self.n = n
        self.offset = np.zeros(n) if offset is None else np.broadcast_to(np.asarray(offset, float), (n,)).copy()
        t = len(self.terms)
        if t > 2:
            raise CollapseError(f"column {self.name}: {t} free parameters ({', '.join(x.name for x in self.terms)}) "
                                "feed one amplitude; only sums of one or two box priors are derived")
        if w.shape != (n, t):
            raise CollapseError(f"column {self.name}: weights must have shape (n, {t}), got {w.shape}")
        if t and not np.all(w > 0):
            raise CollapseError(f"column {self.name}: a weight of {', '.join(x.name for x in self.terms)} is not "
                                "positive (e.g. VOLF at 0 or 1 removes a phase); the induced prior is not derived there")
        for x in self.terms:
            if x.is_log and x.lo <= 0:
                raise CollapseError(f"column {self.name}: {x.name} is loguniform with lo <= 0")
        self.weights = w
        # per-term support of w·a
        self._a = w * np.array([x.lo for x in self.terms]) if t else np.zeros((n, 0))
        self._b = w * np.array([x.hi for x in self.terms]) if t else np.zeros((n, 0))
        self.linear = all(not x.is_log for x in self.terms)
        self.log_coords = t > 0 and all(x.is_log for x in self.terms)
        self.knot_values = None
        off = self.offset[:, None]
        if t == 0:  # a delta at the offset: callers move it into the data (see the likelihood)
            self.knots = np.column_stack([self.offset, self.offset])
        elif t == 1:
            self.knots = np.column_stack([self._a[:, 0], self._b[:, 0]]) + off
            if self.linear:
                h = 1.0 / (self._b[:, 0] - self._a[:, 0])
                self.knot_values = np.column_stack([h, h])
        else:
            a1, a2, b1, b2 = self._a[:, 0], self._a[:, 1], self._b[:, 0], self._b[:, 1]
            if self.linear:
                l1, l2 = b1 - a1, b2 - a2
                lo = a1 + a2
                self.knots = np.column_stack([lo, lo + np.minimum(l1, l2), lo + np.maximum(l1, l2), b1 + b2]) + off
                h = 1.0 / np.maximum(l1, l2)
                z = np.zeros(n)
                self.knot_values = np.column_stack([z, h, h, z])
            else:
                self.knots = np.sort(np.column_stack([a1 + a2, a1 + b2, b1 + a2, b1 + b2]), axis=1) + off

    def take(self, rows) -> "ColumnPrior":
        """The same column for a subset of the population rows."""
        new = object.__new__(ColumnPrior)
        new.__dict__.update(self.__dict__)
        for key in ("weights", "offset", "_a", "_b", "knots", "knot_values"):
            v = getattr(self, key)
            setattr(new, key, None if v is None else v[rows])
        new.n = int(new.offset.shape[0])
        return new

    # -- density ------------------------------------------------------------------------
    @property
    def lo(self) -> np.ndarray:
        return self.knots[:, 0]

    @property
    def hi(self) -> np.ndarray:
        return self.knots[:, -1]

    def pdf(self, amp) -> np.ndarray:
        """Density of A at ``amp`` (n, ...) (0 outside the support)."""
        x = np.asarray(amp, dtype=float)
        if self.linear:
            return _pwlin(x, self.knots, self.knot_values)
        extra = (1,) * (x.ndim - 1)
        r = lambda v: v.reshape((-1,) + extra)  # noqa: E731 - row parameters against x
        s = x - r(self.offset)
        inside = (x >= r(self.lo)) & (x <= r(self.hi))
        with np.errstate(divide="ignore", invalid="ignore"):
            if len(self.terms) == 1:
                out = 1.0 / (s * self.terms[0].log_width)
            else:
                a1, b1, a2, b2 = (r(v) for v in (self._a[:, 0], self._b[:, 0], self._a[:, 1], self._b[:, 1]))
                u0, u1 = np.maximum(a1, s - b2), np.minimum(b1, s - a2)
                t1, t2 = self.terms
                if t1.is_log and t2.is_log:
                    out = (np.log(u1 / (s - u1)) - np.log(u0 / (s - u0))) / (t1.log_width * t2.log_width * s)
                elif t2.is_log:  # u uniform, v = s − u log-uniform
                    out = np.log((s - u0) / (s - u1)) / ((b1 - a1) * t2.log_width)
                else:  # u log-uniform, v uniform: integrate over v instead
                    v0, v1 = np.maximum(a2, s - b1), np.minimum(b2, s - a1)
                    out = np.log((s - v0) / (s - v1)) / ((b2 - a2) * t1.log_width)
        return np.where(inside & np.isfinite(out), np.maximum(out, 0.0), 0.0)

    # -- back to the original parameters --------------------------------------------------
    def split(self, amp, rng: np.random.Generator) -> dict[str, np.ndarray]:
        """Draw the original parameters given the column amplitude, one row per population row.

        Parameters
        ----------
        amp : array (n,)
            Column amplitudes (inside the support).
        rng : numpy.random.Generator

        Returns
        -------
        dict
            ``{name: (n,)}`` for each free term: draws from p(a | A) ∝ Π prior(a_i) on the
            segment Σ w_i·a_i = A − offset (module docstring).
        """
        s = np.asarray(amp, dtype=float) - self.offset
        t = len(self.terms)
        if t == 0:
            return {}
        if t == 1:
            x = self.terms[0]
            return {x.name: np.clip(s / self.weights[:, 0], x.lo, x.hi)}
        a1, b1, a2, b2 = self._a[:, 0], self._b[:, 0], self._a[:, 1], self._b[:, 1]
        u0, u1 = np.maximum(a1, s - b2), np.minimum(b1, s - a2)
        u1 = np.maximum(u1, u0)
        q = rng.random(s.shape)
        t1, t2 = self.terms
        with np.errstate(divide="ignore", invalid="ignore"):
            if t1.is_log and t2.is_log:  # uniform in log(u/(s − u))
                g0, g1 = np.log(u0 / (s - u0)), np.log(u1 / (s - u1))
                g = g0 + q * (g1 - g0)
                u = s / (1.0 + np.exp(-g))
            elif t2.is_log:  # ∝ 1/(s − u): uniform in log(s − u)
                g0, g1 = np.log(s - u0), np.log(s - u1)
                u = s - np.exp(g0 + q * (g1 - g0))
            elif t1.is_log:  # ∝ 1/u: uniform in log u
                u = np.exp(np.log(u0) + q * (np.log(u1) - np.log(u0)))
            else:
                u = u0 + q * (u1 - u0)
        u = np.clip(np.where(np.isfinite(u), u, u0), u0, u1)
        return {t1.name: np.clip(u / self.weights[:, 0], t1.lo, t1.hi),
                t2.name: np.clip((s - u) / self.weights[:, 1], t2.lo, t2.hi)}
