"""Sampling coordinates of the TMCMC moves: the prior box, its logit map, or a caller's bijection.

The prior of θ is uniform on a box.  A move walks in coordinates u = g(θ); the log-density of u
under the prior is the log-Jacobian log|det ∂θ/∂u| up to a constant, which the Metropolis–
Hastings ratio carries, so the tempered target (hence log Ẑ) does not depend on the choice.

* :class:`BoxCoordinates` — u = θ; proposals leaving the box are rejected without evaluation.
* :class:`LogitCoordinates` — u = logit((θ − lo)/(hi − lo)) (the default): proposals never leave
  the box and multiplicative ridges (T1 ∝ 1/(1 − VOLF), A·exp(T2·x)) become nearly straight.
* any :class:`Bijection` of the caller (e.g. :class:`hbm.identifiability.combinations.CombinationCoordinates`).

Also here: the sanitised call of the user's log-likelihood (:func:`log_likelihood_of`), which
every evaluation of a coordinate goes through.
"""

from __future__ import annotations

from typing import Callable, Protocol, runtime_checkable

import numpy as np

from ..errors import HbmError

__all__ = ["Bijection", "BoxCoordinates", "LogitCoordinates", "to_logit", "from_logit", "in_box",
           "log_likelihood_of", "check_bounds"]

LogLikelihood = Callable[[np.ndarray], np.ndarray]


@runtime_checkable
class Bijection(Protocol):
    """Sampling coordinates u = g(θ) of the random walk, replacing the default logit transform.

    The samplers know nothing of the model: a caller that knows the model's degeneracies (e.g.
    :class:`hbm.identifiability.combinations.CombinationCoordinates`) passes an object with

    * ``name`` : str — identifies the map in checkpoint fingerprints;
    * ``support`` : array (d, 2) — the box of u that g maps the prior box onto (±inf allowed);
      proposals outside it are rejected without evaluating the likelihood;
    * ``forward(theta)`` : (n, d) → u (n, d);
    * ``inverse(u)`` : (n, d) → (θ (n, d), log|det ∂θ/∂u| (n,)).

    The prior of θ is uniform on the box, so the log-density of u is the log-Jacobian up to a
    constant: the MH ratio uses it and the tempered target (hence log Ẑ) is unchanged.
    """

    name: str
    support: np.ndarray

    def forward(self, theta: np.ndarray) -> np.ndarray: ...

    def inverse(self, u: np.ndarray) -> "tuple[np.ndarray, np.ndarray]": ...


def check_bounds(bounds) -> np.ndarray:
    """The prior box as a float array (d, 2) with finite lo < hi in every row, else :class:`HbmError`."""
    b = np.asarray(bounds, dtype=float)
    if b.ndim != 2 or b.shape[1] != 2 or b.shape[0] < 1:
        raise HbmError(f"tmcmc: bounds must have shape (d, 2), got {b.shape}")
    if not np.all(np.isfinite(b)) or np.any(b[:, 1] <= b[:, 0]):
        raise HbmError("tmcmc: bounds must be finite with lower < upper in every row")
    return b


def log_likelihood_of(log_likelihood: LogLikelihood, x: np.ndarray) -> np.ndarray:
    """Call the user's log-likelihood on (m, d) and sanitise: NaN/+inf → −inf, shape checked."""
    if x.shape[0] == 0:
        return np.empty(0)
    out = np.asarray(log_likelihood(x), dtype=float)
    if out.shape != (x.shape[0],):
        raise HbmError(f"tmcmc: log_likelihood returned shape {out.shape}, expected ({x.shape[0]},)")
    return np.where(np.isnan(out) | (out == np.inf), -np.inf, out)


def in_box(x: np.ndarray, bounds: np.ndarray) -> np.ndarray:
    """Rows of ``x`` inside the box ``bounds`` (faces included)."""
    return np.all((x >= bounds[:, 0]) & (x <= bounds[:, 1]), axis=1)


def to_logit(x: np.ndarray, bounds: np.ndarray) -> np.ndarray:
    """Box → R^d: u = log(f / (1 − f)), f = (x − lo)/(hi − lo) (kept finite at the faces)."""
    f = np.clip((x - bounds[:, 0]) / (bounds[:, 1] - bounds[:, 0]), 1e-15, 1.0 - 1e-15)
    return np.log(f) - np.log1p(-f)


def from_logit(u: np.ndarray, bounds: np.ndarray, with_log_prior: bool = False):
    """Inverse of :func:`to_logit`; optionally also the log density of u under the uniform prior.

    x uniform on the box ⇔ each u_i standard logistic: log p(u) = Σ log f(1 − f)
    = −Σ|u_i| − 2·log Π(1 + e^{−|u_i|}) (one log per particle instead of one per coordinate; the
    product lies in [1, 2^d], so it is formed directly for d ≤ 500).
    """
    a = np.abs(u)
    e = np.exp(-a)  # stable logistic: never overflows
    r = 1.0 / (1.0 + e)
    f = np.where(u >= 0, r, e * r)
    x = bounds[:, 0] + f * (bounds[:, 1] - bounds[:, 0])
    if not with_log_prior:
        return x
    if u.shape[1] <= 500:
        return x, -np.sum(a, axis=1) - 2.0 * np.log(np.prod(1.0 + e, axis=1))
    return x, np.sum(-a - 2.0 * np.log1p(e), axis=1)


class LogitCoordinates:
    """The default sampling coordinates (``transform="logit"``) as a :class:`Bijection`.

    Passing it as ``bijection`` reproduces the default run bitwise; it is the reference that
    other coordinates are compared with (e.g. the geometry measurement of the benchmark).
    """

    name = "logit"

    def __init__(self, bounds):
        self.bounds = check_bounds(bounds)
        self.support = np.array([[-np.inf, np.inf]] * len(self.bounds))

    def forward(self, theta: np.ndarray) -> np.ndarray:
        return to_logit(np.asarray(theta, float), self.bounds)

    def inverse(self, u: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        return from_logit(np.asarray(u, float), self.bounds, True)


class BoxCoordinates:
    """The prior box itself (``transform="none"``, and the manifold move): u = θ, zero log-Jacobian."""

    name = "box"

    def __init__(self, bounds):
        self.bounds = check_bounds(bounds)
        self.support = self.bounds

    def forward(self, theta: np.ndarray) -> np.ndarray:
        return theta

    def inverse(self, u: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        return u, np.zeros(len(u))
