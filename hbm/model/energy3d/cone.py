"""The cone reading of the helical collagen: the exact azimuthal average (DESIGN.md §8).

Every helix segment n(φ) = cosθ·e1 + sinθ·(cosφ·e2 + sinφ·e3) stretches affinely, l(φ)² = 1 + n·D·n,
and W_coll = ⟨W_c(l(φ))⟩_φ.  With D = C − I,

    l² − 1 = a0 + a1·cosφ + b1·sinφ + a2·cos2φ + b2·sin2φ
    a0 = cos²θ·D_ff + sin²θ·(D_cc + D_nn)/2,   a1 = 2·cosθ·sinθ·D_fc,   b1 = 2·cosθ·sinθ·D_fn,
    a2 = sin²θ·(D_cc − D_nn)/2,                 b2 = sin²θ·D_cn.

The integrand has a kink where a segment goes slack (l = 1), so equally spaced families converge only
as O(N⁻²); here the slack boundaries are found and Gauss–Legendre integrates between them, where the
integrand is analytic:

* ``D_fc = D_fn = 0`` (diagonal F, shear in the c–n plane): l² depends on 2φ through one harmonic,
  a0 + R·cos ψ with ψ = 2(φ − φ0); the taut arc is ψ ∈ [0, ψ*], ψ* = arccos(−a0/R): one interval.
* ``D_fn = D_cn = 0`` (shear in the f–c plane): l² is even in φ, a quadratic in u = cos φ; its roots
  give at most two taut intervals of [0, π] (split at the vertex where that is an interior maximum).
* otherwise: the four roots of the quartic in z = exp(iφ), from batched companion-matrix
  eigenvalues polished by Newton steps, and the four of its derivative (the extrema, so peaks sit at
  interval ends): eight intervals (slow, ~6 µs per point; no shipped load case needs it).

Accuracy (measured against adaptive quadrature, ``tests/test_energy3d.py``): it is set by the largest
collagen exponent κ = T2·(l − 1) over the segments.  With 24 nodes per interval the energy and the
stresses agree to ≤ 1e-13 relative for κ ≲ 20 (T2 ≤ 50 at 20 % strain), ≤ 1e-11 for κ ≤ 100 (stresses
up to ~1e40 MPa) and 1.5e-8 at κ = 161 (W = 8e63 MPa); 32 nodes reached ≤ 3e-14 in every diagonal
state tried up to T2 = 200 and 70 % stretch.  Splitting the arc at the peak's width or mapping the
nodes towards it did worse for the same node count (Gauss–Legendre already clusters at the ends,
where every peak is placed).
"""

from __future__ import annotations

import numpy as np

from .base import DirectionalCollagen, Sym, gauss_unit, is_zero, register_collagen_reading

#: Gauss–Legendre nodes per taut interval (module docstring for the measured accuracy)
GAUSS_NODES = 24


def _trig(theta_deg):
    th = np.deg2rad(theta_deg)
    c, s = np.cos(th), np.sin(th)
    return c * c, c * s, s * s


def _coefficients(D: Sym, c2, cs, s2):
    a0 = c2 * D.ff + 0.5 * s2 * (D.cc + D.nn)
    return a0, 2.0 * cs * D.fc, 2.0 * cs * D.fn, 0.5 * s2 * (D.cc - D.nn), s2 * D.cn


def _rule_double(c2, s2, a0, a2, b2, t, w, with_cn: bool, with_n: bool):
    """l² − 1 = a0 + R·cos ψ, ψ = 2φ − atan2(b2, a2): the taut arc ψ ∈ [0, ψ*] (symmetric in ±ψ and
    in φ → φ + π, so one interval holds the whole average; the N are exact per node for diagonal D)."""
    R = np.hypot(a2, b2)
    pos = R > 0
    Rs = np.where(pos, R, 1.0)
    # R = 0: l is the same for every segment, taut everywhere (a0 > 0) or nowhere
    cos_star = np.where(pos, np.clip(-a0 / Rs, -1.0, 1.0), np.where(a0 > 0, -1.0, 1.0))
    psi_star = np.arccos(cos_star)
    c2phi0 = np.where(pos, a2 / Rs, 1.0)[..., None]
    cp = np.cos(psi_star[..., None] * t)
    weights = (psi_star / np.pi)[..., None] * w
    l2m1 = a0[..., None] + R[..., None] * cp
    if not with_n:
        return None, weights, l2m1
    half = 0.5 * s2[..., None]
    along = cp * c2phi0
    cn = half * cp * np.where(pos, b2 / Rs, 0.0)[..., None] if with_cn else 0.0
    return Sym(c2[..., None], half * (1.0 + along), half * (1.0 - along), 0.0, 0.0, cn), weights, l2m1


