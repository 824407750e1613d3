"""Transitional MCMC (Ching & Chen 2007) with log-evidence and resumable runs: the pure core and the driver.

The sampler is split blackjax-style into a pure core and a driver:

* :func:`init` draws the stage-0 population from the uniform prior on a box and evaluates it;
* :func:`step` performs one tempering stage (choose the next β by a bracketed root find on the
  coefficient of variation of the incremental weights, accumulate the log-evidence per island,
  resample each island from its own particles -- at β = 1 too, so the islands end as independent
  chains (:mod:`.chains`) unless their evidences disagree --, move the population with a
  vectorised Metropolis–Hastings :class:`~.moves.Move`) and
  returns ``(state, info)`` with ``info`` a :class:`~.types.StageInfo`;
* :func:`tmcmc` loops over stages with a tqdm progress bar and an atomic checkpoint after every
  stage (:mod:`.checkpoint`), and returns a :class:`~.types.TMCMCResult`.

The concepts have their own modules: settings, state and result in :mod:`.types`, the moves
(random walk, manifold, local walk; a registry) in :mod:`.moves`, the sampling coordinates in
:mod:`.coordinates`, resampling in :mod:`.resampling`, checkpoints in :mod:`.checkpoint`.

Every random number comes from a numpy ``Generator`` whose ``bit_generator.state`` is part of the
:class:`~.types.TMCMCState`, so a run resumed from a checkpoint is bitwise identical to an
uninterrupted one.  The log-likelihood is always called with a whole ``(m, d)`` population and
must return ``(m,)``; NaN is treated as −inf.  Proposals that leave the prior box are rejected
without evaluation.
"""

from __future__ import annotations

import dataclasses
import math
import os
import sys
import time
import warnings
from pathlib import Path
from typing import Any, Optional

import numpy as np
from scipy.optimize import brentq
from scipy.special import logsumexp

from ..errors import HbmError
from .chains import ISLAND_NOTE, Chains, block_chains
from .checkpoint import checkpoint_progress, fingerprint, load_checkpoint, save_checkpoint
from .coordinates import Bijection, BoxCoordinates, LogitCoordinates, check_bounds, log_likelihood_of
from .linalg import box_covariance, free_covariance, safe_cholesky
from .moves import Manifold, Move, StageSetup, Tuning, Walkers
from .resampling import islands, resample, resample_islands
from .types import (
    DEFAULT_COV_TARGET, DEFAULT_N_SAMPLES, GradientFIM, LogLikelihood, StageInfo, TMCMCConfig, TMCMCResult,
    TMCMCState)

__all__ = ["init", "step", "tmcmc", "PRESETS", "checkpoint_progress", "DEFAULT_N_SAMPLES", "DEFAULT_COV_TARGET",
           "TMCMCConfig", "TMCMCState", "StageInfo", "TMCMCResult", "Bijection", "LogitCoordinates"]

#: Named settings for :func:`tmcmc` (``preset=``); explicit arguments override them.
#: "lean": the default random walk at N = 1500 and CoV target 1.5 — on the muscle benchmark half
#: the default's evaluations (1.25e6 vs 2.43e6) for the same share of runs reaching |log Ẑ error| ≤ 0.3
#: and worst posterior-mean error ≤ 0.3 gold sd (3/5 each, SE covering the error 5/5), but one seed
#: in five put a posterior mean 1.1 gold sd off (results/benchmarks/evaluations_to_accuracy.md).
PRESETS: dict[str, dict[str, Any]] = {
    "default": {},
    "lean": {"n_samples": 1500, "cov_target": 1.5},
}


# ----------------------------------------------------------------------------------------
# small numerical helpers
# ----------------------------------------------------------------------------------------
def _rng_from_state(rng_state: dict) -> np.random.Generator:
    bg = np.random.PCG64()
    bg.state = rng_state
    return np.random.Generator(bg)


