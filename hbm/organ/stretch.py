"""The material along the fibres (nominal stress), the tendon, and the stretch solve per cross-section."""

from __future__ import annotations

import math
from typing import Callable, Mapping, Sequence

import numpy as np

from ..errors import HbmError
from ..model.core import Loading, Model, State
from .geometry import _EPS, FusiformGeometry


# ---------------------------------------------------------------------------------------------
# tissue and tendon laws
# ---------------------------------------------------------------------------------------------
def tendon_strain(force: np.ndarray, geometry: FusiformGeometry) -> np.ndarray:
    """Tendon strain ε_t for axial force(s) ``force`` (N), closed-form inverse of the tendon law."""
    s = np.asarray(force, dtype=float) / geometry.tendon_area  # nominal tendon stress (MPa)
    E = geometry.tendon_modulus
    if math.isinf(E):
        return np.zeros_like(s)
    if geometry.tendon_law == "linear":
        return s / E
    et = geometry.tendon_toe_strain
    toe = s <= 0.5 * E * et
    return np.where(toe, np.sqrt(2.0 * et * np.maximum(s, 0.0) / E), s / E + 0.5 * et)


def _elastic_effects(model: Model):
    elastic = [e for e in model.effects if e.stage == "elastic"]
    if not elastic:
        raise HbmError(f"model {model.name!r} has no elastic effect: no tissue law for the organ")
    excluded = tuple(e.name for e in model.effects if e.stage != "elastic")
    return elastic, excluded


def _nominal_fn(model: Model) -> tuple[Callable[[np.ndarray, Mapping[str, np.ndarray]], np.ndarray], tuple]:
    """P(λ; p) = σ_elastic(λ)/λ from the model's elastic effects, for any broadcastable shapes."""
    elastic, excluded = _elastic_effects(model)
    # Elastic effects read only the strain; a one-point loading satisfies the State contract.
    loading = Loading(np.zeros(1))

    def P(lam: np.ndarray, p: Mapping[str, np.ndarray]) -> np.ndarray:
        state = State(lam - 1.0, loading)
        total = elastic[0].stress(state, p)
        for e in elastic[1:]:
            total = total + e.stress(state, p)
        return total / lam

    return P, excluded


def nominal_stress(model: Model, theta: np.ndarray, stretch: np.ndarray) -> np.ndarray:
    """Nominal stress P = σ/λ (MPa) of the model's elastic effects.

    Parameters
    ----------
    model : Model
    theta : array (n, n_params)
    stretch : array (n_points,) or (n, n_points)
        Fiber stretch λ.

    Returns
    -------
    ndarray (n, n_points)
    """
    theta = _check_theta(model, theta)
    P, _ = _nominal_fn(model)
    lam = np.asarray(stretch, dtype=float)
    p = {q.name: theta[:, i, None] for i, q in enumerate(model.parameters)}
    return np.broadcast_to(P(lam, p), (theta.shape[0],) + lam.shape[-1:]).copy()


def _check_theta(model: Model, theta) -> np.ndarray:
    theta = np.asarray(theta, dtype=float)
    if theta.ndim == 1:
        theta = theta[None, :]
    if theta.ndim != 2 or theta.shape[1] != model.n_params:
        raise HbmError(f"theta must have shape (n_samples, {model.n_params}) with columns "
                       f"{model.parameter_names}, got {theta.shape}")
    if not np.isfinite(theta).all():
        raise HbmError("theta contains non-finite values")
    return theta


