"""The population model of the hierarchical layer: density, hyperprior and the vectorised importance ratios.

Model
-----
Each specimen ``i`` has parameters θ_i (the stage-1 columns).  A chosen subset of them (the
*pooled* parameters, by default all) follows a population distribution:

* each pooled parameter is mapped to a transformed coordinate ``z = g_k(θ_k)``:

  ``"identity"``  z = θ.
  ``"log"``       z = log θ (needs a box with lower bound > 0).  For positive scales
                  (moduli P1, GF, GM) whose plausible values span decades: a normal in log
                  space is a log-normal population, and "sd" reads as a relative spread.
  ``"logit"``     z = log(u / (1 − u)),  u = (θ − lo)/(hi − lo) ("logit on the box").  For
                  bounded fractions such as VOLF and for parameters that pile up at a box
                  edge: the transformed space is the whole real line, so the population is
                  automatically confined to the box and *no truncation is needed*.

* ``z_k ~ Normal(mu_k, sd_k²)`` truncated to the transformed box ``[g(lo), g(hi)]``
  (no-op for logit), independently over k, or jointly normal with a full covariance over
  a chosen subset (``full_cov``; those parameters must use ``"logit"`` so that the box
  truncation of a correlated normal, which has no closed form, never arises).

* The density is a density **in θ**: p(θ|ψ) = Π_k N_trunc(g_k(θ_k); mu_k, sd_k) · |g_k'(θ_k)|.

Hyperpriors (ψ = (mu, sd[, correlations]))
-------------------------------------------
* ``mu_k`` uniform on the transformed box ``[g(lo), g(hi)]``; for logit (infinite box) on
  ``[-logit_range, logit_range]`` (default 8, i.e. u ∈ [3.4e-4, 0.99966]).  ``mu_bounds``
  overrides it per parameter (in transformed units).
* ``sd_k`` on ``[sd_range[0]·w_k, sd_range[1]·w_k]`` with ``w_k`` the width of the mu range;
  ``sd_prior="loguniform"`` (default: scale-free, uninformative about the order of magnitude
  of the spread between specimens) or ``"halfnormal"`` (scale ``w_k/2``, truncated to the
  same interval; favours small spreads).
* correlations (``full_cov``): the correlation matrix is built from its canonical partial
  correlations (CPCs, the Cholesky-factor parametrisation of Lewandowski et al.), each
  uniform on ``[-0.99, 0.99]``.  For two parameters this is a uniform correlation; for more
  it is a simple, proper, documented prior (not LKJ).

Importance ratios as a matrix product
-------------------------------------
The layer reuses stage-1 samples θ_ij through the ratios r_ij(ψ) = p(θ_ij|ψ) / p_prior(θ_ij)
(:mod:`hbm.samplers.hierarchical.reuse`).  ``log r`` is a quadratic form in z, so for the whole ψ
population at once it is the matrix product ``coef(ψ) (n_ψ, n_f) @ F(θ)ᵀ (n_f, N)`` with features
F = [z, z², z_k z_l (pairs in the full-covariance block)] plus per-ψ constants (normal and
truncation normalisers by :func:`hbm.samplers.truncnorm.log_mass`) and per-sample constants (Jacobian,
prior).  Samples are processed in chunks with an online log-sum-exp, so memory is bounded and
time is linear in N.  The per-specimen importance ESS (Σr)²/Σr² comes out of the same pass.

Non-uniform stage-1 priors of the pooled columns (``log_prior``)
----------------------------------------------------------------
The pooled columns need not be stage-1 parameters: a caller may append derived features
(e.g. products of parameters that the data identify) as extra columns, pool those, and pass
``log_prior[i]`` = the log density of each sample's pooled columns under the stage-1 prior
(in the column space).  It replaces −Σ log(hi − lo) in r_ij; everything else (transform
Jacobian, truncation to ``bounds``, which are then the features' support hull) is unchanged.
The unpooled columns keep their stage-1 prior *conditional on* the pooled ones, so a new
specimen's unpooled columns are drawn from that conditional by the caller.

This module is sampler-layer code: it knows nothing about muscles.
"""

from __future__ import annotations

from typing import Mapping, Sequence

import numpy as np

from ...runtime.blas import single_thread_blas
from ...errors import HbmError
from ..truncnorm import log_mass, ppf

