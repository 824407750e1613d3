"""Exact fallback of the hierarchical layer: Metropolis-within-Gibbs on the joint posterior (issue 15).

Target
------
The joint posterior of the population ψ and the specimens' parameters,

    p(ψ, y_1..y_n | data) ∝ p(ψ) Π_i exp(ℓ_i(y_i)) · r(x(y_i), ψ),

with exactly the definition of :mod:`hbm.samplers.hierarchical`: ``r(x, ψ) = p(x|ψ)/p0(x)``
of the pooled columns ``x`` (:meth:`HierarchicalModel.features` and
:meth:`HierarchicalModel.coefficients`: ``log r = coef(ψ)·F(x) + cconst(ψ) + const(x)``), p(ψ)
the model's hyperprior on its sampler box.  Two kinds of specimen (chosen per specimen by the
caller):

* :class:`ExactSpecimen` -- real likelihood.  ``y`` is any coordinate system the caller picks,
  ``ℓ(y)`` its log-likelihood plus the log stage-1 prior density in those coordinates (up to a
  constant; −inf outside the support), ``columns(y)`` the model's columns and the log stage-1
  prior density of the pooled ones that ``r`` divides by.  Moves: random walk in ``y`` (a scale
  mixture 0.3/1/3 × 2.38/√d of the covariance: heavier tails reach flat one-sided tails), the
  covariance and scale adapted during burn-in from the ensemble of chains, then frozen.
* :class:`ReuseSpecimen` -- the empirical stage-1 posterior (sample reuse).  The state is a row
  index; independence proposals drawn uniformly from the rows, accepted with the ratio of
  ``r``: exact for the target "empirical stage-1 posterior × r", i.e. the reuse layer's own
  approximation of that specimen, at no likelihood cost.

Conditional blocks (issue 27): an exact specimen may carry a ``block`` -- columns of ``y`` whose
log-likelihood, with the other columns fixed, the caller evaluates without the model once a
per-chain ``prepare`` pass has run (a model whose stress is linear in some amplitudes: one
basis evaluation, then any amplitudes at the cost of a matrix product).  After the other moves,
every sweep prepares each block once and then runs ``block_rounds`` cheap rounds: an
independence proposal of the caller (:class:`ConditionalBlock`), a random walk within the block,
population moves and a non-centred move of a pooled column that every exact specimen has in
its block; ``block_refresh`` times per sweep a random walk of the other columns redraws the
block from its proposal there (one evaluation: the ridge between the block and the rest no
longer limits the step).  Each is an exact MH step for the joint target (the block's log-likelihood *is* the
likelihood there), so the chains mix along the block -- where the slow direction of the exact
fallback lies, an amplitude whose likelihood is flat on one side -- at one evaluation per sweep.

Population moves: random-walk Metropolis on the model's free sampler coordinates (mu, log sd
[, CPC]) given all specimens' columns, several per sweep (cheap: one ``coefficients`` call and a
row-wise dot product per specimen).  Plus non-centred moves against the funnel between (mu_k,
sd_k) and the specimens' values of a pooled column k whose likelihood is flat (a one-sided
tail): (mu_k, sd_k) random walk with every exact specimen's column moved along,
y' = mu' + (sd'/sd)(y − mu), Jacobian (sd'/sd)^(number moved); one likelihood batch per exact
specimen.  Every likelihood call evaluates all chains' proposals of
one specimen in one batch; there is no per-chain Python loop.

All chains run in lock-step from caller-given starting points (e.g. the reuse layer's hyper
draws and reweighted individuals, near stationarity).  Convergence: rank-normalised split
R-hat and bulk ESS (Vehtari et al. 2021) over chains for every free hyper-parameter and every
``y`` column of the exact specimens.

This module is sampler-layer code: it knows nothing about muscles.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Callable, Mapping

import numpy as np

from ...errors import HbmError
from ..linalg import safe_cholesky  # jittered Cholesky: a degenerate ensemble still gives a proposal
from .chain_states import TARGET_ACCEPT, ConditionalBlock, ExactSpecimen, ExactState, ReuseSpecimen, ReuseState, log_r
from ..convergence import rhat_ess
from .model import HierarchicalModel, draw_population

__all__ = ["ConditionalBlock", "ExactSpecimen", "ReuseSpecimen", "JointGibbsResult", "joint_gibbs", "rhat_ess"]

@dataclass
class JointGibbsResult:
    """Output of :func:`joint_gibbs` (draws kept after burn-in, chain-major).

    Attributes
    ----------
    raw : ndarray (n_chains, n_keep, 2d+q)
        Hyper draws in the model's raw coordinates (``HierarchicalModel.natural`` gives mu, sd).
    states : dict specimen -> ndarray
        (n_chains, n_keep, dy) for exact specimens, (n_chains, n_keep) row indices for reuse ones.
    predictive : ndarray (n_chains * n_keep, d)
        A new specimen's pooled columns drawn from the population at the kept hyper draws.
    rhat, ess : dict name -> float
        Rank-normalised split R-hat and bulk ESS over chains: ``hyper:<name>`` for the free
        hyper-parameters, ``<specimen>:<column k>`` for the exact specimens' ``y`` columns.
    acceptance : dict
        Mean acceptance rate after burn-in: ``population`` and per specimen.
    evaluations : dict specimen -> int
        Rows passed to each exact specimen's ``log_likelihood`` (burn-in included).
    timings : dict
    options : dict
    """

    raw: np.ndarray
    states: dict
    predictive: np.ndarray
    rhat: dict
    ess: dict
    acceptance: dict
    evaluations: dict
    timings: dict
    options: dict = field(default_factory=dict)

    def flat_raw(self) -> np.ndarray:
        """Hyper draws (n_chains * n_keep, 2d+q), chain-major."""
        return self.raw.reshape(-1, self.raw.shape[-1])

    def flat_state(self, specimen: str) -> np.ndarray:
        """A specimen's kept states flattened over chains and draws."""
        s = self.states[specimen]
        return s.reshape((-1,) + s.shape[2:])


