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
from typing import Any, Callable, Mapping, Protocol, Sequence

import numpy as np

from ...errors import HbmError
from ..linalg import safe_cholesky  # jittered Cholesky: a degenerate ensemble still gives a proposal
from .convergence import rhat_ess
from .mixture import fit_mixture, pick
from .model import HierarchicalModel, draw_population

__all__ = ["ConditionalBlock", "ExactSpecimen", "ReuseSpecimen", "JointGibbsResult", "joint_gibbs", "rhat_ess"]

#: random-walk step multipliers (equal probability) of the specimen moves: a symmetric scale mixture
_SCALES = np.array([0.3, 1.0, 3.0])
_TARGET_ACCEPT = 0.25


class ConditionalBlock(Protocol):
    """Columns of an exact specimen's ``y`` whose conditional log-likelihood is cheap once prepared.

    Attributes
    ----------
    columns : sequence of int
        The block's columns of ``y``.
    """

    columns: Sequence[int]

    def prepare(self, y: np.ndarray) -> Any:
        """Per-chain state for rows ``y`` (n, dy): one model evaluation per row (counted as such).  It
        may depend on the non-block columns of ``y`` only (the proposal given it must not depend on
        the block's current values, or the independence moves would not be exact)."""

    def log_likelihood(self, prep: Any, y: np.ndarray, rows: np.ndarray) -> np.ndarray:
        """The specimen's exact ``log_likelihood`` at rows ``y`` (m, dy) that differ from the prepared
        chains ``rows`` (m,) in the block columns only; −inf off the support."""

    def propose(self, prep: Any, rng: np.random.Generator, population: Mapping[int, tuple]) -> np.ndarray | None:
        """Independence proposal of the block columns (n, len(columns)) for every chain, or None (no
        proposal).  ``population``: block position -> (mu, sd) per chain of the pooled columns (the
        population given the chains' ψ, in ``y`` units)."""

    def log_q(self, prep: Any, yb: np.ndarray, population: Mapping[int, tuple]) -> np.ndarray:
        """log density of :meth:`propose` at block values ``yb`` (n, len(columns)) (NaN/−inf: never proposed)."""

    def select(self, prep: Any, other: Any, mask: np.ndarray) -> Any:
        """The per-chain state of ``other`` where ``mask`` (n,), of ``prep`` elsewhere."""


@dataclass
class ExactSpecimen:
    """A specimen sampled with its real likelihood.

    Attributes
    ----------
    log_likelihood : callable y (n, dy) -> (n,)
        Log-likelihood plus log stage-1 prior density in the ``y`` coordinates (up to a constant);
        −inf where the stage-1 prior has no mass.  Called once per move with all chains' proposals.
    columns : callable y (n, dy) -> (columns (n, len(model.all_names)), log_prior (n,) or None)
        The model's columns of ``y`` and the log stage-1 prior density of their pooled columns
        (None: the model's uniform box), as :meth:`HierarchicalModel.features` takes them.
    box : array (dy, 2)
        Box of ``y`` (proposals outside it are rejected).
    init : array (n_chains, dy)
        Starting points (finite target).
    scale_rows : array (m, dy)
        Rows whose covariance starts the random walk (e.g. the stage-1 samples in ``y``).
    pooled_cols : mapping y column -> pooled index, optional
        Columns of ``y`` that *are* a pooled column with the identity transform: the non-centred
        population moves shift and scale them with (mu_k, sd_k).
    block : ConditionalBlock, optional
        Columns whose conditional likelihood is cheap once prepared (module docstring).
    """

    log_likelihood: Callable[[np.ndarray], np.ndarray]
    columns: Callable[[np.ndarray], tuple]
    box: np.ndarray
    init: np.ndarray
    scale_rows: np.ndarray
    pooled_cols: Mapping[int, int] | None = None
    block: ConditionalBlock | None = None


@dataclass
class ReuseSpecimen:
    """A specimen represented by its stage-1 samples (empirical posterior).

    Attributes
    ----------
    rows : array (N, len(model.all_names))
        Stage-1 samples in the model's columns.
    log_prior : array (N,) or None
        Log stage-1 prior density of their pooled columns (None: the model's uniform box).
    init : array (n_chains,) of int
        Starting row of every chain.
    """

    rows: np.ndarray
    log_prior: np.ndarray | None
    init: np.ndarray


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