def _rule_even(c2, cs, s2, a0, a1, a2, t, w, with_n: bool):
    """l² − 1 = a0 + a1·cosφ + a2·cos2φ = q(u) = A·u² + B·u + C, u = cosφ, φ ∈ [0, π] standing for ±φ.

    The taut set is at most two φ-intervals: outside the roots of q when A ≥ 0 (a maximum at each end, at
    φ = 0 and π), between them when A < 0 (split at the vertex, the interior maximum)."""
    A, B, C = 2.0 * a2, a1, a0 - a2
    disc = B * B - 4.0 * A * C
    real = disc > 0
    sq = np.sqrt(np.maximum(disc, 0.0))
    q = -0.5 * (B + np.where(B >= 0, sq, -sq))     # the stable quadratic formula
    with np.errstate(divide="ignore", invalid="ignore"):
        x1, x2 = C / q, q / A                      # ±inf where A = 0 (one root: q is linear in u)
        vertex = np.clip(-B / (2.0 * A), -1.0, 1.0)
    r_lo = np.clip(np.where(real, np.fmin(x1, x2), -1.0), -1.0, 1.0)
    r_hi = np.clip(np.where(real, np.fmax(x1, x2), 1.0), -1.0, 1.0)
    convex = A >= 0
    # no real root: taut everywhere (A > 0, or q ≡ C > 0) or nowhere
    everywhere = ~real & ((A > 0) | ((A == 0) & (C > 0)))
    hi_u = np.where(everywhere, -1.0, r_hi)        # convex: u ∈ [hi_u, 1] and u ∈ [-1, r_lo]
    acos = np.arccos
    ends = np.where(convex, [np.zeros_like(a0), acos(hi_u), acos(r_lo), np.full_like(a0, np.pi)],
                    np.where(real, [acos(r_hi), acos(np.where(real, vertex, 0.0)), acos(np.where(real, vertex, 0.0)),
                                    acos(r_lo)], 0.0))
    lo = np.stack([ends[0], ends[2]], axis=-1)[..., None]
    width = np.maximum(np.stack([ends[1] - ends[0], ends[3] - ends[2]], axis=-1), 0.0)[..., None]
    shape = a0.shape + (2 * t.size,)
    phi = (lo + width * t).reshape(shape)
    weights = (width / np.pi * w).reshape(shape)
    cp = np.cos(phi)
    l2m1 = a0[..., None] + a1[..., None] * cp + a2[..., None] * (2.0 * cp * cp - 1.0)
    if not with_n:
        return None, weights, l2m1
    s2n = s2[..., None]
    return Sym(c2[..., None], s2n * cp * cp, s2n * (1.0 - cp * cp), cs[..., None] * cp), weights, l2m1


def _trig_value(phi, a0, a1, b1, a2, b2):
    return a0 + a1 * np.cos(phi) + b1 * np.sin(phi) + a2 * np.cos(2 * phi) + b2 * np.sin(2 * phi)


def _trig_slope(phi, a1, b1, a2, b2):
    return -a1 * np.sin(phi) + b1 * np.cos(phi) - 2 * a2 * np.sin(2 * phi) + 2 * b2 * np.cos(2 * phi)


def _circle_roots(a0, a1, b1, a2, b2):
    """The four angles in [0, 2π) of the roots of z²·(a0 + a1·cosφ + ... + b2·sin2φ), z = exp(iφ), from
    batched companion-matrix eigenvalues; roots on the unit circle (the real zeros) polished by Newton."""
    scale = np.maximum.reduce([np.abs(v) for v in (a0, a1, b1, a2, b2)])
    c4 = 0.5 * (a2 - 1j * b2)
    c3 = 0.5 * (a1 - 1j * b1)
    flat = np.abs(c4) <= 1e-12 * scale               # degree < 4: a tiny c4 adds two far roots
    c4 = np.where(flat, 1e-12 * scale + 0j, c4)
    zero = scale == 0                                 # p = 0: any split does
    c4 = np.where(zero, 1.0 + 0j, c4)
    M = np.zeros(np.shape(a0) + (4, 4), dtype=complex)
    M[..., 1, 0] = M[..., 2, 1] = M[..., 3, 2] = 1.0
    for k, ck in enumerate((c3, a0 + 0j, np.conj(c3), np.conj(c4))):
        M[..., 0, k] = np.where(zero, 0.0, -ck / c4)
    M[..., 0, 3] = np.where(zero, 1.0, M[..., 0, 3])
    z = np.linalg.eigvals(M)
    phi = np.mod(np.angle(z), 2 * np.pi)
    near = np.abs(np.abs(z) - 1.0) < 1e-3
    args = [v[..., None] for v in (a0, a1, b1, a2, b2)]
    for _ in range(3):
        slope = _trig_slope(phi, *args[1:])
        step = np.where(near & (slope != 0), -_trig_value(phi, *args) / np.where(slope != 0, slope, 1.0), 0.0)
        phi = np.mod(phi + np.clip(step, -1e-3, 1e-3), 2 * np.pi)
    return phi


