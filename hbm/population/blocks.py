"""The amplitude block of the exact fallback: a specimen's linear amplitudes moved given its φ (issue 27).

The base model's stress is X(φ)·A, linear in the amplitudes A = (G, c·P1, (1−c)·T1) given the
nonlinear parameters φ (:mod:`hbm.model.linear`).  In the exact fallback's coordinates of
``--pool combinations`` (:class:`~hbm.population.pooling.PhiCoordinates`) the first three
columns of a specimen's state are y = log A, and the slow direction of the joint chains is one
of them (log c·P1, flat in the likelihood below the noise level, so its population sets the
tail).  :class:`AmplitudeBlock` gives the joint sampler
(:class:`hbm.samplers.hierarchical.ConditionalBlock`) the exact likelihood of any A at fixed φ
and noise parameters q from one basis evaluation,

    ℓ(A) = log N(data; X(φ)·A, Σ(q))        (the noise model's own log-likelihood),

and an independence proposal for log A: a mixture of

* the Gaussian conditional of A given φ, N(Â, H⁻¹) with H = XᵀWᵀWX, Â = H⁻¹XᵀWᵀW·data (W the
  noise model's marginal whitening, for a stress-dependent sd taken at the data: exact for iid
  and weighted noise, an approximation for correlated or stress-dependent noise, which only
  changes the acceptance rate), widened by 1.2, mapped to log A (Jacobian Π A_j); a draw with
  some A ≤ 0 is rejected;
* for each pooled log column j: log A_j from the population N(mu_j, sd_j) at the chain's ψ and
  the other amplitudes from the Gaussian conditional given A_j (precision H_oo).

Its density is evaluated exactly, so the sampler's Metropolis–Hastings step keeps the joint
posterior.  Where the likelihood is flat in an amplitude the population component proposes its
tail; where the data pin an amplitude the Gaussian one proposes it.

:func:`amplitude_block` builds it when it applies and says why not otherwise.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Mapping, Sequence

import numpy as np

from ..errors import HbmError
from ..model.linear import structure_of

__all__ = ["AmplitudeBlock", "amplitude_block"]

_LOG2PI = np.log(2.0 * np.pi)
#: weight of the Gaussian-conditional component of the proposal (the rest is split among the
#: population components of the pooled log columns)
_GAUSS_WEIGHT = 0.5
#: proposal covariances × _INFLATE²: a little wider than the conditional (independence proposals
#: whose tails are lighter than the target's mix poorly)
_INFLATE = 1.2


@dataclass
class _Prep:
    """Per-chain state of the block: basis, noise parameters and the Gaussian conditional of A."""

    X: np.ndarray        # (n, P, k) basis at the chains' φ
    q: np.ndarray        # (n, nq) noise parameters (natural units)
    Ahat: np.ndarray     # (n, m) least-squares amplitudes of the log columns
    H: np.ndarray        # (n, m, m) their precision × 1/_INFLATE²
    L: np.ndarray        # (n, m, m) Cholesky factor of H⁻¹ (proposal covariance)
    logdet: np.ndarray   # (n,) log|H⁻¹|^(1/2)
    given: dict = field(default_factory=dict)  # amplitude p -> its conditional (AmplitudeBlock._given)


def _chol_inv(H: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Cholesky factors of H⁻¹ (n, m, m) and log|H⁻¹|^(1/2), with jitter for ill-conditioned rows."""
    m = H.shape[-1]
    scale = np.sqrt(np.einsum("nii->ni", H))
    scale = np.where(scale > 0, scale, 1.0)
    Hs = H / scale[:, :, None] / scale[:, None, :]  # unit diagonal: well scaled
    for jitter in (1e-10, 1e-6, 1e-3, 1e-1):  # nearly collinear columns: a slightly wider proposal
        try:
            Cs = np.linalg.inv(Hs + jitter * np.eye(m))
            Lc = np.linalg.cholesky(0.5 * (Cs + np.swapaxes(Cs, 1, 2)))
            break
        except np.linalg.LinAlgError:
            continue
    else:
        Lc = np.broadcast_to(np.eye(m), H.shape).copy()
    L = Lc / scale[:, :, None]
    logdet = np.sum(np.log(np.einsum("nii->ni", L)), axis=1)
    return L, logdet


def _log_gauss(x: np.ndarray, mean: np.ndarray, L: np.ndarray, logdet: np.ndarray) -> np.ndarray:
    """log N(x; mean, L Lᵀ) row by row (x, mean (n, m), L (n, m, m), logdet = log|L|)."""
    z = np.linalg.solve(L, (x - mean)[:, :, None])[:, :, 0]
    return -0.5 * np.sum(z * z, axis=1) - logdet - 0.5 * x.shape[1] * _LOG2PI