# ---------------------------------------------------------------------------------------------
# the solver
# ---------------------------------------------------------------------------------------------
def _ab_step(P, p, a, b, fa, fb, side, s, tol, x0=None, bisect=False):
    """One Anderson–Björck regula-falsi step on bracket arrays (updated in place).

    Invariant: fa = P(a) − s < 0 <= fb = P(b) − s (up to the Anderson–Björck scaling of the
    function value kept twice).  Returns (x, converged).
    """
    with np.errstate(divide="ignore", invalid="ignore"):
        if bisect:
            x = 0.5 * (a + b)
        else:
            x = b - fb * (b - a) / (fb - fa) if x0 is None else x0.copy()
        bad = ~((x - a) * (x - b) < 0)  # outside (a, b) in either order, or NaN
        np.copyto(x, 0.5 * (a + b), where=bad)  # bisection fallback
        fx = P(x, p) - s
        conv = (np.abs(fx) <= tol * s) | (np.abs(b - a) <= 4.0 * _EPS * np.abs(b))
        up = fx > 0  # the root is left of x: x becomes the upper end
        # Anderson–Björck: when the same end survives twice, scale its function value down
        m_up = 1.0 - fx / fb
        m_dn = 1.0 - fx / fa
    np.copyto(m_up, 0.5, where=~(m_up > 0))
    np.copyto(m_dn, 0.5, where=~(m_dn > 0))
    np.multiply(fa, m_up, out=fa, where=up & (side == 1))
    np.multiply(fb, m_dn, out=fb, where=~up & (side == -1))
    np.copyto(b, x, where=up)
    np.copyto(fb, fx, where=up)
    np.copyto(a, x, where=~up)
    np.copyto(fa, fx, where=~up)
    np.copyto(side, np.where(up, 1, -1).astype(np.int8))
    return x, conv


def _polish_flat(P, theta, names, idx, K, a, b, fa, fb, side, s, out, *, tol, max_iter, n_iter=0,
                 x_first=None):
    """Anderson–Björck iterations on flat unknowns ``idx`` (indices into a (n, K) block).

    a, b, fa, fb, side, s are (N, 1) arrays for the unknowns; converged roots are written to
    ``out`` (the flat (n·K,) result).  Parameters are gathered once and compressed with the
    unknowns.  ``x_first`` (N, 1) replaces the first regula-falsi point (bisection if it lies
    outside the bracket).  Returns the total number of iterations.
    """
    rows = idx // K
    p = {q: theta[rows, i, None] for i, q in enumerate(names)}
    flat = [a, b, fa, fb, side, s]
    first, k = True, 0
    while idx.size and n_iter < max_iter:
        n_iter += 1
        k += 1
        # Every third step after the sixth is a bisection: guarantees the bracket collapses
        # even where rounding noise in P (tiny forces, P ≈ 0) stalls regula falsi.
        x, conv = _ab_step(P, p, *flat, tol, x_first if first else None, bisect=k > 6 and k % 3 == 0)
        first = False
        conv = conv[:, 0]
        out[idx[conv]] = x[conv, 0]
        keep = ~conv
        if not keep.all():
            idx = idx[keep]
            flat = [v[keep] for v in flat]
            p = {q: v[keep] for q, v in p.items()}
    if idx.size:
        raise HbmError(f"organ stretch solver did not converge for {idx.size} (sample, section, force) "
                       f"points in {max_iter} iterations")
    return n_iter


def _polish(P, theta, names, s, a, b, fa, fb, active, lam, *, tol, max_iter):
    """Anderson–Björck iterations on (n, K) bracket arrays; writes converged roots into ``lam``.

    The first iterations run on the whole block (parameters broadcast per row, nothing
    gathered); once fewer than a fifth of the unknowns remain they continue as flat arrays
    (:func:`_polish_flat`).  Returns the number of iterations.
    """
    n, K = lam.shape
    p_rows = {q: theta[:, i, None] for i, q in enumerate(names)}
    side = np.zeros((n, K), dtype=np.int8)
    n_iter = 0
    while n_iter < max_iter and active.any() and active.mean() > 0.2:
        n_iter += 1
        x, conv = _ab_step(P, p_rows, a, b, fa, fb, side, s, tol)
        now = active & conv
        lam[now] = x[now]
        active &= ~conv
    idx = np.flatnonzero(active)
    flat = [v.ravel()[idx][:, None] for v in (a, b, fa, fb, side, s)]
    return _polish_flat(P, theta, names, idx, K, *flat, lam.reshape(-1), tol=tol, max_iter=max_iter,
                        n_iter=n_iter)


