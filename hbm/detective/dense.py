"""Fits of a dense record: a Gauss–Newton polish of every optimum and the Laplace evidence.

A dense record -- a machine export of thousands of readings, fitted as bin means of its readings
(:mod:`hbm.data.reduction`) or row by row -- carries so much information that its posterior is a
small, nearly Gaussian region of the prior box (Bernstein–von Mises: thousands of readings per
parameter).  Two things the detective does for ordinary curves then fail:

* CMA-ES within the diagnosis's budget stops far from the optimum.  On an 8000-reading ramp-hold
  record (two relaxation times, 1 % noise) the model that generated it reached max log L 1740–2070
  from three starts near the truth (truth: 2277); a bounded Gauss–Newton (trust-region) polish of
  the whitened residuals from the same points reached 2283–2287 in 60–200 evaluations.
  :func:`polish` runs it after every CMA-ES search of a dense record.
* The evidence runs' TMCMC (800 particles, ≤ 25 steps per stage) tempers from the prior box onto a
  posterior a million times smaller: on that record it ran 71 stages (1.4 million evaluations)
  and never reached the optimum (its log Z 1815 sat below the CMA-ES optimum's log L).  Where the
  posterior is that narrow it is also that Gaussian, so the evidence is its Laplace approximation
  (:func:`laplace_fit`) -- exact to O(1/n) for the identified directions; a direction the data do
  not inform (a ridge of the base model, curvature below the prior box's own 12/width²) counts with
  the box, contributing nothing -- and the posterior draws (coverage, intervals) are Gaussian draws
  clipped to the box.  Its "SE" is 0: it has no sampling error (its approximation error is not
  estimated).

A record is dense when it was reduced or has more than :data:`hbm.data.reduction.DENSE_POINTS`
rows; other records take the detective's ordinary path, bitwise as before.
"""

from __future__ import annotations

import math

import numpy as np
from scipy import optimize as _sopt

__all__ = ["polish", "laplace_fit"]


def _whitened(lik, x: np.ndarray):
    """Residual function of the model parameters (rows, working coordinates) at the noise parameters
    of ``x``: the residuals in noise-whitened units (iid N(0, 1) under the noise model)."""
    k = lik.n_model
    noise_row = np.asarray(x, float)[k:]
    q = lik.to_natural(np.asarray(x, float)[None, :])[0, k:]
    y = np.asarray(lik.observed, float)

    def residual(rows: np.ndarray) -> np.ndarray:
        m = np.asarray(lik.predict(np.hstack([rows, np.broadcast_to(noise_row, (rows.shape[0], noise_row.size))])))
        return lik.noise_model.whiten_rows(y - m, np.tile(q, (m.shape[0], 1)), model_stress=m)
    return residual, k


def polish(lik, x: np.ndarray, f: float, check_time=lambda: None, max_nfev: int = 100) -> tuple[np.ndarray, float]:
    """The optimum ``(x, f)`` of ``lik`` improved by a bounded Gauss–Newton (trust-region) fit of
    its model parameters at its noise parameters; the better of the two.  (The caller follows with
    a short CMA-ES over all parameters, so that the noise parameters follow the new residuals.)

    Parameters
    ----------
    lik : Likelihood
        Of a dense record (Gaussian noise models: their whitening makes the residuals iid N(0, 1)).
    x, f : array, float
        A CMA-ES optimum (working coordinates) and its log-likelihood.
    check_time : callable
        Called before every batch of evaluations (a diagnosis's deadline).
    max_nfev : int
        Gauss–Newton iterations at most.
    """
    x = np.asarray(x, float)
    residual, k = _whitened(lik, x)
    box = np.asarray(lik.bounds, float)[:k]
    width = box[:, 1] - box[:, 0]

    def fun(xm):
        check_time()
        return residual(xm[None, :])[0]

    def jac(xm):
        check_time()
        h = 1e-6 * width
        xp = np.clip(xm + np.diag(h), box[:, 0], box[:, 1])
        xn = np.clip(xm - np.diag(h), box[:, 0], box[:, 1])
        r = residual(np.vstack([xp, xn]))
        dx = np.maximum(np.diag(xp - xn), 1e-300)
        return ((r[:k] - r[k:]) / dx[:, None]).T

    start = np.clip(x[:k], box[:, 0] + 1e-12 * width, box[:, 1] - 1e-12 * width)
    try:
        with np.errstate(all="ignore"):
            res = _sopt.least_squares(fun, start, jac=jac, bounds=(box[:, 0], box[:, 1]), x_scale=width,
                                      max_nfev=max_nfev, method="trf")
    except (ValueError, np.linalg.LinAlgError):
        return x, f
    cand = x.copy()
    cand[:k] = res.x
    fc = float(np.asarray(lik(cand[None, :]))[0])
    return (cand, fc) if np.isfinite(fc) and fc > f else (x, f)


def laplace_fit(lik, x: np.ndarray, f: float, n_samples: int, seed: int) -> tuple[float, np.ndarray, int]:
    """Laplace evidence of ``lik`` at its optimum and Gaussian posterior draws.

    log Z ≈ f + Σᵢ ½·log(2π/λᵢ) in the unit box (uniform prior, density 1), λᵢ the eigenvalues of
    the negative Hessian there, each at least 12 (the precision of the box itself: a direction the
    data do not inform contributes nothing).  Draws: N(x, H⁻¹) with the same floor, clipped to the box.

    Returns
    -------
    log_z : float
    samples : ndarray (n_samples, d)
    evaluations : int
    """
    x = np.asarray(x, float)
    b = np.asarray(lik.bounds, float)
    width = b[:, 1] - b[:, 0]
    d = x.size
    h = 1e-4
    u = (x - b[:, 0]) / width
    u = np.clip(u, 2 * h, 1 - 2 * h)          # (a point on a bound: the curvature just inside it)
    E = np.eye(d) * h
    pts = [u] + [u + E[i] for i in range(d)] + [u - E[i] for i in range(d)]
    pairs = [(i, j) for i in range(d) for j in range(i + 1, d)]
    for i, j in pairs:
        pts += [u + E[i] + E[j], u + E[i] - E[j], u - E[i] + E[j], u - E[i] - E[j]]
    F = np.asarray(lik(b[:, 0] + np.array(pts) * width), float)
    H = np.zeros((d, d))
    f0 = F[0]
    for i in range(d):
        H[i, i] = -(F[1 + i] - 2 * f0 + F[1 + d + i]) / h ** 2
    for m, (i, j) in enumerate(pairs):
        a = F[1 + 2 * d + 4 * m: 5 + 2 * d + 4 * m]
        H[i, j] = H[j, i] = -(a[0] - a[1] - a[2] + a[3]) / (4 * h * h)
    if not np.isfinite(H).all():
        H = np.where(np.isfinite(H), H, 0.0)
    lam, V = np.linalg.eigh(0.5 * (H + H.T))
    lam = np.maximum(lam, 12.0)
    log_z = float(max(f, f0)) + float(np.sum(0.5 * np.log(2 * math.pi / lam)))
    z = np.random.default_rng(seed).standard_normal((int(n_samples), d)) / np.sqrt(lam)
    draws = np.clip(u + z @ V.T, 0.0, 1.0)
    return log_z, b[:, 0] + draws * width, len(pts)