def _cov_of_weights(dbeta: float, ll: np.ndarray, ll_max: float) -> float:
    """Coefficient of variation of w = exp(dβ·(L − max L)) (zero weight where L = −inf)."""
    w = np.exp(dbeta * (ll - ll_max))
    m = w.mean()
    return float(w.std() / m)


def _next_beta(ll: np.ndarray, beta: float, cov_target: float, min_dbeta: float,
               force_final: bool) -> tuple[float, bool]:
    """β increment with CoV(w) = cov_target by brentq on [min_dbeta, 1 − β]; jump to 1 if allowed."""
    remaining = 1.0 - beta
    if force_final:
        return remaining, True
    finite = np.isfinite(ll)
    ll_max = float(ll[finite].max())
    f = lambda db: _cov_of_weights(db, ll, ll_max) - cov_target  # noqa: E731
    if f(remaining) <= 0.0:
        return remaining, False
    lo = min(min_dbeta, remaining)
    if f(lo) >= 0.0:
        return lo, False
    db = brentq(f, lo, remaining, xtol=1e-14 + 1e-10 * lo, rtol=1e-10, maxiter=200)
    return float(db), False


def _log_mean_exp(a: np.ndarray) -> float:
    return float(logsumexp(a) - math.log(len(a)))


class _Decorrelation:
    """Largest |correlation| over coordinates between the stage-start and the current positions."""

    def __init__(self, start: np.ndarray):
        a = start - start.mean(axis=0)
        a = a - a.mean(axis=0)
        norm = np.sqrt(np.einsum("ij,ij->j", a, a))
        self.a = a / np.where(norm > 0, norm, 1.0)

    def __call__(self, x: np.ndarray) -> float:
        b = x - x.mean(axis=0)
        num = np.einsum("ij,ij->j", self.a, b)
        den = np.sqrt(np.einsum("ij,ij->j", b, b))
        r = np.where(den > 0, num / np.where(den > 0, den, 1.0), 0.0)
        return float(np.max(np.abs(r)))


def _check_bijection(bijection: Optional[Bijection], move: Move, d: int) -> None:
    """Reject a bijection the move cannot use (checked once per stage: cheap)."""
    if bijection is None:
        return
    if not isinstance(bijection, Bijection):
        raise HbmError("tmcmc: bijection needs name, support, forward(theta) and inverse(u)")
    if move.box_coordinates:
        raise HbmError(f"tmcmc: a bijection needs a move in sampling coordinates such as move='rw' "
                       f"(move {move.name!r} works in box coordinates)")
    sup = np.asarray(bijection.support, float)
    if sup.shape != (d, 2) or np.any(sup[:, 0] >= sup[:, 1]):
        raise HbmError(f"tmcmc: bijection support must be a (d, 2) box with lo < hi, got shape {sup.shape}")
    if move.unbounded and np.isfinite(sup).any():
        raise HbmError(f"tmcmc: move {move.name!r} needs a bijection onto all of R^d (its steps are unbounded)")


def _coordinates(config: TMCMCConfig, bounds: np.ndarray, bijection: Optional[Bijection]) -> Bijection:
    """Sampling coordinates of the stage: the move's box, the caller's bijection, or the transform."""
    if config.move.box_coordinates or (bijection is None and config.transform == "none"):
        return BoxCoordinates(bounds)
    return bijection if bijection is not None else LogitCoordinates(bounds)


def _final_chains(island_log_evidence, log_evidence_var, n: int) -> Chains:
    """Keep the islands as chains at β = 1? (:func:`~.chains.block_chains` on the islands' log Ẑ_k).

    The noise of one island's log Ẑ_k is the per-stage delta method with N/K particles:
    sd = √(K · Σ_j CoV_j²/N).
    """
    k = len(island_log_evidence)
    return block_chains(island_log_evidence, math.sqrt(k * max(float(log_evidence_var), 0.0)), n,
                        "tmcmc_islands", ISLAND_NOTE)


