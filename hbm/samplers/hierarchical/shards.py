"""The specimens of the batched population sampler, a shard at a time (:mod:`.batched`).

Given the population, the specimens are independent, so their moves run for a *shard* of
specimens at once — every chain of every specimen of the shard in one array — in this process or
on a dask worker.  A specimen's coordinates ``y`` split into

* amplitude columns (u = log A, ``k`` of them; may be none): the log-likelihood is quadratic in
  A = e^u given the rest (:mod:`.amplitudes`), so the population sampler moves them together
  with the population parameters, at no model evaluation (:mod:`.batched`);
* the other columns (``v``: the model's nonlinear parameters and the noise parameters): a change
  of the nonlinear ones costs one model evaluation per row.

Moves of one sweep, each an exact Metropolis–Hastings step for the specimen given the population
(all rows at once): an independence jump of ``v`` from a Gaussian mixture fitted to the specimen's
stage-1 rows (k-means clusters, :func:`hbm.samplers.mixtures.kmeans_mixture`), and a random walk of
``v`` (scale mixture 0.3/1/3 × the stage-1 covariance, adapted in burn-in), each with the amplitudes
redrawn from :class:`~.amplitudes.AmplitudeProposal` at the new ``v`` (one evaluation; the ratio
carries both proposal densities, so the move follows the marginal of ``v``); then two random walks
of the noise columns alone (no evaluation).

Random numbers: every specimen has its own streams (children of its seed sequence: 0 the mixture
fit, 1 the moves), drawn ``block`` sweeps ahead, so the draws of a specimen do not depend on the
shard it is in, and a shard's result not on the worker that runs it.

This module is sampler-layer code: it knows nothing about muscles.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Any, Callable, Protocol, Sequence

import numpy as np

from ..linalg import safe_cholesky
from ..mixtures import kmeans_mixture
from .amplitudes import log_mean_exp, modes, particles, pick

__all__ = ["SpecimenBatch", "ShardState", "RoundInput", "RoundOutput", "TARGET_ACCEPT", "partial_weights", "partial_map"]

#: random-walk step multipliers (equal probability)
_SCALES = np.array([0.3, 1.0, 3.0])
TARGET_ACCEPT = 0.25


def partial_weights(prec: np.ndarray, ref: float) -> np.ndarray:
    """How far each specimen follows a non-centred move of its population (Papaspiliopoulos, Roberts &
    Sköld 2007): w = 1/(1 + prec·ref²), 1 (non-centred) where the data say nothing about the column, → 0
    (centred) where they pin it far more than a population of spread ``ref`` does."""
    return 1.0 / (1.0 + prec * ref * ref)


def partial_map(z: np.ndarray, mu, sd, mu_new, sd_new, w) -> tuple[np.ndarray, np.ndarray]:
    """z' = w·mu' + (sd'/sd)^w·(z − w·mu): the partially non-centred value z̃ = (z − w·mu)/sd^w kept while
    the population moves; returns z' and log |dz'/dz| = w·log(sd'/sd)."""
    ratio = sd_new / sd
    f = ratio**w
    return w * mu_new + f * (z - w * mu), w * np.log(ratio)


class SpecimenBatch(Protocol):
    """The likelihoods of a shard's ``n_specimens`` specimens in the sampler's coordinates ``y`` (picklable).

    Attributes
    ----------
    n_specimens, dy : int
    amplitude_cols, nonlinear_cols, noise_cols : ndarray of int
        The columns of ``y`` of each kind (module docstring); ``amplitude_cols`` may be empty.
    box : ndarray (dy, 2)
        Box of ``y``.
    """

    n_specimens: int
    dy: int
    amplitude_cols: np.ndarray
    nonlinear_cols: np.ndarray
    noise_cols: np.ndarray
    box: np.ndarray

    def prepare(self, y: np.ndarray) -> Any:
        """State at rows ``y`` (B, C, dy): one model evaluation per row."""

    def loglik(self, prep: Any, y: np.ndarray) -> np.ndarray:
        """Log-likelihood (B, C) at ``y`` whose nonlinear columns are those ``prep`` was made at."""

    def quadratic(self, prep: Any, y: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(ℓ0 (B, C), G (B, C, k, k), b (B, C, k)) of the amplitudes at ``y``'s noise columns."""

    def select(self, prep: Any, new: Any, mask: np.ndarray) -> Any:
        """``new`` where ``mask`` (B, C), ``prep`` elsewhere."""

    def valid(self, y: np.ndarray) -> np.ndarray:
        """(B, C): rows inside the box and the support of the prior."""


@dataclass
class RoundInput:
    """The population seen by a shard for one round (every array (B, C, ...)).

    ``coef``/``cc``: the population's log-ratio coefficients (:meth:`HierarchicalModel.coefficients`)
    of each row's specimen; ``mu``/``sd``: the population of the amplitude columns; ``u``: the
    amplitudes the population sampler left (None: unchanged); ``burning``: adapt the step scales;
    ``refit``: after the round, refit the proposals to the burn-in draws since the last refit;
    ``nc_accept``: (C,) the population sampler's decision on the shard's last non-centred proposal
    (apply it first); ``nc``: a new non-centred proposal of a nonlinear pooled column to evaluate
    after the sweeps: ``kp`` (pooled index) and the column's population before and after, ``mu``,
    ``sd``, ``mu_new``, ``sd_new`` (B, C) in transformed units.
    """

    coef: np.ndarray
    cc: np.ndarray
    mu: np.ndarray
    sd: np.ndarray
    u: np.ndarray | None
    burning: bool
    sweeps: int = 1
    refit: bool = False
    nc_accept: np.ndarray | None = None
    nc: dict | None = None


@dataclass
class RoundOutput:
    """What a shard returns after a round: coordinates, log-likelihood, the amplitudes' quadratic form
    (None without amplitudes), features, model evaluations per specimen and acceptance counts; ``nc``:
    the evaluated non-centred proposal (``y``, ``ll``, ``quad`` there and ``logjac``, the log Jacobian
    of the map per row) or None."""

    y: np.ndarray
    ll: np.ndarray
    quad: tuple | None
    F: np.ndarray
    c: np.ndarray
    evals: np.ndarray
    accepted: dict
    nc: dict | None = None


class ShardState:
    """The chains of a shard's specimens and their moves (module docstring).

    Parameters
    ----------
    batch : SpecimenBatch
    features : callable y (..., dy) -> (F (..., n_f), c (...))
        The population model's features of the pooled columns (:meth:`HierarchicalModel.features`).
    rows : sequence of ndarray (N_s, dy)
        Each specimen's stage-1 rows in ``y`` (mixture fit, random-walk covariance, starting points).
    init : ndarray of int (B, C)
        Starting row of every chain.
    seeds : sequence of SeedSequence
        One per specimen (children: 0 the mixture fit, 1 the moves).
    amp_pool : ndarray of int (k,)
        The pooled index of each amplitude column (-1: it has no population).
    n_components, inflate : int, float
        The mixture of ``v`` (components per specimen, covariance × inflate²).
    block : int
        Sweeps whose random numbers are drawn at once.
    """

    def __init__(self, batch: SpecimenBatch, features: Callable, rows: Sequence[np.ndarray], init: np.ndarray,
                 seeds: Sequence[np.random.SeedSequence], amp_pool: np.ndarray, *, n_components: int = 16,
                 inflate: float = 1.15, block: int = 16, n_particles: int = 16) -> None:
        self.batch, self.features = batch, features
        B, C = init.shape
        self.B, self.C = B, C
        self.amp = np.asarray(batch.amplitude_cols, int)
        self.vcols = np.concatenate([np.asarray(batch.nonlinear_cols, int), np.asarray(batch.noise_cols, int)])
        self.qcols = np.asarray(batch.noise_cols, int)
        self.k, self.m, self.nq = self.amp.size, self.vcols.size, self.qcols.size
        self.amp_pooled = np.asarray(amp_pool, int) >= 0
        self.other_pooled = [kp for kp in range(features.model.d) if kp not in list(amp_pool)]
        self.box = np.asarray(batch.box, float)
        self.rngs = [np.random.default_rng(np.random.SeedSequence(s.entropy, spawn_key=tuple(s.spawn_key) + (1,)))
                     for s in seeds]
        self.n_components, self.inflate = int(n_components), float(inflate)
        self.fit_rngs = [np.random.default_rng(np.random.SeedSequence(s.entropy, spawn_key=tuple(s.spawn_key) + (0,)))
                         for s in seeds]
        self.stage1_v = [np.asarray(r, float)[:, self.vcols] for r in rows]
        # the stage-1 posterior variance of every pooled column in its transformed coordinate
        self.stage1_var = {kp: np.array([np.var(features.to_z(kp, np.asarray(r, float)[:, col])[0]) + 1e-12
                                         for r in rows]) for kp, col in enumerate(features.pool_y)}
        self._proposals(self.stage1_v)
        m = self.m
        self.rw_step = np.full(B, np.log(2.38 / np.sqrt(m)))
        self.q_sd = np.stack([np.asarray(r, float)[:, self.qcols].std(axis=0) + 1e-300 for r in rows]) \
            if self.nq else np.zeros((B, 0))
        self.q_step = np.zeros(B)
        self.y = np.stack([np.asarray(r, float)[i] for r, i in zip(rows, init)])
        self.evals = np.zeros(B, np.int64)
        self.prep = batch.prepare(self.y)
        self.evals += C
        self.ll = np.asarray(batch.loglik(self.prep, self.y), float)
        self.F, self.c = features(self.y)
        self.block = int(block)
        self._U = self._Z = None
        self._t = self.block
        self.n_particles = int(n_particles)
        self._layout()
        self.window = {key: np.zeros((B, 2)) for key in ("jump", "walk", "noise")}
        self.sweeps_done = 0
        self.history: list = []  # v of every chain during burn-in, for the refits of the proposals
        self._nc_pending = None  # the last non-centred proposal (y, prepared state) until it is decided
        self._cpu0 = time.process_time()

    def cpu(self) -> float:
        """CPU seconds of this process since the shard was made (on a dask worker: the shard's own)."""
        return time.process_time() - self._cpu0

    def _proposals(self, rows: Sequence[np.ndarray]) -> None:
        """Each specimen's mixture of v (k-means clusters, padded to a common number of components) and
        random-walk covariance from rows of v (the stage-1 rows, later the burn-in draws)."""
        B, m = self.B, self.m
        mixes = [kmeans_mixture(r, self.n_components, self.inflate, g) for r, g in zip(rows, self.fit_rngs)]
        M = max(mx[0].size for mx in mixes)
        self.mix_logw = np.full((B, M), -np.inf)
        self.mix_mu = np.zeros((B, M, m))
        self.mix_L = np.broadcast_to(np.eye(m), (B, M, m, m)).copy()
        self.mix_logdet = np.zeros((B, M))
        for b, (logw, mu, L, logdet) in enumerate(mixes):
            n = logw.size
            self.mix_logw[b, :n], self.mix_mu[b, :n], self.mix_L[b, :n], self.mix_logdet[b, :n] = logw, mu, L, logdet
        self.mix_Linv = np.linalg.inv(self.mix_L)
        cw = np.cumsum(np.exp(self.mix_logw), axis=1)
        self.mix_cw = cw / cw[:, -1:]  # the last exactly 1: a uniform never picks a padded component
        self.rw_L = np.stack([safe_cholesky(np.cov(r, rowvar=False).reshape(m, m)) for r in rows])

    # -- random numbers ----------------------------------------------------------------------------
    def _layout(self) -> None:
        """Where each move's random numbers sit in a sweep's uniforms and normals (fixed counts per row)."""
        m, M, na = self.m, self.n_particles, (self.k + 4 if self.k else 0)
        self.n_amp = na
        # per evaluated move: uniforms [choice, accept, select, M new components, M - 1 current components],
        # normals [m for v, M x na new, (M - 1) x na current]
        self.nu_move = 3 + (2 * M - 1 if self.k else 0)
        self.nz_move = m + (2 * M - 1) * na
        self.nu = 2 * self.nu_move + 4
        self.nz = 2 * self.nz_move + 2 * self.nq

    def _randoms(self) -> tuple[np.ndarray, np.ndarray]:
        """This sweep's uniforms (B, C, nu) and normals (B, C, nz), from each specimen's stream."""
        if self._t >= self.block:
            self._U = np.stack([g.random((self.block, self.C, self.nu)) for g in self.rngs])
            self._Z = np.stack([g.standard_normal((self.block, self.C, self.nz)) for g in self.rngs])
            self._t = 0
        t = self._t
        self._t += 1
        return self._U[:, t], self._Z[:, t]

    # -- pieces ------------------------------------------------------------------------------------
    def _population(self, F, c, inp: RoundInput) -> np.ndarray:
        return np.einsum("bcf,bcf->bc", inp.coef, F) + inp.cc + c

    def _nonamp_population(self, y, inp: RoundInput) -> np.ndarray:
        """The population's log ratio of y's pooled columns other than the amplitudes (up to a constant of
        the population): a diagonal population's terms of those columns."""
        return self.features.partial(y, inp.coef, self.other_pooled)

    def _particles(self, prep, y, inp: RoundInput, uniforms, normals, current: bool):
        """Importance particles of the amplitudes at rows y (flattened (B·C, M, k)) and their log weights."""
        ll0, G, b = self.batch.quadratic(prep, y)
        n, k = self.B * self.C, self.k
        return particles(G.reshape(n, k, k), b.reshape(n, k), ll0.reshape(n), inp.mu.reshape(n, k),
                         inp.sd.reshape(n, k), self.amp_pooled, self.box[self.amp, 0], self.box[self.amp, 1],
                         self.batch.amplitude_constraints, uniforms, normals,
                         current=y[..., self.amp].reshape(n, k) if current else None)

    def _mixture_logpdf(self, v: np.ndarray) -> np.ndarray:
        a = np.einsum("bmij,bcmj->bcmi", self.mix_Linv, v[:, :, None, :] - self.mix_mu[:, None, :, :])
        t = self.mix_logw[:, None, :] - 0.5 * np.einsum("bcmi,bcmi->bcm", a, a) - self.mix_logdet[:, None, :]
        mx = np.max(t, axis=2)
        return mx + np.log(np.sum(np.exp(t - mx[..., None]), axis=2))

    def _evaluated_move(self, name: str, vnew: np.ndarray, lq_v, U: np.ndarray, Z: np.ndarray,
                        inp: RoundInput, state: dict) -> None:
        """Move v to ``vnew`` (one evaluation per row); ``lq_v``: log q(v)/q(v').  With amplitudes: M
        particles of u at v' and M − 1 beside the current u at v, accepted with the ratio of their mean
        importance weights, the new u drawn ∝ weight (:mod:`.amplitudes`)."""
        B, C, k, M = self.B, self.C, self.k, self.n_particles
        y = self.y
        prop_y = y.copy()
        prop_y[..., self.vcols] = vnew
        inside = np.all((vnew >= self.box[self.vcols, 0]) & (vnew <= self.box[self.vcols, 1]), axis=2)
        prop_y[~inside] = y[~inside]  # evaluated at the current point, rejected below
        new = self.batch.prepare(prop_y)
        self.evals += C
        with np.errstate(invalid="ignore", over="ignore", divide="ignore"):
            if k:
                n, na = B * C, self.n_amp
                zc = Z[..., self.m:].reshape(n, 2 * M - 1, na)
                uc = U[..., 3:].reshape(n, 2 * M - 1)
                parts, lw_new = self._particles(new, prop_y, inp, uc[:, :M], zc[:, :M], False)
                # the current u and M - 1 particles at the current v (their first uniform and normals unused)
                _, lw_cur = self._particles(self.prep, y, inp, uc[:, M - 1:], zc[:, M - 1:], True)
                if state.get("lpN") is None:
                    state["lpN"] = self._nonamp_population(y, inp)
                lpN = self._nonamp_population(prop_y, inp)
                logr = (log_mean_exp(lw_new) - log_mean_exp(lw_cur)).reshape(B, C) + lpN - state["lpN"] + lq_v
                j = pick(lw_new, U[..., 2].reshape(n))
                prop_y[..., self.amp] = parts[np.arange(n), j].reshape(B, C, k)
                ok = inside & np.isfinite(logr)
            else:
                ok = inside & self.batch.valid(prop_y)
                ll = np.where(ok, self.batch.loglik(new, prop_y), -np.inf)
                F, c = self.features(prop_y)
                logr = ll + self._population(F, c, inp) - self.ll - self._population(self.F, self.c, inp) + lq_v
            acc = ok & (np.log(U[..., 1]) < logr)
        if k:
            ll = self.batch.loglik(new, prop_y)
            state["lpN"] = np.where(acc, lpN, state["lpN"])
            self.y[acc], self.ll[acc] = prop_y[acc], ll[acc]
        else:
            self.y[acc], self.ll[acc], self.F[acc], self.c[acc] = prop_y[acc], ll[acc], F[acc], c[acc]
        self.prep = self.batch.select(self.prep, new, acc)
        self._tally(name, acc)

    def _noise_walk(self, U: np.ndarray, Z: np.ndarray, state: dict) -> None:
        scale = np.exp(self.q_step)[:, None] * _SCALES[np.minimum((U[..., 0] * 3).astype(int), 2)]
        prop_y = self.y.copy()
        prop_y[..., self.qcols] += scale[..., None] * self.q_sd[:, None, :] * Z
        ok = self.batch.valid(prop_y)
        with np.errstate(invalid="ignore", over="ignore", divide="ignore"):
            ll = np.where(ok, self.batch.loglik(self.prep, prop_y), -np.inf)
            acc = ok & np.isfinite(ll) & (np.log(U[..., 1]) < ll - self.ll)
        self.y[acc], self.ll[acc] = prop_y[acc], ll[acc]
        self._tally("noise", acc)

    def _tally(self, name: str, acc: np.ndarray) -> None:
        self.window[name] += np.column_stack([acc.sum(axis=1), np.full(self.B, self.C)])
        self.accepted[name] = self.accepted.get(name, np.zeros((self.B, 2))) + np.column_stack(
            [acc.sum(axis=1), np.full(self.B, self.C)])

    def _adapt(self) -> None:
        """Burn-in: per specimen, the random-walk scales toward the target acceptance."""
        for name, attr in (("walk", "rw_step"), ("noise", "q_step")):
            w = self.window[name]
            rate = w[:, 0] / np.maximum(w[:, 1], 1)
            setattr(self, attr, getattr(self, attr) + np.clip(rate - TARGET_ACCEPT, -0.2, 0.2) * 2.0)
            w[:] = 0
        self.window["jump"][:] = 0

    # -- a round -----------------------------------------------------------------------------------
    def advance(self, inp: RoundInput) -> RoundOutput:
        """``inp.sweeps`` sweeps of every move given the population ``inp``; returns the shard's state."""
        self.accepted = {}
        ev0 = self.evals.copy()
        if inp.nc_accept is not None and self._nc_pending is not None:
            acc = np.broadcast_to(np.asarray(inp.nc_accept, bool), (self.B, self.C))
            y_nc, prep_nc = self._nc_pending
            self.y[acc] = y_nc[acc]
            self.prep = self.batch.select(self.prep, prep_nc, acc)
        self._nc_pending = None
        if inp.u is not None and self.k:
            self.y[..., self.amp] = inp.u
            self.ll = np.asarray(self.batch.loglik(self.prep, self.y), float)
            self.F, self.c = self.features(self.y)
        state: dict = {"lpN": None}
        m, nu, nz = self.m, self.nu_move, self.nz_move
        for _ in range(int(inp.sweeps)):
            U, Z = self._randoms()
            # independence jump of v from the specimen's mixture
            comp = np.minimum((self.mix_cw[:, None, :] < U[..., 0:1]).sum(axis=2), self.mix_cw.shape[1] - 1)
            bidx = np.arange(self.B)[:, None]
            v = self.y[..., self.vcols]
            vnew = self.mix_mu[bidx, comp] + np.einsum("bcij,bcj->bci", self.mix_L[bidx, comp], Z[..., :m])
            with np.errstate(invalid="ignore", over="ignore"):
                lq_v = self._mixture_logpdf(v) - self._mixture_logpdf(vnew)
            self._evaluated_move("jump", vnew, lq_v, U[..., :nu], Z[..., :nz], inp, state)
            # random walk of v
            scale = np.exp(self.rw_step)[:, None] * _SCALES[np.minimum((U[..., nu] * 3).astype(int), 2)]
            v = self.y[..., self.vcols]
            vnew = v + scale[..., None] * np.einsum("bij,bcj->bci", self.rw_L, Z[..., nz:nz + m])
            self._evaluated_move("walk", vnew, 0.0, U[..., nu:2 * nu], Z[..., nz:2 * nz], inp, state)
            for j in range(2 if self.nq else 0):
                self._noise_walk(U[..., 2 * nu + 2 * j:2 * nu + 2 * j + 2],
                                 Z[..., 2 * nz + j * self.nq:2 * nz + (j + 1) * self.nq], state)
            self.sweeps_done += 1
            if inp.burning:
                self.history.append(self.y[..., self.vcols].copy())
                if self.sweeps_done % 20 == 0:
                    self._adapt()
        if inp.refit and len(self.history) > 1:
            # the proposals from the burn-in draws since the last refit and as many stage-1 rows: the mixture
            # then follows the specimen's marginal under the population, and still proposes the regions of
            # its stage-1 posterior the chains have not visited yet
            h = np.concatenate(self.history, axis=1)  # (B, n·C, m)
            self._proposals([np.concatenate([hb, r[np.linspace(0, len(r) - 1, hb.shape[0]).astype(int)]])
                             for hb, r in zip(h, self.stage1_v)])
            self.rw_step[:] = np.log(2.38 / np.sqrt(self.m))
            self.history = []
        quad = self.batch.quadratic(self.prep, self.y) if self.k else None
        if self.k:
            self.F, self.c = self.features(self.y)
        nc = self._noncentred(inp) if inp.nc is not None else None
        return RoundOutput(y=self.y.copy(), ll=self.ll.copy(), quad=quad, F=self.F.copy(), c=self.c.copy(),
                           evals=self.evals - ev0, accepted=self.accepted, nc=nc)

    def _noncentred(self, inp: RoundInput) -> dict:
        """Evaluate a non-centred proposal of nonlinear pooled column ``kp`` (one evaluation per row): its
        transformed value z' = mu' + (sd'/sd)(z − mu) in every row, the amplitudes carried along with the
        centre of their conditional, u' = m(φ') + (u − m(φ)) (a translation: Jacobian 1), and the
        log-likelihood there; the population sampler decides over all specimens and says so next round."""
        nc, f = inp.nc, self.features
        kp = int(nc["kp"])
        col = int(f.pool_y[kp])
        x = self.y[..., col]
        z, jac = f.to_z(kp, x)
        # partially non-centred: each specimen follows as far as its stage-1 posterior leaves it free
        w = partial_weights(1.0 / self.stage1_var[kp][:, None], nc["ref"])
        zn, logjac = partial_map(z, nc["mu"], nc["sd"], nc["mu_new"], nc["sd_new"], w)
        xn = f.from_z(kp, zn)
        _, jac_new = f.to_z(kp, xn)
        y_new = self.y.copy()
        y_new[..., col] = xn
        inside = self.batch.valid(y_new) if not self.k else np.all(
            (y_new >= self.box[:, 0]) & (y_new <= self.box[:, 1]), axis=-1)
        y_new[~inside] = self.y[~inside]
        prep = self.batch.prepare(y_new)
        self.evals += self.C
        quad = None
        if self.k:
            n, k = self.B * self.C, self.k
            lo, hi = self.box[self.amp, 0], self.box[self.amp, 1]
            args = (inp.mu.reshape(n, k), inp.sd.reshape(n, k), self.amp_pooled, lo, hi)
            q_old = self.batch.quadratic(self.prep, self.y)
            q_new = self.batch.quadratic(prep, y_new)
            m_old = modes(q_old[1].reshape(n, k, k), q_old[2].reshape(n, k), *args)
            m_new = modes(q_new[1].reshape(n, k, k), q_new[2].reshape(n, k), *args)
            y_new[..., self.amp] = self.y[..., self.amp] + (m_new - m_old).reshape(self.B, self.C, k)
            quad = q_new
        with np.errstate(invalid="ignore", over="ignore", divide="ignore"):
            ok = inside & self.batch.valid(y_new)
            ll = np.where(ok, self.batch.loglik(prep, y_new), -np.inf)
        self._nc_pending = (y_new, prep)
        return {"y": y_new, "ll": ll, "quad": quad, "logjac": logjac + jac - jac_new}
