"""The integral of a Gaussian over a box of amplitudes with induced priors, and draws from it.

For each population row the data give, in noise-whitened units, the quadratic
``Q(A) = yy − 2·bᵀA + AᵀHA = ‖ỹ − X̃A‖²`` of the k column amplitudes.  This module computes

    log I = log ∫ Π_j p_j(A_j) · exp(−Q(A)/2) dA

with ``p_j`` the induced column priors (:mod:`hbm.likelihood.collapsed.induced`), vectorised over rows.

How
---
* **Elimination.**  Q = c + Σ_j h_j·(A_j − μ_j(A_{>j}))² (a Cholesky factorisation of H taken from
  column 0 on, computed on the unit-diagonal scaled H): column 0 is the innermost integral given
  the others, column k−1 the outermost.  A column whose whole prior box moves the fit by less
  than 1e-9 noise sd (``h_j·width_j² ≤ 1e-9``, e.g. the fibre column when EOPT lies beyond the
  largest strain) is *flat*: the likelihood does not see it and its prior integrates to 1.
* **Innermost column in closed form.**  A piecewise-linear prior (uniform terms: uniform or
  trapezoid) times a Gaussian on each piece integrates to ``s·√(2π)·ΔΦ·p(E[A])`` -- the truncated
  Gaussian's mass times the linear density at its mean (exact because p is linear on the
  piece); ΔΦ and the mean are computed from log Φ so that pieces 40 sd out stay finite.
* **Outer columns by Gauss–Legendre** on a window around the *box-constrained* mode of the
  remaining columns (exact enumeration of the 3^d active sets), half-width ``width`` times the
  conditional sd 1/√h_j (the marginal of a Gaussian restricted to a convex box is no wider,
  Brascamp–Lieb), intersected with the support and split into panels at the prior's kinks;
  log-uniform columns are integrated in log A.
* **Error estimate**: the same integral with 1.5× the nodes per panel; the difference is
  returned with the value (:meth:`BoxGaussianIntegral.log_integral`).
* **Closed-form rows** skip the quadrature (:meth:`BoxGaussianIntegral._interior`): every column
  deep inside one linear piece, or all columns but one constant on the mass and that one
  integrated over its kinks by the 1-D closed form -- with a per-row bound on the neglected mass
  as their error.

Draws of A given the data (:meth:`BoxGaussianIntegral.draw`) go outermost first: each outer
column from its marginal given the columns already drawn, tabulated on a fine grid per panel
and sampled from the piecewise-linear interpolant of that density (discretisation error of
order (grid step)² relative); the innermost closed-form column exactly, by inverting its CDF.
"""

from __future__ import annotations

import itertools

import numpy as np
from scipy.special import ndtr

from ...samplers.truncnorm import log_mass
from .kernels import closed_form_linear, draw_linear_gaussian


__all__ = ["BoxGaussianIntegral", "box_qp"]

_LOG_SQRT_2PI = 0.5 * float(np.log(2.0 * np.pi))
#: a column is flat when its whole box moves Q by less than this (h·width² in whitened units)
FLAT = 1e-9
#: rows whose Gaussian lies this many marginal sd inside one linear piece of every column's
#: density are integrated in closed form (:meth:`BoxGaussianIntegral.interior`)
INTERIOR_MARGIN = 6.0
#: largest bound on the neglected relative mass of a row integrated by the one-kinked-column rule
#: (:meth:`BoxGaussianIntegral._interior`): its error in log I, far below the quadrature's
INTERIOR_TOL = 1e-6


def box_qp(P, q, lo, hi) -> np.ndarray:
    """argmin ½xᵀPx − qᵀx subject to lo ≤ x ≤ hi, batched, exact for small d.

    Enumerates the 3^d active sets (each coordinate free, at lo or at hi), solves the free block
    (with a 1e-12 ridge, so singular P is fine) and keeps the feasible candidate of least
    objective; the all-bound candidates are always feasible.

    Parameters
    ----------
    P : array (..., d, d)
        Positive semi-definite.
    q : array (..., d)
    lo, hi : array (..., d)

    Returns
    -------
    ndarray (..., d)
    """
    P, q, lo, hi = (np.asarray(v, float) for v in (P, q, lo, hi))
    d = q.shape[-1]
    best = np.full(q.shape, np.nan)
    best_f = np.full(q.shape[:-1], np.inf)
    tol = 1e-9 * (hi - lo + 1e-300)
    for pattern in itertools.product((0, 1, 2), repeat=d):  # 3^d patterns, each vectorised over rows
        pat = np.array(pattern)
        free = np.flatnonzero(pat == 0)
        x = np.where(pat == 1, lo, hi).copy()
        if free.size:
            fixed = np.flatnonzero(pat != 0)
            rhs = q[..., free] - np.einsum("...ij,...j->...i", P[..., free[:, None], fixed[None, :]], x[..., fixed])
            A = P[..., free[:, None], free[None, :]] + 1e-12 * np.eye(free.size)
            xf = np.linalg.solve(A, rhs[..., None])[..., 0]
            x[..., free] = xf
            ok = ((xf >= lo[..., free] - tol[..., free]) & (xf <= hi[..., free] + tol[..., free])).all(axis=-1)
        else:
            ok = np.ones(q.shape[:-1], bool)
        f = 0.5 * np.einsum("...i,...ij,...j->...", x, P, x) - np.einsum("...i,...i->...", q, x)
        take = ok & (f < best_f)
        best = np.where(take[..., None], x, best)
        best_f = np.where(take, f, best_f)
    return np.clip(best, lo, hi)


