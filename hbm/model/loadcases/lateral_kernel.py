"""Compiled traction-free lateral root of ``uniaxial_c`` (numba), one element at a time.

The numpy solver (:func:`hbm.model.loadcases.uniaxial_c._lateral_root`) runs the safeguarded Newton on
all particles × points at once and re-evaluates the energy on shrinking active sets (~23 passes per
call, 99 % of a joint fit's CPU).  Here every element runs the same iteration to its own convergence
in one loop, with the energy of :func:`hbm.model.energy3d.diagonal.diagonal_point`, and starts from the
previous point's root of the same particle (``strain`` sorted, so neighbours are close): u/ln λ of
the last converged point, scaled to this point's strain, replaces the isotropic −½ (same sign of
strain only).  The iteration, its stopping rule and its safeguards are the numpy solver's, so the
two agree to the stopping tolerance (RTOL = 1e-12 of the loaded stress; measured in
``tests/test_fast3d.py``).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from ..energy3d.diagonal import diagonal_point, flat_parameters, nodes

__all__ = ["lateral_rows", "flat_parameters", "nodes"]

_EPS = np.finfo(float).eps


@njit(cache=True, nogil=True, error_model="numpy", fastmath={"arcp", "contract"})
def lateral_rows(mu, volf, p1, eopt, t1, t2, theta, ec, reading, t, w, max_iter, rtol, warm):
    """u = ln λf with τ_ff = τ_nn for every element of a (rows, points) grid: parameters (rows,), ``ec`` =
    ln λc (1, points) shared by the rows or (rows, points), ascending along a row for the warm start.

    Returns
    -------
    u, tau0, tau1, tau2 : ndarray (rows, points)
        The root and the principal stresses there (NaN for non-finite input).
    status : ndarray (rows, points) of int8
        0 converged, 1 converged where g' ≤ 0 (no unique root), 2 not converged after ``max_iter``,
        3 non-finite input; ``evaluations`` (rows, points): energy evaluations spent.
    """
    m, k = mu.size, ec.shape[1]
    shared = ec.shape[0] == 1
    u_out = np.empty((m, k))
    tau = np.full((3, m, k), np.nan)
    status = np.zeros((m, k), dtype=np.int8)
    evals = np.zeros((m, k), dtype=np.int32)
    for r in range(m):
        par_ok = (math.isfinite(mu[r]) and math.isfinite(volf[r]) and math.isfinite(p1[r])
                  and math.isfinite(eopt[r]) and math.isfinite(t1[r]) and math.isfinite(t2[r])
                  and math.isfinite(theta[r]))
        ratio = -0.5
        for j in range(k):
            e = ec[0 if shared else r, j]
            if warm and j > 0 and ec[0 if shared else r, j - 1] * e > 0.0:
                u = ratio * e
            else:
                u = -0.5 * e
            if not (par_ok and math.isfinite(e)):
                u_out[r, j] = -0.5 * e
                status[r, j] = 3
                continue
            lo, hi = -math.inf, math.inf
            done = False
            n_ev = 0
            for _ in range(max_iter):
                a0, a1, a2, c00, c01, c02, c11, c12, c22 = diagonal_point(
                    mu[r], volf[r], p1[r], eopt[r], t1[r], t2[r], theta[r], u, e, -u - e, reading, t, w, True)
                n_ev += 1
                g = a0 - a2
                dg = c00 - 2.0 * c02 + c22
                load = abs(a1 - 0.5 * (a0 + a2))
                floor = 8.0 * _EPS * (abs(a0) + abs(a2))
                if g < 0:
                    lo = u
                if g > 0:
                    hi = u
                newton = u - g / dg
                step_ok = math.isfinite(newton) and lo < newton < hi
                if step_ok:
                    new = newton
                elif math.isfinite(lo) and math.isfinite(hi):
                    new = 0.5 * (lo + hi)
                elif g > 0:
                    new = u - 1.0
                else:
                    new = u + 1.0
                if abs(g) <= rtol * load + floor or abs(new - u) <= 4.0 * _EPS * (1.0 + abs(u)):
                    done = True
                    if warm and step_ok:  # the last Newton step, free: τ to first order in it (error O(step²))
                        du = newton - u
                        u = newton
                        a0, a1, a2 = a0 + (c00 - c02) * du, a1 + (c01 - c12) * du, a2 + (c02 - c22) * du
                    tau[0, r, j], tau[1, r, j], tau[2, r, j] = a0, a1, a2
                    if not dg > 0:
                        status[r, j] = 1
                    break
                u = new
            if not done:
                a0, a1, a2, _c0, _c1, _c2, _c3, _c4, _c5 = diagonal_point(
                    mu[r], volf[r], p1[r], eopt[r], t1[r], t2[r], theta[r], u, e, -u - e, reading, t, w, False)
                n_ev += 1
                tau[0, r, j], tau[1, r, j], tau[2, r, j] = a0, a1, a2
                status[r, j] = 2
            u_out[r, j] = u
            evals[r, j] = n_ev
            if done and e != 0.0:
                ratio = u / e
    return u_out, tau[0], tau[1], tau[2], status, evals