def _solve_stretch(P, theta: np.ndarray, names: Sequence[str], targets: np.ndarray, *,
                   max_stretch: float, tol: float, n_grid: int, n_anchors: int, max_iter: int):
    """Solve P(λ; θ_i) = targets[j] for λ in [1, max_stretch] and every sample i, vectorised.

    ``targets`` (K,) are the nominal stresses F/A0 (the same for every sample).  Returns
    (lam (n, K), unreachable (n, K) bool, non_monotone (n,) bool, n_iter).

    Two levels, both bracketed (a root always lies in the bracket, by continuity):

    1. A table of P on ``n_grid`` stretches per sample flags non-monotone samples and brackets
       ``n_anchors`` anchor stresses, log-spaced over the targets and common to all samples;
       the anchors are solved to full accuracy (vectorised binary search + polishing).
    2. Every target lies between two anchors; their stretches (with P recomputed there) are a
       narrow, exact bracket, so the (n, K) polishing needs only a few evaluations and no
       per-element search.
    """
    n = theta.shape[0]
    K = targets.size
    grid = np.linspace(1.0, max_stretch, n_grid)
    p_rows = {q: theta[:, i, None] for i, q in enumerate(names)}
    T = np.broadcast_to(P(grid[None, :], p_rows), (n, n_grid))  # (n, m) table
    with np.errstate(invalid="ignore"):
        dT = np.diff(T, axis=1)
    scale = np.maximum(np.abs(T[:, -1:]), 1e-300)
    non_monotone = (dT < -1e-12 * scale).any(axis=1) | ~np.isfinite(T).all(axis=1)
    # The largest tabulated P bounds the reachable stresses (the last point for a monotone P).
    i_top = np.argmax(np.where(np.isfinite(T), T, -np.inf), axis=1)
    Pmax = T[np.arange(n), i_top][:, None]
    lam_top = grid[i_top][:, None]
    P0 = T[:, :1]

    # -- level 1: anchors --------------------------------------------------------------------
    pos = targets[targets > 0]
    if pos.size == 0:
        anchors = np.empty(0)
    else:
        anchors = np.unique(np.geomspace(pos.min(), pos.max(), n_anchors)) if pos.min() < pos.max() \
            else pos[:1]
    M = anchors.size
    sA = np.broadcast_to(anchors, (n, M))
    lamA = np.full((n, M), np.nan)
    okA = (sA > P0) & (sA <= Pmax)
    lo = np.zeros((n, M), dtype=np.intp)
    hi = np.repeat(i_top[:, None], M, axis=1)
    for _ in range(int(np.ceil(np.log2(n_grid))) + 1):  # bracket T[lo] < s <= T[hi]
        mid = (lo + hi) // 2
        below = np.take_along_axis(T, mid, axis=1) < sA
        np.copyto(lo, mid, where=below)
        np.copyto(hi, mid, where=~below)
    it1 = _polish(P, theta, names, np.where(okA, sA, 1.0), np.where(okA, grid[lo], 1.0),
                  np.where(okA, grid[hi], 1.0),
                  np.where(okA, np.take_along_axis(T, lo, axis=1) - sA, -1.0),
                  np.where(okA, np.take_along_axis(T, hi, axis=1) - sA, 1.0), okA.copy(), lamA,
                  tol=tol, max_iter=max_iter)
    # Augmented anchor table: λ = 1 first, the stretch of the largest tabulated P last (the
    # max_stretch for a monotone P); anchors out of reach take the end values so that every
    # reachable target still has a valid bracket.
    lamA = np.where(okA, lamA, np.where(sA <= P0, 1.0, lam_top))
    lamA = np.concatenate([np.ones((n, 1)), lamA, lam_top], axis=1)
    PA = np.broadcast_to(P(lamA, p_rows), lamA.shape)  # exact P at the bracket ends
    # dP/dλ at the anchors (central differences) for a cubic Hermite first guess of λ(s)
    h = 1e-6 * lamA
    dPA = np.broadcast_to((P(lamA + h, p_rows) - P(np.maximum(lamA - h, 1.0), p_rows))
                          / (lamA + h - np.maximum(lamA - h, 1.0)), lamA.shape)

    # -- level 2: every target between two anchors --------------------------------------------
    # Cubic Hermite coefficients of λ(u), u = ln s, on every anchor interval, with slopes
    # dλ/du = P/P'(λ) (secant slope where unusable: kinks, flat P, P = 0).  In ln s the
    # exponential collagen branch is nearly linear and the small-strain branch smooth, so the
    # interpolant is accurate to about the solver tolerance:  λ ≈ λ_k + t·(c1 + t·(c2 + t·c3)),
    # t = (u − u_k)/(u_{k+1} − u_k).  Computed per (sample, interval), then gathered.
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        UA = np.log(PA)
        du = np.diff(UA, axis=1)  # (n, M+1)
        d = np.diff(lamA, axis=1)
        g = np.where((dPA > 0) & (PA > 0), PA / dPA, np.nan)  # dλ/du at the nodes
        ma = g[:, :-1] * du
        mb = g[:, 1:] * du
        ma = np.where(np.isfinite(ma), ma, d)
        mb = np.where(np.isfinite(mb), mb, d)
        c2 = 3.0 * d - 2.0 * ma - mb
        c3 = ma + mb - 2.0 * d
        inv_du = 1.0 / du
    kb = np.searchsorted(anchors, targets, side="right") + 1  # anchors[kb-2] <= s < anchors[kb-1]
    ka = kb - 1  # interval index (common to all samples); an anchor hit exactly gives t = 0
    s = targets[None, :]
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        t = (np.log(s) - UA[:, ka]) * inv_du[:, ka]
        x0 = lamA[:, ka] + t * (ma[:, ka] + t * (c2[:, ka] + t * c3[:, ka]))
        fx = P(x0, p_rows) - s  # one evaluation on the whole (n, K) block
        conv = np.abs(fx) <= tol * s
    unreachable = (s < P0) | ~(s <= Pmax)  # includes NaN
    exact_rest = s == P0
    active = ~(unreachable | exact_rest)
    lam = np.where(conv & active, x0, np.nan)
    lam[exact_rest] = 1.0
    # the few unconverged unknowns: exact bracket from the anchors, updated with x0 when inside
    idx = np.flatnonzero(active & ~conv)
    rows, cols = np.divmod(idx, K)
    kk = ka[cols]
    a, b = lamA[rows, kk], lamA[rows, kk + 1]
    sf = targets[cols]
    fa, fb = PA[rows, kk] - sf, PA[rows, kk + 1] - sf
    broken = ~((fa < 0) & (fb > 0))  # tolerance-level sign slips or non-monotone samples
    a[broken], b[broken] = 1.0, lam_top[rows[broken], 0]
    fa[broken] = P0[rows[broken], 0] - sf[broken]
    fb[broken] = Pmax[rows[broken], 0] - sf[broken]
    xf, ff = x0.ravel()[idx], fx.ravel()[idx]
    inside = ((xf - a) * (xf - b) < 0) & np.isfinite(ff)
    up = inside & (ff > 0)
    dn = inside & (ff < 0)
    b[up], fb[up] = xf[up], ff[up]
    a[dn], fa[dn] = xf[dn], ff[dn]
    side = np.where(up, 1, np.where(dn, -1, 0)).astype(np.int8)
    # Next point: a Newton step from x0 with the Hermite slope dλ/ds (accurate to high order
    # inside an interval, so it typically lands within tolerance); bisection if outside.
    tf = t.ravel()[idx]
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        slope = (ma[rows, kk] + tf * (2.0 * c2[rows, kk] + 3.0 * tf * c3[rows, kk])) * inv_du[rows, kk] / sf
        x1 = np.where(inside, xf - ff * slope, np.nan)
    it2 = 1 + _polish_flat(P, theta, names, idx, K, a[:, None], b[:, None], fa[:, None], fb[:, None],
                           side[:, None], sf[:, None], lam.reshape(-1), tol=tol, max_iter=max_iter,
                           x_first=x1[:, None])
    return lam, unreachable, non_monotone, it1 + it2


