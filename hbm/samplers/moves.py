"""Metropolis–Hastings moves of the TMCMC population, behind one protocol and a registry.

A move is chosen by name (``tmcmc(move="local")``) or passed as an object (``move=Manifold(ridge=1e-3)``),
as with emcee's moves.  Once per stage :func:`hbm.samplers.tmcmc.step` hands the move a
:class:`StageSetup` (the resampled population, its weighted covariance at the new β, how to
evaluate a point); the move then

* ``prepare(setup)`` → (kernel, walkers): everything fixed during the stage (e.g. neighbourhood
  covariances) and the per-particle state (:class:`Walkers`; ``aux`` is the move's own, e.g. the
  gradient and Fisher information of the manifold move);
* ``step(kernel, walkers, beta, tuning, rng)`` → :class:`MoveStep`: one vectorised MH step of
  the whole population that leaves the tempered target invariant;
* ``adapt(tuning, step, target_acceptance)`` → :class:`Tuning`: the step size after the step.

Shipped moves (registry :data:`MOVES`; :func:`register_move` adds one):

* ``"rw"`` :class:`RandomWalk` — Gaussian random walk with the weighted population covariance;
* ``"manifold"`` :class:`Manifold` — simplified mMALA with the tempered Fisher metric, in box
  coordinates (needs ``gradient_fim``);
* ``"local"`` :class:`LocalWalk` — the random walk with the covariance of the nearest stage-start
  neighbourhood (:mod:`hbm.samplers.local_proposal`; the detective's refined evidence).

Experimental moves measured on the muscle benchmark (differential evolution, a fitted t-mixture
independence proposal) live with the benchmark in ``workflows/benchmarks/`` as Move classes.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Callable, NamedTuple, Optional, Protocol, runtime_checkable

import numpy as np

from ..errors import HbmError
from .coordinates import in_box, log_likelihood_of
from .linalg import batched_cholesky
from .local_proposal import LocalMetric, fit_local_metric, local_step, nearest_reference

__all__ = ["Walkers", "MoveStep", "Tuning", "StageSetup", "Move", "RandomWalk", "Manifold", "LocalWalk",
           "MOVES", "register_move", "get_move", "needs_gradient", "adapt_scale", "metropolis"]


class Walkers(NamedTuple):
    """The population during a stage's moves.

    Attributes
    ----------
    x : ndarray (n, d)
        Positions in the move's coordinates (sampling coordinates, or the box for a move with
        ``box_coordinates``).
    ll : ndarray (n,)
        Log-likelihoods.
    lp : ndarray (n,)
        Log prior density of the coordinates (the log-Jacobian; zero in box coordinates).
    aux : any
        Per-particle state of the move (None for the random walk).
    """

    x: np.ndarray
    ll: np.ndarray
    lp: np.ndarray
    aux: Any = None


class MoveStep(NamedTuple):
    """Outcome of one MH step: new walkers, acceptance per particle, evaluations (particles).

    ``alternative`` marks particles that used a move's second kind of proposal (left out of the
    scale adaptation); ``metric_ok`` the share of particles whose metric was usable (manifold move).
    """

    walkers: Walkers
    accepted: np.ndarray
    n_evaluations: int
    alternative: Optional[np.ndarray] = None
    metric_ok: Optional[float] = None


class Tuning(NamedTuple):
    """Step sizes carried from stage to stage: random-walk scale and manifold step size ε."""

    scale: float
    epsilon: float


class StageSetup(NamedTuple):
    """What a move may use to prepare a stage (fixed during the stage).

    Attributes
    ----------
    walkers : Walkers
        The resampled population (``aux`` None), in the move's coordinates.
    sigma, chol : ndarray (d, d)
        Weighted population covariance at the new β (in those coordinates) and its Cholesky factor.
    beta : float
        Tempering exponent of the stage.
    box : ndarray (d, 2) or None
        Support of the coordinates: proposals outside are rejected without evaluation.
    evaluate : callable
        u (m, d) → (log-likelihood (m,), log prior density of u (m,)).
    bounds : ndarray (d, 2)
        The prior box.
    log_likelihood, gradient_fim : callable, callable or None
        The user's functions of θ (box coordinates), for moves that need derivatives.
    ancestors : ndarray (n,)
        Index of each particle's ancestor before resampling.
    """

    walkers: Walkers
    sigma: np.ndarray
    chol: np.ndarray
    beta: float
    box: Optional[np.ndarray]
    evaluate: Callable
    bounds: np.ndarray
    log_likelihood: Callable
    gradient_fim: Optional[Callable]
    ancestors: np.ndarray


@runtime_checkable
class Move(Protocol):
    """A TMCMC move (see the module docstring).

    Attributes
    ----------
    name : str
    box_coordinates : bool
        The move works in the prior box (ignores ``transform`` and any bijection).
    unbounded : bool
        The move's steps are unbounded: it needs sampling coordinates onto all of R^d.
    adapts : {"scale", "epsilon"}
        Which :class:`Tuning` entry the move adapts (the stage info reports ε only for "epsilon").
    """

    name: str
    box_coordinates: bool
    unbounded: bool
    adapts: str

    def prepare(self, setup: StageSetup) -> tuple[Any, Walkers]: ...

    def step(self, kernel: Any, walkers: Walkers, beta: float, tuning: Tuning,
             rng: np.random.Generator) -> MoveStep: ...

    def adapt(self, tuning: Tuning, step: MoveStep, target_acceptance: float) -> Tuning: ...

    def fingerprint(self) -> dict[str, Any]:
        """Settings that change the random stream (stored in checkpoint fingerprints; must name the move)."""
        ...


def adapt_scale(tuning: Tuning, step: MoveStep, target_acceptance: float) -> Tuning:
    """Multiplicative adaptation of the random-walk scale toward the target acceptance."""
    acc = step.accepted if step.alternative is None else step.accepted[~step.alternative]
    if not len(acc):
        return tuning
    factor = math.exp(0.5 * (float(acc.mean()) - target_acceptance) / max(target_acceptance, 0.1))
    return tuning._replace(scale=float(np.clip(tuning.scale * factor, 1e-4, 10.0)))


def metropolis(walkers: Walkers, prop: np.ndarray, log_u: np.ndarray, beta: float, evaluate: Callable,
               box: Optional[np.ndarray], log_q_ratio: Optional[np.ndarray] = None) -> tuple[Walkers, np.ndarray, int]:
    """Accept/reject ``prop`` for every particle (outside ``box``: rejected without evaluation).

    ``log_q_ratio`` = log q(x | x′) − log q(x′ | x) of an asymmetric proposal.  A particle at
    −inf (β = 0 draws) accepts any finite proposal.  Returns (walkers, accepted, evaluations).
    """
    x, ll, lp = walkers.x, walkers.ll, walkers.lp
    n = len(x)
    inside = in_box(prop, box) if box is not None else None
    if inside is None or inside.all():
        ll_prop, lp_prop = evaluate(prop)
        n_eval = n
        ok_prop = np.isfinite(ll_prop)
    else:
        ll_prop, lp_prop = np.full(n, -np.inf), np.zeros(n)
        ll_prop[inside], lp_prop[inside] = evaluate(prop[inside])
        n_eval = int(inside.sum())
        ok_prop = inside & np.isfinite(ll_prop)
    with np.errstate(invalid="ignore"):
        log_ratio = beta * (ll_prop - ll) + (lp_prop - lp)
        if log_q_ratio is not None:
            log_ratio = log_ratio + log_q_ratio
    accept = ok_prop & ((log_ratio >= log_u) | ~np.isfinite(ll))
    new = Walkers(np.where(accept[:, None], prop, x), np.where(accept, ll_prop, ll),
                  np.where(accept, lp_prop, lp), walkers.aux)
    return new, accept, n_eval


# ----------------------------------------------------------------------------------------
# random walk
# ----------------------------------------------------------------------------------------
@dataclass(frozen=True)
class RandomWalk:
    """Gaussian random walk u′ = u + scale·L z with L Lᵀ the weighted population covariance."""

    name = "rw"
    box_coordinates = False
    unbounded = False
    adapts = "scale"

    def prepare(self, setup: StageSetup) -> tuple[Any, Walkers]:
        return setup, setup.walkers

    def step(self, kernel: StageSetup, walkers: Walkers, beta: float, tuning: Tuning,
             rng: np.random.Generator) -> MoveStep:
        n, d = walkers.x.shape
        prop = walkers.x + tuning.scale * (rng.standard_normal((n, d)) @ kernel.chol.T)
        log_u = np.log(rng.random(n))
        new, accept, n_eval = metropolis(walkers, prop, log_u, beta, kernel.evaluate, kernel.box)
        return MoveStep(new, accept, n_eval)

    def adapt(self, tuning: Tuning, step: MoveStep, target_acceptance: float) -> Tuning:
        return adapt_scale(tuning, step, target_acceptance)

    def fingerprint(self) -> dict[str, Any]:
        # the field names and defaults of the 33-field TMCMCConfig (checkpoints of 287c749 resume)
        return {"kernel": "rw", "ridge": 0.1, "target_acceptance_manifold": 0.57}


# ----------------------------------------------------------------------------------------
# locally adapted random walk
# ----------------------------------------------------------------------------------------
@dataclass(frozen=True)
class LocalWalk(RandomWalk):
    """Random walk with the covariance of the nearest stage-start neighbourhood.

    Parameters
    ----------
    neighbours : int
        Neighbours whose covariance a point uses (at least d + 1 are used).
    ridge : float
        Multiple of the global covariance added to every neighbourhood covariance; must stay well
        below the squared ratio of the thinnest local to the global width (1e-2 hid the muscle
        benchmark's thin direction entirely; 1e-4 did not).

    On the muscle benchmark it cut the whitened Fisher information of the thin direction from
    ~7600 to ~30–60 but decorrelated the early, broad stages worse than the global walk.  Needs
    sampling coordinates onto all of R^d (its steps are unbounded).
    """

    neighbours: int = 30
    ridge: float = 0.01

    name = "local"
    unbounded = True

    def __post_init__(self) -> None:
        if int(self.neighbours) < 2:
            raise HbmError(f"tmcmc: local_neighbours must be >= 2, got {self.neighbours}")
        if not self.ridge > 0:
            raise HbmError(f"tmcmc: local_ridge must be > 0, got {self.ridge}")

    def prepare(self, setup: StageSetup) -> tuple[Any, Walkers]:
        metric = fit_local_metric(setup.walkers.x, setup.sigma, int(self.neighbours), float(self.ridge))
        return (setup, metric), setup.walkers._replace(aux=nearest_reference(metric, setup.walkers.x))

    def step(self, kernel: tuple[StageSetup, LocalMetric], walkers: Walkers, beta: float, tuning: Tuning,
             rng: np.random.Generator) -> MoveStep:
        setup, metric = kernel
        x, ll, lp, near, acc, ne = local_step(walkers.x, walkers.ll, walkers.lp, walkers.aux, beta, tuning.scale,
                                              setup.evaluate, rng, metric)
        return MoveStep(Walkers(x, ll, lp, near), acc, ne)

    def fingerprint(self) -> dict[str, Any]:
        return {**super().fingerprint(), "proposal": "local", "local_neighbours": self.neighbours,
                "local_ridge": self.ridge}


# ----------------------------------------------------------------------------------------
# simplified manifold MALA
# ----------------------------------------------------------------------------------------
def _manifold_parts(grad, fim, beta, ridge_prec, eps):
    """Mean shift, Cholesky of G and validity for mMALA with G = β·F + ridge (per particle)."""
    g = beta * fim + ridge_prec[None, :, :]
    chol, ok = batched_cholesky(g)
    ok &= np.all(np.isfinite(grad), axis=1)
    # G⁻¹ ∇(βL) via two triangular solves (batched through np.linalg.solve on the factor)
    bgrad = np.where(ok[:, None], beta * grad, 0.0)
    y = np.linalg.solve(chol, bgrad[:, :, None])
    drift = np.linalg.solve(np.swapaxes(chol, 1, 2), y)[:, :, 0]
    logdet_g = 2.0 * np.sum(np.log(np.abs(np.diagonal(chol, axis1=1, axis2=2))), axis=1)
    return 0.5 * eps * drift, chol, logdet_g, ok


def _manifold_logq(dest, src, shift, chol, logdet_g, eps):
    """log N(dest; src + shift, ε·G⁻¹) up to the shared −d/2·log 2π, with G = L Lᵀ."""
    r = dest - src - shift
    z = np.einsum("nji,nj->ni", chol, r)  # Lᵀ r
    d = dest.shape[1]
    return -0.5 * np.sum(z * z, axis=1) / eps + 0.5 * logdet_g - 0.5 * d * math.log(eps)


def _rw_logq(dest, src, chol_rw, scale, logdet_rw):
    """log N(dest; src, scale²Σ) up to −d/2·log 2π (needed when forward/reverse kinds differ)."""
    r = (dest - src) / scale
    z = np.linalg.solve(chol_rw, r.T).T
    d = dest.shape[1]
    return -0.5 * np.sum(z * z, axis=1) - 0.5 * logdet_rw - d * math.log(scale)


@dataclass(frozen=True)
class Manifold:
    """Simplified manifold MALA (Girolami & Calderhead 2011) with G = β·F + ridge·Σ⁻¹, in box coordinates.

    Parameters
    ----------
    ridge : float
        Regulariser: Σ the weighted population covariance (keeps G invertible along
        non-identifiable directions).
    target_acceptance : float
        Acceptance rate the step size ε is adapted to (≈ 0.57 is MALA's optimum).

    Particles whose metric fails use the random walk; the reverse density of each proposal uses
    whichever proposal the rule would pick at θ′, so the MH ratio stays exact.
    """

    ridge: float = 0.1
    target_acceptance: float = 0.57

    name = "manifold"
    box_coordinates = True
    unbounded = False
    adapts = "epsilon"
    #: the move needs ``gradient_fim`` (:func:`needs_gradient`)
    needs_gradient = True

    def prepare(self, setup: StageSetup) -> tuple[Any, Walkers]:
        if setup.gradient_fim is None:
            raise HbmError("tmcmc: move='manifold' needs gradient_fim")
        g0, f0 = setup.gradient_fim(setup.walkers.x)
        aux = (np.asarray(g0, dtype=float).copy(), np.asarray(f0, dtype=float).copy())
        ridge_prec = self.ridge * np.linalg.inv(setup.sigma)
        return (setup, 0.5 * (ridge_prec + ridge_prec.T)), setup.walkers._replace(aux=aux)

    def step(self, kernel, walkers: Walkers, beta: float, tuning: Tuning, rng: np.random.Generator) -> MoveStep:
        setup, ridge_prec = kernel
        x, ll, (grad, fim) = walkers.x, walkers.ll, walkers.aux
        eps, scale, chol_rw = tuning.epsilon, tuning.scale, setup.chol
        n, d = x.shape
        shift, chol, logdet, ok = _manifold_parts(grad, fim, beta, ridge_prec, eps)
        z = rng.standard_normal((n, d))
        # manifold draw: θ + shift + sqrt(ε)·L⁻ᵀ z  (covariance ε·G⁻¹)
        step_m = shift + math.sqrt(eps) * np.linalg.solve(np.swapaxes(chol, 1, 2), z[:, :, None])[:, :, 0]
        step_rw = scale * (z @ chol_rw.T)
        prop = x + np.where(ok[:, None], step_m, step_rw)
        log_u = np.log(rng.random(n))
        inside = in_box(prop, setup.bounds)
        ll_p = np.full(n, -np.inf)
        grad_p = np.zeros((n, d))
        fim_p = np.zeros((n, d, d))
        if inside.any():
            ll_p[inside] = log_likelihood_of(setup.log_likelihood, prop[inside])
            gi, fi = setup.gradient_fim(prop[inside])
            grad_p[inside] = np.asarray(gi, dtype=float)
            fim_p[inside] = np.asarray(fi, dtype=float)
        finite = inside & np.isfinite(ll_p)
        logdet_rw = 2.0 * np.sum(np.log(np.diag(chol_rw)))
        lq_fwd = np.where(ok, _manifold_logq(prop, x, shift, chol, logdet, eps),
                          _rw_logq(prop, x, chol_rw, scale, logdet_rw))
        # reverse densities with the metric at θ'
        fim_safe = np.where(finite[:, None, None], fim_p, 0.0)
        grad_safe = np.where(finite[:, None], grad_p, np.nan)  # invalid where not finite → RW rule
        shift_p, chol_p, logdet_p, ok_p = _manifold_parts(grad_safe, fim_safe, beta, ridge_prec, eps)
        lq_rev = np.where(ok_p, _manifold_logq(x, prop, shift_p, chol_p, logdet_p, eps),
                          _rw_logq(x, prop, chol_rw, scale, logdet_rw))
        with np.errstate(invalid="ignore"):
            log_ratio = beta * (ll_p - ll) + lq_rev - lq_fwd
        accept = finite & ((log_ratio >= log_u) | ~np.isfinite(ll))
        new = Walkers(np.where(accept[:, None], prop, x), np.where(accept, ll_p, ll), walkers.lp,
                      (np.where(accept[:, None], grad_p, grad), np.where(accept[:, None, None], fim_p, fim)))
        return MoveStep(new, accept, int(inside.sum()), metric_ok=float(np.mean(ok)))

    def adapt(self, tuning: Tuning, step: MoveStep, target_acceptance: float) -> Tuning:
        ta = self.target_acceptance  # the move's own target (MALA's), not the random walk's
        a = float(step.accepted.mean())
        return tuning._replace(epsilon=float(np.clip(tuning.epsilon * math.exp((a - ta) / max(ta, 0.1)), 1e-8, 1e3)))

    def fingerprint(self) -> dict[str, Any]:
        return {"kernel": "manifold", "ridge": self.ridge, "target_acceptance_manifold": self.target_acceptance}


# ----------------------------------------------------------------------------------------
# registry
# ----------------------------------------------------------------------------------------
#: move name -> factory of the move with its default settings
MOVES: dict[str, Callable[[], Move]] = {"rw": RandomWalk, "manifold": Manifold, "local": LocalWalk}


def register_move(name: str, factory: Callable[[], Move]) -> None:
    """Make ``factory()`` selectable as ``tmcmc(move=name)``.

    Parameters
    ----------
    name : str
        Registry key (an existing key is replaced).
    factory : callable
        No-argument callable returning a :class:`Move` (e.g. the move's class).
    """
    MOVES[str(name)] = factory


def get_move(move: "str | Move") -> Move:
    """The move named ``move`` in :data:`MOVES`, or ``move`` itself if it is a :class:`Move`."""
    if isinstance(move, str):
        if move not in MOVES:
            raise HbmError(f"tmcmc: unknown move {move!r}; choose from {sorted(MOVES)}")
        return MOVES[move]()
    if not isinstance(move, Move):
        raise HbmError("tmcmc: move must be a registered name or an object with name, box_coordinates, "
                       "unbounded, adapts, prepare, step, adapt and fingerprint")
    return move


def needs_gradient(move: "str | Move") -> bool:
    """Whether ``move`` (a name of :data:`MOVES` or a :class:`Move`) needs the log-likelihood's
    gradient and Fisher information (``gradient_fim``; a move says so by ``needs_gradient = True``)."""
    return bool(getattr(get_move(move), "needs_gradient", False))