__all__ = ["HierarchicalModel", "TRANSFORMS", "draw_population", "kernel_bandwidth"]

TRANSFORMS = ("identity", "log", "logit")
_LOG2PI = np.log(2.0 * np.pi)
_CPC_MAX = 0.99
# Stage-1 samples sitting exactly on a box edge would map to ±inf under log/logit.
_EDGE = 1e-12


# --------------------------------------------------------------------------------------
# small numerical helpers
# --------------------------------------------------------------------------------------
def _cpc_to_corr_chol(cpc: np.ndarray, m: int) -> np.ndarray:
    """Cholesky factors (n, m, m) of correlation matrices from canonical partial correlations.

    ``cpc`` is (n, m(m−1)/2), ordered row by row of the strict lower triangle (i > j).
    Row i of L: L_ij = z_ij·sqrt(1 − Σ_{k<j} L_ik²) for j < i, L_ii = sqrt(1 − Σ_{k<i} L_ik²).
    Unit-norm rows ⇒ L Lᵀ has a unit diagonal and is positive definite for |z| < 1.
    """
    n = cpc.shape[0]
    L = np.zeros((n, m, m))
    L[:, 0, 0] = 1.0
    pos = 0
    for i in range(1, m):  # loops over the (small) block dimension only, not over particles
        rem = np.ones(n)
        for j in range(i):
            z = cpc[:, pos]
            pos += 1
            L[:, i, j] = z * np.sqrt(rem)
            rem = rem - L[:, i, j] ** 2
        L[:, i, i] = np.sqrt(np.maximum(rem, 0.0))
    return L


