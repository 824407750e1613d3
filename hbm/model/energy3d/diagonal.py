"""Compiled principal stresses and tangent of the energy form at a diagonal F (numba).

Every mode with a diagonal F (``uniaxial_f``, ``uniaxial_c``, planar, biaxial) spends its time in
:meth:`Energy3D.principal`; its numpy form builds a dozen temporaries of (elements × Gauss nodes) per
call, and the lateral root of ``uniaxial_c`` calls it ~10 times per element.  :func:`diagonal_point`
evaluates the same formulas for one element in one pass over the quadrature nodes: the cone's exact
taut-arc rule (:func:`hbm.model.energy3d.cone._rule_double`, slack nodes skipped since they add 0) or
the gst's closed form, the neo-Hookean matrix and the fibres.  It is used only for the exact classes
:class:`Energy3D` with :class:`ConeCollagen` or :class:`GstCollagen` (their ``kernel_code``; :attr:`Energy3D.kernel`); a
subclass with another fibre or segment law keeps the numpy path, which stays the reference
(``tests/test_fast3d.py`` compares the two to ≤ 1e-12).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from ..spyrou import _EXP_CLIP

#: reading codes of the kernel (``kernel_code`` of ConeCollagen and GstCollagen)
CONE, GST = 0, 1
_DEG = math.pi / 180.0


@njit(cache=True, nogil=True, error_model="numpy", fastmath={"arcp", "contract"})
def diagonal_point(mu, volf, p1, eopt, t1, t2, theta, e0, e1, e2, reading, t, w, tangent):
    """τ_i − μ and (``tangent``) c_ij = ∂τ_i/∂ln λ_j of one element at F = diag(exp(e0, e1, e2)).

    Returns the 9-tuple (τ0, τ1, τ2, c00, c01, c02, c11, c12, c22); the c's are 0 unless ``tangent``.
    Formulas and operation order as :meth:`Energy3D.principal` with
    :meth:`DirectionalCollagen.principal` (module docstring)."""
    d0 = math.expm1(2.0 * e0)
    d1 = math.expm1(2.0 * e1)
    d2 = math.expm1(2.0 * e2)
    th = theta * _DEG
    if reading == CONE:
        cth = math.cos(th)
        sth = math.sin(th)
        c2 = cth * cth
        s2 = sth * sth
        half = 0.5 * s2
        a0 = c2 * d0 + 0.5 * s2 * (d1 + d2)
        a2 = 0.5 * s2 * (d1 - d2)
    else:
        cth = math.cos(th)
        c2 = cth * cth
        half = 0.5 * (1.0 - c2)
        a0 = c2 * d0 + half * (d1 + d2)
        a2 = 0.0
    R = abs(a2)
    c2phi0 = 1.0
    psi = 0.0
    scale = 1.0
    n_nodes = 1  # gst, or every cone segment at the same stretch (stresses only): one node is exact
    if reading == CONE and R > 0.0:
        c2phi0 = a2 / R
        psi = math.acos(min(max(-a0 / R, -1.0), 1.0))
        scale = psi / math.pi
        n_nodes = t.size
    elif reading == CONE and tangent:  # N ⊗ N must be exact per node: the whole circle, taut or slack
        psi = math.pi if a0 > 0.0 else 0.0
        scale = psi / math.pi
        n_nodes = t.size
    s0 = s1 = s2n = 0.0
    k00 = k01 = k02 = k11 = k12 = k22 = 0.0
    for k in range(n_nodes):
        if n_nodes == 1:  # N = (c2, half, half), l² − 1 = a0
            cp = 0.0
            wq = 1.0
            l2m1 = a0
        else:
            cp = math.cos(psi * t[k])
            wq = scale * w[k]
            l2m1 = a0 + R * cp
        l = math.sqrt(1.0 + l2m1)
        x = l2m1 / (l + 1.0)
        if not x > 0.0:  # slack: no force, no stiffness
            continue
        z = t2 * x
        em1 = math.expm1(min(z, _EXP_CLIP))
        force = t1 * em1
        h = force / l
        wh = wq * h
        along = cp * c2phi0
        ncc = half * (1.0 + along)
        nnn = half * (1.0 - along)
        s0 += wh * c2
        s1 += wh * ncc
        s2n += wh * nnn
        if tangent:
            stiff = t1 * t2 * (em1 + 1.0) if z < _EXP_CLIP else 0.0   # exp(z) = expm1(z) + 1 to round-off
            wk = wq * (stiff - h) / (2.0 * l * l)
            k00 += wk * c2 * c2
            k01 += wk * c2 * ncc
            k02 += wk * c2 * nnn
            k11 += wk * ncc * ncc
            k12 += wk * ncc * nnn
            k22 += wk * nnn * nnn
    lam0 = 1.0 + d0
    lam1 = 1.0 + d1
    lam2 = 1.0 + d2
    ct0 = lam0 * s0
    ct1 = lam1 * s1
    ct2 = lam2 * s2n
    m = 1.0 - volf
    lf = math.exp(e0)
    fm1 = math.expm1(e0)
    fibre = lf * (volf * p1 * max(fm1 - eopt, 0.0))
    tau0 = mu * d0 + fibre + m * ct0
    tau1 = mu * d1 + m * ct1
    tau2 = mu * d2 + m * ct2
    if not tangent:
        return tau0, tau1, tau2, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0
    fibre_k = fibre + lf * lf * (volf * p1 * (1.0 if fm1 > eopt else 0.0))
    c00 = m * (2.0 * lam0 * lam0 * k00 + 2.0 * ct0) + 2.0 * mu * (1.0 + d0) + fibre_k
    c11 = m * (2.0 * lam1 * lam1 * k11 + 2.0 * ct1) + 2.0 * mu * (1.0 + d1)
    c22 = m * (2.0 * lam2 * lam2 * k22 + 2.0 * ct2) + 2.0 * mu * (1.0 + d2)
    c01 = m * (2.0 * lam0 * lam1 * k01)
    c02 = m * (2.0 * lam0 * lam2 * k02)
    c12 = m * (2.0 * lam1 * lam2 * k12)
    return tau0, tau1, tau2, c00, c01, c02, c11, c12, c22


@njit(cache=True, nogil=True, error_model="numpy", fastmath={"arcp", "contract"})
def diagonal_batch(mu, volf, p1, eopt, t1, t2, theta, e0, e1, e2, reading, t, w, tangent):
    """:func:`diagonal_point` over flat arrays (n,) -> (9, n) (rows as its tuple; c's only with ``tangent``)."""
    n = e0.size
    out = np.zeros((9 if tangent else 3, n))
    for i in range(n):
        r = diagonal_point(mu[i], volf[i], p1[i], eopt[i], t1[i], t2[i], theta[i], e0[i], e1[i], e2[i],
                           reading, t, w, tangent)
        for j in range(out.shape[0]):
            out[j, i] = r[j]
    return out


def flat_parameters(energy, p, shape) -> tuple[np.ndarray, ...]:
    """(μ, VOLF, P1, EOPT, T1, T2, THETA) broadcast to ``shape`` and flattened (contiguous float arrays)."""
    mu = energy.shear_modulus(p)
    cols = (mu,) + tuple(p[k] for k in ("VOLF", "P1", "EOPT", "T1", "T2", "THETA"))
    return tuple(np.ascontiguousarray(np.broadcast_to(np.asarray(v, dtype=float), shape)).reshape(-1) for v in cols)


def nodes(energy) -> tuple[np.ndarray, np.ndarray]:
    """The reading's Gauss nodes and weights on [0, 1] (a dummy pair for gst)."""
    t = getattr(energy.collagen, "_t", None)
    if t is None:
        return np.zeros(1), np.ones(1)
    return np.ascontiguousarray(t, dtype=float), np.ascontiguousarray(energy.collagen._w, dtype=float)


def principal_diagonal(energy, code: int, p, e: tuple, tangent: bool):
    """:meth:`Energy3D.principal` by the kernel: same arguments, same broadcast shapes."""
    e = tuple(np.asarray(ei, dtype=float) for ei in e)
    shape = np.broadcast_shapes(*(np.shape(v) for v in e), *(np.shape(p[k]) for k in
                                                            ("VOLF", "GF", "GM", "P1", "EOPT", "T1", "T2", "THETA")))
    cols = flat_parameters(energy, p, shape)
    es = tuple(np.ascontiguousarray(np.broadcast_to(v, shape)).reshape(-1) for v in e)
    t, w = nodes(energy)
    out = diagonal_batch(*cols, *es, code, t, w, bool(tangent)).reshape((-1,) + shape)
    tau = (out[0], out[1], out[2])
    if not tangent:
        return tau, None
    c00, c01, c02, c11, c12, c22 = out[3:]
    return tau, ((c00, c01, c02), (c01, c11, c12), (c02, c12, c22))