def _log_r(coef: np.ndarray, cc: np.ndarray, F: np.ndarray, c: np.ndarray) -> np.ndarray:
    """log r row by row: chain k's ψ (coef_k, cc_k) at chain k's columns (F_k, c_k)."""
    return np.einsum("ij,ij->i", coef, F) + cc + c


class _Exact:
    """Lock-step state of one exact specimen over all chains.

    Four moves per cycle (each exact MH for the conditional of the specimen given ψ): an
    independence proposal from a Gaussian mixture fitted to ``scale_rows`` (k-means clusters with
    their own covariances: it follows the thin curved ridges that the posteriors of several
    parameters form, where a random walk needs tiny steps -- on the gold a step of 0.2 global sd
    across the ridge of log (1−c)·T1 and T2 costs 65 nats), the same mixture conditioned on one
    coordinate k (kept: the rest jumps also where k lies in a tail the rows do not cover), a random
    walk of that coordinate alone, and a random walk of all coordinates (ensemble covariance).
    """

    def __init__(self, spec: ExactSpecimen, model: HierarchicalModel, n_chains: int, name: str,
                 rng: np.random.Generator, n_components: int, inflate: float) -> None:
        self.spec, self.model, self.name = spec, model, name
        self.box = np.asarray(spec.box, float)
        self.y = np.array(spec.init, float)
        if self.y.shape != (n_chains, self.box.shape[0]):
            raise HbmError(f"joint_gibbs: init of {name!r} must have shape ({n_chains}, {self.box.shape[0]}), "
                           f"got {self.y.shape}")
        self.dy = self.y.shape[1]
        self.pooled_cols = {int(j): int(k) for j, k in dict(spec.pooled_cols or {}).items()
                            if model.kinds[int(k)] == "identity"}
        self.evals = 0
        self.ll, self.F, self.c = self.evaluate(self.y)
        if not np.all(np.isfinite(self.ll + self.c)):
            raise HbmError(f"joint_gibbs: a starting point of {name!r} has no finite target")
        rows = np.asarray(spec.scale_rows, float)
        self.L = safe_cholesky(np.cov(rows, rowvar=False).reshape(self.dy, self.dy))
        self.log_step = np.log(2.38 / np.sqrt(self.dy))
        self.coord_step = np.log(2.38 * np.sqrt(np.diag(self.L @ self.L.T)))
        self.mix = fit_mixture(rows, int(n_components), float(inflate), rng)
        self.cond = {}  # coordinate k -> per-component (beta, Cholesky of the conditional covariance)
        self.block = spec.block
        self.prep = None  # the block's per-chain state, valid between block_prepare and block_release
        if self.block is not None:
            self.block_cols = np.asarray(self.block.columns, int)
            self.block_step = np.log(2.38 / np.sqrt(self.block_cols.size))
            # pooled identity columns in the block: block position -> pooled index
            self.block_pooled = {int(np.nonzero(self.block_cols == j)[0][0]): k
                                 for j, k in self.pooled_cols.items() if j in self.block_cols}
            self.other_cols = np.array([j for j in range(self.dy) if j not in self.block_cols], int)
            self.refresh_step = np.log(2.38 / np.sqrt(max(self.other_cols.size, 1)))
            if self.other_cols.size:  # the mixture's marginal over the other columns (refresh proposals)
                logw, mu, L, _ = self.mix
                o = self.other_cols
                Lo = np.stack([safe_cholesky((Lm @ Lm.T)[np.ix_(o, o)]) for Lm in L])
                self.mix_other = (logw, mu[:, o], Lo, np.sum(np.log(np.diagonal(Lo, axis1=1, axis2=2)), axis=1))

    def _log_q(self, y: np.ndarray, mix=None) -> np.ndarray:
        """log density of the Gaussian-mixture proposal (default ``self.mix``) at ``y``."""
        logw, mu, L, logdet = self.mix if mix is None else mix
        terms = np.empty((y.shape[0], logw.size))
        for m in range(logw.size):  # few components; vectorised over chains
            a = np.linalg.solve(L[m], (y - mu[m]).T)
            terms[:, m] = logw[m] - 0.5 * np.sum(a * a, axis=0) - logdet[m]
        mx = terms.max(axis=1)
        return mx + np.log(np.exp(terms - mx[:, None]).sum(axis=1)) - 0.5 * y.shape[1] * np.log(2 * np.pi)

    def _conditional(self, k: int):
        if k not in self.cond:
            _, _, L, _ = self.mix
            K = L @ np.swapaxes(L, 1, 2)
            o = np.array([j for j in range(self.dy) if j != k])
            beta = K[:, o, k] / K[:, k, k][:, None]
            Lc = np.stack([safe_cholesky(K[m][np.ix_(o, o)] - np.outer(beta[m], K[m, k, o])) for m in range(K.shape[0])])
            self.cond[k] = (o, beta, Lc, K[:, k, k])
        return self.cond[k]

    def evaluate(self, y: np.ndarray, cheap: bool = False, prep: Any = None):
        """(ℓ, F, const) of rows ``y``; −inf ℓ outside the box, the support or the population's box.

        ``cheap``: ``y`` differs from the chains' states in the block columns only and ℓ comes from
        the prepared block (no model evaluation); ``prep``: a block state prepared at ``y``'s other
        columns instead of the chains'."""
        n = y.shape[0]
        ll = np.full(n, -np.inf)
        F = np.zeros((n, 2 * self.model.d + self.model.q))
        c = np.zeros(n)
        with np.errstate(invalid="ignore"):
            ok = np.all((y >= self.box[:, 0]) & (y <= self.box[:, 1]), axis=1)
        if ok.any():
            if cheap:
                ll[ok] = np.asarray(self.block.log_likelihood(self.prep if prep is None else prep, y[ok],
                                                              np.nonzero(ok)[0]), float)
            else:
                self.evals += int(ok.sum())
                ll[ok] = np.asarray(self.spec.log_likelihood(y[ok]), float)
            cols, lp = self.spec.columns(y[ok])
            cols = np.asarray(cols, float)
            pooled = cols[:, self.model.cols]
            fine = np.isfinite(ll[ok]) & np.all((pooled >= self.model.lo) & (pooled <= self.model.hi), axis=1)
            if lp is not None:
                lp = np.asarray(lp, float)
                fine &= np.isfinite(lp)
            idx = np.nonzero(ok)[0]
            ll[idx[~fine]] = -np.inf
            if fine.any():
                F[idx[fine]], c[idx[fine]] = self.model.features(cols[fine], None if lp is None else lp[fine])
        return ll, F, c

    def _mh(self, prop, coef, cc, rng, log_q_ratio=0.0, cheap: bool = False, prep: Any = None) -> np.ndarray:
        n = self.y.shape[0]
        ll, F, c = self.evaluate(prop, cheap, prep)
        with np.errstate(invalid="ignore"):
            new = np.where(np.isfinite(ll), ll + _log_r(coef, cc, F, c), -np.inf)
            old = self.ll + _log_r(coef, cc, self.F, self.c)
            acc = np.log(rng.random(n)) < new - old + log_q_ratio  # NaN (never proposed): rejected
        self.y[acc], self.ll[acc], self.F[acc], self.c[acc] = prop[acc], ll[acc], F[acc], c[acc]
        return acc

    def move(self, coef, cc, rng, k: int, nat: np.ndarray | None = None) -> dict:
        """One cycle of the moves of every chain (``k``: the coordinate kept / walked alone; ``nat``: the
        chains' natural hyper-parameters, for the population draw of a pooled column)."""
        n = self.y.shape[0]
        out = {}
        # a specimen with a block: its pooled block columns get their population draws in the block
        # rounds (no evaluation); the others' population draws were accepted < 2 % on the gold
        # benchmark, where the refresh moves do better for the same evaluation
        outside = sorted(self.pooled_cols.items()) if self.block is None else []
        if outside and nat is not None:
            # independence proposal of one pooled column from the population N(mu_k, sd_k): where the
            # likelihood is flat in it (a one-sided tail) the ratio is ~1 and the chain jumps anywhere
            j, kk = outside[k % len(outside)]
            mu, sd = nat[:, kk], nat[:, self.model.d + kk]
            prop = self.y.copy()
            prop[:, j] = mu + sd * rng.standard_normal(n)
            lq = 0.5 * (((prop[:, j] - mu) / sd) ** 2 - ((self.y[:, j] - mu) / sd) ** 2)
            out["population_draw"] = self._mh(prop, coef, cc, rng, lq)
        if self.block is not None:
            # with a block, the joint jumps and walks of the other columns are the refresh moves (the
            # block redrawn, far higher acceptance); one coordinate walk of a non-block column stays
            if self.other_cols.size:
                k = int(self.other_cols[k % self.other_cols.size])
                out[f"coord{k}"] = self._coord_walk(coef, cc, rng, k)
            return out
        logw, mu, L, _ = self.mix
        # independence proposal from the mixture
        m = pick(np.broadcast_to(logw, (n, logw.size)), rng)
        prop = mu[m] + np.einsum("nab,nb->na", L[m], rng.standard_normal((n, self.dy)))
        with np.errstate(invalid="ignore"):
            out["mixture"] = self._mh(prop, coef, cc, rng, self._log_q(self.y) - self._log_q(prop))
        # the mixture conditioned on coordinate k (kept): components weighted by their density at y_k,
        # the rest from the component's Gaussian given y_k; the MH ratio needs only the joint q
        if self.dy > 1:
            out["mixture_given_one"] = self._given_one(coef, cc, rng, k)
        out[f"coord{k}"] = self._coord_walk(coef, cc, rng, k)
        scale = np.exp(self.log_step) * _SCALES[rng.integers(0, _SCALES.size, n)]
        out["rw"] = self._mh(self.y + scale[:, None] * (rng.standard_normal((n, self.dy)) @ self.L.T), coef, cc, rng)
        return out

    def _coord_walk(self, coef, cc, rng, k: int) -> np.ndarray:
        """Random walk of coordinate k alone (scale mixture); returns the accepted mask."""
        n = self.y.shape[0]
        prop = self.y.copy()
        prop[:, k] += np.exp(self.coord_step[k]) * _SCALES[rng.integers(0, _SCALES.size, n)] * rng.standard_normal(n)
        return self._mh(prop, coef, cc, rng)

    def _given_one(self, coef, cc, rng, k: int) -> np.ndarray:
        """Proposal from the mixture conditioned on coordinate k (kept); returns the accepted mask."""
        n = self.y.shape[0]
        logw, mu, _, _ = self.mix
        o, beta, Lc, vk = self._conditional(k)
        dk = self.y[:, k][:, None] - mu[None, :, k]
        m = pick(logw[None, :] - 0.5 * dk * dk / vk[None, :] - 0.5 * np.log(vk)[None, :], rng)
        prop = self.y.copy()
        prop[:, o] = (mu[m][:, o] + beta[m] * dk[np.arange(n), m][:, None]
                      + np.einsum("nab,nb->na", Lc[m], rng.standard_normal((n, o.size))))
        with np.errstate(invalid="ignore"):
            return self._mh(prop, coef, cc, rng, self._log_q(self.y) - self._log_q(prop))

    # -- the conditional block ------------------------------------------------------------------
    def block_prepare(self) -> None:
        """Prepare the block at the chains' states (one evaluation per chain) and check that its
        likelihood is the specimen's there."""
        self.prep = self.block.prepare(self.y)
        self.evals += self.y.shape[0]
        ll = np.asarray(self.block.log_likelihood(self.prep, self.y, np.arange(self.y.shape[0])), float)
        if not np.allclose(ll, self.ll, rtol=1e-8, atol=1e-6):
            bad = int(np.argmax(np.abs(ll - self.ll)))
            raise HbmError(f"joint_gibbs: the conditional block of {self.name!r} gives log-likelihood {ll[bad]:.9g} "
                           f"where the specimen's is {self.ll[bad]:.9g}; the block is not this likelihood")

    def block_moves(self, coef, cc, rng, nat: np.ndarray) -> dict:
        """One round of cheap moves of the block columns: the block's independence proposal (with the
        population of its pooled columns at the chains' ψ) and a random walk (ensemble covariance)."""
        n, cols, out = self.y.shape[0], self.block_cols, {}
        pop = {p: (nat[:, kk], nat[:, self.model.d + kk]) for p, kk in self.block_pooled.items()}
        yb = self.block.propose(self.prep, rng, pop)
        if yb is not None:
            prop = self.y.copy()
            prop[:, cols] = yb
            with np.errstate(invalid="ignore", divide="ignore"):
                lq = self.block.log_q(self.prep, self.y[:, cols], pop) - self.block.log_q(self.prep, yb, pop)
            out["block_independence"] = self._mh(prop, coef, cc, rng, lq, cheap=True)
        K = self.L @ self.L.T
        Lb = safe_cholesky(K[np.ix_(cols, cols)])
        scale = np.exp(self.block_step) * _SCALES[rng.integers(0, _SCALES.size, n)]
        prop = self.y.copy()
        prop[:, cols] += scale[:, None] * (rng.standard_normal((n, cols.size)) @ Lb.T)
        out["block_rw"] = self._mh(prop, coef, cc, rng, cheap=True)
        return out

    def block_refresh(self, coef, cc, rng, nat: np.ndarray, independent: bool = False) -> np.ndarray:
        """Move the other columns with the block redrawn from its proposal there.

        Proposes y'_other -- a random walk step, or (``independent``) a draw from the Gaussian
        mixture's marginal over the other columns (a jump between modes of the nonlinear
        parameters) -- prepares the block at y' (one evaluation per chain) and draws y'_block from
        its proposal q(·|y'_other); the MH ratio carries q(y_block|y_other) / q(y'_block|y'_other)
        (and the mixture's densities), so the move follows the other columns' marginal as the
        block's proposal approximates its conditional -- the ridge between the nonlinear
        parameters and the amplitudes no longer limits the step.  Returns the accepted mask.
        """
        n, cols, other = self.y.shape[0], self.block_cols, self.other_cols
        pop = {p: (nat[:, kk], nat[:, self.model.d + kk]) for p, kk in self.block_pooled.items()}
        prop = self.y.copy()
        lq_other = 0.0
        if independent:
            logw, mu, Lo, _ = self.mix_other
            m = pick(np.broadcast_to(logw, (n, logw.size)), rng)
            prop[:, other] = mu[m] + np.einsum("nab,nb->na", Lo[m], rng.standard_normal((n, other.size)))
            lq_other = self._log_q(self.y[:, other], self.mix_other) - self._log_q(prop[:, other], self.mix_other)
        else:
            K = self.L @ self.L.T
            Lo = safe_cholesky(K[np.ix_(other, other)])
            scale = np.exp(self.refresh_step) * _SCALES[rng.integers(0, _SCALES.size, n)]
            prop[:, other] += scale[:, None] * (rng.standard_normal((n, other.size)) @ Lo.T)
        inside = np.all((prop >= self.box[:, 0]) & (prop <= self.box[:, 1]), axis=1)
        prop[~inside] = self.y[~inside]  # rejected below; the block is prepared at valid rows only
        new = self.block.prepare(prop)
        self.evals += n  # the basis is evaluated at every row (those outside the box are rejected)
        yb = self.block.propose(new, rng, pop)
        prop[:, cols] = yb
        with np.errstate(invalid="ignore", divide="ignore"):
            lq = self.block.log_q(self.prep, self.y[:, cols], pop) - self.block.log_q(new, yb, pop)
        lq = np.where(inside, lq + lq_other, -np.inf)
        acc = self._mh(prop, coef, cc, rng, lq, cheap=True, prep=new)
        self.prep = self.block.select(self.prep, new, acc)
        return acc

    def block_release(self) -> None:
        self.prep = None

    def adapt(self, rates: dict) -> None:
        """Burn-in only: covariance from the ensemble of chains, step scales toward the target acceptance."""
        if self.y.shape[0] > 2 * self.dy:
            self.L = safe_cholesky(np.cov(self.y, rowvar=False).reshape(self.dy, self.dy))
        if "rw" in rates:
            self.log_step += float(np.clip(rates["rw"] - _TARGET_ACCEPT, -0.2, 0.2)) * 2.0
        if "block_rw" in rates:
            self.block_step += float(np.clip(rates["block_rw"] - _TARGET_ACCEPT, -0.2, 0.2)) * 2.0
        if "block_refresh" in rates:
            self.refresh_step += float(np.clip(rates["block_refresh"] - _TARGET_ACCEPT, -0.2, 0.2)) * 2.0
        for k in range(self.dy):
            if f"coord{k}" in rates:
                self.coord_step[k] += float(np.clip(rates[f"coord{k}"] - 0.35, -0.2, 0.2)) * 2.0

    def terms(self):
        return self.F, self.c


