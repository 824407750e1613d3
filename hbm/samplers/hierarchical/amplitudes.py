"""Moves of log amplitudes whose log-likelihood is quadratic in the amplitudes, by importance sampling.

A model that is linear in k amplitudes A given its other parameters, observed with Gaussian noise
of fixed covariance, has the log-likelihood

    ℓ(A) = ℓ0 + Aᵀb − ½ AᵀGA          (G = XᵀΣ⁻¹X, b = XᵀΣ⁻¹(y − s0), ℓ0 = ℓ at A = 0)

and the population layer puts a normal population on u = log A (independent columns N(mu_j, sd_j);
a column without a population is flat).  The conditional of u given the rest is

    π(u) ∝ exp(ℓ(e^u)) · Π_j N(u_j; mu_j, sd_j)   on the support,

where the support is a box in u and, optionally, linear constraints on A with one latent scalar c:
A is allowed iff some c satisfies P·A + Q·c ≤ R row by row (the combinations of a muscle model are
the image of its original parameters exactly so; the caller gives P, Q, R).

The proposal q of a row (compiled, :func:`particles`) is a mixture of a multivariate t (``df``
degrees of freedom) around a Gauss–Newton estimate of π's mode (``iters`` steps from the
least-squares amplitudes where they are positive, the population mean elsewhere; covariance the
inverse Gauss–Newton precision × ``inflate``²) and, with weight ``1 − weight``, the population
itself (a column without one from the t's scale): where the data bound an amplitude from one side
only the conditional's tail is the population's.  It is used through importance weights
w = π/q of ``M`` particles, never as a plain proposal:

* :func:`conditional_draw` — the conditional importance sampling kernel: the current u and M − 1
  particles from q, one kept with probability ∝ w (a Gibbs step of the extended target
  (1/M)·π(u_k)·Π_{m≠k} q(u_m); exact for any q);
* the joint moves of the shards (:mod:`.shards`) propose new nonlinear parameters φ' with M fresh
  particles at φ' and accept with the ratio of the mean weights at φ' and at φ (the current u among
  φ's particles): the same extended target, so exact; it approaches the independence sampler on the
  marginal of φ as M grows.

All random numbers come from the caller (one uniform and k + df normals per particle), so they can
be drawn from per-specimen streams in advance.

This module is sampler-layer code: it knows nothing about muscles.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

__all__ = ["quadratic_loglik", "particles", "modes", "amplitudes_valid", "log_mean_exp", "pick", "conditional_draw", "NO_CONSTRAINTS"]

#: no linear constraints on the amplitudes (P (0, k) is broadcast by the caller)
NO_CONSTRAINTS = None


def quadratic_loglik(u: np.ndarray, ll0: np.ndarray, G: np.ndarray, b: np.ndarray) -> np.ndarray:
    """ℓ0 + Aᵀb − ½AᵀGA at A = e^u (u, b (..., k), G (..., k, k), ll0 (...))."""
    A = np.exp(u)
    GA = np.einsum("...ij,...j->...i", G, A)
    return ll0 + np.einsum("...i,...i->...", A, b - 0.5 * GA)


@njit(cache=True, nogil=True)
def _chol(H, L) -> None:
    """Lower Cholesky factor of the k×k matrix H into L (a floor keeps it defined)."""
    k = H.shape[0]
    for j in range(k):
        s = H[j, j]
        for m in range(j):
            s -= L[j, m] * L[j, m]
        L[j, j] = math.sqrt(max(s, 1e-300))
        for i in range(j + 1, k):
            s = H[i, j]
            for m in range(j):
                s -= L[i, m] * L[j, m]
            L[i, j] = s / L[j, j]
        for i in range(j):
            L[i, j] = 0.0


@njit(cache=True, nogil=True)
def _solve(L, x, out) -> None:
    """(LLᵀ)⁻¹x into out."""
    k = L.shape[0]
    for i in range(k):
        s = x[i]
        for m in range(i):
            s -= L[i, m] * out[m]
        out[i] = s / L[i, i]
    for i in range(k - 1, -1, -1):
        s = out[i]
        for m in range(i + 1, k):
            s -= L[m, i] * out[m]
        out[i] = s / L[i, i]


@njit(cache=True, nogil=True)
def _valid(u, lo, hi, P, Q, R, A) -> bool:
    """u inside its box and some c with P·A + Q·c ≤ R, A = e^u (filled in here)."""
    k = u.shape[0]
    for j in range(k):
        if not (lo[j] <= u[j] <= hi[j]):
            return False
    for j in range(k):
        A[j] = math.exp(u[j])
    c_lo, c_hi = -math.inf, math.inf
    for i in range(P.shape[0]):
        s = 0.0
        for j in range(k):
            s += P[i, j] * A[j]
        if Q[i] > 0.0:
            c_hi = min(c_hi, (R[i] - s) / Q[i])
        elif Q[i] < 0.0:
            c_lo = max(c_lo, (R[i] - s) / Q[i])
        elif s > R[i]:
            return False
    return P.shape[0] == 0 or c_lo < c_hi


@njit(cache=True, nogil=True)
def _laplace(G, b, mu, sd, pooled, lo, hi, iters, prec, H, L, g, step, A, mode) -> None:
    """The mode of π (into ``mode``) by Gauss–Newton steps from the least-squares amplitudes where they
    are positive (else the population mean, else the box middle), and the Cholesky factor ``L`` of
    the Gauss–Newton precision there (``H``); one row, k×k work arrays given."""
    k = b.shape[0]
    for j in range(k):
        prec[j] = 1.0 / (sd[j] * sd[j]) if pooled[j] else 0.0
    for i in range(k):
        for j in range(k):
            H[i, j] = G[i, j] / math.sqrt(max(G[i, i] * G[j, j], 1e-300)) + (1e-9 if i == j else 0.0)
        g[i] = b[i] / math.sqrt(max(G[i, i], 1e-300))
    _chol(H, L)
    _solve(L, g, step)
    for j in range(k):
        a = step[j] / math.sqrt(max(G[j, j], 1e-300))
        if a > 0.0:
            mode[j] = math.log(a)
        else:
            mode[j] = mu[j] if pooled[j] else 0.5 * (lo[j] + hi[j])
        mode[j] = min(max(mode[j], lo[j]), hi[j])
    for it in range(iters + 1):
        for j in range(k):
            A[j] = math.exp(mode[j])
        for i in range(k):
            for j in range(k):
                H[i, j] = A[i] * G[i, j] * A[j]
            H[i, i] += prec[i] + 1e-10
        _chol(H, L)
        if it == iters:
            break
        for i in range(k):
            s = b[i]
            for j in range(k):
                s -= G[i, j] * A[j]
            g[i] = A[i] * s - prec[i] * (mode[i] - mu[i])
        _solve(L, g, step)
        for j in range(k):
            mode[j] = min(max(mode[j] + min(max(step[j], -2.0), 2.0), lo[j]), hi[j])


@njit(cache=True, nogil=True)
def _modes(G, b, mu, sd, pooled, lo, hi, iters, out) -> None:
    n, k = b.shape
    prec, g, step, A = np.empty(k), np.empty(k), np.empty(k), np.empty(k)
    H, L = np.empty((k, k)), np.empty((k, k))
    for r in range(n):
        _laplace(G[r], b[r], mu[r], sd[r], pooled, lo, hi, iters, prec, H, L, g, step, A, out[r])


def modes(G, b, mu, sd, pooled, lo, hi, *, iters: int = 3) -> np.ndarray:
    """The proposal's centre (an estimate of π's mode, module docstring) of every row, (n, k): a
    deterministic function of the row's quadratic form and population (for moves that carry the
    amplitudes along with it)."""
    G, b, mu, sd = (np.ascontiguousarray(a, dtype=float) for a in (G, b, mu, sd))
    out = np.empty(b.shape)
    _modes(G, b, mu, sd, np.asarray(pooled, np.bool_), np.asarray(lo, float), np.asarray(hi, float), int(iters), out)
    return out


@njit(cache=True, nogil=True)
def _particles(G, b, ll0, mu, sd, pooled, lo, hi, P, Q, R, current, has_current, U, Z, df, inflate, weight,
               iters, parts, lw) -> None:
    n, k = b.shape
    M = U.shape[1]
    H = np.empty((k, k))
    L = np.empty((k, k))
    A = np.empty(k)
    g = np.empty(k)
    step = np.empty(k)
    u = np.empty(k)
    mode = np.empty(k)
    e = np.empty(k)
    prec = np.empty(k)
    psd = np.empty(k)
    tconst = math.lgamma(0.5 * (df + k)) - math.lgamma(0.5 * df) - 0.5 * k * math.log(df * math.pi)
    any_pooled = False
    for j in range(k):
        any_pooled = any_pooled or pooled[j]
    w_t = weight if any_pooled else 1.0
    lw_t, lw_p = math.log(w_t), (math.log(1.0 - w_t) if w_t < 1.0 else -math.inf)
    for r in range(n):
        _laplace(G[r], b[r], mu[r], sd[r], pooled, lo, hi, iters, prec, H, L, g, step, A, mode)
        logdet = -k * math.log(inflate)  # log |precision / inflate²|^½
        for j in range(k):
            logdet += math.log(L[j, j])
            psd[j] = sd[r, j] if pooled[j] else inflate / math.sqrt(H[j, j])
        logpsd = 0.0
        for j in range(k):
            logpsd += math.log(psd[j])
        for m in range(M):
            if m == 0 and has_current:
                for j in range(k):
                    u[j] = current[r, j]
            else:
                chi = 0.0
                for j in range(df):
                    chi += Z[r, m, k + j] * Z[r, m, k + j]
                if U[r, m] < w_t:  # t: mode + inflate·L⁻ᵀz/√(χ²/df)
                    f = inflate / math.sqrt(chi / df)
                    for i in range(k - 1, -1, -1):
                        s = Z[r, m, i]
                        for q in range(i + 1, k):
                            s -= L[q, i] * e[q]
                        e[i] = s / L[i, i]
                    for j in range(k):
                        u[j] = mode[j] + f * e[j]
                else:
                    for j in range(k):
                        u[j] = (mu[r, j] if pooled[j] else mode[j]) + psd[j] * Z[r, m, j]
            for j in range(k):
                parts[r, m, j] = u[j]
            if not _valid(u, lo, hi, P, Q, R, A):  # fills A = e^u
                lw[r, m] = -math.inf
                continue
            # log q: t component and population component
            maha, zz = 0.0, 0.0
            for j in range(k):
                s = 0.0
                for i in range(j, k):
                    s += L[i, j] * (u[i] - mode[i])
                maha += s * s
                c = (u[j] - (mu[r, j] if pooled[j] else mode[j])) / psd[j]
                zz += c * c
            maha /= inflate * inflate
            lt = lw_t + tconst + logdet - 0.5 * (df + k) * math.log1p(maha / df)
            lp = lw_p - 0.5 * zz - logpsd - 0.5 * k * math.log(2.0 * math.pi)
            mx = max(lt, lp)
            logq = mx + math.log(math.exp(lt - mx) + math.exp(lp - mx))
            # log π: quadratic log-likelihood plus the population of the pooled columns
            val = ll0[r]
            for i in range(k):
                s = b[r, i]
                for j in range(k):
                    s -= 0.5 * G[r, i, j] * A[j]
                val += A[i] * s
                if pooled[i]:
                    c = (u[i] - mu[r, i]) / sd[r, i]
                    val -= 0.5 * c * c
            lw[r, m] = val - logq if math.isfinite(val) else -math.inf


@njit(cache=True, nogil=True)
def _valid_rows(u, lo, hi, P, Q, R, out) -> None:
    A = np.empty(u.shape[1])
    for r in range(u.shape[0]):
        out[r] = _valid(u[r], lo, hi, P, Q, R, A)


def amplitudes_valid(u: np.ndarray, lo, hi, constraints) -> np.ndarray:
    """(n,): rows u (n, k) inside the box and the constraints (module docstring)."""
    u = np.ascontiguousarray(u, dtype=float)
    k = u.shape[1]
    P, Q, R = constraints if constraints is not None else (np.zeros((0, k)), np.zeros(0), np.zeros(0))
    out = np.empty(u.shape[0], np.bool_)
    _valid_rows(u, np.asarray(lo, float), np.asarray(hi, float), np.ascontiguousarray(P, dtype=float),
                np.asarray(Q, float), np.asarray(R, float), out)
    return out


def particles(G, b, ll0, mu, sd, pooled, lo, hi, constraints, uniforms, normals, current=None, *, df: int = 4,
              inflate: float = 1.3, weight: float = 0.6, iters: int = 3) -> tuple[np.ndarray, np.ndarray]:
    """Importance particles of u = log A for ``n`` rows (module docstring).

    Parameters
    ----------
    G, b, ll0 : ndarray (n, k, k), (n, k), (n,)
        The quadratic log-likelihood of every row.
    mu, sd : ndarray (n, k)
        Population of each column; ``pooled`` (k,) False: the column has none.
    lo, hi : ndarray (k,)
        Box of u.
    constraints : (P (m, k), Q (m,), R (m,)) or None
        Linear constraints on A with a latent scalar (module docstring); None: the box only.
    uniforms, normals : ndarray (n, M), (n, M, k + df)
        Random numbers (one uniform and k + df normals per particle).
    current : ndarray (n, k), optional
        Particle 0 of every row (its random numbers are not used).

    Returns
    -------
    parts : ndarray (n, M, k)
    lw : ndarray (n, M)
        log π(u)/q(u) up to a constant of the row (−inf off the support).
    """
    G, b, ll0, mu, sd = (np.ascontiguousarray(a, dtype=float) for a in (G, b, ll0, mu, sd))
    n, k = b.shape
    M = uniforms.shape[1]
    P, Q, R = constraints if constraints is not None else (np.zeros((0, k)), np.zeros(0), np.zeros(0))
    parts = np.empty((n, M, k))
    lw = np.empty((n, M))
    cur = np.zeros((n, k)) if current is None else np.ascontiguousarray(current, dtype=float)
    _particles(G, b, ll0, mu, sd, np.asarray(pooled, np.bool_), np.asarray(lo, float), np.asarray(hi, float),
               np.ascontiguousarray(P, dtype=float), np.asarray(Q, float), np.asarray(R, float), cur, current is not None,
               np.ascontiguousarray(uniforms, dtype=float), np.ascontiguousarray(normals, dtype=float), int(df),
               float(inflate), float(weight), int(iters), parts, lw)
    return parts, lw


def log_mean_exp(lw: np.ndarray) -> np.ndarray:
    """log of the mean of exp over the last axis (−inf where every term is)."""
    mx = np.max(lw, axis=-1)
    safe = np.where(np.isfinite(mx), mx, 0.0)
    with np.errstate(divide="ignore"):
        return np.where(np.isfinite(mx), safe + np.log(np.mean(np.exp(lw - safe[..., None]), axis=-1)), -np.inf)


def pick(lw: np.ndarray, uniform: np.ndarray) -> np.ndarray:
    """One index per row of ``lw`` (n, M) with probability ∝ exp(lw), by inverse CDF of ``uniform`` (n,)."""
    mx = np.max(lw, axis=-1, keepdims=True)
    w = np.exp(lw - np.where(np.isfinite(mx), mx, 0.0))
    cw = np.cumsum(w, axis=-1)
    return np.minimum(np.sum(cw < (uniform * cw[:, -1])[:, None], axis=-1), lw.shape[-1] - 1)


def conditional_draw(u: np.ndarray, G, b, ll0, mu, sd, pooled, lo, hi, constraints, uniforms: np.ndarray,
                     normals: np.ndarray, **kw) -> tuple[np.ndarray, np.ndarray]:
    """The conditional importance sampling kernel (module docstring): the current ``u`` (n, k) and M − 1
    particles; returns the kept u (n, k) and whether it changed.  ``uniforms`` (n, M + 1): M component
    choices (the first unused) and the selection; ``normals`` (n, M, k + df)."""
    parts, lw = particles(G, b, ll0, mu, sd, pooled, lo, hi, constraints, uniforms[:, :-1], normals, current=u, **kw)
    j = pick(lw, uniforms[:, -1])
    return parts[np.arange(u.shape[0]), j], j > 0