def _stage_indices(logw, island_prev, beta, rng, scheme, keep_islands: bool = False) -> np.ndarray:
    """Resampling indices: per island, or pooled (each island weighted by its evidence) at the end.

    At β = 1 the islands are resampled separately when ``keep_islands`` (they become the chains).
    """
    n, k = len(logw), len(island_prev)
    if k == 1:
        return resample(np.exp(logw - logw.max()), n, rng, scheme)
    starts, sizes, isl = islands(n, k)
    m_k = np.maximum.reduceat(logw, starts)
    if (beta >= 1.0 and not keep_islands) or not np.isfinite(m_k).all():
        # final stage when the islands are not kept (their evidences disagree), or a dead island: pool
        # the islands, each weighted by its evidence so far; after this they are no longer independent
        with np.errstate(invalid="ignore"):
            lw = np.where(np.isfinite(logw), island_prev[isl] - np.log(sizes)[isl] + logw, -np.inf)
        return resample(np.exp(lw - lw.max()), n, rng, scheme)
    return resample_islands(logw, m_k, starts, sizes, isl, rng, scheme)


# ----------------------------------------------------------------------------------------
# pure core
# ----------------------------------------------------------------------------------------
def init(log_likelihood: LogLikelihood, bounds, config: TMCMCConfig, seed) -> TMCMCState:
    """Stage-0 state: N draws from the uniform prior on ``bounds`` and their log-likelihoods.

    Parameters
    ----------
    log_likelihood : callable
        (n, d) → (n,) log-likelihood.
    bounds : array_like (d, 2)
        Prior box.
    config : TMCMCConfig
    seed : int, SeedSequence or None
        Seeds a PCG64 generator (its state travels in the returned state).

    Returns
    -------
    TMCMCState
    """
    bounds = check_bounds(bounds)
    config.validate()
    if isinstance(seed, np.random.Generator):
        raise HbmError("tmcmc: pass an int seed (the generator state is stored in checkpoints)")
    rng = np.random.Generator(np.random.PCG64(seed))
    n, d = int(config.n_samples), len(bounds)
    x = bounds[:, 0] + rng.random((n, d)) * (bounds[:, 1] - bounds[:, 0])
    ll = log_likelihood_of(log_likelihood, x)
    if not np.isfinite(ll).any():
        raise HbmError("tmcmc: the log-likelihood is -inf/NaN for every prior draw; "
                       "check the bounds and the likelihood")
    k = max(1, min(int(config.n_islands), n // 20))
    return TMCMCState(x, ll, np.zeros(k), 0.0, 0.0, 0.0, 0, float(config.proposal_scale), 1.0, n,
                      rng.bit_generator.state)


def step(state: TMCMCState, log_likelihood: LogLikelihood, bounds, config: TMCMCConfig,
         gradient_fim: Optional[GradientFIM] = None,
         bijection: Optional[Bijection] = None) -> tuple[TMCMCState, StageInfo]:
    """One TMCMC stage: next β, evidence increment, resampling, MH moves.

    Parameters
    ----------
    state : TMCMCState
        State after the previous stage (or :func:`init`); not modified.
    log_likelihood : callable
        (n, d) → (n,).
    bounds : array_like (d, 2)
    config : TMCMCConfig
    gradient_fim : callable, optional
        θ (n, d) → (∇ log L (n, d), Fisher information (n, d, d)); required for the manifold move.
    bijection : Bijection, optional
        Sampling coordinates of the move (instead of ``config.transform``); see
        :class:`~.coordinates.Bijection`.  None (default) leaves the run unchanged.

    Returns
    -------
    state : TMCMCState
    info : StageInfo
        Per-stage diagnostics.
    """
    bounds, move = check_bounds(bounds), config.move
    _check_bijection(bijection, move, len(bounds))
    if state.beta >= 1.0:
        raise HbmError("tmcmc: the run is already at beta = 1")
    rng = _rng_from_state(state.rng_state)
    x, ll = state.samples, state.log_likelihood
    n = len(x)

    # 1. next β from the CoV of the incremental weights (root find, min step, stage cap); below one
    # MH step's worth (n) of the evaluation budget no move is affordable: jump straight to β = 1
    force = state.stage + 1 >= int(config.max_stages)
    remaining = None if config.max_evaluations is None else int(config.max_evaluations) - int(state.n_evaluations)
    budget_hit = bool(state.budget_bound)
    if remaining is not None and remaining < n:
        force, budget_hit = True, True
    dbeta, capped = _next_beta(ll, state.beta, config.cov_target, config.min_dbeta, force)
    beta = 1.0 if state.beta + dbeta >= 1.0 - 1e-12 else state.beta + dbeta
    dbeta = beta - state.beta

    # 2. incremental weights; per-island evidence increments (their spread is the honest SE)
    with np.errstate(invalid="ignore"):
        logw = np.where(np.isfinite(ll), dbeta * ll, -np.inf)
    w = np.exp(logw - logw.max())
    cov = float((w / w.mean()).std())
    var_inc = cov * cov / n  # delta method for log mean w with iid particles
    starts, sizes, isl = islands(n, len(state.island_log_evidence))
    m_k = np.maximum.reduceat(logw, starts)
    with np.errstate(invalid="ignore", divide="ignore"):
        s_k = np.add.reduceat(np.exp(logw - np.where(np.isfinite(m_k), m_k, 0.0)[isl]), starts)
        inc_k = np.where(np.isfinite(m_k), m_k + np.log(s_k), -np.inf) - np.log(sizes)
    island_new = state.island_log_evidence + inc_k
    log_z_new = _log_mean_exp(island_new)

    # 3. move to the sampling coordinates, covariance at the new β, resample, prepare the move
    coords = _coordinates(config, bounds, bijection)
    u = coords.forward(x)
    sigma = box_covariance(u, w, bounds) if isinstance(coords, BoxCoordinates) else free_covariance(u, w)
    chol = safe_cholesky(sigma)
    n_chains = 0
    if beta >= 1.0:  # the islands stay separate (chains) unless their evidences disagree
        keep = config.final_resampling == "islands" and \
            _final_chains(island_new, state.log_evidence_var + var_inc, n).n_chains > 1
        n_chains = len(island_new) if keep else 1
    idx = _stage_indices(logw, state.island_log_evidence, beta, rng, config.resampling, n_chains > 1)
    u, ll = u[idx], ll[idx]
    sup = np.asarray(coords.support, float)

    def evaluate(v):
        theta, lp_v = coords.inverse(v)
        return log_likelihood_of(log_likelihood, theta), lp_v

    setup = StageSetup(Walkers(u, ll, coords.inverse(u)[1]), sigma, chol, beta,
                       sup if np.isfinite(sup).any() else None, evaluate, bounds, log_likelihood, gradient_fim, idx)
    kernel, walkers = move.prepare(setup)

    # 4. Metropolis–Hastings steps until decorrelated from the stage start (or a cap)
    tuning = Tuning(float(state.scale), float(state.epsilon))
    fixed = config.n_steps is not None
    max_steps = int(config.n_steps) if fixed else int(config.max_steps)
    min_steps = int(config.n_steps) if fixed else int(config.min_steps)
    decorrelation = _Decorrelation(u)
    n_eval, acc_total, n_done, mix, mix_at = 0, 0.0, 0, 1.0, -1
    oks = []
    for k in range(max_steps):
        if remaining is not None and n_eval + n > remaining:
            budget_hit = True  # the next step could exceed the budget: stop moving here
            break
        res = move.step(kernel, walkers, beta, tuning, rng)
        walkers = res.walkers
        n_eval += res.n_evaluations
        acc_total += float(res.accepted.mean())
        n_done += 1
        if res.metric_ok is not None:
            oks.append(res.metric_ok)
        if config.adapt_scale:
            tuning = move.adapt(tuning, res, config.target_acceptance)
        if not fixed and k + 1 >= min_steps:
            mix, mix_at = decorrelation(walkers.x), n_done
            if mix <= config.mixing_target:
                break
    if mix_at != n_done:
        mix = decorrelation(walkers.x)

    new = TMCMCState(coords.inverse(walkers.x)[0], walkers.ll, island_new, beta, log_z_new,
                     state.log_evidence_var + var_inc, state.stage + 1, tuning.scale, tuning.epsilon,
                     state.n_evaluations + n_eval, rng.bit_generator.state, budget_hit, n_chains)
    info = StageInfo(
        beta=float(beta), dbeta=float(dbeta), log_evidence_increment=float(log_z_new - state.log_evidence),
        log_evidence_increment_var=float(var_inc), cov_weights=float(cov), ess=float(n / (1.0 + cov * cov)),
        acceptance_rate=acc_total / max(n_done, 1),
        proposal_scale=tuning.scale,
        epsilon=tuning.epsilon if move.adapts == "epsilon" else float("nan"), n_steps=n_done,
        evaluations=int(n_eval), mixing=float(mix), metric_ok=float(np.mean(oks)) if oks else float("nan"),
        capped=bool(capped))
    return new, info


def _evidence_se(state: TMCMCState) -> float:
    """Within-run SE of the pooled log-evidence.

    With K ≥ 4 islands (independently resampled blocks sharing β and proposal shape):
    Var(log mean Ẑ_k) ≈ var_k(Ẑ_k / mean Ẑ)/K, which includes the error due to incomplete
    mixing, floored by the per-stage delta method Σ CoV_j²/N (the iid part, valid for
    well-mixed populations); with fewer islands the delta method alone.
    """
    z = np.asarray(state.island_log_evidence, dtype=float)
    var_delta = max(float(state.log_evidence_var), 0.0)
    if len(z) >= 4 and np.isfinite(z).any():
        r = np.exp(z - z.max())
        r = r / r.mean()
        # with few islands the spread estimate is itself noisy (K − 1 dof); the iid delta-method
        # variance is a floor the true variance cannot go below, so an unlucky small spread
        # does not produce an overconfident SE
        return float(math.sqrt(max(np.var(r, ddof=1) / len(z), var_delta)))
    return float(math.sqrt(var_delta))


def _result_chains(state: TMCMCState, config: TMCMCConfig) -> Chains:
    """The chains of a finished run's population, as its last stage made them."""
    decision = _final_chains(state.island_log_evidence, state.log_evidence_var, len(state.samples))
    if state.n_chains > 1:
        return decision
    if decision.n_chains > 1:  # the rule would have kept them: pooled by setting or by an older hbm
        why = ("final_resampling='pooled'" if config.final_resampling == "pooled"
               else "the run was resumed from a finished checkpoint of an hbm that always pooled them")
        return Chains(1, "pooled", f"the islands were pooled at beta = 1 ({why}): one chain, no R-hat",
                      decision.spread, decision.tolerance)
    return decision


def _resolve_move(move: "str | Move | None", kernel: Optional[str], proposal: Optional[str]) -> "str | Move":
    """The move of the driver's arguments: ``move=``, or the older names ``kernel=`` / ``proposal=``
    (deprecated: they warn)."""
    for old, value in (("kernel", kernel), ("proposal", proposal)):
        if value is not None:
            warnings.warn(f"tmcmc({old}=...) is deprecated; use move=", DeprecationWarning, stacklevel=3)
    if kernel not in (None, "rw", "manifold"):
        raise HbmError(f"tmcmc: kernel must be 'rw' or 'manifold', got {kernel!r}")
    if proposal not in (None, "rw", "local"):
        raise HbmError(f"tmcmc: proposal must be 'rw' or 'local', got {proposal!r}")
    if move is not None:
        if kernel not in (None, "rw") or proposal not in (None, "rw"):
            raise HbmError("tmcmc: give either move= or kernel=/proposal=, not both")
        return move
    if kernel == "manifold" and proposal == "local":
        raise HbmError("tmcmc: proposal='local' needs kernel='rw'")
    return "manifold" if kernel == "manifold" else (proposal or "rw")


# ----------------------------------------------------------------------------------------
# driver
# ----------------------------------------------------------------------------------------
def tmcmc(log_likelihood: LogLikelihood, bounds, n_samples: Optional[int] = None, *, seed,
          move: "str | Move | None" = None, gradient_fim: Optional[GradientFIM] = None,
          cov_target: Optional[float] = None,
          proposal_scale: float = 0.2, n_steps: Optional[int] = None, max_stages: int = 100,
          checkpoint: Optional[str | os.PathLike] = None, progress: bool = True,
          max_evaluations: Optional[int] = None, preset: Optional[str] = None,
          bijection: Optional[Bijection] = None, kernel: Optional[str] = None, **options: Any) -> TMCMCResult:
    """Transitional MCMC from the uniform prior on ``bounds`` to the posterior, with log-evidence.

    Parameters
    ----------
    log_likelihood : callable
        θ (n, d) → log-likelihood (n,); NaN is treated as −inf.  Called with whole populations.
    bounds : array_like (d, 2)
        Uniform prior box.
    n_samples : int or None
        Population size N; None = the preset's, else :data:`~.types.DEFAULT_N_SAMPLES`.
    seed : int
        Seed of the PCG64 generator (required: runs are reproducible and resumable).
    move : str or Move, optional
        The MH move: a name of :data:`hbm.samplers.moves.MOVES` ("rw", the default: random walk with
        the population covariance and an adapted scale; "manifold": simplified mMALA; "local") or a
        :class:`~.moves.Move` object (e.g. ``Manifold(ridge=1e-3)``, ``LocalWalk(neighbours=15)``).
    gradient_fim : callable, optional
        θ (n, d) → (gradient (n, d), Fisher information (n, d, d)) of the log-likelihood;
        required for the manifold move.
    cov_target : float or None
        Target CoV of the incremental weights per stage (1 ⇔ ESS ≈ N/2); None = 1.0.
    proposal_scale : float
        Initial random-walk scale relative to the weighted population covariance.
    n_steps : int or None
        MH steps per stage; None = adaptive by the mixing diagnostic (see :class:`~.types.TMCMCConfig`).
    max_stages : int
        Stage cap (the last stage jumps to β = 1 and is flagged ``capped``).
    checkpoint : path, optional
        ``.npz`` file written atomically after every stage; if it exists, the run resumes from it
        (same settings required, else :class:`HbmError`).
    progress : bool
        tqdm progress bar on stderr.
    max_evaluations : int or None
        Hard cap on log-likelihood evaluations (rows passed to ``log_likelihood``), including the
        initial N; see :class:`~.types.TMCMCConfig`.  ``result.budget_exhausted`` says whether it
        bound the run.
    preset : str or None
        Named settings of :data:`PRESETS` ("default", "lean") used as defaults for the population
        size, ``cov_target`` and the options; explicit arguments override them.
    bijection : Bijection or None
        Sampling coordinates of the random walk replacing the logit transform (see
        :class:`~.coordinates.Bijection`; e.g. :class:`hbm.identifiability.combinations.CombinationCoordinates`
        for the muscle model).  None (default): the run is unchanged.
    **options
        Further :class:`~.types.TMCMCConfig` fields (transform, n_islands, min_steps, max_steps,
        mixing_target, target_acceptance, adapt_scale, resampling, min_dbeta).
    kernel : {"rw", "manifold"}, optional
        Deprecated name of ``move`` (as ``proposal="rw"|"local"`` in ``options``); warns.

    Returns
    -------
    TMCMCResult
    """
    t0 = time.perf_counter()
    if preset is not None:
        if preset not in PRESETS:
            raise HbmError(f"tmcmc: unknown preset {preset!r}; choose from {sorted(PRESETS)}")
        base = dict(PRESETS[preset])
        n_samples = base.pop("n_samples", None) if n_samples is None else n_samples
        cov_target = base.pop("cov_target", None) if cov_target is None else cov_target
        base.pop("n_samples", None), base.pop("cov_target", None)
        options = {**base, **options}
    n_samples = DEFAULT_N_SAMPLES if n_samples is None else n_samples
    move = _resolve_move(move, kernel, options.pop("proposal", None))
    if max_evaluations is not None:
        options["max_evaluations"] = int(max_evaluations)
    unknown = set(options) - {f.name for f in dataclasses.fields(TMCMCConfig)}
    if unknown:
        raise HbmError(f"tmcmc: unknown options {sorted(unknown)}")
    config = TMCMCConfig(n_samples=int(n_samples), move=move,
                         cov_target=None if cov_target is None else float(cov_target),
                         proposal_scale=float(proposal_scale), n_steps=None if n_steps is None else int(n_steps),
                         max_stages=int(max_stages), **options)
    config.validate()
    b = check_bounds(bounds)
    if isinstance(config.move, Manifold) and gradient_fim is None:
        raise HbmError("tmcmc: move='manifold' needs gradient_fim")
    if seed is None or isinstance(seed, np.random.Generator):
        raise HbmError("tmcmc: seed must be an int (reproducible, resumable runs)")
    _check_bijection(bijection, config.move, len(b))

    timer = [0.0]

    def timed(f):  # seconds inside the user's functions (likelihood_time)
        def call(x):
            t = time.perf_counter()
            try:
                return f(x)
            finally:
                timer[0] += time.perf_counter() - t
        return call

    ll_timed = timed(log_likelihood)
    gf_timed = None if gradient_fim is None else timed(gradient_fim)
    fp = fingerprint(config, b, seed, None if bijection is None else str(bijection.name))
    settings = {"n_samples": config.n_samples, "move": getattr(config.move, "name", str(config.move)),
                "seed": repr(seed), "d": len(b)}
    path = Path(checkpoint) if checkpoint is not None else None
    stages: list[StageInfo] = []
    resumed = 0
    if path is not None and path.exists():
        state, stages = load_checkpoint(path, fp)
        resumed = state.stage
        if state.samples.shape != (config.n_samples, len(b)):
            raise HbmError(f"tmcmc: checkpoint {path} holds a population of shape "
                           f"{state.samples.shape}, expected {(config.n_samples, len(b))}")
    else:
        state = init(ll_timed, b, config, seed)
        if path is not None:
            save_checkpoint(path, state, stages, fp, settings)

    bar = None
    if progress:
        from tqdm.auto import tqdm
        bar = tqdm(total=1000, file=sys.stderr, desc="tmcmc", unit="‰β", leave=False,
                   bar_format="{desc}: {percentage:3.0f}%|{bar}| {postfix}")
        bar.update(int(1000 * state.beta))
    try:
        while state.beta < 1.0:
            state, info = step(state, ll_timed, b, config, gf_timed, bijection)
            stages.append(info)
            if path is not None:
                save_checkpoint(path, state, stages, fp, settings)
            if bar is not None:
                bar.update(int(1000 * state.beta) - bar.n)
                bar.set_postfix_str(f"stage {state.stage} β={state.beta:.3g} "
                                    f"logZ={state.log_evidence:.2f} acc={info.acceptance_rate:.2f} "
                                    f"steps={info.n_steps}")
    finally:
        if bar is not None:
            bar.close()
    return TMCMCResult(
        samples=state.samples, log_likelihood=state.log_likelihood, log_evidence=float(state.log_evidence),
        log_evidence_se=_evidence_se(state), stages=stages, n_evaluations=int(state.n_evaluations),
        wall_time=time.perf_counter() - t0, likelihood_time=timer[0], config=config,
        resumed_from_stage=resumed, budget_exhausted=bool(state.budget_bound), chains=_result_chains(state, config))
