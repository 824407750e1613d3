"""The population layer's sampler: Metropolis-within-Gibbs over the population and every specimen, batched.

Target
------
The joint posterior of the population ψ and the specimens' coordinates y_1..y_S,

    p(ψ, y_1..y_S | data) ∝ p(ψ) Π_s exp(ℓ_s(y_s)) · r(x(y_s), ψ_{g(s)}),

with ``r = p(x|ψ)/p0(x)`` of the pooled columns x exactly as the reuse layer defines it
(:meth:`HierarchicalModel.features` / :meth:`HierarchicalModel.coefficients`), ψ_{g} the population
of specimen s's group (one group for the two-level layer) given by :class:`HyperLevel`.

Sampling
--------
Given ψ the specimens are independent, and given its nonlinear parameters a specimen's amplitude
columns have a quadratic log-likelihood (:mod:`.amplitudes`).  One *round*:

1. the shards (:mod:`.shards`, a fixed partition of the specimens; in this process or as dask
   actors) run a sweep of their evaluated moves given ψ — one model evaluation per move per chain
   and specimen — and return each specimen's coordinates, log-likelihood, the quadratic form of its
   amplitudes and its pooled features;
2. here, without any model evaluation, all specimens and chains at once: ``pop_rounds`` times the
   amplitudes' independence move (:class:`~.amplitudes.AmplitudeProposal` with the population at the
   chain's ψ) and random walk, ``psi_steps`` random-walk moves of ψ (adapted covariance) and a
   non-centred move of each pooled amplitude column (its population's centre and spread moved with
   every specimen's value along, u' = mu' + (sd'/sd)(u − mu), Jacobian (sd'/sd)^S): the funnel between
   a population's spread and the one-sided amplitudes that the data bound from above only.

Every step is an exact Metropolis–Hastings step of the joint target.  The shard partition and all
random streams depend on the number of specimens only (:mod:`hbm.runtime.seeds`: the run's stream for ψ and
the amplitudes, one stream per specimen for its evaluated moves), so the draws are bitwise the same
in-process and on any number of workers.

Convergence: rank-normalised split R-hat and bulk ESS (:func:`.convergence.rhat_ess`) of every free
hyper-parameter and every specimen column over the chains.  With a ``converged`` rule the chains are checked
at the planned length and go on, half of it at a time, while the rule says no and a cap allows (the check
reads the kept draws alone: an extended run is the run planned at that length).

This module is sampler-layer code: it knows nothing about muscles.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Any, Callable, Sequence

import numpy as np

from ...errors import HbmError
from ..linalg import safe_cholesky
from .amplitudes import amplitudes_valid, conditional_draw, quadratic_loglik
from ..convergence import rhat_ess
from .model import HierarchicalModel
from .shards import TARGET_ACCEPT, RoundInput, ShardState, partial_map, partial_weights

__all__ = ["HyperLevel", "one_population", "ShardSpec", "BatchedResult", "PooledFeatures", "batched_gibbs"]


@dataclass
class HyperLevel:
    """The population above the specimens, in its sampler coordinates x.

    Attributes
    ----------
    model : HierarchicalModel
        The specimen-level population (transforms, features, coefficients).
    box : ndarray (nx, 2)
        Box of x (the hyperprior is uniform on it up to ``log_prior_correction``).
    names : list of str
        Names of the x coordinates.
    raws_of : callable x (n, nx) -> list of (n, 2d+q)
        Each group's population in the model's raw coordinates.
    log_prior_correction : callable x -> (n,)
    groups : ndarray of int (S,)
        Each specimen's group.
    nc_coords : callable pooled index -> list of int
        The x coordinates of a pooled column's population (moved by its non-centred move).
    """

    model: HierarchicalModel
    box: np.ndarray
    names: list
    raws_of: Callable
    log_prior_correction: Callable
    groups: np.ndarray
    nc_coords: Callable


def one_population(model: HierarchicalModel, n_specimens: int) -> HyperLevel:
    """The two-level layer: one population (the model's free hyper-parameters) over every specimen."""
    free = list(model.free)
    d = model.d

    def nc(k: int) -> list:
        return [free.index(i) for i in (k, d + k) if i in free]

    return HyperLevel(model=model, box=model.box, names=list(model.free_names), raws_of=lambda x: [model.expand(x)],
                      log_prior_correction=lambda x: model.log_hyperprior_correction(model.expand(x)),
                      groups=np.zeros(int(n_specimens), int), nc_coords=nc)


@dataclass
class ShardSpec:
    """What builds a shard (:class:`~.shards.ShardState`): its batch, the specimens' stage-1 rows in y,
    starting rows (B, C) and one seed sequence per specimen; ``index``: its specimens' positions."""

    batch: Any
    rows: list
    init: np.ndarray
    seeds: list
    index: np.ndarray


@dataclass
class BatchedResult:
    """Output of :func:`batched_gibbs` (kept draws, chain-major).

    Attributes
    ----------
    x : ndarray (n_chains, n_keep, nx)
        Hyper draws in the sampler coordinates.
    y : ndarray (n_chains, n_keep, S, dy)
        The specimens' coordinates.
    rhat, ess : dict
        ``hyper:<name>`` and ``<specimen index>:<column>`` -> rank-normalised split R-hat / bulk ESS.
    acceptance : dict
    evaluations : ndarray (S,)
        Model evaluations per specimen (every evaluated row, burn-in included).
    timings, options : dict
    """

    x: np.ndarray
    y: np.ndarray
    rhat: dict
    ess: dict
    acceptance: dict
    evaluations: np.ndarray
    timings: dict
    options: dict = field(default_factory=dict)


class _Shards:
    """The shards, in this process or as dask actors (one per shard): ``advance`` returns their outputs."""

    def __init__(self, specs: Sequence[ShardSpec], features, amp_pool, client=None, **kw) -> None:
        self.client = client
        if client is None:
            self.states = [ShardState(s.batch, features, s.rows, s.init, s.seeds, amp_pool, **kw) for s in specs]
        else:
            futs = [client.submit(ShardState, s.batch, features, s.rows, s.init, s.seeds, amp_pool, actor=True,
                                  pure=False, **kw) for s in specs]
            self.states = [f.result() for f in futs]

    def cpu(self) -> float:
        """The shards' CPU seconds (on the workers)."""
        if self.client is None:
            return sum(s.cpu() for s in self.states)
        return float(sum(f.result() for f in [s.cpu() for s in self.states]))

    def advance(self, inputs: Sequence[RoundInput]) -> list:
        if self.client is None:
            return [s.advance(i) for s, i in zip(self.states, inputs)]
        futs = [s.advance(i) for s, i in zip(self.states, inputs)]
        return [f.result() for f in futs]


class PooledFeatures:
    """The population model's features of the pooled columns of rows y (..., dy) (picklable).

    ``__call__``: (F, c) of :meth:`HierarchicalModel.features` (``log_prior``: the stage-1 prior's
    constant log density of the pooled columns, None for the model's box); :meth:`with_amplitudes`:
    F with the entries of identity-transformed pooled columns replaced (no other entry depends on
    them: a diagonal population); :meth:`partial`: the population's log ratio restricted to some
    pooled columns (their terms of coef·F and of c), for the parts of a move that do not change the others.
    """

    def __init__(self, model: HierarchicalModel, pool_y: Sequence[int], log_prior: float | None) -> None:
        self.model, self.pool_y, self.log_prior = model, np.asarray(pool_y, int), log_prior
        self.diagonal = model.m == 0

    def full(self, y: np.ndarray) -> np.ndarray:
        """Rows (n, len(model.all_names)) with the pooled columns of y (n, dy) in place (others 0)."""
        full = np.zeros((y.shape[0], len(self.model.all_names)))
        full[:, self.model.cols] = y[:, self.pool_y]
        return np.where(np.isfinite(full), full, 0.0)

    def __call__(self, y: np.ndarray):
        shape = y.shape[:-1]
        n = int(np.prod(shape))
        lp = None if self.log_prior is None else np.full(n, self.log_prior)
        with np.errstate(all="ignore"):
            F, c = self.model.features(self.full(y.reshape(n, -1)), lp)
        return F.reshape(shape + (-1,)), c.reshape(shape)

    def with_amplitudes(self, F: np.ndarray, u: np.ndarray, pooled: Sequence[int]) -> np.ndarray:
        """F with identity pooled columns ``pooled`` (pooled index per column of u, -1: none) set to u."""
        m, d = self.model, self.model.d
        F = F.copy()
        for j, kp in enumerate(pooled):
            if kp >= 0:
                zt = (u[..., j] - m.c[kp]) / m.s[kp]
                F[..., kp], F[..., d + kp] = zt, zt * zt
        return F

    def to_z(self, kp: int, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Transformed value of pooled column kp and log|dz/dx| (as :meth:`HierarchicalModel.to_z`)."""
        m = self.model
        kind, lo, hi = m.kinds[kp], m.lo[kp], m.hi[kp]
        with np.errstate(divide="ignore", invalid="ignore"):
            if kind == "identity":
                return x, np.zeros(np.shape(x))
            if kind == "log":
                x = np.maximum(x, lo)
                return np.log(x), -np.log(x)
            u = np.clip((x - lo) / (hi - lo), 1e-12, 1.0 - 1e-12)
            return np.log(u) - np.log1p(-u), -(np.log(u) + np.log1p(-u) + np.log(hi - lo))

    def from_z(self, kp: int, z: np.ndarray) -> np.ndarray:
        """The inverse of :meth:`to_z` (clipped to the column's box as :meth:`HierarchicalModel.from_z`)."""
        m = self.model
        kind, lo, hi = m.kinds[kp], m.lo[kp], m.hi[kp]
        if kind == "identity":
            return z
        with np.errstate(over="ignore"):
            x = np.exp(z) if kind == "log" else lo + (hi - lo) / (1.0 + np.exp(-z))
        return np.clip(x, lo, hi)

    def partial(self, y: np.ndarray, coef: np.ndarray, pooled: Sequence[int]) -> np.ndarray:
        """Σ over pooled columns ``pooled`` of their terms of coef·F + c (a diagonal population)."""
        m, d = self.model, self.model.d
        out = 0.0
        for kp in pooled:
            z, jac = self.to_z(kp, y[..., self.pool_y[kp]])
            zt = (z - m.c[kp]) / m.s[kp]
            out = out + coef[..., kp] * zt + coef[..., d + kp] * zt * zt + jac
        return out


class _Master:
    """ψ and the amplitudes of every specimen (S, C): the moves of step 2 (module docstring)."""

    def __init__(self, hyper: HyperLevel, x0: np.ndarray, features: PooledFeatures, valid, constraints, amp_cols,
                 amp_pool, box, seed, psi_steps: int, pop_rounds: int, n_particles: int = 16) -> None:
        self.h, self.m = hyper, hyper.model
        self.x = np.array(x0, float)
        self.features, self.valid, self.constraints = features, valid, constraints
        self.n_particles = int(n_particles)
        self.amp, self.amp_pool = np.asarray(amp_cols, int), np.asarray(amp_pool, int)
        self.k = self.amp.size
        self.lo, self.hi = box[self.amp, 0], box[self.amp, 1]
        # the amplitudes' features are updated in place when their columns are identity-transformed
        self.fast = features.diagonal and all(self.m.kinds[kp] == "identity" for kp in self.amp_pool if kp >= 0)
        ss = seed
        self.rng_psi, self.rng_amp, self.rng_nc = (np.random.default_rng(
            np.random.SeedSequence(ss.entropy, spawn_key=tuple(ss.spawn_key) + (j,))) for j in (1, 2, 3))
        self.psi_steps, self.pop_rounds = int(psi_steps), int(pop_rounds)
        # ψ's random walk starts from the chains' starting spread (adapted in burn-in)
        self.psi_L = np.diag(np.maximum(np.std(self.x, axis=0), 1e-3 * np.ptp(hyper.box, axis=1)))
        self.psi_step = 0.0
        self.nc_step = 0.0
        self.window = {"psi": np.zeros(2), "nc": np.zeros(2)}
        self.accepted: dict = {}
        self.history: list = []
        self.nc_cols = [(j, kp) for j, kp in enumerate(self.amp_pool) if kp >= 0 and len(hyper.nc_coords(kp)) == 2]
        # the other pooled columns get non-centred moves evaluated by the shards (one evaluation per row)
        self.nc_other = [kp for kp in range(self.m.d) if kp not in list(self.amp_pool)
                         and len(hyper.nc_coords(kp)) == 2] if features.diagonal else []
        self.nc_scale = None
        # one population without full covariance or fixed hyper-parameters and a log-uniform sd prior: its
        # columns move one by one (:meth:`psi_column_moves`)
        d = self.m.d
        self.by_column = (self.n_groups_of(hyper) == 1 and features.diagonal and len(self.m.free) == 2 * d
                          and self.m.sd_prior == "loguniform")
        self.col_step = np.zeros(d)
        self.col_L = np.stack([np.diag(np.maximum(np.std(self.x[:, [k, d + k]], axis=0), 1e-3))
                               for k in range(d)]) if self.by_column else None
        self.col_window = np.zeros((d, 2))
        self.nco_step = 0.0
        self._nc_turn = 0
        self.window["nco"] = np.zeros(2)
        self.pending = None
        g = np.asarray(hyper.groups, int)
        self.groups, self.n_groups = g, int(g.max()) + 1
        self.onehot = (g[None, :] == np.arange(self.n_groups)[:, None]).astype(float)  # (G, S)

    @staticmethod
    def n_groups_of(hyper: HyperLevel) -> int:
        return int(np.max(hyper.groups)) + 1

    # -- the population at x ---------------------------------------------------------------------
    def coefficients(self, x: np.ndarray):
        """Per group coef (G, C, nf), cc (G, C) and the natural population (G, C, 2d+q) at x."""
        raws = self.h.raws_of(x)
        out = [self.m.coefficients(r) for r in raws]
        return (np.stack([o[0] for o in out]), np.stack([o[1] for o in out]),
                np.stack([self.m.natural(r) for r in raws]))

    def set_population(self) -> None:
        self.coef, self.cc, self.nat = self.coefficients(self.x)
        self.corr = self.h.log_prior_correction(self.x)

    def amp_population(self, nat: np.ndarray):
        """mu, sd (S, C, k) of the amplitude columns from the groups' natural populations (1: no population)."""
        d = self.m.d
        nat_s = nat[self.groups]
        mu = np.zeros(nat_s.shape[:2] + (self.k,))
        sd = np.ones_like(mu)
        for j, kp in enumerate(self.amp_pool):
            if kp >= 0:
                mu[..., j], sd[..., j] = nat_s[..., kp], nat_s[..., d + kp]
        return mu, sd

    def receive(self, y, ll, quad, F, c) -> None:
        self.y, self.ll, self.F, self.c = y, ll, F, c
        self.quad = quad
        self.sums()
        if self.nc_scale is None:
            self.scales()

    def sums(self) -> None:
        """Per group Σ_s F (G, C, nf) and Σ_s c (C,): the population part of the target is linear in them."""
        self.SF = np.einsum("gs,scf->gcf", self.onehot, self.F)
        self.Sc = self.c.sum(axis=0)

    def scales(self) -> None:
        """Non-centred step scales from the spread of the chains (set in burn-in only, then frozen: a scale
        that followed the chains' current states would make the proposals asymmetric)."""
        kps = [kp for _, kp in self.nc_cols] + self.nc_other
        self.nc_scale = {kp: np.std(self.x[:, self.h.nc_coords(kp)], axis=0) + 1e-9 for kp in kps}
        # the population spread that sets how far each specimen follows a non-centred move
        self.nc_ref = {kp: float(np.median(self.nat[..., self.m.d + kp])) for kp in kps}

    def _tally(self, name, acc) -> None:
        a = self.accepted.setdefault(name, np.zeros(2))
        a += (np.sum(acc), np.size(acc))

    def _set_amplitudes(self, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Features (F, c) of y whose amplitudes changed."""
        if self.fast:
            return self.features.with_amplitudes(self.F, y[..., self.amp], self.amp_pool), self.c
        return self.features(y)

    # -- moves -----------------------------------------------------------------------------------
    def amplitude_moves(self) -> None:
        """Every specimen's amplitudes by the conditional importance sampling kernel (:mod:`.amplitudes`)."""
        S, C = self.y.shape[:2]
        n, k, M = S * C, self.k, self.n_particles
        mu, sd = self.amp_population(self.nat)
        ll0, G, b = (q.reshape((n,) + q.shape[2:]) for q in self.quad)
        u = self.y[..., self.amp].reshape(n, k)
        unew, moved = conditional_draw(u, G, b, ll0, mu.reshape(n, k), sd.reshape(n, k), self.amp_pool >= 0, self.lo,
                                       self.hi, self.constraints, self.rng_amp.random((n, M + 1)),
                                       self.rng_amp.standard_normal((n, M, k + 4)))
        self.y[..., self.amp] = unew.reshape(S, C, k)
        self.ll = quadratic_loglik(self.y[..., self.amp], *self.quad)
        self.F, self.c = self._set_amplitudes(self.y)
        self.sums()
        self._tally("amplitudes", moved)

    def psi_target(self, coef, cc, corr) -> np.ndarray:
        """Σ_s log r(x_s, ψ_{g(s)}) + log prior correction, per chain."""
        n_g = self.onehot.sum(axis=1)
        return np.einsum("gcf,gcf->c", coef, self.SF) + np.einsum("g,gc->c", n_g, cc) + self.Sc + corr

    def psi_moves(self, burning: bool) -> None:
        if self.by_column:
            return self.psi_column_moves(burning)
        box = self.h.box
        lp = self.psi_target(self.coef, self.cc, self.corr)
        for _ in range(self.psi_steps):
            C, nx = self.x.shape
            xp = self.x + np.exp(self.psi_step) * (self.rng_psi.standard_normal((C, nx)) @ self.psi_L.T)
            inside = np.all((xp >= box[:, 0]) & (xp <= box[:, 1]), axis=1)
            xp = np.where(inside[:, None], xp, self.x)
            coef, cc, nat = self.coefficients(xp)
            corr = self.h.log_prior_correction(xp)
            lpp = self.psi_target(coef, cc, corr)
            with np.errstate(invalid="ignore"):
                acc = inside & np.isfinite(lpp) & (np.log(self.rng_psi.random(C)) < lpp - lp)
            self.x[acc], lp[acc], self.corr[acc] = xp[acc], lpp[acc], corr[acc]
            self.coef[:, acc], self.cc[:, acc], self.nat[:, acc] = coef[:, acc], cc[:, acc], nat[:, acc]
            self._tally("psi", acc)
            if burning:
                self.window["psi"] += (acc.sum(), acc.size)

    def psi_column_moves(self, burning: bool) -> None:
        """Random walks of every column's (mu_k, log sd_k) at once, each accepted on its own: given the
        specimens the population's columns are independent (one group, no full covariance, log-uniform sd
        prior), so these are d independent 2-D Metropolis steps."""
        m, d = self.m, self.m.d
        S = self.groups.size
        C = self.x.shape[0]
        box = self.h.box
        raw = m.expand(self.x)
        old = m.column_terms(raw, self.SF[0], S)
        for _ in range(self.psi_steps):
            z = self.rng_psi.standard_normal((C, d, 2))
            step = np.exp(self.col_step)[None, :, None] * np.einsum("kij,ckj->cki", self.col_L, z)
            rawp = raw.copy()
            rawp[:, :d] += step[..., 0]
            rawp[:, d:2 * d] += step[..., 1]
            xp = rawp[:, m.free]
            inside = (xp >= box[:, 0]) & (xp <= box[:, 1])
            inside = inside[:, :d] & inside[:, d:2 * d]
            new = m.column_terms(rawp, self.SF[0], S)
            with np.errstate(invalid="ignore"):
                acc = inside & np.isfinite(new) & (np.log(self.rng_psi.random((C, d))) < new - old)
            raw[:, :d] = np.where(acc, rawp[:, :d], raw[:, :d])
            raw[:, d:2 * d] = np.where(acc, rawp[:, d:2 * d], raw[:, d:2 * d])
            old = np.where(acc, new, old)
            self._tally("psi", acc)
            if burning:
                self.col_window += np.column_stack([acc.sum(axis=0), np.full(d, C)])
        self.x = raw[:, m.free].copy()
        self.set_population()

    def _column_proposal(self, kp: int, step: float):
        """A random walk of the x coordinates of pooled column kp's population (frozen scale × e^step):
        (x', inside the box, coef', cc', natural', prior correction'); outside the box x' = x."""
        C = self.x.shape[0]
        cols = self.h.nc_coords(kp)
        xp = self.x.copy()
        xp[:, cols] += np.exp(step) * self.nc_scale[kp] * self.rng_nc.standard_normal((C, len(cols)))
        box = self.h.box
        inside = np.all((xp >= box[:, 0]) & (xp <= box[:, 1]), axis=1)
        xp = np.where(inside[:, None], xp, self.x)
        return (xp, inside, *self.coefficients(xp), self.h.log_prior_correction(xp))

    def noncentred(self, j: int, kp: int, burning: bool) -> None:
        """(mu, sd) of pooled amplitude column kp moved with every specimen's u_j along, partially
        (:func:`partial_weights`; the weights depend on the data and the specimen's nonlinear parameters,
        which the move does not change)."""
        C, d = self.x.shape[0], self.m.d
        xp, inside, coef, cc, nat, corr = self._column_proposal(kp, self.nc_step)
        g = self.groups
        mu, sd = self.nat[g][..., kp], self.nat[g][..., d + kp]
        mup, sdp = nat[g][..., kp], nat[g][..., d + kp]
        ll0, G, b = self.quad
        with np.errstate(divide="ignore", invalid="ignore"):
            # the data's precision of u_j at the least-squares amplitude (0 where it is not positive: flat)
            ahat = b[..., j] / G[..., j, j]
            prec = np.where(ahat > 0, ahat * ahat * G[..., j, j], 0.0)
        w = partial_weights(prec, self.nc_ref[kp])
        ynew = self.y.copy()
        col = self.amp[j]
        ynew[..., col], logjac = partial_map(self.y[..., col], mu, sd, mup, sdp, w)
        with np.errstate(invalid="ignore", over="ignore", divide="ignore"):
            S = ynew.shape[0]
            ok = inside & np.all(amplitudes_valid(ynew[..., self.amp].reshape(S * C, -1), self.lo, self.hi,
                                                  self.constraints).reshape(S, C), axis=0)
            ll = quadratic_loglik(ynew[..., self.amp], ll0, G, b)
            F, c = self._set_amplitudes(ynew)
            SF = np.einsum("gs,scf->gcf", self.onehot, F)
            n_g = self.onehot.sum(axis=1)
            new = np.einsum("gcf,gcf->c", coef, SF) + np.einsum("g,gc->c", n_g, cc) + c.sum(axis=0)
            logr = (np.sum(ll - self.ll + logjac, axis=0) + new - self.psi_target(self.coef, self.cc, 0.0)
                    + corr - self.corr)
            acc = ok & np.isfinite(logr) & (np.log(self.rng_nc.random(C)) < logr)
        self.x[acc], self.corr[acc] = xp[acc], corr[acc]
        self.coef[:, acc], self.cc[:, acc], self.nat[:, acc] = coef[:, acc], cc[:, acc], nat[:, acc]
        self.y[:, acc], self.ll[:, acc], self.F[:, acc], self.c[:, acc] = ynew[:, acc], ll[:, acc], F[:, acc], c[:, acc]
        self.sums()
        self._tally("non_centred", acc)
        if burning:
            self.window["nc"] += (acc.sum(), acc.size)

    def propose_other(self, r: int) -> dict | None:
        """A non-centred proposal of the next nonlinear pooled column (cycling), for the shards to evaluate:
        its population before and after per specimen (S, C); None when there is none."""
        if not self.nc_other or self.nc_scale is None:
            return None
        kp = self.nc_other[r % len(self.nc_other)]
        d = self.m.d
        xp, inside, coef, cc, nat, corr = self._column_proposal(kp, self.nco_step)
        g = self.groups
        self.pending = {"kp": kp, "x": xp, "coef": coef, "cc": cc, "nat": nat, "inside": inside, "corr": corr}
        return {"kp": kp, "mu": self.nat[g][..., kp], "sd": self.nat[g][..., d + kp], "mu_new": nat[g][..., kp],
                "sd_new": nat[g][..., d + kp], "ref": float(self.nc_ref[kp])}

    def decide_other(self, y, ll, quad, logjac, burning: bool) -> np.ndarray | None:
        """Accept or reject the pending non-centred proposal over all specimens (per chain); returns the
        decision (C,) that the shards apply, and applies it here."""
        p, self.pending = self.pending, None
        if p is None:
            return None
        C = self.x.shape[0]
        with np.errstate(invalid="ignore", over="ignore", divide="ignore"):
            F, c = self.features(y)
            SF = np.einsum("gs,scf->gcf", self.onehot, F)
            n_g = self.onehot.sum(axis=1)
            new = np.einsum("gcf,gcf->c", p["coef"], SF) + np.einsum("g,gc->c", n_g, p["cc"]) + c.sum(axis=0)
            logr = (np.sum(ll - self.ll + logjac, axis=0) + new - self.psi_target(self.coef, self.cc, 0.0)
                    + p["corr"] - self.corr)
            acc = p["inside"] & np.isfinite(logr) & (np.log(self.rng_nc.random(C)) < logr)
        self.x[acc], self.corr[acc] = p["x"][acc], p["corr"][acc]
        self.coef[:, acc], self.cc[:, acc], self.nat[:, acc] = p["coef"][:, acc], p["cc"][:, acc], p["nat"][:, acc]
        self.y[:, acc], self.ll[:, acc], self.F[:, acc], self.c[:, acc] = y[:, acc], ll[:, acc], F[:, acc], c[:, acc]
        if self.k:
            for q, qn in zip(self.quad, quad):
                q[:, acc] = qn[:, acc]
        self.sums()
        self._tally("non_centred_nonlinear", acc)
        if burning:
            self.window["nco"] += (acc.sum(), acc.size)
        return acc

    def moves(self, burning: bool) -> None:
        self.set_population()
        for r in range(self.pop_rounds):
            if self.k:
                self.amplitude_moves()
            self.psi_moves(burning)
            if self.nc_cols:  # one pooled amplitude column per pop round, in turn
                self.noncentred(*self.nc_cols[self._nc_turn % len(self.nc_cols)], burning)
                self._nc_turn += 1
        if burning:
            self.history.append(self.x.copy())

    def adapt(self) -> None:
        """Burn-in: ψ's proposal covariance from the recent history of all chains; step scales."""
        w = self.window
        self.psi_step += float(np.clip(w["psi"][0] / max(w["psi"][1], 1) - TARGET_ACCEPT, -0.2, 0.2)) * 2.0
        if w["nc"][1]:
            self.nc_step += float(np.clip(w["nc"][0] / w["nc"][1] - TARGET_ACCEPT, -0.2, 0.2)) * 2.0
        if w["nco"][1]:
            self.nco_step += float(np.clip(w["nco"][0] / w["nco"][1] - TARGET_ACCEPT, -0.2, 0.2)) * 2.0
        hist = np.concatenate(self.history[-50:])
        nx = hist.shape[1]
        if hist.shape[0] > 4 * nx:
            self.psi_L = safe_cholesky(np.cov(hist, rowvar=False).reshape(nx, nx)) * (2.38 / np.sqrt(nx))
            if self.by_column:
                d = self.m.d
                self.col_L = np.stack([safe_cholesky(np.cov(hist[:, [k, d + k]], rowvar=False)) * (2.38 / np.sqrt(2))
                                       for k in range(d)])
        if self.by_column:
            rate = self.col_window[:, 0] / np.maximum(self.col_window[:, 1], 1)
            self.col_step += np.clip(rate - TARGET_ACCEPT, -0.2, 0.2) * 2.0
            self.col_window[:] = 0
        self.scales()
        for key in ("psi", "nc", "nco"):
            w[key][:] = 0

    def inputs(self, shards: Sequence[ShardSpec], burning: bool, r: int, refit: bool = False,
               nc_accept: np.ndarray | None = None) -> list:
        """The shards' inputs of round ``r``: the population, the amplitudes, the decision on their last
        non-centred proposal and a new one."""
        self.set_population()
        coef_s, cc_s = self.coef[self.groups], self.cc[self.groups]
        mu, sd = self.amp_population(self.nat)
        u = None if r == 0 or not self.k else self.y[..., self.amp]
        nc = self.propose_other(r) if r > 0 else None
        # the shards' arrays are (B, C, ...): specimens first
        return [RoundInput(coef=coef_s[s.index], cc=cc_s[s.index], mu=mu[s.index], sd=sd[s.index],
                           u=None if u is None else u[s.index], burning=burning, refit=refit, nc_accept=nc_accept,
                           nc=None if nc is None else {"kp": nc["kp"], "ref": nc["ref"],
                                                       **{key: nc[key][s.index] for key in ("mu", "sd", "mu_new", "sd_new")}})
                for s in shards]


def _diagnostics(names: Sequence[str], kept_x: np.ndarray, kept_y: np.ndarray) -> tuple[dict, dict]:
    """Rank-normalised split R-hat and bulk ESS of every hyper-parameter (``hyper:<name>``) and every
    specimen column (``<specimen>:<column>``) of the kept draws."""
    rhat, ess = {}, {}
    for j, name in enumerate(names):
        rhat[f"hyper:{name}"], ess[f"hyper:{name}"] = rhat_ess(kept_x[:, :, j])
    for s in range(kept_y.shape[2]):
        for col in range(kept_y.shape[3]):
            rhat[f"{s}:{col}"], ess[f"{s}:{col}"] = rhat_ess(kept_y[:, :, s, col])
    return rhat, ess


def batched_gibbs(hyper: HyperLevel, shards: Sequence[ShardSpec], x0: np.ndarray, *, features: Callable,
                  valid: Callable, constraints, amp_cols, amp_pool, box: np.ndarray,
                  seed: np.random.SeedSequence,
                  n_burn: int = 300, n_keep: int = 250, thin: int = 4, psi_steps: int = 3, pop_rounds: int = 2,
                  adapt_every: int = 20, client=None, log: Callable[[str], None] | None = None,
                  shard_options: dict | None = None, converged: Callable[[dict, dict], bool] | None = None,
                  max_keep: int | None = None) -> BatchedResult:
    """Sample the joint posterior of the population and the specimens (module docstring).

    Parameters
    ----------
    hyper : HyperLevel
    shards : sequence of ShardSpec
        The fixed partition of the specimens (its ``index`` arrays cover 0..S-1 in order).
    x0 : ndarray (n_chains, nx)
        Starting hyper coordinates, inside ``hyper.box``.
    features, valid : callables on y (S, C, dy)
        Pooled features (F, c) and support of the specimens' coordinates.
    constraints : (P, Q, R) or None
        The amplitudes' support constraints (:func:`~.amplitudes.particles`).
    amp_cols : ndarray of int (k,)
        The amplitude columns of y (empty: none); ``amp_pool``: each one's pooled index (-1: none).
    box : ndarray (dy, 2)
    seed : SeedSequence
        The run's layer stream (children 1–3: ψ, amplitudes, non-centred moves).
    n_burn, n_keep, thin : int
        Burn-in rounds, kept draws per chain and rounds per kept draw.
    psi_steps, pop_rounds, adapt_every : int
    client : distributed.Client, optional
        Run the shards as dask actors (results bitwise those of ``client=None``).
    log : callable, optional
        Progress lines (an estimate after the first rounds, then about every 10 s).
    shard_options : dict, optional
        Keyword arguments of :class:`~.shards.ShardState`.
    converged : callable (rhat, ess) -> bool, optional
        Whether the kept draws' diagnostics (the ``rhat``/``ess`` dicts of :class:`BatchedResult`) are good
        enough.  When they are not after ``n_keep`` draws per chain, the chains go on, ``n_keep // 2`` kept
        draws at a time, until they are or ``max_keep`` draws per chain are kept.  The decision reads the
        chains alone, so the draws stay the same on any number of workers.
    max_keep : int, optional
        Most kept draws per chain when extending (default ``n_keep``: never extend).

    Returns
    -------
    BatchedResult
    """
    t0 = time.perf_counter()
    x0 = np.atleast_2d(np.asarray(x0, float))
    C = x0.shape[0]
    if C < 2 or n_keep < 4 or thin < 1 or n_burn < 0:
        raise HbmError("batched_gibbs: need n_chains >= 2, n_keep >= 4, thin >= 1, n_burn >= 0")
    if np.any((x0 < hyper.box[:, 0]) | (x0 > hyper.box[:, 1])):
        raise HbmError("batched_gibbs: starting hyper coordinates outside the hyperprior box")
    amp_cols, amp_pool = np.asarray(amp_cols, int), np.asarray(amp_pool, int)
    S = int(sum(len(s.index) for s in shards))
    ex = _Shards(shards, features, amp_pool, client, **dict(shard_options or {}))
    master = _Master(hyper, x0, features, valid, constraints, amp_cols, amp_pool, np.asarray(box, float), seed,
                     psi_steps, pop_rounds, n_particles=int(dict(shard_options or {}).get("n_particles", 16)))
    dy = shards[0].rows[0].shape[1]
    y = np.zeros((S, C, dy))
    ll, F, c = np.zeros((S, C)), None, np.zeros((S, C))
    k = amp_cols.size
    quad = (np.zeros((S, C)), np.zeros((S, C, k, k)), np.zeros((S, C, k))) if k else None
    evals = np.zeros(S, np.int64)
    n_keep, n_keep0 = int(n_keep), int(n_keep)
    max_keep = n_keep if converged is None or max_keep is None else max(int(max_keep), n_keep)
    n_rounds = int(n_burn) + n_keep * int(thin)
    kept_x = np.empty((C, n_keep, x0.shape[1]))
    kept_y = np.empty((C, n_keep, S, dy))
    checks: list = []  # (kept draws per chain, max hyper R-hat, min hyper ESS, max specimen R-hat) per check
    rhat = ess = None
    acc_shard: dict = {}
    master.set_population()
    inputs = None
    nc_accept = None
    t_start, t_last = time.perf_counter(), time.perf_counter()
    r = -1
    while r + 1 < n_rounds:
        r += 1
        burning = r < n_burn
        # the shards refit their proposals to their own burn-in draws at a third and two thirds of burn-in
        inputs = master.inputs(shards, burning, r, refit=r + 1 in (n_burn // 3, 2 * n_burn // 3), nc_accept=nc_accept)
        outs = ex.advance(inputs)
        for s, o in zip(shards, outs):
            y[s.index], ll[s.index], c[s.index] = o.y, o.ll, o.c
            if F is None:
                F = np.zeros((S, C, o.F.shape[-1]))
            F[s.index] = o.F
            if k:
                for q, part in zip(quad, o.quad):
                    q[s.index] = part
            evals[s.index] += o.evals
            if not burning:
                for name, a in o.accepted.items():
                    acc_shard.setdefault(name, np.zeros((S, 2)))[s.index] += a
        master.receive(y, ll, quad, F, c)
        nc_accept = None
        if outs[0].nc is not None:
            yn, lln, ljn = np.empty_like(y), np.empty_like(ll), np.empty_like(ll)
            qn = tuple(np.empty_like(q) for q in quad) if k else None
            for s, o in zip(shards, outs):
                yn[s.index], lln[s.index], ljn[s.index] = o.nc["y"], o.nc["ll"], o.nc["logjac"]
                if k:
                    for q, part in zip(qn, o.nc["quad"]):
                        q[s.index] = part
            nc_accept = master.decide_other(yn, lln, qn, ljn, burning)
        master.moves(burning)
        if burning and (r + 1) % adapt_every == 0:
            master.adapt()
        if r == n_burn - 1:
            master.accepted = {}
        if not burning and (r - n_burn + 1) % thin == 0:
            j = (r - n_burn + 1) // thin - 1
            kept_x[:, j] = master.x
            kept_y[:, j] = np.swapaxes(master.y, 0, 1)
        now = time.perf_counter()
        if r == 1:
            t_start = now  # the first round loads the compiled kernels: the estimate starts after it
        if log is not None and (r == 11 or (r > 11 and now - t_last > 10.0)):
            per = (now - t_start) / (r - 1)
            left = per * (n_rounds - r - 1)
            if r == 11:
                most = n_burn + max_keep * thin
                log(f"population sampler: {S} specimens x {C} chains, {n_rounds} rounds "
                    f"({n_burn} burn-in), about {int(evals.sum() / (r + 1) * n_rounds):,} model evaluations; "
                    f"estimated {left:.0f} s" + (f" (up to {most} rounds, {per * (most - r - 1):.0f} s, if the chains "
                                                   f"need extending to converge)" if most > n_rounds else ""))
            else:
                log(f"population sampler: round {r + 1}/{n_rounds}, {left:.0f} s left")
            t_last = now
        if r + 1 == n_rounds and max_keep > n_keep0:
            # a convergence check: go on, half the planned draws at a time, while the chains say so
            rhat, ess = _diagnostics(hyper.names, kept_x, kept_y)
            hyper_r = [v for key, v in rhat.items() if key.startswith("hyper:")]
            hyper_e = [v for key, v in ess.items() if key.startswith("hyper:")]
            spec_r = [v for key, v in rhat.items() if not key.startswith("hyper:") and np.isfinite(v)]
            checks.append((n_keep, float(np.nanmax(hyper_r)), float(np.nanmin(hyper_e)),
                           max(spec_r, default=float("nan"))))
            if n_keep < max_keep and not converged(rhat, ess):
                add = min(max(n_keep0 // 2, 1), max_keep - n_keep)
                if log is not None:
                    log(f"population sampler: not converged after {n_keep} draws per chain (hyper-parameters: max "
                        f"R-hat {checks[-1][1]:.3f}, min bulk ESS {checks[-1][2]:.0f}; specimens: max R-hat "
                        f"{checks[-1][3]:.3f}): {add} more per chain (at most {max_keep})")
                kept_x = np.concatenate([kept_x, np.empty((C, add) + kept_x.shape[2:])], axis=1)
                kept_y = np.concatenate([kept_y, np.empty((C, add) + kept_y.shape[2:])], axis=1)
                n_keep += add
                n_rounds += add * int(thin)
                rhat = ess = None
    shard_cpu = ex.cpu() if client is not None else 0.0
    t1 = time.perf_counter()
    if rhat is None:
        rhat, ess = _diagnostics(hyper.names, kept_x, kept_y)
    t2 = time.perf_counter()
    acceptance = {name: float(a[0] / max(a[1], 1)) for name, a in master.accepted.items()}
    acceptance.update({name: float(a[:, 0].sum() / max(a[:, 1].sum(), 1)) for name, a in acc_shard.items()})
    per_specimen = {name: (a[:, 0] / np.maximum(a[:, 1], 1)).tolist() for name, a in acc_shard.items()}
    return BatchedResult(x=kept_x, y=kept_y, rhat=rhat, ess=ess, acceptance={**acceptance, "per_specimen": per_specimen},
                         evaluations=evals,
                         timings={"sampling": t1 - t0, "diagnostics": t2 - t1, "total": t2 - t0,
                                  "shard_cpu": shard_cpu if client is not None else 0.0},
                         options={"n_chains": C, "n_burn": int(n_burn), "n_keep": int(n_keep), "thin": int(thin),
                                  "n_keep_planned": n_keep0, "max_keep": int(max_keep),
                                  "convergence_checks": [list(c) for c in checks],
                                  "psi_steps": int(psi_steps), "pop_rounds": int(pop_rounds),
                                  "shards": len(shards), "workers": "dask" if client is not None else "in-process"})