class AmplitudeBlock:
    """A specimen's amplitude columns as a conditional block of the exact fallback (module docstring).

    Parameters
    ----------
    lik : Likelihood
        The specimen's stage-1 likelihood.
    coords : PhiCoordinates-like
        The fallback's coordinates (``theta_of(y) -> (θ, ok)`` in the likelihood's columns).
    log_columns : mapping y column -> structure column
        Columns of ``y`` that are the log of an amplitude column of the model's structure.
    structure : LinearStructure, optional
        Default :func:`hbm.model.linear.structure_of` of the likelihood's model.
    """

    def __init__(self, lik, coords, log_columns: Mapping[int, int], structure=None) -> None:
        self.lik, self.coords = lik, coords
        self.structure = structure_of(lik.model) if structure is None else structure
        self.columns = tuple(sorted(int(j) for j in log_columns))
        self.amp = np.array([int(log_columns[j]) for j in self.columns])  # structure column of each
        if sorted(self.amp.tolist()) != list(range(self.structure.n_columns)):
            raise HbmError("AmplitudeBlock: every amplitude column of the model needs a log column in y")

    # -- the block's likelihood -------------------------------------------------------------------
    def _theta(self, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Model rows (natural units) of the fibre points of ``y`` and whether each is in the support."""
        theta, ok = self.coords.theta_of(np.asarray(y, float))
        ok = ok & self.lik.in_box(theta)
        return self.lik.model_theta(theta), ok

    def prepare(self, y: np.ndarray) -> _Prep:
        """The basis at the chains' φ (one model pass per row) and the Gaussian conditional of A."""
        theta, _ = self.coords.theta_of(np.asarray(y, float))
        rows = self.lik.model_theta(theta)
        X = np.asarray(self.structure.basis(self.lik.loading, rows), float)
        q = self.lik.to_natural(theta)[:, self.lik.n_model:]
        noise = self.lik.noise_model
        # the proposal must not depend on the block's current values: a stress-dependent sd is taken
        # at the data, not at the current amplitudes
        obs = np.broadcast_to(self.lik.observed, (X.shape[0], X.shape[1]))
        sd = noise.sd(q, obs.copy() if noise.needs_model_stress else None)
        Xw = X[:, :, self.amp] / sd[:, :, None]
        H = np.einsum("npi,npj->nij", Xw, Xw)
        b = np.einsum("npi,np->ni", Xw, obs / sd)
        L, logdet = _chol_inv(H / _INFLATE**2)
        Ahat = np.einsum("nij,nkj,nk->ni", L, L, b) / _INFLATE**2  # H⁻¹ b
        return _Prep(X, q, Ahat, H / _INFLATE**2, L, logdet)

    def log_likelihood(self, prep: _Prep, y: np.ndarray, rows: np.ndarray) -> np.ndarray:
        """The specimen's log-likelihood at ``y`` (the chains ``rows``' φ and q): X(φ)·A(y) through the
        noise model; −inf where ``y`` has no parameters in the box."""
        model_rows, ok = self._theta(y)
        out = np.full(y.shape[0], -np.inf)
        if ok.any():
            A = self.structure.amplitudes(model_rows[ok])
            stress = np.einsum("npk,nk->np", prep.X[rows[ok]], A)
            with np.errstate(all="ignore"):
                v = self.lik.noise_model.loglik(prep.q[rows[ok]], stress, overwrite=True)
            out[ok] = np.where(np.isfinite(v), v, -np.inf)
        return out

    def select(self, prep: _Prep, other: _Prep, mask: np.ndarray) -> _Prep:
        """Rows of ``other`` where ``mask``, of ``prep`` elsewhere (a chain moved its φ)."""
        m = np.asarray(mask, bool)
        pick = [np.where(m.reshape((-1,) + (1,) * (a.ndim - 1)), b, a)
                for a, b in ((prep.X, other.X), (prep.q, other.q), (prep.Ahat, other.Ahat), (prep.H, other.H),
                             (prep.L, other.L), (prep.logdet, other.logdet))]
        return _Prep(*pick)

    # -- the independence proposal ----------------------------------------------------------------
    def _weights(self, population: Mapping[int, tuple]) -> list[tuple[int | None, float]]:
        comps = [(None, _GAUSS_WEIGHT if population else 1.0)]
        comps += [(p, (1.0 - _GAUSS_WEIGHT) / len(population)) for p in sorted(population)]
        return comps

    @staticmethod
    def _given(prep: _Prep, p: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """The Gaussian conditional of the other amplitudes given amplitude p: (others, beta, L, logdet)
        with mean Âₒ + beta·(A_p − Â_p) and covariance (H_oo)⁻¹ = L Lᵀ (computed once per prepare)."""
        if p not in prep.given:
            prep.given[p] = AmplitudeBlock._conditional(prep, p)
        return prep.given[p]

    @staticmethod
    def _conditional(prep: _Prep, p: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        m = prep.H.shape[1]
        o = np.array([i for i in range(m) if i != p], int)
        Hoo = prep.H[:, o][:, :, o]
        L, logdet = _chol_inv(Hoo)
        beta = -np.einsum("nij,nkj,nk->ni", L, L, prep.H[:, o, p])  # −H_oo⁻¹ H_op
        return o, beta, L, logdet

    def propose(self, prep: _Prep, rng: np.random.Generator, population: Mapping[int, tuple]) -> np.ndarray:
        """log A for every chain from the mixture (module docstring); NaN where a drawn A is ≤ 0."""
        n, m = prep.Ahat.shape
        comps = self._weights(population)
        pick = rng.choice(len(comps), n, p=[w for _, w in comps])
        A = prep.Ahat + np.einsum("nij,nj->ni", prep.L, rng.standard_normal((n, m)))
        for c, (p, _) in enumerate(comps):
            sel = pick == c
            if p is None or not sel.any():
                continue
            mu, sd = (np.asarray(v, float)[sel] for v in population[p])
            u = mu + sd * rng.standard_normal(sel.sum())
            o, beta, L, _ = (v[sel] if k else v for k, v in enumerate(self._given(prep, p)))
            a = np.exp(u)
            Ao = (prep.Ahat[sel][:, o] + beta * (a - prep.Ahat[sel, p])[:, None]
                  + np.einsum("nij,nj->ni", L, rng.standard_normal((sel.sum(), o.size))))
            A[sel, p] = a
            A[np.ix_(np.nonzero(sel)[0], o)] = Ao
        with np.errstate(invalid="ignore", divide="ignore"):
            return np.where(A > 0, np.log(np.where(A > 0, A, 1.0)), np.nan)

    def log_q(self, prep: _Prep, yb: np.ndarray, population: Mapping[int, tuple]) -> np.ndarray:
        """log density of :meth:`propose` at log A = ``yb`` (n, m), Jacobian of A = e^y included."""
        yb = np.asarray(yb, float)
        A = np.exp(yb)
        jac = yb.sum(axis=1)
        terms = []
        for p, w in self._weights(population):
            if p is None:
                terms.append(np.log(w) + _log_gauss(A, prep.Ahat, prep.L, prep.logdet) + jac)
                continue
            mu, sd = (np.asarray(v, float) for v in population[p])
            o, beta, L, logdet = self._given(prep, p)
            mean = prep.Ahat[:, o] + beta * (A[:, p] - prep.Ahat[:, p])[:, None]
            lu = -0.5 * ((yb[:, p] - mu) / sd) ** 2 - np.log(sd) - 0.5 * _LOG2PI
            terms.append(np.log(w) + lu + _log_gauss(A[:, o], mean, L, logdet) + yb[:, o].sum(axis=1))
        t = np.stack(terms, axis=1)
        mx = np.max(t, axis=1)
        with np.errstate(invalid="ignore"):
            return mx + np.log(np.sum(np.exp(t - mx[:, None]), axis=1))


def amplitude_block(lik, coords, names_y: Sequence[str], probe_y: np.ndarray,
                    rng: np.random.Generator) -> tuple[AmplitudeBlock | None, str]:
    """The amplitude block of one specimen, or None and the reason it does not apply.

    It applies when the model has a linear structure, every amplitude column has a ``log_<column>``
    column in the fallback's coordinates ``names_y`` and the basis does not change along the fibre
    of the amplitudes (checked at ``probe_y`` rows with their log amplitudes exchanged: the
    likelihood must depend on them through X(φ)·A only).
    """
    structure = structure_of(lik.model)
    if structure is None:
        return None, "the model has no linear amplitudes"
    cols = {j: structure.columns.index(n[4:]) for j, n in enumerate(names_y)
            if n.startswith("log_") and n[4:] in structure.columns}
    if sorted(cols.values()) != list(range(structure.n_columns)):
        return None, "not every amplitude column has a log column in the fallback's coordinates"
    block = AmplitudeBlock(lik, coords, cols, structure)
    probe = np.asarray(probe_y, float)
    swapped = probe.copy()
    swapped[:, list(cols)] = probe[rng.permutation(probe.shape[0])][:, list(cols)]
    rows, ok = block._theta(probe)
    rows2, ok2 = block._theta(swapped)
    both = ok & ok2
    if not both.any():
        return None, "no probe point of the fibre check lies in the box"
    X1 = np.asarray(structure.basis(lik.loading, rows[both]), float)
    X2 = np.asarray(structure.basis(lik.loading, rows2[both]), float)
    if not np.allclose(X1, X2, rtol=1e-9, atol=1e-12 * np.abs(X1).max()):
        return None, "the model's basis depends on the parameters along the amplitudes' fibre"
    return block, ""
