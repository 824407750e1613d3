"""``uniaxial_c``: load across the fibres, the f and n faces traction-free (a scalar root per point)."""

from __future__ import annotations

import numpy as np

from ...errors import HbmError
from .base import LoadCase, Observable, full_shape, lateral_strain
from .registry import register_load_case

#: Newton iterations before giving up (measured: at most 22 over the prior box, :func:`_lateral_root`)
MAX_ITER = 60
#: the solve stops when |σ_ff| <= RTOL·|σ_cc| (or the step reaches round-off) ...
RTOL = 1e-12
#: ... and refuses a result whose residual exceeds this fraction of the loaded stress
ACCEPT = 1e-9
#: the compiled solver starts each particle's point from its previous point's root and returns the exact
#: root (one free Newton step past the stop); False: the numpy solver's iterates from the isotropic start
#: (its results to round-off, ~2x the evaluations; :func:`_lateral_root_compiled`)
WARM_START = True


@register_load_case
class UniaxialC(LoadCase):
    """Uniaxial load along c (across the fibres, in the specimen plane); the f and n faces are free.

    F = diag(λf, λ, 1/(λ·λf)) with λ = 1 + strain and λf unknown: traction-free f and n faces need
    τ_ff = τ_nn (= p).  With u = ln λf, g(u) = τ_ff − τ_nn = dw/du of the convex w(u) = W(F(u)), so g is
    increasing and has one root (μ > 0); a safeguarded Newton solve (bracket kept, bisection when a
    step leaves it) runs per element, compiled for the cone and gst readings (on the test's distinct
    strains, warm-started along each particle's strain path: :func:`_lateral_root_compiled`), else on
    all particles × points at once by numpy, starting from the isotropic λ^-1/2.  The
    two lateral strains differ and depend on μ, (1 − c)·T1, T2 and THETA (DESIGN.md §8).
    ``stress`` = σ_cc = τ_cc − p.  Not linear in the amplitudes (the free stretch depends on them).
    """

    name = "uniaxial_c"
    aliases = ("transverse", "cross")
    description = "load across the fibres along c; f and n faces traction-free (lateral stretches solved)"
    observables = (Observable("stress", "MPa", "Cauchy stress across the fibres, sigma_cc", "c"),
                   lateral_strain("f", name), lateral_strain("n", name))

    def prescribed_log_stretch(self, axis, strain, strain_2):
        if axis != "c":
            return super().prescribed_log_stretch(axis, strain, strain_2)
        return np.log1p(strain)

    def solve(self, energy, params, strain, strain_2=None):
        s, _ = self.controls(strain, strain_2)
        shape = full_shape(params, s.size)
        if energy.kernel is not None:
            u, sigma, _ = _lateral_root_compiled(energy, params, s, shape)
            ec = np.broadcast_to(np.log1p(s), shape)
            out = {"stress": sigma, "strain_f": np.expm1(u), "strain_n": np.expm1(-u - ec)}
            return {k: np.ascontiguousarray(v) for k, v in out.items()}
        p = {k: np.broadcast_to(v, shape).reshape(-1) for k, v in params.items()}
        ec = np.broadcast_to(np.log1p(s), shape).reshape(-1)
        u, sigma = _lateral_root(energy, p, ec)
        out = {"stress": sigma, "strain_f": np.expm1(u), "strain_n": np.expm1(-u - ec)}
        return {k: v.reshape(shape) for k, v in out.items()}


def _evaluate(energy, p, u, ec, tangent):
    tau, c = energy.principal(p, (u, ec, -u - ec), tangent)
    g = tau[0] - tau[2]
    dg = None if c is None else c[0][0] - 2.0 * c[0][2] + c[2][2]
    return tau, g, dg