def _lse(x: np.ndarray, axis: int) -> np.ndarray:
    """log Σ exp(x) along ``axis`` (−inf where every term is −inf)."""
    m = np.max(x, axis=axis, keepdims=True)
    m = np.where(np.isfinite(m), m, 0.0)
    with np.errstate(divide="ignore"):
        return np.log(np.sum(np.exp(x - m), axis=axis)) + np.squeeze(m, axis=axis)


def _gl(n: int) -> tuple[np.ndarray, np.ndarray]:
    x, w = np.polynomial.legendre.leggauss(int(n))
    return (x + 1.0) / 2.0, w / 2.0  # on [0, 1]


class BoxGaussianIntegral:
    """log ∫ Π_j p_j(A_j)·exp(−Q(A)/2) dA for a population (module docstring).

    Parameters
    ----------
    H : array (n, k, k)
        X̃ᵀX̃ (whitened basis).
    b : array (n, k)
        X̃ᵀỹ.
    yy : array (n,)
        ỹᵀỹ.
    priors : sequence of ColumnPrior
        One per column (population size n each).
    nodes : int
        Gauss–Legendre nodes per panel of an outer column (each outer column has at least three
        panels: cut at the prior's kinks and at :meth:`_breaks`).
    width : float
        Window half-width in conditional sd.
    """

    def __init__(self, H, b, yy, priors, *, nodes: int = 6, width: float = 5.0) -> None:
        H, b, yy = np.asarray(H, float), np.asarray(b, float), np.asarray(yy, float)
        n, k = b.shape
        self.n, self.k = n, k
        self.nodes, self.width = int(nodes), float(width)
        # innermost: a piecewise-linear column (closed form), preferring the one with most kinks
        lin = [j for j, p in enumerate(priors) if p.linear]
        first = max(lin, key=lambda j: priors[j].knots.shape[1]) if lin else 0
        self.column_priors = list(priors)  # caller's column order (draws are returned in it)
        self.perm = np.array([first] + [j for j in range(k) if j != first], dtype=int)
        self.priors = [priors[j] for j in self.perm]
        self.closed = bool(self.priors[0].linear)
        H = H[:, self.perm][:, :, self.perm]
        b = b[:, self.perm]
        lo = np.column_stack([p.lo for p in self.priors])
        hi = np.column_stack([p.hi for p in self.priors])
        self.lo, self.hi = lo, hi
        diag = np.einsum("nii->ni", H).copy()
        flat = diag * (hi - lo) ** 2 <= FLAT
        d = np.sqrt(np.where(flat, 1.0, diag))
        Hs = H / (d[:, :, None] * d[:, None, :])
        bs = b / d
        Hs = np.where(flat[:, :, None] | flat[:, None, :], 0.0, Hs)
        bs = np.where(flat, 0.0, bs)
        self.d = d
        self.Hs0, self.bs0 = Hs.copy(), bs.copy()  # for the box-constrained modes
        # elimination from column 0 on: Q = c + Σ h_j (A_j − g_j + Σ_{l>j} C_jl A_l)²
        h = np.zeros((n, k))
        g = np.zeros((n, k))
        C = np.zeros((n, k, k))
        const = yy.copy()
        for j in range(k):  # loop over the k ≤ 5 columns, vectorised over rows
            p = Hs[:, j, j]
            fl = flat[:, j] | (p * (d[:, j] * (hi[:, j] - lo[:, j])) ** 2 <= FLAT) | (p <= 1e-14)
            ps = np.where(fl, 1.0, p)
            h[:, j] = np.where(fl, 0.0, p * d[:, j] ** 2)
            g[:, j] = np.where(fl, 0.0, bs[:, j] / (ps * d[:, j]))
            C[:, j, j + 1:] = np.where(fl[:, None], 0.0, Hs[:, j, j + 1:] * d[:, j + 1:] / (ps * d[:, j])[:, None])
            const -= np.where(fl, 0.0, bs[:, j] ** 2 / ps)
            col = np.where(fl[:, None], 0.0, Hs[:, j + 1:, j])
            Hs[:, j + 1:, j + 1:] -= col[:, :, None] * col[:, None, :] / ps[:, None, None]
            bs[:, j + 1:] -= col * (np.where(fl, 0.0, bs[:, j]) / ps)[:, None]
        self.h, self.g, self.C, self.const = h, g, C, const

    # -- pieces -----------------------------------------------------------------------------
    def _mu(self, pos: int, vals: np.ndarray) -> np.ndarray:
        """Conditional centre μ_pos given the values of columns pos+1.. (vals (n, M, k−pos−1))."""
        c = self.C[:, pos, pos + 1:]
        return self.g[:, pos][:, None] - np.einsum("nl,nml->nm", c, vals)

    def _closed_form(self, mu: np.ndarray, upper=None) -> np.ndarray:
        """log ∫ p_0(a)·exp(−h_0(a − μ)²/2) da over the support (or up to ``upper``), (n, M).

        Fast path: Φ and exp(−z²/2) once per knot (tail probabilities, so no cancellation
        beyond the piece's own width); entries whose every piece lies > 37 sd out (the total
        underflows) are recomputed from log Φ (:meth:`_closed_form_log`).
        """
        if upper is not None:
            return self._closed_form_log(mu, upper)
        pr = self.priors[0]
        out = closed_form_linear(np.ascontiguousarray(pr.knots, float), np.ascontiguousarray(pr.knot_values, float),
                                 np.ascontiguousarray(self.h[:, 0], float), np.ascontiguousarray(mu, float))
        bad = np.isnan(out)
        if bad.any():
            rows, cols = np.nonzero(bad)
            out[rows, cols] = self._take(rows)._closed_form_log(mu[rows, cols][:, None])[:, 0]
        return out

    def _closed_form_log(self, mu: np.ndarray, upper=None) -> np.ndarray:
        """:meth:`_closed_form` in log space, piece by piece (any distance; ``upper`` cuts the support)."""
        pr = self.priors[0]
        h = self.h[:, 0][:, None]
        flat = h == 0.0
        s = 1.0 / np.sqrt(np.where(flat, 1.0, h))
        terms = []
        for i in range(pr.knots.shape[1] - 1):
            a0 = pr.knots[:, i][:, None] + 0.0 * mu
            a1 = pr.knots[:, i + 1][:, None] + 0.0 * mu
            if upper is not None:
                a1 = np.minimum(a1, np.maximum(upper, a0))
            p0, p1 = pr.knot_values[:, i][:, None], pr.knot_values[:, i + 1][:, None]
            full = pr.knots[:, i + 1][:, None] - pr.knots[:, i][:, None]
            slope = np.where(full > 0, (p1 - p0) / np.where(full > 0, full, 1.0), 0.0)
            logd, mz = log_mass((a0 - mu) / s, (a1 - mu) / s, mean=True)
            am = np.clip(mu + s * mz, a0, a1)
            pm = p0 + slope * (am - a0)
            with np.errstate(divide="ignore"):
                val = np.log(s) + _LOG_SQRT_2PI + logd + np.log(np.maximum(pm, 0.0))
                # flat: ∫ of the linear density over the piece
                flat_val = np.log(np.maximum((a1 - a0) * (p0 + 0.5 * slope * (a1 - a0)), 0.0))
            terms.append(np.where(flat, flat_val, val))
        return _lse(np.stack(terms), axis=0)

    def _window(self, pos: int, vals: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """[lo, hi] (n, M) of column ``pos`` around the box-constrained mode of columns ≤ pos,
        and that mode's value of column ``pos``."""
        n, M = vals.shape[:2]
        lo, hi = self.lo[:, pos][:, None], self.hi[:, pos][:, None]
        hp = self.h[:, pos][:, None]
        if np.all(hp == 0.0):
            wl, wr = np.broadcast_to(lo, (n, M)), np.broadcast_to(hi, (n, M))
            return wl, wr, 0.5 * (wl + wr)
        m = pos + 1
        d = self.d
        P = np.broadcast_to(self.Hs0[:, None, :m, :m], (n, M, m, m))
        B = vals * d[:, None, m:]  # outer columns in scaled units
        q = self.bs0[:, None, :m] - np.einsum("nij,nmj->nmi", self.Hs0[:, :m, m:], B)
        blo = np.broadcast_to((self.lo[:, :m] * d[:, :m])[:, None], (n, M, m))
        bhi = np.broadcast_to((self.hi[:, :m] * d[:, :m])[:, None], (n, M, m))
        # zero rows of flat columns: any value is a mode; take the box middle
        diag = np.einsum("nmii->nmi", P)
        P = P + np.where(diag == 0.0, 1.0, 0.0)[..., None] * np.eye(m)
        q = np.where(diag == 0.0, 0.5 * (blo + bhi), q)
        x = box_qp(P, q, blo, bhi)
        centre = x[..., pos] / d[:, pos][:, None]
        half = self.width / np.sqrt(np.where(hp > 0, hp, 1.0))
        wl = np.where(hp > 0, np.maximum(lo, centre - half), lo)
        wr = np.where(hp > 0, np.minimum(hi, centre + half), hi)
        return wl, np.maximum(wr, wl), centre

    def _breaks(self, pos: int, vals: np.ndarray, wl, wr, centre) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Two interior panel edges of column ``pos`` (n, M, 2) and its window, narrowed.

        Along a ridge of two nearly collinear columns the integral over the next inner column
        (pos−1) is a smoothed copy of its box seen through its centre μ_{pos−1}(A_pos): it rises
        and falls steeply where μ crosses that box's ends.  Those two crossings become panel
        edges when they fall inside the window (else the window is cut in thirds), and the
        window is narrowed to where μ lies within ``width`` sd of the box, plus its distance from
        the box at the constrained mode (``centre``) when the data pull it outside.
        """
        n, M = wl.shape
        thirds = wl[..., None] + (wr - wl)[..., None] * np.array([1.0 / 3.0, 2.0 / 3.0])
        j = pos - 1
        if j < 0:
            return thirds, wl, wr
        inner = self.priors[j]
        slope = self.C[:, j, pos][:, None]  # μ_j = rest − slope·A_pos
        rest = self.g[:, j][:, None] - np.einsum("nl,nml->nm", self.C[:, j, pos + 1:], vals)
        hj = self.h[:, j][:, None]
        ok = (slope != 0.0) & (hj > 0.0)
        ss = np.where(ok, slope, 1.0)
        mu_c = rest - slope * centre
        far = np.maximum(0.0, np.maximum(inner.lo[:, None] - mu_c, mu_c - inner.hi[:, None]))
        sj = self.width / np.sqrt(np.where(hj > 0, hj, 1.0)) + far
        e1 = (rest - (inner.lo[:, None] - sj)) / ss
        e2 = (rest - (inner.hi[:, None] + sj)) / ss
        nwl = np.where(ok, np.clip(np.minimum(e1, e2), wl, wr), wl)
        nwr = np.where(ok, np.clip(np.maximum(e1, e2), nwl, wr), wr)
        ends = np.column_stack([inner.lo, inner.hi])[:, None, :]
        cross = (rest[..., None] - ends) / ss[..., None]
        thirds = nwl[..., None] + (nwr - nwl)[..., None] * np.array([1.0 / 3.0, 2.0 / 3.0])
        inside = ok[..., None] & (cross > nwl[..., None]) & (cross < nwr[..., None])
        return np.sort(np.where(inside, cross, thirds), axis=-1), nwl, nwr

    def _nodes(self, pos: int, wl, wr, per_panel: int, kind: str = "gl", breaks=None) -> tuple[np.ndarray, np.ndarray]:
        """Nodes (n, M, Q) in A and log weights (incl. the log-coordinate Jacobian) of column pos,
        panels split at the prior's knots and at ``breaks`` (n, M, B)."""
        pr = self.priors[pos]
        if kind == "gl":
            x, w = _gl(per_panel)
        else:  # uniform grid with end points (for draws): trapezoid weights
            x = np.linspace(0.0, 1.0, per_panel)
            w = np.full(per_panel, 1.0 / (per_panel - 1))
            w[[0, -1]] *= 0.5
        kn = np.broadcast_to(pr.knots[:, None, :], wl.shape + (pr.knots.shape[1],))
        if breaks is not None and breaks.shape[-1]:
            kn = np.sort(np.concatenate([np.clip(kn, wl[..., None], wr[..., None]), breaks], axis=-1), axis=-1)
        if pr.log_coords:
            tiny = pr.lo[:, None] * (1 - 1e-15)
            el = np.log(np.clip(kn, np.maximum(wl, tiny)[..., None], np.maximum(wr, tiny)[..., None]))
        else:
            el = np.clip(kn, wl[..., None], wr[..., None])
        e0, e1 = el[..., :-1], el[..., 1:]  # panels (n, M, K−1)
        u = e0[..., None] + (e1 - e0)[..., None] * x  # (n, M, K−1, q)
        with np.errstate(divide="ignore"):
            lw = np.log((e1 - e0)[..., None] * w)
        if pr.log_coords:
            a = np.exp(u)
            lw = lw + u
        else:
            a = u
        n, M = wl.shape
        return a.reshape(n, M, -1), lw.reshape(n, M, -1)

    def _log_density(self, pos: int, a: np.ndarray, mu: np.ndarray) -> np.ndarray:
        with np.errstate(divide="ignore"):
            return np.log(self.priors[pos].pdf(a)) - 0.5 * self.h[:, pos][:, None, None] * (a - mu[..., None]) ** 2

    def _inner(self, j: int, vals: np.ndarray, per_panel: int) -> np.ndarray:
        """log ∫ over columns < j given the values of columns ≥ j (vals (n, M, k−j)) -> (n, M)."""
        n, M = vals.shape[:2]
        if j == 0:
            return np.zeros((n, M))
        pos = j - 1
        mu = self._mu(pos, vals)
        if pos == 0 and self.closed:
            return self._closed_form(mu)
        wl, wr, centre = self._window(pos, vals)
        br, wl, wr = self._breaks(pos, vals, wl, wr, centre)
        a, lw = self._nodes(pos, wl, wr, per_panel, breaks=br)
        Q = a.shape[2]
        f = lw + self._log_density(pos, a, mu)
        sub = np.concatenate([a[..., None], np.broadcast_to(vals[:, :, None, :], (n, M, Q, vals.shape[2]))], axis=3)
        inner = self._inner(pos, sub.reshape(n, M * Q, -1), per_panel).reshape(n, M, Q)
        return _lse(f + inner, axis=2)

    def _take(self, rows) -> "BoxGaussianIntegral":
        """The same integral for a subset of the rows."""
        new = object.__new__(BoxGaussianIntegral)
        new.__dict__.update(self.__dict__)
        for key in ("h", "g", "C", "const", "lo", "hi", "d", "Hs0", "bs0"):
            setattr(new, key, getattr(self, key)[rows])
        new.priors = [p.take(rows) for p in self.priors]
        new.column_priors = [p.take(rows) for p in self.column_priors]
        new.n = int(new.const.shape[0])
        return new

    def _value(self, nodes: int) -> np.ndarray:
        return -0.5 * self.const + self._inner(self.k, np.zeros((self.n, 1, 0)), nodes)[:, 0]

    def interior(self, margin: float = INTERIOR_MARGIN) -> tuple[np.ndarray, np.ndarray]:
        """Rows whose log I has a closed form (:meth:`_interior`), and that value.

        Returns
        -------
        mask : ndarray (n,) of bool
        value : ndarray (mask.sum(),)
        """
        mask, value, _, _ = self._interior(margin)
        return mask, value

    def _gaussian(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The unconstrained Gaussian N(Â, H⁻¹) of each row: mode (n, k), covariance (n, k, k), and
        a mask of rows where it exists (no flat column, finite inverse)."""
        n, k = self.n, self.k
        ok = np.all(self.h > 0.0, axis=1)
        # the unconstrained mode by back-substitution of the elimination, μ_j = g_j − Σ_{l>j} C_jl A_l
        mode = np.zeros((n, k))
        for j in range(k - 1, -1, -1):
            mode[:, j] = self.g[:, j] - np.einsum("nl,nl->n", self.C[:, j, j + 1:], mode[:, j + 1:])
        with np.errstate(all="ignore"):
            cov_s = np.linalg.inv(np.where(ok[:, None, None], self.Hs0, np.eye(k)))
        cov = cov_s / (self.d[:, :, None] * self.d[:, None, :])
        ok &= np.all(np.isfinite(cov), axis=(1, 2))
        return mode, cov, ok

    def _interior(self, margin: float = INTERIOR_MARGIN, tol: float = INTERIOR_TOL):
        """Rows whose Gaussian lies inside the prior's linear pieces, their exact log I and error bound.

        **All columns inside one piece.**  Where the unconstrained Gaussian N(Â, H⁻¹) of a row
        lies ``margin`` marginal sd inside its column's support *and* inside one linear piece of
        that column's density, for every column, the box truncation removes less than
        2k·Φ(−margin) of the mass (2e-8 relative at 6 sd for k = 3) and the density is a product
        of linear functions over the mass:

            log I = −c/2 + Σ_j log √(2π/h_j) + log E[Π_j p_j(A_j)],
            E[Π_j p_j(A_j)] = Π_j p_j(Â_j) + s_a·s_b·Σ_ab·Π_{j≠a,b} p_j(Â_j)

        (s_j the density slopes; Isserlis' theorem; exact for at most two sloped columns).

        **One column across its kinks.**  Where every column but one (j*) is constant (density
        p_j(Â_j)) on the piece holding its mode, E[Π_j p_j(A_j)] = Π_{j≠j*} p_j(Â_j)·E[p_j*(A_j*)]
        with A_j* ~ N(Â_j*, Σ_j*j*) its marginal: the 1-D closed form of the innermost column
        (:func:`~hbm.likelihood.collapsed.kernels.closed_form_linear`), exact over j*'s whole support and
        kinks.  Neglected: the Gaussian mass of the other columns outside their pieces, where
        the density differs from the constant; relative to I it is at most

            x = max p_j* / E[p_j*(A_j*)] · Σ_{j≠j*} max p_j / p_j(Â_j) · P(A_j ∉ piece_j),

        computed per row; the row is taken when its error bound −log(1 − x) ≤ ``tol``.  On
        the muscle benchmark this is the common case (G's posterior straddles its trapezoid's
        kinks while the fibre and collagen amplitudes sit well inside their boxes).

        Rows that qualify for neither -- a flat column, two columns near a box edge or a kink, a
        log-uniform column, three sloped columns -- go through the quadrature.

        Returns
        -------
        mask : ndarray (n,) of bool
        value, error : ndarray (mask.sum(),)
            log I and a bound on its error (log units).
        kink : ndarray (mask.sum(),) of int
            A column j* such that every other column is constant on the mass (the draws of
            :meth:`draw` go through it), −1 for rows with two sloped columns.
        """
        n, k = self.n, self.k
        none = (np.zeros(n, bool), np.zeros(0), np.zeros(0), np.zeros(0, int))
        if not all(p.linear for p in self.priors):
            return none
        mode, cov, ok = self._gaussian()
        if not ok.any():
            return none
        sd = np.sqrt(np.maximum(np.einsum("nii->ni", cov), 0.0))
        rows = np.arange(n)
        dens = np.ones((n, k))
        slope = np.zeros((n, k))
        inside = np.ones((n, k), bool)  # margin sd inside the mode's piece
        out = np.ones((n, k))  # Gaussian mass outside the mode's piece
        peak = np.ones((n, k))  # max of the density
        for j, pr in enumerate(self.priors):
            kn, kv = pr.knots, pr.knot_values
            piece = np.clip(np.sum(kn <= mode[:, j][:, None], axis=1) - 1, 0, kn.shape[1] - 2)
            a0, a1 = kn[rows, piece], kn[rows, piece + 1]
            v0, v1 = kv[rows, piece], kv[rows, piece + 1]
            inside[:, j] = (mode[:, j] - margin * sd[:, j] >= a0) & (mode[:, j] + margin * sd[:, j] <= a1) & (a1 > a0)
            with np.errstate(divide="ignore", invalid="ignore"):
                slope[:, j] = np.where(a1 > a0, (v1 - v0) / (a1 - a0), 0.0)
                s = np.where(sd[:, j] > 0, sd[:, j], 1.0)
                out[:, j] = np.where((a1 > a0) & (sd[:, j] > 0),
                                     ndtr((a0 - mode[:, j]) / s) + ndtr((mode[:, j] - a1) / s), 1.0)
            dens[:, j] = v0 + slope[:, j] * (mode[:, j] - a0)
            peak[:, j] = kv.max(axis=1)
        sloped = np.abs(slope) * sd > 1e-12 * np.maximum(dens, 1e-300)
        first = ok & inside.all(axis=1) & (np.sum(sloped, axis=1) <= 2) & np.all(dens > 0.0, axis=1)
        # second rule: j* = the worst column (a sloped one must be j*); the others constant
        with np.errstate(divide="ignore", invalid="ignore"):
            tail = np.where(dens > 0.0, peak / np.where(dens > 0.0, dens, 1.0) * out, np.inf)
        key = np.where(sloped, np.inf, tail)
        kink = np.argmax(np.where(np.isnan(key), np.inf, key), axis=1)
        others = np.ones((n, k), bool)
        others[rows, kink] = False
        rest = np.where(others, tail, 0.0)
        second = ok & ~first & np.all(~(others & sloped), axis=1) & np.all(np.isfinite(rest), axis=1)
        second &= np.sum(rest, axis=1) * 1.0 <= tol  # before E[p_j*], which only widens the bound
        value = np.full(n, np.nan)
        error = np.zeros(n)
        with np.errstate(divide="ignore", invalid="ignore"):
            base = -0.5 * self.const + k * _LOG_SQRT_2PI - 0.5 * np.sum(np.log(self.h), axis=1)
            r = np.flatnonzero(first)
            if r.size:
                expect = np.prod(dens[r], axis=1)
                for a, b in itertools.combinations(range(k), 2):  # the pair term of Isserlis' theorem
                    both = sloped[r, a] & sloped[r, b]
                    if both.any():
                        oth = np.prod(np.delete(dens[r], [a, b], axis=1), axis=1)
                        expect = expect + np.where(both, slope[r, a] * slope[r, b] * cov[r, a, b] * oth, 0.0)
                value[r] = base[r] + np.log(expect)
                error[r] = 2.0 * k * ndtr(-margin)
            for j, pr in enumerate(self.priors):
                r = np.flatnonzero(second & (kink == j))
                if not r.size:
                    continue
                var = cov[r, j, j]
                # log E[p_j(A_j)] = log ∫ p_j(a)·exp(−(a − Â_j)²/2v) da − log √(2πv)
                le = closed_form_linear(np.ascontiguousarray(pr.knots[r], float),
                                        np.ascontiguousarray(pr.knot_values[r], float),
                                        np.ascontiguousarray(1.0 / var),
                                        np.ascontiguousarray(mode[r, j][:, None]))[:, 0]
                le -= _LOG_SQRT_2PI + 0.5 * np.log(var)
                lrest = np.sum(np.log(np.where(others[r], dens[r], 1.0)), axis=1)
                value[r] = base[r] + lrest + le
                # neglected/I ≤ x (relative to the closed form), so |Δ log I| ≤ −log(1 − x)
                error[r] = -np.log1p(-np.minimum(np.exp(np.log(peak[r, j]) - le) * np.sum(rest[r], axis=1), 0.5))
        mask = (first | second) & np.isfinite(value) & (error <= np.maximum(tol, 2.0 * k * ndtr(-margin)))
        # rows with two sloped columns (first rule) are drawn through the quadrature: kink −1
        kinks = np.where(first & (np.sum(sloped, axis=1) > 1), -1, kink)
        return mask, value[mask], error[mask], kinks[mask]

    # -- public ------------------------------------------------------------------------------
    def log_integral(self, refine: bool = False) -> tuple[np.ndarray, np.ndarray | None]:
        """log I per row, and (``refine``) |log I − log I'| with 1.5× the nodes per panel.

        Returns
        -------
        value : ndarray (n,)
        error : ndarray (n,) or None
        """
        inside, exact, bound, _ = self._interior()
        v = np.empty(self.n)
        v[inside] = exact
        err = np.zeros(self.n) if refine else None
        rest = np.flatnonzero(~inside)
        if rest.size:  # rows near a box edge or a kink: the quadrature
            sub = self._take(rest) if rest.size < self.n else self
            v[rest] = sub._value(self.nodes)
            if refine:
                err[rest] = np.abs(sub._value(self.nodes + self.nodes // 2) - v[rest])
        if refine:  # the interior rows' only error is the neglected mass (its bound)
            err[inside] = bound
        return v, err

    def draw(self, rng: np.random.Generator, grid: int = 17) -> np.ndarray:
        """One draw of A per row from ∝ Π p_j(A_j)·exp(−Q(A)/2) on the box, (n, k) in column order.

        Rows with a closed form in which all columns but one (j*) are constant on the mass
        (:meth:`_interior`): A_j* exactly from p_j*(a)·N(a; Â_j*, Σ_j*j*) by inverting its CDF,
        the others from their Gaussian given A_j* (the mass this leaves outside their pieces is
        the row's error bound, ≤ :data:`INTERIOR_TOL`; such a draw is moved to the piece's edge).
        Other rows: outer columns from their tabulated conditional marginal (``grid`` points per
        panel, piecewise-linear interpolant); the innermost closed-form column exactly by
        inverting its CDF.
        """
        n, k = self.n, self.k
        out = np.empty((n, k))
        inside, _, _, kink = self._interior()
        r = np.flatnonzero(inside)[kink >= 0]
        kink = kink[kink >= 0]
        rest = np.setdiff1d(np.arange(n), r)
        if rest.size:
            out[rest] = (self._take(rest) if rest.size < n else self)._draw_quadrature(rng, grid)
        if r.size:
            mode, cov, _ = self._take(r)._gaussian()
            rows = np.arange(r.size)
            var = cov[rows, kink, kink]
            a = np.empty(r.size)
            for j, pr in enumerate(self.priors):
                sel = np.flatnonzero(kink == j)
                if sel.size:
                    a[sel] = self._take(r[sel])._draw_closed(mode[sel, j], rng, column=j, h=1.0 / var[sel])
            # the others given A_j*: Gaussian with mean Â + Σ_·j*(a − Â_j*)/Σ_j*j*
            cj = cov[rows, :, kink]  # (m, k)
            m = mode + cj * ((a - mode[rows, kink]) / var)[:, None]
            cc = cov - cj[:, :, None] * cj[:, None, :] / var[:, None, None]
            keep = np.ones((r.size, k), bool)
            keep[rows, kink] = False
            # the kinked column's row and column replaced by the identity (its value is set below)
            cc = np.where(keep[:, :, None] & keep[:, None, :], cc, 0.0) + (~keep)[:, :, None] * np.eye(k)
            L = np.linalg.cholesky(cc)
            z = np.einsum("nij,nj->ni", L, rng.standard_normal((r.size, k)))
            val = np.where(keep, m + z, 0.0)
            val[rows, kink] = a
            for j, pr in enumerate(self.priors):  # the neglected tail (≤ INTERIOR_TOL): onto the box
                val[:, j] = np.clip(val[:, j], pr.lo[r], pr.hi[r])
            out[r] = val
        res = np.empty((n, k))
        res[:, self.perm] = out
        return res

    def _draw_quadrature(self, rng: np.random.Generator, grid: int) -> np.ndarray:
        """:meth:`draw` of rows without a closed form, (n, k) in the internal column order."""
        n, k = self.n, self.k
        vals = np.zeros((n, 1, 0))
        for pos in range(k - 1, -1, -1):
            mu = self._mu(pos, vals)
            if pos == 0 and self.closed:
                a = self._draw_closed(mu[:, 0], rng)
            else:
                wl, wr, centre = self._window(pos, vals)
                br, wl, wr = self._breaks(pos, vals, wl, wr, centre)
                pts, lw = self._nodes(pos, wl, wr, grid, kind="grid", breaks=br)
                Q = pts.shape[2]
                f = self._log_density(pos, pts, mu)
                sub = np.concatenate([pts[..., None], np.broadcast_to(vals[:, :, None, :], (n, 1, Q, vals.shape[2]))],
                                     axis=3)
                f = f + self._inner(pos, sub.reshape(n, Q, -1), self.nodes).reshape(n, 1, Q)
                a = self._draw_grid(pos, pts[:, 0], f[:, 0], grid, rng)
            vals = np.concatenate([a[:, None, None], vals], axis=2)
        return vals[:, 0, :]

    def _draw_grid(self, pos, pts, logf, grid, rng) -> np.ndarray:
        """Sample the piecewise-linear interpolant of exp(logf) on the per-panel grids."""
        pr = self.priors[pos]
        n = pts.shape[0]
        u = np.log(pts) if pr.log_coords else pts
        with np.errstate(invalid="ignore"):
            f = np.exp(logf - np.max(np.where(np.isfinite(logf), logf, -np.inf), axis=1, keepdims=True))
        f = np.where(np.isfinite(f), f, 0.0)
        if pr.log_coords:
            f = f * pts  # density in log A
        u = u.reshape(n, -1, grid)
        f = f.reshape(n, -1, grid)
        u0, u1, f0, f1 = u[..., :-1], u[..., 1:], f[..., :-1], f[..., 1:]
        mass = (0.5 * (f0 + f1) * (u1 - u0)).reshape(n, -1)
        cum = np.cumsum(mass, axis=1)
        r = rng.random(n) * cum[:, -1]
        idx = np.minimum((cum < r[:, None]).sum(axis=1), mass.shape[1] - 1)
        rows = np.arange(n)
        a0, a1 = u0.reshape(n, -1)[rows, idx], u1.reshape(n, -1)[rows, idx]
        y0, y1 = f0.reshape(n, -1)[rows, idx], f1.reshape(n, -1)[rows, idx]
        # inverse CDF of the linear density y0 + (y1 − y0)t on [0, 1]
        v = rng.random(n)
        dy = y1 - y0
        with np.errstate(divide="ignore", invalid="ignore"):
            t = np.where(np.abs(dy) > 1e-12 * np.maximum(y0 + y1, 1e-300),
                         (-y0 + np.sqrt(np.maximum(y0 * y0 + v * (y0 * y0 + 2 * y0 * dy + dy * dy - y0 * y0)
                                                   * 1.0, 0.0))) / dy, v)
        # y0² + v·((y0+dy)² − y0²) under the root: t solves y0·t + dy·t²/2 = v·(y0 + dy/2)
        t = np.where(np.isfinite(t), np.clip(t, 0.0, 1.0), v)
        x = a0 + t * (a1 - a0)
        return np.exp(x) if pr.log_coords else x

    def _draw_closed(self, mu, rng, iters: int = 60, column: int = 0, h=None) -> np.ndarray:
        """Exact draw of a piecewise-linear column (default the innermost) given its centre μ (n,)
        and precision ``h`` (default the innermost's conditional one), by inverting its CDF:
        compiled (:func:`~hbm.likelihood.collapsed.kernels.draw_linear_gaussian`), with a log-space bisection
        for the rows whose mass underflows there."""
        pr = self.priors[column]
        h = self.h[:, 0] if h is None else np.asarray(h, float)
        u = rng.random(mu.shape[0])
        out = draw_linear_gaussian(np.ascontiguousarray(pr.knots, float), np.ascontiguousarray(pr.knot_values, float),
                                   np.ascontiguousarray(h, float), np.ascontiguousarray(mu, float), u)
        bad = np.flatnonzero(np.isnan(out))
        if bad.size:
            sub = self._take(bad)
            if column:  # the log-space path works on column 0: move this column there
                sub.priors = [sub.priors[column]] + sub.priors[1:]
            sub.h = np.column_stack([h[bad]] + [sub.h[:, 1:]]) if sub.h.shape[1] > 1 else h[bad][:, None]
            out[bad] = sub._bisect_closed(mu[bad], np.log(u[bad]), iters)
        return out

    def _bisect_closed(self, mu, log_u, iters: int) -> np.ndarray:
        """Inverse CDF of the innermost column at quantile exp(log_u) by bisection in log space."""
        pr = self.priors[0]
        lo, hi = pr.lo.copy(), pr.hi.copy()
        total = self._closed_form_log(mu[:, None])[:, 0]
        target = total + log_u
        a, z = lo.copy(), hi.copy()
        for _ in range(iters):  # bisection steps, each vectorised over rows
            mid = 0.5 * (a + z)
            c = self._closed_form(mu[:, None], upper=mid[:, None])[:, 0]
            below = c < target
            a = np.where(below, mid, a)
            z = np.where(below, z, mid)
        return 0.5 * (a + z)