def _noncentred(model: HierarchicalModel, states: dict, raw: np.ndarray, lp: np.ndarray, k: int,
                scale: np.ndarray, rng: np.random.Generator, cheap: bool = False):
    """Non-centred move of pooled column k: (mu_k, raw sd_k) random walk, exact specimens' column along.

    ``cheap``: every exact specimen has column k in its prepared block (no model evaluation).
    Returns (accepted mask, proposed raw, its population log target, coef, cconst) or None.
    """
    n, d = raw.shape[0], model.d
    rawp = raw.copy()
    rawp[:, k] += scale[0] * rng.standard_normal(n)
    rawp[:, d + k] += scale[1] * rng.standard_normal(n)
    xb = model.box
    inside = np.all((rawp[:, model.free] >= xb[:, 0]) & (rawp[:, model.free] <= xb[:, 1]), axis=1)
    if not inside.any():
        return None
    rawp[~inside] = raw[~inside]
    nat, natp = model.natural(raw), model.natural(rawp)
    mu, sd, mup, sdp = nat[:, k], nat[:, d + k], natp[:, k], natp[:, d + k]
    coefp, ccp = model.coefficients(rawp)
    corr = model.log_hyperprior_correction(rawp)
    tot = corr - lp
    moved = []
    for st in states.values():
        cols = [j for j, kk in getattr(st, "pooled_cols", {}).items() if kk == k]
        if not cols:
            F, c = st.terms()
            tot = tot + log_r(coefp, ccp, F, c)
            continue
        y = st.y.copy()
        y[:, cols[0]] = mup + (sdp / sd) * (st.y[:, cols[0]] - mu)
        ll, F, c = st.evaluate(np.where(inside[:, None], y, st.y), cheap)
        with np.errstate(invalid="ignore"):
            tot = tot + np.where(np.isfinite(ll), ll + log_r(coefp, ccp, F, c), -np.inf) - st.ll
        tot = tot + np.log(sdp / sd)  # Jacobian of y -> y'
        moved.append((st, y, ll, F, c))
    acc = inside & (np.log(rng.random(n)) < tot)
    for st, y, ll, F, c in moved:
        st.y[acc], st.ll[acc], st.F[acc], st.c[acc] = y[acc], ll[acc], F[acc], c[acc]
    lpp = _population_terms(states, coefp, ccp, corr)  # population part of the target at the new states
    return acc, rawp, lpp, coefp, ccp