def _rule_general(c2, cs, s2, a0, a1, b1, a2, b2, t, w, with_n: bool):
    """Any D: the slack boundaries (zeros of l² − 1) and the extrema of l² (zeros of its derivative, so
    that every peak sits at an interval end, where Gauss nodes cluster) split [0, 2π) into 8 intervals."""
    phi = np.concatenate([_circle_roots(a0, a1, b1, a2, b2),
                          _circle_roots(np.zeros_like(a0), b1, -a1, 2 * b2, -2 * a2)], axis=-1)
    phi = np.sort(phi, axis=-1)
    lo = phi[..., :, None]
    width = (np.diff(np.concatenate([phi, phi[..., :1] + 2 * np.pi], axis=-1), axis=-1))[..., None]
    shape = a0.shape + (phi.shape[-1] * t.size,)
    nodes = (lo + width * t).reshape(shape)
    weights = (width / (2 * np.pi) * w).reshape(shape)
    cp, sp = np.cos(nodes), np.sin(nodes)
    l2m1 = _trig_value(nodes, *(v[..., None] for v in (a0, a1, b1, a2, b2)))
    if not with_n:
        return None, weights, l2m1
    s2n, csn = s2[..., None], cs[..., None]
    return Sym(c2[..., None], s2n * cp * cp, s2n * sp * sp, csn * cp, csn * sp, s2n * cp * sp), weights, l2m1


@register_collagen_reading
class ConeCollagen(DirectionalCollagen):
    """Affine helix segments on the cone at THETA around the fibre, averaged exactly over the azimuth.

    W_coll = (1/2π)·∫ W_c(|F·n(φ)|) dφ with n(φ) = cosθ·e1 + sinθ·(cosφ·e2 + sinφ·e3).  Along the
    fibres every segment has the thesis's λH, so this reading equals the 1-D energy form there.
    Convex (each |F·n| is convex in F and W_c is convex and non-decreasing).

    Parameters
    ----------
    n_nodes : int
        Gauss–Legendre nodes per taut interval (default :data:`GAUSS_NODES`).
    """

    name = "cone"
    description = "affine helix segments on a cone around the fibre, averaged exactly over the azimuth"
    kernel_code = 0     # hbm.model.energy3d.diagonal.CONE

    def __init__(self, n_nodes: int = GAUSS_NODES) -> None:
        self.n_nodes = int(n_nodes)
        self._t, self._w = gauss_unit(self.n_nodes)

    def rule(self, D, theta_deg, need="tangent"):
        c2, cs, s2 = _trig(theta_deg)
        a0, a1, b1, a2, b2 = _coefficients(D, c2, cs, s2)
        with_n = need != "energy"
        if need != "tangent" and is_zero(D.fc) and is_zero(D.fn) and is_zero(a2) and is_zero(b2):
            # every segment has the same stretch (along-fibre uniaxial kinematics): one node is exact
            half = 0.5 * s2
            l2m1 = np.asarray(a0 + 0.0 * c2)[..., None]
            N = Sym(c2[..., None], half[..., None], half[..., None]) if with_n else None
            return N, np.ones_like(l2m1), l2m1
        shape = np.broadcast_shapes(*(np.shape(v) for v in (a0, a1, b1, a2, b2, c2)))
        c2, cs, s2, a0, a1, b1, a2, b2 = (np.broadcast_to(v, shape) for v in (c2, cs, s2, a0, a1, b1, a2, b2))
        if is_zero(D.fc) and is_zero(D.fn):
            return _rule_double(c2, s2, a0, a2, b2, self._t, self._w, not is_zero(D.cn), with_n)
        if is_zero(D.fn) and is_zero(D.cn):
            return _rule_even(c2, cs, s2, a0, a1, a2, self._t, self._w, with_n)
        return _rule_general(c2, cs, s2, a0, a1, b1, a2, b2, self._t, self._w, with_n)


class ConeFamilies(DirectionalCollagen):
    """The cone discretised by ``n`` equally spaced families at φ_k = 2π(k + ½)/n, weight 1/n each (what
    FE cards with fibre families compute; converges to :class:`ConeCollagen` only as O(n⁻²) in the
    stress because of the slack kink).  Not a ``collagen3d`` choice: a reference for the error of a
    discretised card."""

    name = "cone-families"
    description = "the cone discretised by n equally spaced fibre families"

    def __init__(self, n: int = 24) -> None:
        self.n = int(n)
        self.name = f"cone-families({self.n})"
        self._phi = (np.arange(self.n) + 0.5) * 2.0 * np.pi / self.n

    def rule(self, D, theta_deg, need="tangent"):
        c2, cs, s2 = (v[..., None] for v in _trig(theta_deg))
        cp, sp = np.cos(self._phi), np.sin(self._phi)
        N = Sym(c2, s2 * cp * cp, s2 * sp * sp, cs * cp, cs * sp, s2 * cp * sp)
        l2m1 = N.contract(Sym(*(0.0 if is_zero(v) else np.asarray(v)[..., None] for v in D)))
        shape = np.broadcast_shapes(np.shape(l2m1), c2.shape[:-1] + (self.n,))
        l2m1 = np.broadcast_to(l2m1, shape)
        return N, np.full(shape, 1.0 / self.n), l2m1
