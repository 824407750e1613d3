"""The lock-step states of the exact fallback's specimens (:mod:`.joint_gibbs`), one object per specimen.

* :class:`ExactSpecimen` / ``ExactState`` -- a specimen with its real likelihood: the moves of its
  ``y`` (Gaussian-mixture independence proposals, coordinate and joint random walks) and, with a
  :class:`ConditionalBlock`, the cheap block moves and the refresh moves of the other columns;
* :class:`ReuseSpecimen` / ``ReuseState`` -- a specimen represented by its stage-1 samples.

Every move is a Metropolis–Hastings step for the specimen's conditional given ψ, all chains in
one batch.  This module is sampler-layer code: it knows nothing about muscles.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Callable, Mapping, Protocol, Sequence

import numpy as np

from ...errors import HbmError
from ..linalg import safe_cholesky  # jittered Cholesky: a degenerate ensemble still gives a proposal
from ..mixtures import gaussian_mixture_logpdf, kmeans_mixture, pick
from .model import HierarchicalModel

__all__ = ["ConditionalBlock", "ExactSpecimen", "ReuseSpecimen", "ExactState", "ReuseState", "log_r", "TARGET_ACCEPT"]

#: random-walk step multipliers (equal probability) of the specimen moves: a symmetric scale mixture
_SCALES = np.array([0.3, 1.0, 3.0])
TARGET_ACCEPT = 0.25


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


def log_r(coef: np.ndarray, cc: np.ndarray, F: np.ndarray, c: np.ndarray) -> np.ndarray:
    """log r row by row: chain k's ψ (coef_k, cc_k) at chain k's columns (F_k, c_k)."""
    return np.einsum("ij,ij->i", coef, F) + cc + c


class ExactState:
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
        self.mix = kmeans_mixture(rows, int(n_components), float(inflate), rng)
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
        return gaussian_mixture_logpdf(y, self.mix if mix is None else mix)

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
            new = np.where(np.isfinite(ll), ll + log_r(coef, cc, F, c), -np.inf)
            old = self.ll + log_r(coef, cc, self.F, self.c)
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
            self.log_step += float(np.clip(rates["rw"] - TARGET_ACCEPT, -0.2, 0.2)) * 2.0
        if "block_rw" in rates:
            self.block_step += float(np.clip(rates["block_rw"] - TARGET_ACCEPT, -0.2, 0.2)) * 2.0
        if "block_refresh" in rates:
            self.refresh_step += float(np.clip(rates["block_refresh"] - TARGET_ACCEPT, -0.2, 0.2)) * 2.0
        for k in range(self.dy):
            if f"coord{k}" in rates:
                self.coord_step[k] += float(np.clip(rates[f"coord{k}"] - 0.35, -0.2, 0.2)) * 2.0

    def terms(self):
        return self.F, self.c


class ReuseState:
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
        new = log_r(coef, cc, self.Fall[prop], self.call[prop])
        old = log_r(coef, cc, self.Fall[self.idx], self.call[self.idx])
        acc = np.log(rng.random(n)) < new - old
        self.idx[acc] = prop[acc]
        return {"reuse": acc}

    def adapt(self, rates: dict) -> None:
        pass

    def terms(self):
        return self.Fall[self.idx], self.call[self.idx]