class _Reuse:
    """Lock-step state of one reuse specimen: a row index per chain."""

    def __init__(self, spec: ReuseSpecimen, model: HierarchicalModel, n_chains: int, name: str) -> None:
        self.name = name
        rows = np.asarray(spec.rows, float)
        self.Fall, self.call = model.features(rows, spec.log_prior)
        self.idx = np.asarray(spec.init, int).copy()
        if self.idx.shape != (n_chains,) or self.idx.min() < 0 or self.idx.max() >= rows.shape[0]:
            raise HbmError(f"joint_gibbs: init of {name!r} must be {n_chains} row indices of its samples")
        self.evals = 0

    def move(self, coef, cc, rng, k: int = 0, nat: np.ndarray | None = None) -> dict:
        n = self.idx.shape[0]
        prop = rng.integers(0, self.Fall.shape[0], n)
        new = _log_r(coef, cc, self.Fall[prop], self.call[prop])
        old = _log_r(coef, cc, self.Fall[self.idx], self.call[self.idx])
        acc = np.log(rng.random(n)) < new - old
        self.idx[acc] = prop[acc]
        return {"reuse": acc}

    def adapt(self, rates: dict) -> None:
        pass

    def terms(self):
        return self.Fall[self.idx], self.call[self.idx]


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
            tot = tot + _log_r(coefp, ccp, F, c)
            continue
        y = st.y.copy()
        y[:, cols[0]] = mup + (sdp / sd) * (st.y[:, cols[0]] - mu)
        ll, F, c = st.evaluate(np.where(inside[:, None], y, st.y), cheap)
        with np.errstate(invalid="ignore"):
            tot = tot + np.where(np.isfinite(ll), ll + _log_r(coefp, ccp, F, c), -np.inf) - st.ll
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
        tot = tot + _log_r(coef, cc, F, c)
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
        ``_Exact``) and reuse-specimen moves per sweep.
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
        Moves per sweep of the other columns with the block redrawn (``_Exact.block_refresh``; one
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
        states[sid] = (_Exact(s, model, n_chains, sid, rng, int(n_components), float(inflate)) if isinstance(s, ExactSpecimen)
                       else _Reuse(s, model, n_chains, sid))

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
    nc_ks = sorted({k for st in states.values() if isinstance(st, _Exact) for k in st.pooled_cols.values()
                    if k in model.free and d + k in model.free})
    exact_states = [st for st in states.values() if isinstance(st, _Exact)]
    blocked = [st for st in exact_states if st.block is not None] if block_rounds > 0 else []
    # pooled columns that every exact specimen has in its block: their non-centred moves are cheap
    nc_cheap = [k for k in nc_ks if blocked and len(blocked) == len(exact_states)
                and all(k in st.block_pooled.values() for st in blocked)]
    nc_full = [k for k in nc_ks if k not in nc_cheap]
    nc_scale = {k: np.array([raw[:, k].std(), raw[:, d + k].std()]) + 1e-12 for k in nc_ks}
    nc_step, nc_count = 0.0, 0
    acc_nc, win_nc = np.zeros(2), np.zeros(2)
    kept_raw = np.empty((n_chains, n_keep, raw.shape[1]))
    kept = {sid: (np.empty((n_chains, n_keep, st.dy)) if isinstance(st, _Exact) else np.empty((n_chains, n_keep), int))
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
            for step in range(spec_steps if isinstance(st, _Exact) else reuse_steps):
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
            pop_step += float(np.clip(win_pop[0] / max(win_pop[1], 1) - _TARGET_ACCEPT, -0.2, 0.2)) * 2.0
            if win_nc[1]:
                nc_step += float(np.clip(win_nc[0] / win_nc[1] - _TARGET_ACCEPT, -0.2, 0.2)) * 2.0
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
                kept[sid][:, k] = st.y if isinstance(st, _Exact) else st.idx
    t1 = time.perf_counter()
    rhat, ess = {}, {}
    for j, i in enumerate(free):
        rhat[f"hyper:{model.hyper_names[i]}"], ess[f"hyper:{model.hyper_names[i]}"] = rhat_ess(kept_raw[:, :, i])
    for sid, st in states.items():
        if isinstance(st, _Exact):
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
        evaluations={sid: int(st.evals) for sid, st in states.items() if isinstance(st, _Exact)},
        timings={"sampling": t1 - t0, "diagnostics": t2 - t1, "total": t2 - t0},
        options={"n_chains": int(n_chains), "n_keep": int(n_keep), "n_burn": int(n_burn), "thin": int(thin),
                 "pop_steps": int(pop_steps), "nc_steps": int(nc_steps), "spec_steps": int(spec_steps), "reuse_steps": int(reuse_steps),
                 "block_rounds": int(block_rounds) if blocked else 0, "block_refresh": int(block_refresh) if blocked else 0,
                 "blocks": [st.name for st in blocked],
                 "exact": [s for s, st in states.items() if isinstance(st, _Exact)],
                 "reuse": [s for s, st in states.items() if isinstance(st, _Reuse)]},
    )