def _population_terms(states: dict, coef: np.ndarray, cc: np.ndarray, tot: np.ndarray) -> np.ndarray:
    """``tot`` + Σ_i log r(x_i, ψ) over the specimens' current states, chain by chain."""
    for st in states.values():
        F, c = st.terms()
        tot = tot + log_r(coef, cc, F, c)
    return tot


def _population_target(model: HierarchicalModel, states: dict, raw: np.ndarray, coef: np.ndarray,
                       cc: np.ndarray) -> np.ndarray:
    """log p(ψ) + Σ_i log r(x_i, ψ): the population part of the joint target (coef, cc those of ``raw``)."""
    return _population_terms(states, coef, cc, model.log_hyperprior_correction(raw))


def joint_gibbs(
    model: HierarchicalModel,
    init_raw: np.ndarray,
    specimens: Mapping[str, ExactSpecimen | ReuseSpecimen],
    *,
    n_keep: int = 40,
    n_burn: int = 400,
    thin: int = 5,
    pop_steps: int = 4,
    nc_steps: int = 2,
    spec_steps: int = 1,
    reuse_steps: int = 4,
    adapt_every: int = 20,
    n_components: int = 80,
    inflate: float = 1.15,
    block_rounds: int = 4,
    block_pop_steps: int = 2,
    block_refresh: int = 4,
    seed=None,
    progress: bool = False,
    log: Callable[[str], None] | None = None,
) -> JointGibbsResult:
    """Metropolis-within-Gibbs over (ψ, specimens), all chains vectorised (module docstring).

    Parameters
    ----------
    model : HierarchicalModel
        The population model (the definition of the reuse layer).
    init_raw : array (n_chains, 2d+q)
        Starting hyper draws in raw coordinates, one per chain (e.g. the layer's ``raw_samples``).
    specimens : mapping specimen -> ExactSpecimen or ReuseSpecimen
    n_keep, n_burn, thin : int
        Sweeps: ``n_burn`` adaptive burn-in sweeps, then ``n_keep × thin`` sweeps keeping every
        ``thin``-th state of every chain.
    pop_steps, nc_steps, spec_steps, reuse_steps : int
        Population moves, non-centred population moves, exact-specimen move cycles (four likelihood batches each, class
        ``ExactState``) and reuse-specimen moves per sweep.
    adapt_every : int
        Burn-in sweeps between two adaptations of the proposals.
    n_components, inflate : int, float
        Gaussian mixture proposal of the exact specimens: k-means clusters of ``scale_rows``, each
        with its own covariance × ``inflate``².
    block_rounds, block_pop_steps : int
        With conditional blocks (:class:`ConditionalBlock`): cheap rounds per sweep (each: every
        block's independence and random-walk moves, ``block_pop_steps`` population moves, a
        non-centred move of one pooled column that every exact specimen has in its block, in turn).
    block_refresh : int
        Moves per sweep of the other columns with the block redrawn (``ExactState.block_refresh``; one
        evaluation each), spread over the rounds.
    seed : int, SeedSequence or Generator
    progress : bool
        Progress lines through ``log``.
    log : callable, optional
        Receives progress lines.

    Returns
    -------
    JointGibbsResult
    """
    t0 = time.perf_counter()
    rng = seed if isinstance(seed, np.random.Generator) else np.random.default_rng(seed)
    raw = np.array(np.atleast_2d(init_raw), float)
    n_chains = raw.shape[0]
    if n_chains < 4 or raw.shape[1] != len(model.hyper_names):
        raise HbmError(f"joint_gibbs: init_raw must be (n_chains >= 4, {len(model.hyper_names)}), got {raw.shape}")
    if n_keep < 4 or n_burn < 0 or thin < 1:
        raise HbmError("joint_gibbs: need n_keep >= 4, n_burn >= 0, thin >= 1")
    free = np.asarray(model.free)
    box = model.box
    x = raw[:, free]
    if np.any((x < box[:, 0]) | (x > box[:, 1])):
        raise HbmError("joint_gibbs: init_raw outside the hyperprior box")
    names = list(specimens)
    states = {}
    for sid in names:
        s = specimens[sid]
        states[sid] = (ExactState(s, model, n_chains, sid, rng, int(n_components), float(inflate)) if isinstance(s, ExactSpecimen)
                       else ReuseState(s, model, n_chains, sid))

    def pop_logp(raw_: np.ndarray):
        coef, cc = model.coefficients(raw_)
        return _population_target(model, states, raw_, coef, cc), coef, cc

    lp, coef, cc = pop_logp(raw)
    if not np.all(np.isfinite(lp)):
        raise HbmError("joint_gibbs: the joint target is not finite at the starting points")
    Lpsi = safe_cholesky(np.cov(x, rowvar=False).reshape(len(free), len(free))) * (2.38 / np.sqrt(len(free)))
    pop_step = 0.0
    # non-centred moves: pooled columns k with free mu_k and sd_k that some exact specimen maps
    d = model.d
    nc_ks = sorted({k for st in states.values() if isinstance(st, ExactState) for k in st.pooled_cols.values()
                    if k in model.free and d + k in model.free})
    exact_states = [st for st in states.values() if isinstance(st, ExactState)]
    blocked = [st for st in exact_states if st.block is not None] if block_rounds > 0 else []
    # pooled columns that every exact specimen has in its block: their non-centred moves are cheap
    nc_cheap = [k for k in nc_ks if blocked and len(blocked) == len(exact_states)
                and all(k in st.block_pooled.values() for st in blocked)]
    nc_full = [k for k in nc_ks if k not in nc_cheap]
    nc_scale = {k: np.array([raw[:, k].std(), raw[:, d + k].std()]) + 1e-12 for k in nc_ks}
    nc_step, nc_count = 0.0, 0
    acc_nc, win_nc = np.zeros(2), np.zeros(2)
    kept_raw = np.empty((n_chains, n_keep, raw.shape[1]))
    kept = {sid: (np.empty((n_chains, n_keep, st.dy)) if isinstance(st, ExactState) else np.empty((n_chains, n_keep), int))
            for sid, st in states.items()}
    acc_pop = np.zeros(2)  # accepted, tried (after burn-in)
    acc_spec: dict = {sid: {} for sid in names}  # move -> [accepted, tried] after burn-in
    win_pop = np.zeros(2)
    win_spec: dict = {sid: {} for sid in names}
    n_total = n_burn + n_keep * thin

    def population_move(burning: bool) -> None:
        xp = x + np.exp(pop_step) * (rng.standard_normal(x.shape) @ Lpsi.T)
        inside = np.all((xp >= box[:, 0]) & (xp <= box[:, 1]), axis=1)
        xp = np.where(inside[:, None], xp, x)  # outside the box: rejected below
        rawp = raw.copy()
        rawp[:, free] = xp
        lpp, coefp, ccp = pop_logp(rawp)
        a = inside & (np.log(rng.random(n_chains)) < lpp - lp)
        x[a], raw[a], lp[a], coef[a], cc[a] = xp[a], rawp[a], lpp[a], coefp[a], ccp[a]
        (win_pop if burning else acc_pop)[:] += (a.sum(), n_chains)

    def noncentred_move(k: int, burning: bool, cheap: bool) -> None:
        a = _noncentred(model, states, raw, lp, k, np.exp(nc_step) * nc_scale[k], rng, cheap)
        if a is not None:
            acc, rawp, lpp, coefp, ccp = a
            raw[acc], lp[acc], coef[acc], cc[acc] = rawp[acc], lpp[acc], coefp[acc], ccp[acc]
            x[acc] = rawp[acc][:, free]
            (win_nc if burning else acc_nc)[:] += (acc.sum(), n_chains)

    def tally(sid: str, moves: dict, burning: bool) -> None:
        for move, a in moves.items():
            (win_spec if burning else acc_spec)[sid].setdefault(move, np.zeros(2))[:] += (a.sum(), n_chains)

    refresh_count = 0
    for sweep in range(n_total):
        burning = sweep < n_burn
        for _ in range(pop_steps):
            population_move(burning)
        for _ in range(nc_steps if nc_full else 0):
            noncentred_move(nc_full[nc_count % len(nc_full)], burning, False)
            nc_count += 1
        nat = model.natural(raw)
        for sid, st in states.items():
            for step in range(spec_steps if isinstance(st, ExactState) else reuse_steps):
                k = (sweep * spec_steps + step) % getattr(st, "dy", 1)
                tally(sid, st.move(coef, cc, rng, k, nat), burning)
        lp = _population_target(model, states, raw, coef, cc)  # the specimens moved, ψ did not
        if blocked:
            for st in blocked:
                st.block_prepare()
            for r_ in range(block_rounds):
                nat = model.natural(raw)
                due = (r_ * block_refresh) // block_rounds != ((r_ + 1) * block_refresh) // block_rounds
                for st in blocked:
                    if st.other_cols.size and due:  # alternately a walk and a mixture jump
                        jump = bool(refresh_count % 2)
                        tally(st.name, {"block_jump" if jump else "block_refresh":
                                        st.block_refresh(coef, cc, rng, nat, jump)}, burning)
                    tally(st.name, st.block_moves(coef, cc, rng, nat), burning)
                refresh_count += int(due)
                lp = _population_target(model, states, raw, coef, cc)
                for _ in range(block_pop_steps):
                    population_move(burning)
                if nc_cheap:  # one per round, cycling over the pooled block columns
                    noncentred_move(nc_cheap[nc_count % len(nc_cheap)], burning, True)
                    nc_count += 1
            for st in blocked:
                st.block_release()
        if burning and (sweep + 1) % adapt_every == 0:
            if n_chains > 2 * len(free):
                Lpsi = safe_cholesky(np.cov(x, rowvar=False).reshape(len(free), len(free))) * (2.38 / np.sqrt(len(free)))
            pop_step += float(np.clip(win_pop[0] / max(win_pop[1], 1) - TARGET_ACCEPT, -0.2, 0.2)) * 2.0
            if win_nc[1]:
                nc_step += float(np.clip(win_nc[0] / win_nc[1] - TARGET_ACCEPT, -0.2, 0.2)) * 2.0
            nc_scale = {k: np.array([raw[:, k].std(), raw[:, d + k].std()]) + 1e-12 for k in nc_ks}
            win_nc[:] = 0
            for sid, st in states.items():
                st.adapt({m: v[0] / max(v[1], 1) for m, v in win_spec[sid].items()})
                win_spec[sid] = {}
            win_pop[:] = 0
            if progress and log is not None:
                log(f"joint Gibbs burn-in {sweep + 1}/{n_burn}")
        if not burning and (sweep - n_burn + 1) % thin == 0:
            k = (sweep - n_burn + 1) // thin - 1
            kept_raw[:, k] = raw
            for sid, st in states.items():
                kept[sid][:, k] = st.y if isinstance(st, ExactState) else st.idx
    t1 = time.perf_counter()
    rhat, ess = {}, {}
    for j, i in enumerate(free):
        rhat[f"hyper:{model.hyper_names[i]}"], ess[f"hyper:{model.hyper_names[i]}"] = rhat_ess(kept_raw[:, :, i])
    for sid, st in states.items():
        if isinstance(st, ExactState):
            for k in range(st.dy):
                rhat[f"{sid}:{k}"], ess[f"{sid}:{k}"] = rhat_ess(kept[sid][:, :, k])
    flat = kept_raw.reshape(-1, raw.shape[1])
    predictive = draw_population(model, flat, flat.shape[0], rng)
    t2 = time.perf_counter()
    return JointGibbsResult(
        raw=kept_raw, states=kept, predictive=predictive, rhat=rhat, ess=ess,
        acceptance={"population": float(acc_pop[0] / max(acc_pop[1], 1)),
                    "non_centred": float(acc_nc[0] / max(acc_nc[1], 1)),
                    **{sid: {m: float(v[0] / max(v[1], 1)) for m, v in moves.items()}
                       for sid, moves in acc_spec.items()}},
        evaluations={sid: int(st.evals) for sid, st in states.items() if isinstance(st, ExactState)},
        timings={"sampling": t1 - t0, "diagnostics": t2 - t1, "total": t2 - t0},
        options={"n_chains": int(n_chains), "n_keep": int(n_keep), "n_burn": int(n_burn), "thin": int(thin),
                 "pop_steps": int(pop_steps), "nc_steps": int(nc_steps), "spec_steps": int(spec_steps), "reuse_steps": int(reuse_steps),
                 "block_rounds": int(block_rounds) if blocked else 0, "block_refresh": int(block_refresh) if blocked else 0,
                 "blocks": [st.name for st in blocked],
                 "exact": [s for s, st in states.items() if isinstance(st, ExactState)],
                 "reuse": [s for s, st in states.items() if isinstance(st, ReuseState)]},
    )