def _lateral_root(energy, p, ec):
    """u = ln λf with τ_ff = τ_nn for every element (flat arrays): (u, σ_cc).

    Newton on g(u) = τ_ff − τ_nn; a step that leaves the bracket of the signs seen so far is replaced by
    bisection, or by a unit step in u while only one side is known.  Measured, cone: 200 prior-box draws
    x strains -40..44 %: 9.8 evaluations per element on average, at most 22; the six specimens'
    parameters (5 % jitter) x -30..30 %: 6.4.  Newton on ln(τ_ff/τ_nn) (linear for the neo-Hookean) saved a quarter of
    them but cycled at the collagen onset in compression; it is not used."""
    n = ec.size
    u = -0.5 * ec                                   # isotropic start
    lo, hi = np.full(n, -np.inf), np.full(n, np.inf)
    finite = np.isfinite(ec)
    for v in p.values():
        finite &= np.isfinite(v)
    taus = np.full((3, n), np.nan)
    active = np.flatnonzero(finite)
    flat = np.zeros(n, dtype=bool)                  # a root where g' = 0: the lateral stretch is not unique
    for _ in range(MAX_ITER):
        if active.size == 0:
            break
        pa = {k: v[active] for k, v in p.items()}
        ua, ea = u[active], ec[active]
        tau, g, dg = _evaluate(energy, pa, ua, ea, True)
        load = np.abs(tau[1] - 0.5 * (tau[0] + tau[2]))
        floor = 8 * np.finfo(float).eps * (np.abs(tau[0]) + np.abs(tau[2]))
        lo[active] = np.where(g < 0, ua, lo[active])
        hi[active] = np.where(g > 0, ua, hi[active])
        la, ha = lo[active], hi[active]
        with np.errstate(divide="ignore", invalid="ignore"):
            newton = ua - g / dg
        ok = np.isfinite(newton) & (newton > la) & (newton < ha)
        bracketed = np.isfinite(la) & np.isfinite(ha)
        with np.errstate(invalid="ignore"):      # inf - inf where unbracketed: not used
            fallback = np.where(bracketed, 0.5 * (la + ha), np.where(g > 0, ua - 1.0, ua + 1.0))
        new = np.where(ok, newton, fallback)
        done = (np.abs(g) <= RTOL * load + floor) | (np.abs(new - ua) <= 4 * np.finfo(float).eps * (1 + np.abs(ua)))
        u[active] = np.where(done, ua, new)
        flat[active] = done & ~(dg > 0)
        taus[:, active[done]] = np.stack(tau)[:, done]
        active = active[~done]
    if active.size:
        taus[:, active] = np.stack(_evaluate(energy, {k: v[active] for k, v in p.items()}, u[active],
                                             ec[active], False)[0])
    sigma, bad = _accepted(tuple(taus), finite)
    bad[active] = True
    bad |= flat
    _refuse(bad, p, ec)
    return u, sigma


def _accepted(tau, finite):
    """σ_cc, and where a returned root is refused: its residual |τ_ff − τ_nn| exceeds ACCEPT of σ_cc."""
    g = tau[0] - tau[2]
    sigma = tau[1] - 0.5 * (tau[0] + tau[2])
    bad = finite & (np.abs(g) > ACCEPT * np.abs(sigma) + 8 * np.finfo(float).eps * (np.abs(tau[0]) + np.abs(tau[2])))
    return sigma, bad


def _refuse(bad, p, ec) -> None:
    """:class:`HbmError` naming the first refused element (flat arrays), if any."""
    if bad.any():
        i = int(np.flatnonzero(bad)[0])
        values = ", ".join(f"{k}={v[i]:.6g}" for k, v in p.items())
        raise HbmError(f"mode uniaxial_c: no unique traction-free lateral stretch for {int(bad.sum())} of {bad.size} "
                       f"(particle, point) pairs (e.g. strain {np.expm1(ec[i]):.6g} at {values}); it is undetermined "
                       "where nothing resists the lateral deformation (shear modulus 0, collagen and fibres slack)")


def _lateral_root_compiled(energy, params, s, shape, warm: bool = WARM_START):
    """:func:`_lateral_root` by the compiled per-element solver (:mod:`.lateral_kernel`), for an energy with
    a kernel (:attr:`Energy3D.kernel`).

    Each distinct strain of the test is solved once per particle, in ascending order, from the previous
    point's root (``warm``; the isotropic start when parameters vary along the points).  With ``warm``
    the returned root is the Newton step past the stopping test (τ updated to first order in it), the
    exact root to round-off; the numpy solver's returned iterate is off it by up to its stopping
    tolerance (measured ≤ 4.5e-12 relative in the lateral strains).  Without ``warm`` the iterates are
    the numpy solver's (agreement ≤ 1e-15).  Measured in ``workflows/benchmarks/modes_throughput.py``.

    Returns
    -------
    u, sigma : ndarray of ``shape``
        ln λf and σ_cc.
    evaluations : ndarray
        Energy evaluations per solved element (particles × distinct strains).
    """
    from .lateral_kernel import flat_parameters, lateral_rows, nodes  # numba loads on first use
    ec_all = np.log1p(s)
    if all(np.ndim(v) == 0 or np.shape(v)[-1] == 1 for v in params.values()):
        ec, inverse = np.unique(ec_all, return_inverse=True)   # one parameter row per particle
        rows = shape[:-1] + (1,)
        grid = ec.reshape(1, -1)
    else:                                                      # parameters vary along the points
        rows, inverse = shape, np.zeros(1, dtype=int)
        grid = np.broadcast_to(ec_all, shape).reshape(-1, 1).copy()
    cols = flat_parameters(energy, params, rows)
    t, w = nodes(energy)
    u, *tau, status, evaluations = lateral_rows(*cols, grid, energy.kernel, t, w, MAX_ITER, RTOL, bool(warm))
    sigma, bad = _accepted(tau, status != 3)
    bad |= (status == 1) | (status == 2)
    if bad.any():
        flat = {k: np.broadcast_to(np.broadcast_to(v, rows).reshape(-1, 1), u.shape).reshape(-1)
                for k, v in params.items()}
        _refuse(bad.reshape(-1), flat, np.broadcast_to(grid, u.shape).reshape(-1))
    return u[:, inverse].reshape(shape), sigma[:, inverse].reshape(shape), evaluations