# --------------------------------------------------------------------------------------
# the population model
# --------------------------------------------------------------------------------------
class HierarchicalModel:
    """Population model, hyperprior and the vectorised importance-sampling likelihood.

    Parameters
    ----------
    names : sequence of str
        Names of *all* stage-1 columns.
    bounds : array_like, shape (d, 2)
        Uniform prior box used at stage 1 (all columns).
    pooled : sequence of str, optional
        Columns given a population distribution (default all).  The others keep their
        stage-1 uniform prior (their ratio is 1) and are only carried along.
    transforms : mapping name -> {"identity","log","logit"}, optional
        Default "identity", except "logit" for parameters in ``full_cov``.
    full_cov : sequence of str, optional
        Pooled parameters that share a full covariance matrix (≥ 2 names, logit transform).
    sd_prior : {"loguniform", "halfnormal"}
    sd_range : (float, float)
        sd_k ∈ [sd_range[0]·w_k, sd_range[1]·w_k], w_k the width of mu_k's range.
    mu_bounds : mapping name -> (lo, hi), optional
        Range of the uniform prior on mu_k, in transformed units.
    logit_range : float
        Default mu range ``[-logit_range, logit_range]`` for logit parameters.
    fix : mapping hyper-name -> value, optional
        Hold hyperparameters fixed (e.g. ``{"sd_x": 1.0}``); ``sd_*`` values are sds.
    """

    def __init__(
        self,
        names: Sequence[str],
        bounds,
        *,
        pooled: Sequence[str] | None = None,
        transforms: Mapping[str, str] | None = None,
        full_cov: Sequence[str] | None = None,
        sd_prior: str = "loguniform",
        sd_range: tuple[float, float] = (1e-3, 1.0),
        mu_bounds: Mapping[str, tuple[float, float]] | None = None,
        logit_range: float = 8.0,
        fix: Mapping[str, float] | None = None,
    ) -> None:
        self.all_names = [str(n) for n in names]
        bounds = np.asarray(bounds, dtype=float)
        if bounds.shape != (len(self.all_names), 2):
            raise HbmError(
                f"hierarchical: bounds must have shape ({len(self.all_names)}, 2) matching names, "
                f"got {bounds.shape}"
            )
        if not np.all(np.isfinite(bounds)) or np.any(bounds[:, 1] <= bounds[:, 0]):
            raise HbmError("hierarchical: bounds must be finite with lower < upper for every parameter")
        self.all_bounds = bounds
        pooled = list(self.all_names) if pooled is None else [str(p) for p in pooled]
        unknown = [p for p in pooled if p not in self.all_names]
        if unknown or not pooled:
            raise HbmError(f"hierarchical: pooled parameters {unknown or pooled} are not among names {self.all_names}")
        self.names = pooled
        self.cols = np.array([self.all_names.index(p) for p in pooled])
        self.d = len(pooled)
        self.lo = bounds[self.cols, 0]
        self.hi = bounds[self.cols, 1]

        full_cov = [] if full_cov is None else [str(p) for p in full_cov]
        bad = [p for p in full_cov if p not in pooled]
        if bad:
            raise HbmError(f"hierarchical: full_cov names {bad} are not pooled parameters")
        if len(full_cov) == 1:
            raise HbmError("hierarchical: full_cov needs at least two parameter names")
        self.full_cov = full_cov
        self.S = np.array([pooled.index(p) for p in full_cov], dtype=int)
        self.m = len(self.S)

        transforms = dict(transforms or {})
        unknown = [k for k in transforms if k not in self.all_names]
        if unknown:
            raise HbmError(f"hierarchical: transforms given for unknown parameters {unknown}")
        kinds = []
        for p in pooled:
            kind = transforms.get(p, "logit" if p in full_cov else "identity")
            if kind not in TRANSFORMS:
                raise HbmError(f"hierarchical: transform for {p!r} must be one of {TRANSFORMS}, got {kind!r}")
            if p in full_cov and kind != "logit":
                raise HbmError(
                    f"hierarchical: full_cov parameter {p!r} needs transform 'logit' (a correlated normal "
                    f"truncated to a box has no closed-form normaliser), got {kind!r}"
                )
            if kind == "log" and self.lo[pooled.index(p)] <= 0:
                raise HbmError(
                    f"hierarchical: transform 'log' for {p!r} needs a positive lower bound, box starts at "
                    f"{self.lo[pooled.index(p)]:g} (use 'logit' or narrow the box)"
                )
            kinds.append(kind)
        self.kinds = kinds
        self.transforms = dict(zip(pooled, kinds))

        # transformed box (truncation) and the hyperprior range of mu
        zlo, zhi = np.empty(self.d), np.empty(self.d)
        for k, kind in enumerate(kinds):
            if kind == "identity":
                zlo[k], zhi[k] = self.lo[k], self.hi[k]
            elif kind == "log":
                zlo[k], zhi[k] = np.log(self.lo[k]), np.log(self.hi[k])
            else:
                zlo[k], zhi[k] = -np.inf, np.inf
        self.zlo, self.zhi = zlo, zhi
        self._truncated = np.isfinite(zlo) | np.isfinite(zhi)  # columns whose population is truncated to the box
        mu_lo = np.where(np.isfinite(zlo), zlo, -logit_range)
        mu_hi = np.where(np.isfinite(zhi), zhi, logit_range)
        for p, (a, b) in dict(mu_bounds or {}).items():
            if p not in pooled or not b > a:
                raise HbmError(f"hierarchical: mu_bounds[{p!r}] must name a pooled parameter with lo < hi")
            mu_lo[pooled.index(p)], mu_hi[pooled.index(p)] = a, b
        self.mu_lo, self.mu_hi = mu_lo, mu_hi
        width = mu_hi - mu_lo
        if not (0 < sd_range[0] < sd_range[1]):
            raise HbmError(f"hierarchical: sd_range must satisfy 0 < lo < hi, got {sd_range}")
        self.sd_lo, self.sd_hi = sd_range[0] * width, sd_range[1] * width
        if sd_prior not in ("loguniform", "halfnormal"):
            raise HbmError(f"hierarchical: sd_prior must be 'loguniform' or 'halfnormal', got {sd_prior!r}")
        self.sd_prior = sd_prior

        # Numerical centring: features are standardised on the mu range so that the expanded
        # quadratic form (z²/sd² − 2 z mu/sd² + mu²/sd²) does not lose digits to cancellation.
        self.c = 0.5 * (mu_lo + mu_hi)
        self.s = 0.5 * width

        # hyperparameter layout: mu (d), sd (d), cpc (q)
        self.pairs = [(self.S[i], self.S[j]) for i in range(self.m) for j in range(i)]
        self.q = len(self.pairs)
        self.hyper_names = (
            [f"mu_{p}" for p in pooled]
            + [f"sd_{p}" for p in pooled]
            + [f"corr_{pooled[i]}_{pooled[j]}" for i, j in self.pairs]
        )
        fix = dict(fix or {})
        bad = [k for k in fix if k not in self.hyper_names]
        if bad:
            raise HbmError(f"hierarchical: fix names {bad} are not hyperparameters {self.hyper_names}")
        self.fix = fix
        self.free = [i for i, n in enumerate(self.hyper_names) if n not in fix]
        if not self.free:
            raise HbmError("hierarchical: every hyperparameter is fixed; nothing to sample")

        # Box of the sampled coordinates: mu as is, sd as log sd (log-uniform prior ⇔ uniform
        # box) or as sd (half-normal prior is then added to the target), CPC in [-0.99, 0.99].
        if sd_prior == "loguniform":
            sbox = np.column_stack([np.log(self.sd_lo), np.log(self.sd_hi)])
        else:
            sbox = np.column_stack([self.sd_lo, self.sd_hi])
        box = np.vstack([np.column_stack([mu_lo, mu_hi]), sbox, np.tile([-_CPC_MAX, _CPC_MAX], (self.q, 1))])
        self.full_box = box
        self.box = box[self.free]
        self.free_names = [self.hyper_names[i] for i in self.free]
        # default full vector with fixed values in sampler coordinates
        self._fixed_raw = np.zeros(len(self.hyper_names))
        for k, v in fix.items():
            i = self.hyper_names.index(k)
            v = float(v)
            if self.d <= i < 2 * self.d:
                if not v > 0:
                    raise HbmError(f"hierarchical: fixed {k} must be > 0, got {v}")
                v = np.log(v) if sd_prior == "loguniform" else v
            self._fixed_raw[i] = v

    # ---- coordinates --------------------------------------------------------------------
    def expand(self, x: np.ndarray) -> np.ndarray:
        """Sampler coordinates of the free hyperparameters (n, n_free) -> full raw (n, 2d+q)."""
        x = np.atleast_2d(np.asarray(x, float))
        out = np.tile(self._fixed_raw, (x.shape[0], 1))
        out[:, self.free] = x
        return out

    def natural(self, raw: np.ndarray) -> np.ndarray:
        """Raw coordinates (n, 2d+q) -> (mu, sd, corr) named by ``hyper_names``."""
        raw = np.atleast_2d(raw)
        out = raw.copy()
        if self.sd_prior == "loguniform":
            out[:, self.d : 2 * self.d] = np.exp(raw[:, self.d : 2 * self.d])
        if self.q:
            R = self._corr(raw)
            out[:, 2 * self.d :] = np.stack([R[:, a, b] for a, b in self._block_pairs()], axis=1)
        return out

    def _block_pairs(self):
        return [(i, j) for i in range(self.m) for j in range(i)]

    def _corr(self, raw: np.ndarray) -> np.ndarray:
        L = _cpc_to_corr_chol(raw[:, 2 * self.d :], self.m)
        return L @ np.swapaxes(L, 1, 2)

    def log_hyperprior_correction(self, raw: np.ndarray) -> np.ndarray:
        """log hyperprior minus log of the uniform density on the sampler box (0 if loguniform)."""
        if self.sd_prior == "loguniform":
            return np.zeros(raw.shape[0])
        sd = raw[:, self.d : 2 * self.d]
        scale = (self.mu_hi - self.mu_lo) / 2.0
        # half-normal truncated to [sd_lo, sd_hi], relative to the uniform on the same interval
        lognorm = log_mass(self.sd_lo / scale, self.sd_hi / scale)
        logpdf = -0.5 * (sd / scale) ** 2 - np.log(scale) - 0.5 * _LOG2PI - lognorm
        logu = -np.log(self.sd_hi - self.sd_lo)
        free_sd = np.array([f"sd_{p}" not in self.fix for p in self.names])
        return np.sum((logpdf - logu)[:, free_sd], axis=1)

    # ---- transforms ---------------------------------------------------------------------
    def to_z(self, theta: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Pooled columns of stage-1 samples -> (z (N, d), Σ_k log|g_k'(θ_k)| (N,))."""
        th = np.asarray(theta, float)[:, self.cols]
        z = np.empty_like(th)
        logjac = np.zeros(th.shape[0])
        for k, kind in enumerate(self.kinds):  # loop over parameters, vectorised over samples
            x = th[:, k]
            if kind == "identity":
                z[:, k] = x
            elif kind == "log":
                x = np.maximum(x, self.lo[k])
                z[:, k] = np.log(x)
                logjac -= np.log(x)
            else:
                w = self.hi[k] - self.lo[k]
                u = np.clip((x - self.lo[k]) / w, _EDGE, 1.0 - _EDGE)
                z[:, k] = np.log(u) - np.log1p(-u)
                logjac -= np.log(u) + np.log1p(-u) + np.log(w)
        return z, logjac

    def from_z(self, z: np.ndarray) -> np.ndarray:
        """Inverse transform (n, d) -> θ of the pooled columns."""
        th = np.empty_like(z)
        for k, kind in enumerate(self.kinds):
            if kind == "identity":
                th[:, k] = z[:, k]
            elif kind == "log":
                th[:, k] = np.exp(z[:, k])
            else:
                th[:, k] = self.lo[k] + (self.hi[k] - self.lo[k]) / (1.0 + np.exp(-z[:, k]))
        return np.clip(th, self.lo, self.hi)

    def features(self, theta: np.ndarray, log_prior: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """Quadratic features F (N, n_f) and per-sample constants (N,) of log r = coef·F + const.

        ``log_prior`` (N,): log density of the pooled columns of each sample under the stage-1
        prior, in the column (θ) space; default the uniform box, −Σ log(hi − lo).
        """
        theta = np.asarray(theta, float)
        if theta.ndim != 2 or theta.shape[1] != len(self.all_names):
            raise HbmError(
                f"hierarchical: stage-1 samples must have shape (N, {len(self.all_names)}), got {theta.shape}"
            )
        z, logjac = self.to_z(theta)
        zt = (z - self.c) / self.s
        cross = [zt[:, a] * zt[:, b] for a, b in self.pairs]
        F = np.column_stack([zt, zt * zt] + cross) if cross else np.column_stack([zt, zt * zt])
        # r = p(θ|ψ)/p0(θ) with p(θ|ψ) = N(z)·|g'(θ)| (logjac) and the density of z that of z̃ / Π s.
        if log_prior is None:
            log_p0 = -np.sum(np.log(self.hi - self.lo))
        else:
            log_p0 = np.asarray(log_prior, float)
            if log_p0.shape != (theta.shape[0],) or not np.all(np.isfinite(log_p0)):
                raise HbmError(f"hierarchical: log_prior must be {theta.shape[0]} finite values (one per "
                               f"stage-1 sample), got shape {log_p0.shape}")
        const = logjac - log_p0 - np.sum(np.log(self.s))
        return F, const

    def coefficients(self, raw: np.ndarray, extra_var: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """Coefficients (n_ψ, n_f) and constants (n_ψ,) of the quadratic form, for all ψ at once.

        ``extra_var`` (d,), in transformed units², is added to the population covariance
        (S → S + diag(extra_var)) before truncation to the box: the kernel-smoothed estimator
        (see the module docstring) evaluates this widened population at the stage-1 samples.
        """
        raw = np.atleast_2d(raw)
        n, d = raw.shape[0], self.d
        mu = (raw[:, :d] - self.c) / self.s
        sd = raw[:, d : 2 * d]
        sd = np.exp(sd) if self.sd_prior == "loguniform" else sd
        sdt = sd / self.s
        if not self.m and extra_var is None:
            return self._diagonal_coefficients(mu, sdt)
        ext = None
        if extra_var is not None:
            ext = np.asarray(extra_var, float) / self.s**2  # standardised units
            if ext.shape != (d,) or np.any(ext < 0) or not np.all(np.isfinite(ext)):
                raise HbmError(f"hierarchical: extra_var must be {d} finite values >= 0, got {extra_var!r}")
        prec = np.zeros((n, d))
        lin = np.empty((n, d))
        diag = np.ones(d, bool)
        diag[self.S] = False
        if ext is not None:  # independent Gaussians: the variances add
            sdt = sdt.copy()
            sdt[:, diag] = np.sqrt(sdt[:, diag] ** 2 + ext[diag])
        prec[:, diag] = 1.0 / sdt[:, diag] ** 2
        lin[:, diag] = mu[:, diag] * prec[:, diag]
        # −½ μᵀPμ − ½ log det Σ − d/2 log 2π − log(truncation mass)
        const = -0.5 * np.sum(mu[:, diag] ** 2 * prec[:, diag], axis=1) - np.sum(np.log(sdt[:, diag]), axis=1)
        a = (self.zlo[diag] - self.c[diag]) / self.s[diag]
        b = (self.zhi[diag] - self.c[diag]) / self.s[diag]
        const -= np.sum(log_mass((a - mu[:, diag]) / sdt[:, diag], (b - mu[:, diag]) / sdt[:, diag]), axis=1)
        const -= 0.5 * d * _LOG2PI
        cross = np.zeros((n, self.q))
        if self.m:
            Lc = _cpc_to_corr_chol(raw[:, 2 * d :], self.m)
            ss = sdt[:, self.S]
            Lcov = ss[:, :, None] * Lc  # Cholesky factor of D R D
            if ext is not None:  # Cholesky factor of D R D + diag(extra)
                Lcov = np.linalg.cholesky(Lcov @ np.swapaxes(Lcov, 1, 2) + np.diag(ext[self.S]))
            eye = np.broadcast_to(np.eye(self.m), Lcov.shape)
            Linv = np.linalg.solve(Lcov, eye)
            P = np.swapaxes(Linv, 1, 2) @ Linv  # Σ⁻¹ = L⁻ᵀ L⁻¹
            muS = mu[:, self.S]
            lin[:, self.S] = np.einsum("nab,nb->na", P, muS)
            prec[:, self.S] = np.diagonal(P, axis1=1, axis2=2)
            const += -0.5 * np.einsum("na,na->n", muS, lin[:, self.S])
            const -= np.sum(np.log(np.diagonal(Lcov, axis1=1, axis2=2)), axis=1)
            idx = {(int(self.S[i]), int(self.S[j])): (i, j) for i in range(self.m) for j in range(self.m)}
            for t, (ka, kb) in enumerate(self.pairs):
                i, j = idx[(int(ka), int(kb))]
                cross[:, t] = -P[:, i, j]  # off-diagonal appears twice in zᵀPz
        coef = np.concatenate([lin, -0.5 * prec, cross], axis=1)
        return coef, const

    def _log_truncation(self, mu: np.ndarray, sdt: np.ndarray) -> np.ndarray:
        """log of each independent column's mass inside the transformed box, (n_ψ, d): computed only where
        the box is finite (elsewhere exactly 0)."""
        lnm = np.zeros(mu.shape)
        t = self._truncated
        if t.any():
            a = (self.zlo[t] - self.c[t]) / self.s[t]
            b = (self.zhi[t] - self.c[t]) / self.s[t]
            lnm[:, t] = log_mass((a - mu[:, t]) / sdt[:, t], (b - mu[:, t]) / sdt[:, t])
        return lnm

    def _diagonal_coefficients(self, mu: np.ndarray, sdt: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """:meth:`coefficients` of independent columns (no full covariance, no extra variance): the same
        numbers by fewer operations (the joint sampler calls it for every ψ move); the truncation mass
        is computed only where the transformed box is finite (elsewhere it is exactly 0)."""
        d = self.d
        prec = 1.0 / sdt**2
        const = -0.5 * np.sum(mu**2 * prec, axis=1) - np.sum(np.log(sdt), axis=1)
        lnm = self._log_truncation(mu, sdt)
        const -= np.sum(lnm, axis=1)
        const -= 0.5 * d * _LOG2PI
        return np.concatenate([mu * prec, -0.5 * prec], axis=1), const

    def column_terms(self, raw: np.ndarray, SF: np.ndarray, n: int) -> np.ndarray:
        """Σ over ``n`` samples of log r split by pooled column, (n_ψ, d), for a population without full
        covariance: column k's coefficients times its two summed features ``SF`` (n_ψ, n_f) plus n times
        its constant (the per-sample constants are left out).  Their sum over k is coef·SF + n·cconst of
        :meth:`coefficients`; given the samples the columns' populations are independent, so a sampler
        can move each (mu_k, sd_k) alone."""
        raw = np.atleast_2d(raw)
        d = self.d
        mu = (raw[:, :d] - self.c) / self.s
        sd = raw[:, d : 2 * d]
        sdt = (np.exp(sd) if self.sd_prior == "loguniform" else sd) / self.s
        prec = 1.0 / sdt**2
        lnm = self._log_truncation(mu, sdt)
        const = -0.5 * mu**2 * prec - np.log(sdt) - lnm - 0.5 * _LOG2PI
        return mu * prec * SF[:, :d] - 0.5 * prec * SF[:, d : 2 * d] + n * const

    def log_ratio_stats(
        self, F: np.ndarray, const: np.ndarray, coef: np.ndarray, cconst: np.ndarray, chunk_bytes: float = 4e6
    ) -> tuple[np.ndarray, np.ndarray]:
        """log Σ_j exp(coef_r·F_j + cconst_r + const_j) and its ESS, for every row r of ``coef``.

        Chunks over the samples j with an online log-sum-exp (running max per row), so memory
        is bounded by ``chunk_bytes`` and time is linear in the number of samples.  Both
        additive constants and the running max are folded into the matrix product through two
        augmented columns, so each chunk costs one GEMM, one max, one exp and two reductions.
        """
        n = coef.shape[0]
        N = F.shape[0]
        chunk = int(max(256, chunk_bytes // (8 * max(n, 1))))
        Fa = np.empty((F.shape[1] + 2, N))
        Fa[:-2] = F.T
        Fa[-2] = 1.0
        Fa[-1] = const
        Ca = np.empty((n, F.shape[1] + 2))
        Ca[:, :-2] = coef
        Ca[:, -1] = 1.0
        with single_thread_blas():
            M, S1, S2 = self._lse_loop(Fa, Ca, cconst, N, chunk)
        with np.errstate(divide="ignore", invalid="ignore"):
            lse = M + np.log(S1)
            ess = np.where(S2 > 0, S1 * S1 / S2, 0.0)
        lse = np.where(np.isfinite(lse), lse, -np.inf)
        return lse, ess

    @staticmethod
    def _lse_loop(Fa, Ca, cconst, N, chunk):
        n = Ca.shape[0]
        M = np.full(n, -np.inf)  # running max of the log terms per row
        S1 = np.zeros(n)  # Σ exp(term − M)
        S2 = np.zeros(n)  # Σ exp(2(term − M))
        ones = np.ones(chunk)
        for start in range(0, N, chunk):
            ref = np.where(np.isfinite(M), M, 0.0)
            Ca[:, -2] = cconst - ref
            lr = Ca @ Fa[:, start : start + chunk]  # log terms relative to the running max
            mc = lr.max(axis=1)
            up = np.where(np.isfinite(M), np.maximum(mc, 0.0), mc)  # raise of the max (≥ 0)
            up = np.where(np.isfinite(up), up, 0.0)
            if np.any(up != 0.0):
                lr -= up[:, None]
            # Clamp far-underflowing terms (≤ e⁻⁷⁰⁰ relative to the max: negligible) because exp
            # of huge negative numbers takes a slow denormal path.
            np.maximum(lr, -700.0, out=lr)
            np.exp(lr, out=lr)
            with np.errstate(over="ignore", invalid="ignore"):
                scale = np.where(np.isfinite(M), np.exp(-up), 0.0)
            S1 = S1 * scale + lr @ ones[: lr.shape[1]]  # GEMV: faster than a strided row sum
            S2 = S2 * (scale * scale) + np.einsum("ij,ij->i", lr, lr)
            M = np.where(np.isfinite(mc), ref + up, M)
        return M, S1, S2

    def kernel_variance(self, theta: np.ndarray, bandwidth: str | float = "silverman") -> tuple[float, np.ndarray]:
        """(h, h²·diag Σ) of the smoothing kernel for one specimen's stage-1 samples ``theta``.

        Σ is the sample covariance of the pooled columns in the transformed space (diagonal),
        h the bandwidth factor of :func:`kernel_bandwidth` for N samples in d = len(pooled) dims.
        """
        theta = np.asarray(theta, float)
        h = kernel_bandwidth(theta.shape[0], self.d, bandwidth)
        z, _ = self.to_z(theta)
        return h, h * h * z.var(axis=0, ddof=1)

    def log_mean_ratio(
        self, theta: np.ndarray, raw: np.ndarray, kernel_var: np.ndarray | None = None, chunk_bytes: float = 4e6,
        log_prior: np.ndarray | None = None,
    ) -> tuple[np.ndarray, np.ndarray]:
        """log p̂(d|ψ) − log Z and the importance ESS for one specimen, at every ψ row of ``raw``.

        ``kernel_var=None``: raw ratios, log mean_j p(θ_j|ψ)/p_prior(θ_j).  Otherwise the
        kernel-smoothed estimator (module docstring) with kernel covariance diag(kernel_var),
        e.g. from :meth:`kernel_variance`.  ``log_prior``: per-sample stage-1 prior log density
        of the pooled columns (default uniform box), as in :meth:`features`.
        """
        F, c = self.features(theta, log_prior)
        coef, cconst = self.coefficients(raw, kernel_var)
        lse, ess = self.log_ratio_stats(F, c, coef, cconst, chunk_bytes)
        return lse - np.log(F.shape[0]), ess

    def log_density(self, theta: np.ndarray, raw: np.ndarray, weights: np.ndarray | None = None) -> np.ndarray:
        """log Σ_m w_m p(θ|ψ_m) for θ (n, all columns), ψ raw (M, ·): population predictive density.

        Only the pooled columns have a population density; the result is the density of those
        columns (the others are not modelled).  ``weights`` default to 1/M.
        """
        F, const = self.features(theta)
        coef, cconst = self.coefficients(raw)
        const = const - np.sum(np.log(self.hi - self.lo))  # undo the prior ratio: density, not ratio
        w = np.full(coef.shape[0], 1.0 / coef.shape[0]) if weights is None else np.asarray(weights, float)
        with np.errstate(divide="ignore"):
            lw = np.log(w / w.sum())
        # sum over ψ rows: treat the rows as the "samples" axis of log_ratio_stats
        lse, _ = self.log_ratio_stats(coef, cconst + lw, F, const)
        return lse


def draw_population(model: HierarchicalModel, raw: np.ndarray, n: int, rng: np.random.Generator) -> np.ndarray:
    """θ_new ~ p(θ|ψ) with ψ drawn uniformly from ``raw`` (pooled columns)."""
    idx = rng.integers(0, raw.shape[0], n)
    nat = model.natural(raw[idx])
    d = model.d
    mu, sd = nat[:, :d], nat[:, d : 2 * d]
    z = np.empty((n, d))
    diag = np.ones(d, bool)
    diag[model.S] = False
    if diag.any():
        # inverse-CDF sampling of the truncated normal in the transformed space
        u = rng.random((n, int(diag.sum())))
        z[:, diag] = ppf(u, mu[:, diag], sd[:, diag], model.zlo[diag], model.zhi[diag])
    if model.m:
        L = _cpc_to_corr_chol(raw[idx, 2 * d :], model.m) * sd[:, model.S][:, :, None]
        z[:, model.S] = mu[:, model.S] + np.einsum("nab,nb->na", L, rng.standard_normal((n, model.m)))
    return model.from_z(z)


def kernel_bandwidth(n: int, d: int, rule: str | float = "silverman") -> float:
    """Bandwidth factor h of the Gaussian kernel N(θ_ij, h²Σ_i) for ``n`` samples in ``d`` dims.

    ``"silverman"``: h = (4 / (d + 2))^(1/(d+4)) · n^(−1/(d+4)) (AMISE-optimal for a normal
    density, Silverman 1986 eq. 4.14); ``"scott"``: h = n^(−1/(d+4)).  A float is used as is.
    """
    if isinstance(rule, str):
        if n < 2 or d < 1:
            raise HbmError(f"hierarchical: kernel bandwidth needs n >= 2 samples and d >= 1, got n={n}, d={d}")
        if rule == "silverman":
            return float((4.0 / (d + 2.0)) ** (1.0 / (d + 4.0)) * n ** (-1.0 / (d + 4.0)))
        if rule == "scott":
            return float(n ** (-1.0 / (d + 4.0)))
        raise HbmError(f"hierarchical: bandwidth must be 'silverman', 'scott' or a number > 0, got {rule!r}")
    h = float(rule)
    if not (np.isfinite(h) and h > 0):
        raise HbmError(f"hierarchical: bandwidth must be 'silverman', 'scott' or a number > 0, got {rule!r}")
    return h

