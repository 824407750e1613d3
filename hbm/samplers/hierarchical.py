"""Hierarchical Bayesian layer over per-specimen TMCMC posteriors (two-stage, sample reuse).

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

Hyper-posterior by sample reuse
-------------------------------
Stage-1 samples θ_ij ~ p(θ|d_i) were drawn under the uniform prior on ``bounds``, so

    p(d_i|ψ) = Z_i · E_{θ~p(θ|d_i)}[ p(θ|ψ) / p_prior(θ) ]
             ≈ Z_i · mean_j r_ij(ψ),      r_ij(ψ) = p(θ_ij|ψ) / p_prior(θ_ij).

``log r`` is a quadratic form in z, so for the whole ψ population at once it is the matrix
product ``coef(ψ) (n_ψ, n_f) @ F(θ)ᵀ (n_f, N)`` with features F = [z, z², z_k z_l (pairs in
the full-covariance block)] plus per-ψ constants (normal and truncation normalisers via
``scipy.special.log_ndtr``) and per-sample constants (Jacobian, prior).  Samples are processed
in chunks with an online log-sum-exp, so memory is bounded and time is linear in N.  The
per-specimen importance ESS (Σr)²/Σr² comes out of the same pass.

TMCMC over ψ targets Σ_i log mean_j r_ij(ψ); the hyper-evidence is its log-evidence plus
Σ_i log Z_i, so it is log p(all data | hyperprior family) and families (transforms, full
covariance, sd prior) can be compared by it.

When the sample reuse fails, and what to pool
---------------------------------------------
The ESS of the ratios is a product over the pooled parameters (one factor per dimension for
a diagonal population), and a factor is small in two situations:

* *wide populations of prior-like parameters*: for a parameter the data do not inform, the
  stage-1 samples follow the uniform prior, whose density in the transformed space has
  exponential tails (logistic for logit, e^z for log), while p(d_i|ψ) is flat in its (mu, sd),
  so the hyper-posterior returns the hyperprior, which reaches |mu| near ``logit_range`` and
  sd of several units.  Such a population puts its mass where the samples are exponentially
  rare and one or two extreme samples carry all the weight.  On the six shipped specimens
  (2000 samples each, all eight parameters pooled) this is what collapses the ESS (min ≈ 1,
  10 % quantile 1.8–31): per parameter the ESS falls as sd_k grows (correlation of log ESS_k
  with log sd_k −0.5 to −0.8 for VOLF, EOPT, P1, GF, GM), VOLF/EOPT/GM alone keep a median of
  300–600 of 2000, and eight such factors multiply to a handful.  Capping sd at the prior's
  sd does not help: the populations then become narrower than the prior-like posteriors and
  the factors stay ≈ 0.5 each.
* *narrow populations*: a population much narrower than a specimen's posterior leaves few
  samples in its support (the kernel estimator below addresses this).

Hence :func:`auto_pool`: pool only parameters whose stage-1 posterior sd in the transformed
space is below ``max_sd_ratio`` (2/3) of the uniform prior's sd there
(:func:`prior_sd_transformed`) in at least half of the specimens; the others keep their
stage-1 prior and cost nothing.  On the shipped specimens it selects T2 and THETA (VOLF, T1
and GM are prior-like everywhere, EOPT, P1 and GF informed in one or two specimens) and the
ESS 10 % quantile becomes 174–987 with a minimum of 121.

Kernel-smoothed estimator (``estimator="kernel"``)
--------------------------------------------------
Each stage-1 sample is replaced by a Gaussian kernel N(z; z_ij, H_i) in the transformed space,
H_i = h_i²·diag Σ_i with Σ_i the specimen's posterior covariance of the pooled z (diagonal) and
h_i from Silverman's rule for d = number of pooled parameters (:func:`kernel_bandwidth`).
This smooths the stage-1 likelihood L_i(z) ∝ post_i(z)/p0(z) (p0 the density of the uniform
θ prior in z, i.e. including the transform's Jacobian, exactly as in the raw ratio) into
L_i * K_H, and for a Gaussian population the z-integral is analytic:

    p(d_i|ψ) ≈ Z_i · mean_j N(z_ij; mu, S + H_i) / p0(z_ij),

i.e. the raw estimator applied to the population widened by H_i; for identity/log the widened
normal is truncated to the transformed box like the population itself (its normaliser uses
the widened sd).  It keeps the matrix-product form (per-specimen coefficients), is linear in
N, and its bias is O(h²): the marginal's variance grows by h²Σ_i, a relative change ≤ h² of
the marginal variance.  Measured on the Gaussian toy of the tests (six specimens, N = 2500):
hyper-evidence error +0.07 ± 0.07 nat (raw: −0.006 ± 0.09), posterior mean of sd −0.018
(raw +0.005), of mu unchanged.  Where populations are narrow it raises the ESS a lot (the
collapse toy: 29–33 → 640 of 2000); on the shipped specimens the collapse is of the first kind and
the gain is small (auto pool: 10 % quantiles +0 to +21 % over raw), so the default is "raw".
The updated individuals always reweight the stage-1 samples with the *raw* ratios (no
smoothing bias; ``ess_raw`` is their ESS and triggers ``ess_collapsed``).

Non-uniform stage-1 priors of the pooled columns (``log_prior``)
----------------------------------------------------------------
The pooled columns need not be stage-1 parameters: a caller may append derived features
(e.g. products of parameters that the data identify) as extra columns, pool those, and pass
``log_prior[i]`` = the log density of each sample's pooled columns under the stage-1 prior
(in the column space).  It replaces −Σ log(hi − lo) in r_ij; everything else (transform
Jacobian, truncation to ``bounds``, which are then the features' support hull) is unchanged.
The unpooled columns keep their stage-1 prior *conditional on* the pooled ones, so a new
specimen's unpooled columns are drawn from that conditional by the caller.

What the reused samples cannot represent (issue 15)
--------------------------------------------------
The ESS measures how unevenly the existing samples are weighted, not the mass they never
reach.  Under the uniform stage-1 prior the density of log c·P1 falls off as e^y, and where the
data bound c·P1 only from above the samples barely reach the small values a population may put
mass on.  :func:`reuse_diagnostics` reports per specimen the PSIS k̂ of the ratios (over
hyper-posterior draws) and the conditional-posterior mass beyond the range of the stage-1
samples (the likelihood extrapolated with its log-slope at the samples' edge, from the stored
stage-1 log-likelihoods; flat without them, an upper bound that is reported but not acted on),
plus, with reference draws, the same mass measured with real likelihoods.
:func:`reuse_unreliable` turns them, with the ESS, into a per-specimen flag; the caller
refines flagged specimens (:func:`refine_individual`).

Defensive reference draws (``log_weights``, ``stage1_rows``)
-----------------------------------------------------------
A caller may append draws from a reference density q that covers such tails to a specimen's
stage-1 samples, with their real log-likelihoods, and pass ω = post/q_mix
(:func:`defensive_log_weights`): p(d_i|ψ) = Z_i · mean_j ω_j r_ij(ψ) is then the deterministic
mixture estimator, unbiased wherever q has mass, and the stage-1 results and log Z_i are
untouched.  The updated individuals reweight all rows.

Updated individuals ("shrinkage")
---------------------------------
p(θ_i | all data) = ∫ p(θ_i | d_i, ψ) p(ψ | all data) dψ.  p(θ_i|d_i, ψ) is represented by
the stage-1 samples with self-normalised weights r_ij(ψ)/Σ_j r_ij(ψ), so the updated
posterior is the stage-1 sample set with weights averaged *per draw after normalisation*
over the hyper-posterior draws, then resampled (systematic resampling).  (Averaging the
unnormalised ratios instead would weight each draw by p(d_i|ψ) again — double-counting d_i.)

When the importance ESS collapses (a population much narrower than a specimen's stage-1
posterior), :func:`refine_individual` runs a fresh TMCMC of that posterior given the
specimen's log-likelihood callable.

This module is sampler-layer code: it knows nothing about muscles.
"""

from __future__ import annotations

import time
import warnings
from dataclasses import dataclass, field
from typing import Any, Callable, Mapping, Sequence

import numpy as np
from scipy.special import log_ndtr, ndtri

from ..errors import HbmError
from .psis import K_HAT_THRESHOLD, pareto_khat
from .tmcmc import tmcmc as _tmcmc

__all__ = [
    "HierarchicalResult",
    "HierarchicalModel",
    "hierarchical",
    "refine_individual",
    "systematic_resample",
    "kernel_bandwidth",
    "auto_pool",
    "PoolChoice",
    "prior_sd_transformed",
    "TRANSFORMS",
    "ESTIMATORS",
    "reuse_diagnostics",
    "reuse_unreliable",
    "defensive_log_weights",
    "mixture_log_weights",
]

TRANSFORMS = ("identity", "log", "logit")
ESTIMATORS = ("raw", "kernel")
_LOG2PI = np.log(2.0 * np.pi)
_CPC_MAX = 0.99
# Stage-1 samples sitting exactly on a box edge would map to ±inf under log/logit.
_EDGE = 1e-12


# --------------------------------------------------------------------------------------
# BLAS threads
# --------------------------------------------------------------------------------------
_BLAS_API: list | None = None


def _blas_api() -> list:
    """(set, get) pairs of OpenBLAS thread controls of the loaded BLAS libraries (Linux)."""
    global _BLAS_API
    if _BLAS_API is None:
        import ctypes

        found = []
        try:
            with open("/proc/self/maps") as fh:
                libs = sorted({ln.split()[-1] for ln in fh if "openblas" in ln.lower() and "/" in ln})
        except OSError:
            libs = []
        for path in libs:
            try:
                lib = ctypes.CDLL(path)
            except OSError:
                continue
            for prefix, suffix in (("openblas", ""), ("scipy_openblas", "64_"), ("openblas", "64_")):
                setter = getattr(lib, f"{prefix}_set_num_threads{suffix}", None)
                getter = getattr(lib, f"{prefix}_get_num_threads{suffix}", None)
                if setter is not None and getter is not None:
                    found.append((setter, getter))
                    break
        _BLAS_API = found
    return _BLAS_API


class _single_thread_blas:
    """Run the hot loop with one BLAS thread.

    The GEMMs here are thin (K = 2d+2 columns); OpenBLAS threads give no speed-up for them
    and, on a loaded machine or inside several dask workers, spin-waiting threads made one
    likelihood call 3× slower (measured).  Restores the previous setting; no-op if the BLAS
    is not OpenBLAS.
    """

    def __enter__(self):
        self._old = []
        for setter, getter in _blas_api():
            try:
                self._old.append((setter, int(getter())))
                setter(1)
            except Exception:  # pragma: no cover - exotic BLAS builds
                pass
        return self

    def __exit__(self, *exc):
        for setter, n in self._old:
            setter(n)
        return False


# --------------------------------------------------------------------------------------
# small numerical helpers
# --------------------------------------------------------------------------------------
def _log_norm_mass(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """log(Φ(b) − Φ(a)) for a < b, accurate in both tails."""
    a, b = np.broadcast_arrays(np.asarray(a, float), np.asarray(b, float))
    # In the upper tail use the mirror image so that both Φ values are small (no cancellation).
    flip = a > 0
    lo = np.where(flip, -b, a)
    hi = np.where(flip, -a, b)
    lhi = log_ndtr(hi)
    llo = log_ndtr(lo)
    with np.errstate(divide="ignore", invalid="ignore"):
        out = lhi + np.log1p(-np.exp(np.minimum(llo - lhi, 0.0)))
    return out


def systematic_resample(weights: np.ndarray, n: int, rng: np.random.Generator) -> np.ndarray:
    """Indices of ``n`` systematic-resampling draws from normalised-or-not ``weights``."""
    w = np.asarray(weights, float)
    c = np.cumsum(w)
    c /= c[-1]
    u = (rng.random() + np.arange(n)) / n
    return np.minimum(np.searchsorted(c, u, side="right"), len(w) - 1)


def _ess(w: np.ndarray) -> float:
    s = w.sum()
    return float(s * s / np.sum(w * w)) if s > 0 else 0.0


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
        lognorm = _log_norm_mass(self.sd_lo / scale, self.sd_hi / scale)
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
        const -= np.sum(_log_norm_mass((a - mu[:, diag]) / sdt[:, diag], (b - mu[:, diag]) / sdt[:, diag]), axis=1)
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
        with _single_thread_blas():
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


# --------------------------------------------------------------------------------------
# result
# --------------------------------------------------------------------------------------
@dataclass
class HierarchicalResult:
    """Output of :func:`hierarchical`.

    Attributes
    ----------
    hyper_samples : ndarray (n, 2d+q)
        Hyper-posterior draws (equal weights): ``mu_<P>`` (transformed units, see
        ``transforms``), ``sd_<P>`` (transformed units), ``corr_<P>_<Q>`` (full_cov only).
        Fixed hyperparameters appear as constant columns.
    hyper_names : list of str
    names : list of str
        Pooled parameter names (columns of ``predictive``).
    all_names : list of str
        Stage-1 column names (columns of ``updated[...]``).
    bounds : ndarray (len(all_names), 2)
    transforms : dict name -> transform
    specimens : list of str
    log_evidence, log_evidence_se : float
        log p(all data | hyperprior family) = TMCMC log-evidence over ψ + Σ_i log Z_i; the SE
        combines the TMCMC SE, the stage-1 SEs and the importance-sampling noise in quadrature.
    log_evidence_parts : dict
    log_marginal : ndarray (n, n_specimens)
        log p̂(d_i | ψ_m) at each hyper-posterior draw.
    ess : ndarray (n, n_specimens)
        Importance ESS of each specimen at each hyper-posterior draw, of the estimator used
        for p(d_i|ψ) (raw or kernel-smoothed ratios).
    ess_raw : ndarray (n, n_specimens)
        ESS of the raw ratios (which weight the updated individuals); equals ``ess`` for the
        raw estimator.
    ess_summary : dict specimen -> {"min", "q10", "median", "n", "estimator", "raw_min",
        "raw_q10", "raw_median"}
    ess_collapsed : dict specimen -> bool
        True when the 10 % quantile over hyper-posterior draws of ``ess`` or of ``ess_raw``
        is below ``ess_threshold``: the updated individual (and, if ``hyper_ess_collapsed``,
        p̂(d_i|ψ)) rest on too few samples; run :func:`refine_individual` for that specimen.
    hyper_ess_collapsed : dict specimen -> bool
        The same test on ``ess`` only: p̂(d_i|ψ), hence the hyper-posterior, is unreliable.
    ess_trace : list of ndarray
        Per TMCMC likelihood call, the minimum ESS over the ψ population for each specimen.
    updated : dict specimen -> ndarray (n_updated, len(all_names))
        Updated individual posteriors p(θ_i | all data) (equal weights, resampled).
    updated_weights : dict specimen -> ndarray (N_i,)
        Normalised weights on the stage-1 samples behind ``updated``.
    updated_ess : dict specimen -> float
    predictive : ndarray (n, d)
        Posterior predictive of a new, unseen specimen (pooled columns).
    warnings : list of str
    timings : dict
    sampler_result : object
        The TMCMC result over the free hyperparameters.
    model : HierarchicalModel
    raw_samples : ndarray (n, 2d+q)
        Hyper draws in sampler coordinates (used by :func:`refine_individual`).
    """

    hyper_samples: np.ndarray
    hyper_names: list
    names: list
    all_names: list
    bounds: np.ndarray
    transforms: dict
    specimens: list
    log_evidence: float
    log_evidence_se: float
    log_evidence_parts: dict
    log_marginal: np.ndarray
    ess: np.ndarray
    ess_raw: np.ndarray
    ess_summary: dict
    ess_collapsed: dict
    hyper_ess_collapsed: dict
    ess_trace: list
    updated: dict
    updated_weights: dict
    updated_ess: dict
    predictive: np.ndarray
    warnings: list
    timings: dict
    sampler_result: Any
    model: HierarchicalModel
    raw_samples: np.ndarray
    options: dict = field(default_factory=dict)
    reuse: dict = field(default_factory=dict)

    @property
    def collapsed(self) -> bool:
        """True if any specimen's importance ESS collapsed."""
        return any(self.ess_collapsed.values())

    def hyper(self, name: str) -> np.ndarray:
        """Draws of one hyperparameter by name (e.g. ``"mu_VOLF"``)."""
        try:
            return self.hyper_samples[:, self.hyper_names.index(name)]
        except ValueError:
            raise HbmError(f"hierarchical: no hyperparameter {name!r}; have {self.hyper_names}") from None

    def summary(self, q: tuple[float, float] = (0.05, 0.95)) -> dict[str, dict[str, float]]:
        """Mean, sd and quantile interval of every hyperparameter."""
        lo, hi = np.quantile(self.hyper_samples, q, axis=0)
        return {
            n: {"mean": float(m), "sd": float(s), "lo": float(a), "hi": float(b)}
            for n, m, s, a, b in zip(
                self.hyper_names, self.hyper_samples.mean(0), self.hyper_samples.std(0), lo, hi
            )
        }

    def updated_array(self) -> np.ndarray:
        """Updated individuals stacked as (n_updated, n_specimens, len(all_names)) (draw, specimen, param)."""
        return np.stack([self.updated[k] for k in self.specimens], axis=1)

    def population_summary(self, q: tuple[float, float] = (0.05, 0.95)) -> dict[str, dict[str, float]]:
        """Population estimates on the θ scale, per pooled parameter.

        ``center`` / ``center_lo`` / ``center_hi``: median and interval of g⁻¹(mu) (the
        population median for log/logit, the untruncated mean for identity);
        ``predictive_median`` / ``predictive_lo`` / ``predictive_hi``: the new-specimen
        predictive (population spread plus hyper-uncertainty).
        """
        d = self.model.d
        centre = self.model.from_z(self.hyper_samples[:, :d].copy())
        out = {}
        for k, p in enumerate(self.names):
            c = np.quantile(centre[:, k], [0.5, q[0], q[1]])
            pr = np.quantile(self.predictive[:, k], [0.5, q[0], q[1]])
            out[p] = {"center": float(c[0]), "center_lo": float(c[1]), "center_hi": float(c[2]),
                      "predictive_median": float(pr[0]), "predictive_lo": float(pr[1]),
                      "predictive_hi": float(pr[2])}
        return out

    def population_log_density(self, theta: np.ndarray, n_hyper: int = 500, seed=0) -> np.ndarray:
        """log of the population predictive density of new-specimen θ (pooled columns), averaged
        over (a thinned subset of) the hyper-posterior draws."""
        raw = _thin(self.raw_samples, n_hyper, seed)
        return self.model.log_density(theta, raw)


def _thin(a: np.ndarray, n: int, seed) -> np.ndarray:
    if a.shape[0] <= n:
        return a
    rng = np.random.default_rng(seed)
    return a[np.sort(rng.choice(a.shape[0], n, replace=False))]


# --------------------------------------------------------------------------------------
# entry point
# --------------------------------------------------------------------------------------
def _parse_stage1(stage1, n_cols):
    specs, samples, logz, logz_se = [], [], [], []
    if not isinstance(stage1, Mapping) or not stage1:
        raise HbmError("hierarchical: stage1 must be a non-empty mapping specimen -> (samples, log_Z[, log_Z_se])")
    for key, val in stage1.items():
        if not isinstance(val, (tuple, list)) or len(val) not in (2, 3):
            raise HbmError(f"hierarchical: stage1[{key!r}] must be (samples, log_Z) or (samples, log_Z, log_Z_se)")
        x = np.asarray(val[0], float)
        if x.ndim != 2 or x.shape[1] != n_cols or x.shape[0] < 2:
            raise HbmError(f"hierarchical: stage1[{key!r}] samples must be (N>=2, {n_cols}), got {x.shape}")
        if not np.all(np.isfinite(x)):
            raise HbmError(f"hierarchical: stage1[{key!r}] samples contain non-finite values")
        lz = float(val[1])
        if not np.isfinite(lz):
            raise HbmError(f"hierarchical: stage1[{key!r}] log_Z must be finite, got {val[1]!r}")
        specs.append(str(key))
        samples.append(x)
        logz.append(lz)
        logz_se.append(float(val[2]) if len(val) == 3 and val[2] is not None else 0.0)
    return specs, samples, np.array(logz), np.array(logz_se)


def hierarchical(
    stage1: Mapping[str, tuple],
    names: Sequence[str],
    bounds,
    *,
    transforms: Mapping[str, str] | None = None,
    pooled: Sequence[str] | None = None,
    n_samples: int = 2000,
    seed=None,
    full_cov: Sequence[str] | None = None,
    sd_prior: str = "loguniform",
    sd_range: tuple[float, float] = (1e-3, 1.0),
    mu_bounds: Mapping[str, tuple[float, float]] | None = None,
    logit_range: float = 8.0,
    fix: Mapping[str, float] | None = None,
    ess_threshold: float = 50.0,
    thin: int | None = None,
    n_updated: int | None = None,
    n_hyper_updated: int = 1000,
    chunk_bytes: float = 4e6,
    progress: bool = True,
    sampler: Callable | None = None,
    tmcmc_options: Mapping[str, Any] | None = None,
    estimator: str = "raw",
    bandwidth: str | float = "silverman",
    log_prior: Mapping[str, np.ndarray] | None = None,
    log_weights: Mapping[str, np.ndarray] | None = None,
    stage1_rows: Mapping[str, int] | None = None,
    log_likelihood: Mapping[str, np.ndarray] | None = None,
) -> HierarchicalResult:
    """Hyper-posterior, hyper-evidence, updated individuals and population predictive.

    Parameters
    ----------
    stage1 : mapping specimen -> (samples (N_i, d), log_Z_i[, log_Z_se_i])
        Equal-weight stage-1 posterior samples drawn under the uniform prior on ``bounds``
        and their log-evidence.
    names : sequence of str
        Column names of the stage-1 samples.
    bounds : array_like (d, 2)
        The stage-1 uniform prior box.
    transforms : mapping name -> {"identity","log","logit"}, optional
        Transform of each pooled parameter (module docstring explains the choice).
    pooled : sequence of str, optional
        Parameters with a population distribution (default all); e.g. leave the noise
        ``sigma`` out.
    n_samples : int
        TMCMC population size over ψ (= number of hyper-posterior draws).
    seed : int, SeedSequence or Generator
        Everything random (TMCMC, resampling, predictive) derives from it.
    full_cov : sequence of str, optional
        Pooled parameters sharing a full covariance (logit transform required).
    sd_prior, sd_range, mu_bounds, logit_range, fix
        Hyperprior choices, see :class:`HierarchicalModel`.
    ess_threshold : float
        ESS below which a specimen's importance sampling is flagged as collapsed.
    thin : int, optional
        Use at most this many stage-1 samples per specimen (a seeded random subset) in the
        hyper-posterior; cost is linear in it.  Default: all.  The updated individuals are
        then weights over the subset.
    n_updated : int, optional
        Draws per updated individual (default ``n_samples``).
    n_hyper_updated : int
        Hyper-posterior draws used to average the shrinkage weights.
    chunk_bytes : float
        Memory bound of one (n_ψ, chunk) block of log-ratios.
    progress : bool
        Passed to the TMCMC driver.
    sampler : callable, optional
        Replacement for :func:`hbm.samplers.tmcmc.tmcmc` (same signature); default tmcmc.
    tmcmc_options : mapping, optional
        Extra keyword arguments for the sampler (``n_steps``, ``kernel``, ...).
    estimator : {"raw", "kernel"}
        Estimator of p(d_i|ψ) in the hyper-posterior: plain importance ratios ("raw",
        unbiased) or the kernel-smoothed ratios ("kernel": O(h²) bias, no collapse when the
        population is narrower than a specimen's posterior; module docstring).  The updated
        individuals always use the raw ratios.
    bandwidth : {"silverman", "scott"} or float
        Kernel bandwidth factor h (kernel covariance h²·Σ_i, Σ_i the diagonal posterior
        covariance of specimen i in the transformed space); see :func:`kernel_bandwidth`.
    log_prior : mapping specimen -> ndarray (N_i,), optional
        Log density of each stage-1 sample's *pooled columns* under the stage-1 prior, in the
        column space (before the transform; the transform's Jacobian is applied as usual).
        Default: the uniform box density −Σ log(hi − lo).  Needed when the pooled columns are
        derived features whose stage-1 prior is not uniform (e.g. products of parameters drawn
        uniformly); their ``bounds`` are then the support hull of the features, and the
        unpooled columns must keep a prior independent of ψ given the pooled ones.
    log_weights : mapping specimen -> ndarray (N_i,), optional
        Log importance weights ω_ij of the rows, multiplying the ratios: p̂(d_i|ψ) =
        Z_i · mean_j ω_ij r_ij(ψ).  For rows that are a defensive mixture of the stage-1
        posterior and a reference distribution q (:func:`defensive_log_weights`), ω is the
        posterior density over the mixture density; default 0 (plain stage-1 samples).
    stage1_rows : mapping specimen -> int, optional
        Number of leading rows that are stage-1 samples (the rest are reference draws); used by
        the coverage diagnostic (:func:`reuse_diagnostics`).  Default: all rows.
    log_likelihood : mapping specimen -> ndarray, optional
        Log-likelihoods of the stage-1 rows (at least ``stage1_rows``; before ``thin``): the
        coverage diagnostic extrapolates the likelihood beyond the samples with its log-slope at
        the edge (flat without them, the conservative choice).

    Returns
    -------
    HierarchicalResult
    """
    t0 = time.perf_counter()
    names = [str(n) for n in names]
    model = HierarchicalModel(
        names, bounds, pooled=pooled, transforms=transforms, full_cov=full_cov, sd_prior=sd_prior,
        sd_range=sd_range, mu_bounds=mu_bounds, logit_range=logit_range, fix=fix,
    )
    specs, samples, logz, logz_se = _parse_stage1(stage1, len(names))
    if log_prior is None:
        lps: list = [None] * len(specs)
    else:
        missing = [k for k in specs if k not in log_prior]
        if missing:
            raise HbmError(f"hierarchical: log_prior has no entry for specimens {missing}")
        lps = [np.asarray(log_prior[k], float) for k in specs]
        for key, x, lp in zip(specs, samples, lps):
            if lp.shape != (x.shape[0],):
                raise HbmError(f"hierarchical: log_prior[{key!r}] must have shape ({x.shape[0]},), got {lp.shape}")
    lws = [None] * len(specs) if log_weights is None else [np.asarray(log_weights[k], float) for k in specs]
    for key, x, lw in zip(specs, samples, lws):
        if lw is not None and (lw.shape != (x.shape[0],) or np.any(np.isnan(lw)) or np.any(lw == np.inf)):
            raise HbmError(f"hierarchical: log_weights[{key!r}] must be {x.shape[0]} values < +inf")
    n1s = [int((stage1_rows or {}).get(k, x.shape[0])) for k, x in zip(specs, samples)]
    lls = [None] * len(specs) if log_likelihood is None else [
        np.asarray(log_likelihood[k], float)[:n] if k in log_likelihood else None for k, n in zip(specs, n1s)]
    ss = np.random.SeedSequence(seed if not isinstance(seed, np.random.Generator) else seed.integers(2**63))
    s_tmcmc, s_upd, s_pred, s_thin = ss.spawn(4)
    if thin is not None:
        if int(thin) < 2:
            raise HbmError(f"hierarchical: thin must be >= 2, got {thin}")
        rng_t = np.random.default_rng(s_thin)
        sel = [None if x.shape[0] <= thin else np.sort(rng_t.choice(x.shape[0], int(thin), replace=False))
               for x in samples]
        samples = [x if j is None else x[j] for x, j in zip(samples, sel)]
        lps = [lp if (j is None or lp is None) else lp[j] for lp, j in zip(lps, sel)]
        lws = [lw if (j is None or lw is None) else lw[j] for lw, j in zip(lws, sel)]
        lls = [ll if (j is None or ll is None) else ll[j[j < len(ll)]] for ll, j in zip(lls, sel)]
        n1s = [n if j is None else int(np.sum(j < n)) for n, j in zip(n1s, sel)]
    for key, x in zip(specs, samples):
        out = (x < model.all_bounds[:, 0] - 1e-12 * np.ptp(model.all_bounds, axis=1)) | (
            x > model.all_bounds[:, 1] + 1e-12 * np.ptp(model.all_bounds, axis=1)
        )
        if out.any():
            j = int(np.argmax(out.any(axis=0)))
            raise HbmError(f"hierarchical: stage1[{key!r}] has samples of {names[j]} outside the prior box {model.all_bounds[j].tolist()}")
    feats = [model.features(x, lp) for x, lp in zip(samples, lps)]
    # importance weights of the rows (defensive mixture) enter as per-sample constants of log r
    feats = [(F, c if lw is None else c + lw) for (F, c), lw in zip(feats, lws)]
    logN = np.log([x.shape[0] for x in samples])
    trace: list[np.ndarray] = []
    if estimator not in ESTIMATORS:
        raise HbmError(f"hierarchical: estimator must be one of {ESTIMATORS}, got {estimator!r}")
    kernel_var: list[np.ndarray | None] = [None] * len(specs)
    kernel_h: dict[str, float] = {}
    if estimator == "kernel":
        for i, (key, x) in enumerate(zip(specs, samples)):
            kernel_h[key], kernel_var[i] = model.kernel_variance(x, bandwidth)

    def per_specimen(raw: np.ndarray, kvar=kernel_var) -> tuple[np.ndarray, np.ndarray]:
        coef, cconst = model.coefficients(raw)
        lm = np.empty((raw.shape[0], len(specs)))
        ess = np.empty_like(lm)
        for i, (F, c) in enumerate(feats):  # loop over specimens (few), vectorised over ψ and samples
            # kernel: each specimen sees the population widened by its own kernel covariance
            ci, cci = (coef, cconst) if kvar[i] is None else model.coefficients(raw, kvar[i])
            lse, e = model.log_ratio_stats(F, c, ci, cci, chunk_bytes)
            lm[:, i] = lse - logN[i]
            ess[:, i] = e
        return lm, ess

    def target(x: np.ndarray) -> np.ndarray:
        x = np.atleast_2d(np.asarray(x, float))
        raw = model.expand(x)
        lm, ess = per_specimen(raw)
        trace.append(ess.min(axis=0))
        out = lm.sum(axis=1) + model.log_hyperprior_correction(raw)
        return np.where(np.isfinite(out), out, -np.inf)

    if sampler is None:
        sampler = _tmcmc
    opts = dict(tmcmc_options or {})
    t1 = time.perf_counter()
    res = sampler(target, model.box, int(n_samples), seed=int(s_tmcmc.generate_state(1)[0]), progress=progress, **opts)
    t2 = time.perf_counter()

    x = np.asarray(res.samples, float)
    raw = model.expand(x)
    lm, ess = per_specimen(raw)
    # the updated individuals reweight the stage-1 samples with the raw ratios: their ESS
    lm_raw, ess_raw = (lm, ess) if estimator == "raw" else per_specimen(raw, [None] * len(specs))
    hyper = model.natural(raw)

    # --- ESS diagnostics ------------------------------------------------------------------
    warn_list: list[str] = []
    ess_summary, collapsed, hyper_collapsed = {}, {}, {}
    for i, key in enumerate(specs):
        e, er = ess[:, i], ess_raw[:, i]
        ess_summary[key] = {
            "min": float(e.min()), "q10": float(np.quantile(e, 0.1)), "median": float(np.median(e)),
            "n": int(samples[i].shape[0]), "estimator": estimator,
            "raw_min": float(er.min()), "raw_q10": float(np.quantile(er, 0.1)),
            "raw_median": float(np.median(er)),
        }
        hyper_collapsed[key] = bool(ess_summary[key]["q10"] < ess_threshold)
        collapsed[key] = bool(hyper_collapsed[key] or ess_summary[key]["raw_q10"] < ess_threshold)
        if hyper_collapsed[key]:
            msg = (
                f"hierarchical: importance ESS of specimen {key!r} collapsed (10% quantile "
                f"{ess_summary[key]['q10']:.1f}, median {ess_summary[key]['median']:.1f} of "
                f"{samples[i].shape[0]} stage-1 samples < {ess_threshold:g}, estimator {estimator!r}); "
                f"its updated posterior and p(d|psi) are unreliable: run "
                f"hbm.samplers.hierarchical.refine_individual for it"
            )
        elif collapsed[key]:
            msg = (
                f"hierarchical: importance ESS of specimen {key!r} collapsed for its updated posterior "
                f"(raw ratios: 10% quantile {ess_summary[key]['raw_q10']:.1f} < {ess_threshold:g}); "
                f"p(d|psi) is fine ({estimator} ESS 10% quantile {ess_summary[key]['q10']:.1f}): run "
                f"hbm.samplers.hierarchical.refine_individual for its updated posterior"
            )
        if collapsed[key]:
            warn_list.append(msg)
            warnings.warn(msg, RuntimeWarning, stacklevel=2)

    # --- evidence -------------------------------------------------------------------------
    # IS noise: Var[log mean r] ≈ 1/ESS − 1/N per specimen (delta method), at each draw.
    is_var = np.sum(np.maximum(1.0 / np.maximum(ess, 1e-300) - 1.0 / np.exp(logN), 0.0), axis=1)
    se_tm = float(getattr(res, "log_evidence_se", 0.0) or 0.0)
    se_is = float(np.sqrt(np.median(is_var)))
    se_st1 = float(np.sqrt(np.sum(logz_se**2)))
    log_ev = float(res.log_evidence) + float(logz.sum())
    se = float(np.sqrt(se_tm**2 + se_is**2 + se_st1**2))
    parts = {
        "tmcmc": float(res.log_evidence), "tmcmc_se": se_tm, "sum_log_Z": float(logz.sum()),
        "stage1_se": se_st1, "importance_se": se_is,
    }

    # --- updated individuals (per-draw normalised weights, averaged over draws) -----------
    t3 = time.perf_counter()
    rng_u = np.random.default_rng(s_upd)
    sub = np.arange(raw.shape[0]) if raw.shape[0] <= n_hyper_updated else np.sort(
        rng_u.choice(raw.shape[0], n_hyper_updated, replace=False)
    )
    coef, cconst = model.coefficients(raw[sub])
    n_upd = int(n_updated or n_samples)
    updated, upd_w, upd_ess = {}, {}, {}
    for i, key in enumerate(specs):
        lse = lm_raw[sub, i] + logN[i]  # log Σ_j r_ij(ψ_m), raw ratios
        # Σ_m exp(log r_mj − lse_m): rows are draws; use the chunked kernel with the roles swapped
        F, c = feats[i]
        lw, _ = model.log_ratio_stats(coef, cconst - lse, F, c, chunk_bytes)
        w = np.exp(lw - lw.max())
        w /= w.sum()
        upd_w[key] = w
        upd_ess[key] = _ess(w)
        updated[key] = samples[i][systematic_resample(w, n_upd, rng_u)]
    t4 = time.perf_counter()

    # --- posterior predictive of a new specimen -------------------------------------------
    predictive = _draw_population(model, raw, raw.shape[0], np.random.default_rng(s_pred))
    t5 = time.perf_counter()

    # --- what the reused samples cannot represent (no random numbers: streams unchanged) ---
    reuse = {}
    for i, key in enumerate(specs):
        reuse[key] = reuse_diagnostics(model, samples[i], raw, log_prior=lps[i], updated_weights=upd_w[key],
                                       log_weights=lws[i], n_stage1=n1s[i], log_likelihood=lls[i])
        reuse[key].update(ess_q10=ess_summary[key]["q10"], ess_raw_q10=ess_summary[key]["raw_q10"])
    for key, (bad, why) in reuse_unreliable(reuse, ess_threshold=ess_threshold).items():
        reuse[key].update(unreliable=bad, reasons=why)
    t6 = time.perf_counter()

    return HierarchicalResult(
        hyper_samples=hyper, hyper_names=list(model.hyper_names), names=list(model.names),
        all_names=list(names), bounds=model.all_bounds.copy(), transforms=dict(model.transforms),
        specimens=specs, log_evidence=log_ev, log_evidence_se=se, log_evidence_parts=parts,
        log_marginal=lm + logz[None, :], ess=ess, ess_raw=ess_raw, ess_summary=ess_summary,
        ess_collapsed=collapsed, hyper_ess_collapsed=hyper_collapsed,
        ess_trace=trace, updated=updated, updated_weights=upd_w, updated_ess=upd_ess,
        predictive=predictive, warnings=warn_list,
        timings={"setup": t1 - t0, "tmcmc": t2 - t1, "updated": t4 - t3, "predictive": t5 - t4,
                 "diagnostics": t6 - t5, "total": t6 - t0, "likelihood_calls": len(trace)},
        sampler_result=res, model=model, raw_samples=raw, reuse=reuse,
        options={"n_samples": int(n_samples), "sd_prior": sd_prior, "sd_range": list(sd_range),
                 "full_cov": list(model.full_cov), "fix": dict(model.fix), "ess_threshold": ess_threshold,
                 "logit_range": logit_range, "mu_lo": model.mu_lo.tolist(), "mu_hi": model.mu_hi.tolist(),
                 "estimator": estimator, "log_prior": log_prior is not None, "bandwidth": bandwidth if isinstance(bandwidth, str) else float(bandwidth),
                 "kernel_h": kernel_h,
                 "kernel_sd": {k: np.sqrt(v).tolist() for k, v in zip(specs, kernel_var) if v is not None}},
    )


def _draw_population(model: HierarchicalModel, raw: np.ndarray, n: int, rng: np.random.Generator) -> np.ndarray:
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
        a = (model.zlo[diag] - mu[:, diag]) / sd[:, diag]
        b = (model.zhi[diag] - mu[:, diag]) / sd[:, diag]
        la, lb = np.exp(log_ndtr(a)), np.exp(log_ndtr(b))
        u = rng.random((n, int(diag.sum())))
        # mirror in the upper tail for accuracy
        flip = a > 0
        lam, lbm = np.exp(log_ndtr(-b)), np.exp(log_ndtr(-a))
        x = np.where(flip, -ndtri(lam + u * (lbm - lam)), ndtri(la + u * (lb - la)))
        zz = mu[:, diag] + sd[:, diag] * x
        z[:, diag] = np.clip(zz, model.zlo[diag], model.zhi[diag])
    if model.m:
        L = _cpc_to_corr_chol(raw[idx, 2 * d :], model.m) * sd[:, model.S][:, :, None]
        z[:, model.S] = mu[:, model.S] + np.einsum("nab,nb->na", L, rng.standard_normal((n, model.m)))
    return model.from_z(z)


# --------------------------------------------------------------------------------------
# what the reused samples cannot represent
# --------------------------------------------------------------------------------------
def _diag_rows(n: int, n_draws: int) -> np.ndarray:
    """Evenly spaced hyper-draw indices (deterministic: the diagnostic consumes no random numbers)."""
    return np.unique(np.linspace(0, n - 1, min(n, int(n_draws))).round().astype(int))


def reuse_diagnostics(
    model: HierarchicalModel,
    theta: np.ndarray,
    raw: np.ndarray,
    *,
    log_prior: np.ndarray | None = None,
    log_weights: np.ndarray | None = None,
    n_stage1: int | None = None,
    log_likelihood: np.ndarray | None = None,
    updated_weights: np.ndarray | None = None,
    edge: float = 0.02,
    cover: float = 0.0,
    slope_bin: float = 0.1,
    outer: float = 0.005,
    n_draws: int = 200,
) -> dict:
    """How well one specimen's reused samples represent p(θ_i | d_i, ψ) over the hyper-posterior.

    The importance ESS measures how unevenly the existing samples are weighted; it cannot see
    mass where the samples never went.  Diagnostics that can:

    * **PSIS k̂** (:func:`hbm.samplers.psis.pareto_khat`) of the ratios r_ij(ψ) at ``n_draws``
      evenly spaced hyper-posterior draws: a heavy ratio tail (k̂ > 0.7) means the target has
      mass where the samples are too sparse for the estimate to converge.
    * **uncovered mass** (``uncovered``): per pooled coordinate z_k, the share of the
      conditional posterior p(z | d_i, ψ) ∝ L_i(z) p(z|ψ) beyond the range [min z_k, max z_k]
      of the stage-1 samples, with the likelihood extrapolated as flat beyond the range at its
      value in the edge bin (the samples below the ``edge`` quantile, resp. above 1 − ``edge``):

          U_k,lo(ψ) = W_lo(ψ) · P_ψ(z_k < min) / P_ψ(min ≤ z_k ≤ q_edge),

      W_lo the share of the normalised ratios in the edge bin, P_ψ the population marginal of
      z_k.  Flat extrapolation is exact where the data bound a parameter from one side only (the
      likelihood no longer changes beyond the samples) and conservative where it decays.
      U = Σ_k (U_k,lo + U_k,hi); uncovered = U/(1 + U), averaged over the draws.
    * **measured outside mass** (``outside_measured``, only with reference draws appended to
      the stage-1 samples, ``n_stage1`` < N): the share of the normalised ratios carried by the
      rows outside the stage-1 samples' range in some pooled coordinate, with their real
      likelihoods; averaged over the draws.
    * ``population_outside``: the population-predictive probability of a pooled coordinate
      outside the stage-1 samples' [``outer``, 1 − ``outer``] quantile range (likelihood
      ignored: large for every informed specimen whose posterior is narrower than the
      population, so it is information, not a trigger).

    Parameters
    ----------
    model : HierarchicalModel
    theta : ndarray (N, len(model.all_names))
        The specimen's samples as used by the layer (stage-1 rows first).
    raw : ndarray (n, 2d+q)
        Hyper-posterior draws in sampler coordinates (``result.raw_samples``).
    log_prior, log_weights : ndarray (N,), optional
        As passed to :func:`hierarchical`.
    n_stage1 : int, optional
        Number of leading rows that are stage-1 posterior samples (default all).
    updated_weights : ndarray (N,), optional
        The updated individual's weights (``result.updated_weights[key]``); adds ``khat_updated``.
    edge, outer : float
        Quantile of the edge bins, and of the range for ``population_outside``.
    n_draws : int
        Hyper-posterior draws used (evenly spaced).

    Returns
    -------
    dict
        ``khat_median``, ``khat_q90``, ``khat_frac`` (share of draws with k̂ > 0.7),
        ``khat_updated`` (if weights given), ``uncovered``, ``uncovered_by`` (name -> value),
        ``outside_measured`` (NaN without reference rows), ``population_outside``, ``n_draws``,
        ``likelihood_slope`` (whether the extrapolation used the log-likelihoods; without them it
        is flat, an upper bound that :func:`reuse_unreliable` does not act on).
    """
    if not (0 < edge < 0.5 and 0 < outer < 0.5 and 0 <= cover < edge):
        raise HbmError(f"reuse_diagnostics: need 0 <= cover < edge < 0.5 and 0 < outer < 0.5, got {cover}, {edge}, "
                       f"{outer}")
    theta = np.asarray(theta, float)
    n1 = theta.shape[0] if n_stage1 is None else int(n_stage1)
    F, c = model.features(theta, log_prior)
    if log_weights is not None:
        c = c + np.asarray(log_weights, float)
    ll1 = None if log_likelihood is None else np.asarray(log_likelihood, float)[:n1]
    if ll1 is not None and (ll1.shape != (n1,) or not np.all(np.isfinite(ll1))):
        raise HbmError(f"reuse_diagnostics: log_likelihood must be {n1} finite values (the stage-1 rows)")
    rows = _diag_rows(raw.shape[0], n_draws)
    coef, cconst = model.coefficients(raw[rows])
    lr = coef @ F.T + cconst[:, None] + c[None, :]  # (n_draws, N) log ratios
    khat = pareto_khat(np.where(np.isfinite(lr), lr, -np.inf))
    w = np.exp(lr - lr.max(axis=1, keepdims=True))
    w /= w.sum(axis=1, keepdims=True)
    z, _ = model.to_z(theta)
    z1 = z[:n1]
    nat = model.natural(raw[rows])
    mu, sd = nat[:, : model.d], nat[:, model.d : 2 * model.d]

    def lmass(a, b, k, tilt=0.0):
        # log ∫_a^b e^{tilt·z} N(z; mu, sd) dz up to factors that cancel in the ratios below:
        # an exponential tilt of a normal is the normal shifted by tilt·sd²
        m = mu[:, k] + tilt * sd[:, k] ** 2
        with np.errstate(divide="ignore", invalid="ignore"):
            return _log_norm_mass((a - m) / sd[:, k], (b - m) / sd[:, k])

    U = np.zeros(len(rows))
    by = {}
    log_keep = np.zeros(len(rows))  # log P(all coordinates inside the outer range)
    outside_rows = np.zeros(theta.shape[0], bool)
    log_cov_beyond = np.zeros(len(rows))  # log P(every coordinate inside), likelihood-tilted beyond
    for k, name in enumerate(model.names):  # loop over the pooled parameters, vectorised over draws
        zk = z1[:, k]
        zmin, zmax = np.quantile(zk, [cover, 1.0 - cover])
        outside_rows |= (z[:, k] < zmin) | (z[:, k] > zmax)
        qlo, qhi = np.quantile(zk, [edge, 1.0 - edge])
        Uk = np.zeros(len(rows))
        for side, beyond, binm, sel in ((-1, (model.zlo[k], zmin), (zmin, qlo), z[:, k] <= qlo),
                                        (1, (zmax, model.zhi[k]), (qhi, zmax), z[:, k] >= qhi)):
            if not beyond[1] > beyond[0]:
                continue  # the samples reach the box edge: nothing beyond them
            sel = sel.copy()
            sel[n1:] = False  # the extrapolation is of the stage-1 samples' edge bin
            wb = w[:, sel].sum(axis=1)
            tilt = 0.0 if ll1 is None else _edge_slope(zk, ll1, side, slope_bin)
            with np.errstate(divide="ignore", invalid="ignore"):
                lu = np.log(wb) + lmass(*beyond, k, tilt) - lmass(*binm, k, tilt)
            Uk += np.where(wb > 0, np.exp(np.minimum(np.nan_to_num(lu, nan=-np.inf), 700.0)), 0.0)
        U += Uk
        by[name] = float(np.mean(Uk / (1.0 + Uk)))
        o_lo, o_hi = np.quantile(zk, [outer, 1.0 - outer])
        log_keep += lmass(o_lo, o_hi, k) - lmass(model.zlo[k], model.zhi[k], k)
        # population mass beyond the samples' [outer, 1 − outer] range, the likelihood modelled as
        # flat inside and as e^{s (z − edge)} beyond (s: its log-slope at that edge of the samples)
        log_in = lmass(o_lo, o_hi, k)
        parts = [log_in]
        for side, (a, b), e in ((-1, (model.zlo[k], o_lo), o_lo), (1, (o_hi, model.zhi[k]), o_hi)):
            if not b > a:
                continue
            t = 0.0 if ll1 is None else _edge_slope(zk, ll1, side, slope_bin)
            # ∫_a^b e^{t(z−e)} N(z; mu, sd) dz = e^{t(mu−e) + t² sd²/2} · mass of N(mu + t sd², sd)
            parts.append(t * (mu[:, k] - e) + 0.5 * t * t * sd[:, k] ** 2 + lmass(a, b, k, t))
        tot = np.logaddexp.reduce(np.array(parts), axis=0)
        log_cov_beyond += log_in - tot
    out = {
        "khat_median": float(np.median(khat)), "khat_q90": float(np.quantile(khat, 0.9)),
        "khat_frac": float(np.mean(khat > K_HAT_THRESHOLD)),
        "uncovered": float(np.mean(U / (1.0 + U))), "uncovered_by": by,
        "outside_measured": float(np.mean(w[:, outside_rows].sum(axis=1))) if n1 < theta.shape[0] else float("nan"),
        "population_outside": float(np.mean(-np.expm1(log_keep))),
        "population_beyond": float(np.mean(-np.expm1(log_cov_beyond))), "n_draws": int(len(rows)),
        "likelihood_slope": ll1 is not None,
    }
    if updated_weights is not None:
        with np.errstate(divide="ignore"):
            out["khat_updated"] = float(pareto_khat(np.log(np.asarray(updated_weights, float))))
    return out


def defensive_log_weights(log_lik: np.ndarray, log_rho: np.ndarray, log_z: float, n_post: int,
                          n_drawn: int) -> np.ndarray:
    """Log importance weights ω = post/q_mix of stage-1 samples plus reference draws (defensive mixture).

    Rows: ``n_post`` stage-1 posterior samples, then the kept reference draws (of ``n_drawn``
    drawn from a reference density q; draws outside the support were dropped).  With the
    stage-1 posterior post(θ) = L(θ) p0(θ)/Z and ρ(θ) = q(θ)/p0(θ), the rows are a draw from the
    deterministic mixture q_mix = a·post + (1 − a)·q, a = n_post/(n_post + n_drawn) (Owen & Zhou
    2000, "Safe and effective importance sampling"), so

        ω = post/q_mix = (L/Z) / (a·L/Z + (1 − a)·ρ),

    and mean_j ω_j r_j(ψ) over the n_post + n_drawn draws estimates p(d|ψ)/Z without bias —
    also where the posterior samples never went, as long as q goes there; ω ≤ 1/a bounds the
    weights of the posterior samples.  Dropped draws count as zeros: ω is scaled by
    (rows kept)/(n_post + n_drawn) so that the layer's mean over the kept rows is that estimate.

    Parameters
    ----------
    log_lik : ndarray (R,)
        Log-likelihood of every row.
    log_rho : ndarray (R,)
        log q(θ)/p0(θ) of every row.
    log_z : float
        Stage-1 log-evidence.
    n_post, n_drawn : int
        Stage-1 rows (leading) and reference draws made (kept + dropped).

    Returns
    -------
    ndarray (R,)
    """
    log_lik, log_rho = np.asarray(log_lik, float), np.asarray(log_rho, float)
    rows = log_lik.shape[0]
    if log_rho.shape != (rows,) or not (0 < n_post <= rows) or n_drawn < rows - n_post:
        raise HbmError(f"defensive_log_weights: need {rows} log_rho values and 0 < n_post <= rows <= "
                       f"n_post + n_drawn, got {log_rho.shape}, {n_post}, {n_drawn}")
    a = n_post / (n_post + n_drawn)
    lp = log_lik - log_z
    mix = np.logaddexp(np.log(a) + lp, np.log1p(-a) + log_rho) if a < 1 else lp
    return lp - mix + np.log(rows / (n_post + n_drawn))


def mixture_log_weights(log_pmix_ratio: np.ndarray, n_post: int, *, tol: float = 1e-10,
                        max_iter: int = 10_000) -> np.ndarray:
    """Log weights ω = post/q_mix of stage-1 samples plus draws of the posterior under a population mixture.

    Rows: ``n_post`` stage-1 samples of post = L·p0/Z, then n_q draws of q = L·p_mix/Z_q, the
    specimen's posterior under a mixture of populations p_mix (e.g. a fresh TMCMC run of
    :func:`refine_individual`).  With l = p_mix/p0 (``log_pmix_ratio``, for pooled derived
    columns the ratio of their densities) and a = n_post/R,

        ω = post/(a·post + (1 − a)·q) = 1 / (a + (1 − a)·l/c),   c = Z_q/Z,

    the likelihood cancels.  c is not taken from the TMCMC evidence (its error, 0.5–2.7 nats in
    the gold benchmark's refits, biases the weights) but solved from both sample sets by the
    two-state MBAR / optimal bridge fixed point c = Σ_rows l/(n_post + n_q·l/c) (Meng & Wong 1996;
    Shirts & Chodera 2008), so the weights are self-consistent and mean_j ω_j r_j(ψ) estimates
    p(d_i|ψ)/Z_i.  The mixture draws go where the populations of the hyper-posterior put mass,
    which the stage-1 samples drawn under p0 may never reach (issue 15).

    Parameters
    ----------
    log_pmix_ratio : ndarray (R,)
    n_post : int
        Leading stage-1 rows.

    Returns
    -------
    ndarray (R,)
    """
    lr = np.asarray(log_pmix_ratio, float)
    rows = lr.shape[0]
    if not (0 < n_post < rows) or not np.all(np.isfinite(lr)):
        raise HbmError(f"mixture_log_weights: need 0 < n_post < rows and finite ratios, got {n_post}, {rows}")
    n_q = rows - n_post
    log_c = float(np.logaddexp.reduce(lr[:n_post]) - np.log(n_post))  # importance identity as a start
    for _ in range(int(max_iter)):
        new = float(np.logaddexp.reduce(lr - np.logaddexp(np.log(n_post), np.log(n_q) + lr - log_c)))
        if abs(new - log_c) < tol:
            log_c = new
            break
        log_c = new
    a = n_post / rows
    return -np.logaddexp(np.log(a), np.log1p(-a) + lr - log_c)


def _edge_slope(z: np.ndarray, ll: np.ndarray, side: int, frac: float) -> float:
    """d log L / dz of the likelihood at one edge of the samples, from the ``frac`` outermost samples.

    Least-squares slope of the samples' log-likelihoods on z, clipped so that the likelihood can
    only fall beyond the edge (never rise: then flat extrapolation, the conservative choice).  A
    likelihood that is flat at the edge (data bounding the parameter from the other side only)
    gives ≈ 0; a decaying one gives its local log-slope, which the extrapolation uses.
    """
    q = np.quantile(z, frac if side < 0 else 1.0 - frac)
    sel = z <= q if side < 0 else z >= q
    if sel.sum() < 5 or np.ptp(z[sel]) <= 0:
        return 0.0
    x = z[sel] - z[sel].mean()
    slope = float(np.dot(x, ll[sel] - ll[sel].mean()) / np.dot(x, x))
    return max(slope, 0.0) if side < 0 else min(slope, 0.0)


def reuse_unreliable(
    reuse: Mapping[str, Mapping],
    *,
    ess_threshold: float = 50.0,
    khat_max: float = K_HAT_THRESHOLD,
    beyond_max: float = 0.35,
) -> dict[str, tuple[bool, list[str]]]:
    """Decide per specimen whether reusing its samples is unreliable (then refine it).

    Parameters
    ----------
    reuse : mapping specimen -> dict
        ``result.reuse`` (entries of :func:`reuse_diagnostics` plus ``ess_q10`` / ``ess_raw_q10``).
    ess_threshold : float
        10 % quantile of the importance ESS over hyper draws below which the reuse collapsed.
    khat_max : float
        Hyper-posterior median PSIS k̂ (or k̂ of the updated weights) above which the ratios
        have too heavy a tail.
    beyond_max : float
        ``population_beyond`` (population-predictive mass beyond the samples' 0.5–99.5 % range,
        the likelihood extrapolated with its edge slope) above which the samples miss the
        tails.  Calibrated on the gold benchmark (workflows/benchmarks/hierarchical_gold.py):
        the specimens whose reweighted individuals were 1.2–2.2 NUTS sd off had 0.44–0.67, the
        ones within 0.64 sd 0.22–0.26.  Without stored log-likelihoods (flat extrapolation, an
        upper bound) it is reported but not acted on.

    Returns
    -------
    dict specimen -> (unreliable, reasons)
    """
    out = {}
    for key, r in reuse.items():
        why = []
        for name in ("ess_q10", "ess_raw_q10"):
            if name in r and r[name] < ess_threshold:
                why.append(f"{name} {r[name]:.1f} < {ess_threshold:g}")
        for name in ("khat_median", "khat_updated"):
            if name in r and r[name] > khat_max:
                why.append(f"{name} {r[name]:.2f} > {khat_max:g}")
        # flat extrapolation (no stored log-likelihoods) is only an upper bound: reported, not a trigger
        if r.get("likelihood_slope", True) and r.get("population_beyond", 0.0) > beyond_max:
            why.append(f"population mass beyond the samples {r['population_beyond']:.2f} > {beyond_max:g}")
        out[key] = (bool(why), why)
    return out


def refine_individual(
    result: HierarchicalResult,
    specimen: str,
    log_likelihood: Callable[[np.ndarray], np.ndarray],
    *,
    n_samples: int = 2000,
    seed=None,
    n_hyper: int = 500,
    weighting: str = "loo",
    progress: bool = True,
    sampler: Callable | None = None,
    augment: Callable[[np.ndarray], tuple[np.ndarray, np.ndarray]] | None = None,
    bounds=None,
    return_mixture: bool = False,
    **tmcmc_options,
) -> Any:
    """Fresh TMCMC of p(θ_i | all data) for a specimen whose importance ESS collapsed.

    The target (on the stage-1 box, uniform reference) is

        log p(d_i|θ) + log Σ_m w_m p(θ|ψ_m) − log p_prior(θ),

    over hyper-posterior draws ψ_m.  ``weighting="loo"`` (default) uses
    w_m ∝ 1/p̂(d_i|ψ_m), which turns p(ψ|all data) into p(ψ|data without i): then the target
    is exactly p(d_i|θ)·∫p(θ|ψ)p(ψ|D₋ᵢ)dψ ∝ p(θ_i|all data).  ``weighting="plain"`` uses
    w_m = 1/M (the population predictive given all data; counts d_i twice, slightly
    over-concentrated, but does not rely on p̂(d_i|ψ)).

    Parameters
    ----------
    result : HierarchicalResult
    specimen : str
    log_likelihood : callable (n, len(result.all_names)) -> (n,)
        The specimen's stage-1 log-likelihood.
    n_samples, seed, progress, sampler, **tmcmc_options
        Passed to the TMCMC driver.
    n_hyper : int
        Number of hyper-posterior draws in the mixture (thinned at random).
    weighting : {"loo", "plain"}
    augment : callable theta (n, d) -> (columns (n, len(result.all_names)), log_prior (n,)), optional
        Required for a result built with ``log_prior`` (pooled derived features): maps the
        likelihood's parameters to the hierarchical model's columns and returns the stage-1
        prior log density of the pooled columns, exactly as passed to :func:`hierarchical`.
        With a uniform stage-1 prior on θ and the unpooled directions keeping their stage-1
        prior given the pooled ones, p(θ|ψ) = p_pop(φ(θ)|ψ)·p0(θ)/p0(φ(θ)), so the target is
        log p(d_i|θ) + log Σ_m w_m p_pop(φ(θ)|ψ_m) − log p0(φ(θ)).  A θ whose log_prior is not
        finite gets −inf.
    bounds : array (d, 2), optional
        Box of θ for the fresh run; default ``result.bounds`` (required with ``augment``,
        whose θ are not the hierarchical model's columns).
    return_mixture : bool
        Also return the mixture (raw hyper draws (M, ·), normalised weights (M,)) that defines
        the population part of the target, e.g. for :func:`mixture_log_weights`.

    Returns
    -------
    TMCMCResult (or (TMCMCResult, raw, weights) with ``return_mixture``)
        ``.samples`` are draws of the updated posterior of the specimen (the columns of θ);
        ``.log_evidence`` is log ∫ p(d_i|θ) Σ_m w_m p(θ|ψ_m) dθ.
    """
    if specimen not in result.specimens:
        raise HbmError(f"refine_individual: unknown specimen {specimen!r}; have {result.specimens}")
    if weighting not in ("loo", "plain"):
        raise HbmError(f"refine_individual: weighting must be 'loo' or 'plain', got {weighting!r}")
    if result.options.get("log_prior") and augment is None:
        # without the map θ -> pooled columns the stage-1 prior density of the columns is unknown
        raise HbmError("refine_individual: a result built with log_prior (pooled derived features) needs "
                       "augment= (theta -> (columns, log_prior)) and bounds= of the likelihood's parameters")
    if augment is not None and bounds is None:
        raise HbmError("refine_individual: augment= needs bounds= (the box of the likelihood's parameters)")
    ss = np.random.SeedSequence(seed if not isinstance(seed, np.random.Generator) else seed.integers(2**63))
    s_thin, s_run = ss.spawn(2)
    rng = np.random.default_rng(s_thin)
    idx = np.arange(result.raw_samples.shape[0])
    if idx.size > n_hyper:
        idx = np.sort(rng.choice(idx.size, n_hyper, replace=False))
    raw = result.raw_samples[idx]
    i = result.specimens.index(specimen)
    if weighting == "loo":
        lw = -result.log_marginal[idx, i]
        w = np.exp(lw - lw.max())
    else:
        w = np.ones(idx.size)
    model = result.model
    log_prior = -np.sum(np.log(model.hi - model.lo))

    def target(theta: np.ndarray) -> np.ndarray:
        theta = np.atleast_2d(np.asarray(theta, float))
        ll = np.asarray(log_likelihood(theta), float)
        if augment is None:
            cols, lp0 = theta, log_prior
        else:
            cols, lp0 = augment(theta)
            cols, lp0 = np.asarray(cols, float), np.asarray(lp0, float)
        ab = model.all_bounds
        # the population is truncated to the box: columns outside it have density 0
        ok = np.isfinite(lp0) & np.all((cols >= ab[:, 0]) & (cols <= ab[:, 1]), axis=-1)
        # columns of a rejected θ are replaced by the box centre so the density stays finite
        cols = np.where(ok[:, None], cols, 0.5 * (ab[:, 0] + ab[:, 1]))
        lp = model.log_density(cols, raw, w)
        with np.errstate(invalid="ignore"):
            out = ll + lp - lp0
        return np.where(ok & np.isfinite(out), out, -np.inf)

    if sampler is None:
        sampler = _tmcmc
    box = result.bounds if bounds is None else np.asarray(bounds, float)
    res = sampler(target, box, int(n_samples), seed=int(s_run.generate_state(1)[0]), progress=progress,
                  **tmcmc_options)
    if return_mixture:
        return res, raw, w / w.sum()
    return res


# --------------------------------------------------------------------------------------
# kernel bandwidth and the choice of pooled parameters
# --------------------------------------------------------------------------------------
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


def prior_sd_transformed(kind: str, lo: float, hi: float) -> float:
    """sd of z = g(θ) when θ is uniform on [lo, hi] (the stage-1 prior seen in the transformed space).

    identity: (hi − lo)/√12; logit: π/√3 (the standard logistic); log: sd of log θ, whose density
    is e^z/(hi − lo) on [log lo, log hi] (64-point Gauss–Legendre, exact to rounding for any box).
    """
    if kind == "identity":
        return float((hi - lo) / np.sqrt(12.0))
    if kind == "logit":
        return float(np.pi / np.sqrt(3.0))
    if kind == "log":
        if not lo > 0:
            raise HbmError(f"hierarchical: transform 'log' needs a positive lower bound, got {lo:g}")
        a, b = np.log(lo), np.log(hi)
        x, w = np.polynomial.legendre.leggauss(64)
        z = 0.5 * (b - a) * x + 0.5 * (a + b)
        p = w * np.exp(z - b)  # density ∝ e^z; scaled by e^−b against overflow
        p /= p.sum()
        m = np.sum(p * z)
        return float(np.sqrt(np.sum(p * (z - m) ** 2)))
    raise HbmError(f"hierarchical: transform must be one of {TRANSFORMS}, got {kind!r}")


@dataclass
class PoolChoice:
    """Result of :func:`auto_pool`: the chosen names (also iterable as ``pooled, reasons = ...``).

    Attributes
    ----------
    pooled : list of str
        Parameters to pool, in column order.
    reasons : dict name -> dict
        Per candidate: ``sd_ratio`` (per specimen, posterior sd / prior sd in the transformed
        space), ``informative`` (per specimen, bool), ``n_informative``, ``n_specimens``,
        ``pooled`` (bool) and a one-line ``reason``.
    """

    pooled: list
    reasons: dict

    def __iter__(self):
        return iter((self.pooled, self.reasons))


def auto_pool(
    samples_by_specimen: Mapping[str, np.ndarray],
    names: Sequence[str],
    bounds,
    transforms: Mapping[str, str] | None = None,
    *,
    candidates: Sequence[str] | None = None,
    max_sd_ratio: float = 2.0 / 3.0,
    min_fraction: float = 0.5,
    min_pooled: int = 1,
) -> PoolChoice:
    """Choose the parameters worth pooling: those the stage-1 data inform in most specimens.

    A parameter is *informative* for a specimen when its stage-1 posterior sd in the
    transformed space (the space of the population model) is below ``max_sd_ratio`` times the
    sd of the stage-1 uniform prior in that space (:func:`prior_sd_transformed`); the default
    2/3 means a variance contraction 1 − σ²_post/σ²_prior of at least 5/9.  It is pooled when it
    is informative in at least ``min_fraction`` of the specimens.

    Why: for a parameter whose posteriors are prior-like, p(d_i|ψ) is flat in its (mu, sd), the
    hyper-posterior returns the hyperprior, and that hyperprior reaches populations whose mass
    lies in the transformed tails (|mu| near logit_range, sd of several logit units) where the
    stage-1 samples, drawn under a uniform prior, are exponentially rare: the importance ratios
    are then dominated by one or two extreme samples and the ESS collapses, multiplicatively
    over such parameters.  Pooling them adds nothing but noise; they keep their stage-1 prior.

    Parameters
    ----------
    samples_by_specimen : mapping specimen -> ndarray (N_i, len(names))
        Stage-1 posterior samples.
    names : sequence of str
        Column names.
    bounds : array_like (len(names), 2)
        Stage-1 uniform prior box.
    transforms : mapping name -> {"identity","log","logit"}, optional
        Transform of each candidate (default identity), as passed to :func:`hierarchical`.
    candidates : sequence of str, optional
        Names that may be pooled (default all), e.g. the model parameters without ``sigma``.
    max_sd_ratio : float
        Posterior/prior sd ratio below which a specimen counts as informed.
    min_fraction : float
        Fraction of specimens that must be informed.
    min_pooled : int
        If fewer candidates pass, the best-informed ones (most informed specimens, then the
        smallest median ratio) are added up to this number, with a reason saying so, so that a
        hierarchical layer can always run; 0 allows an empty choice.

    Returns
    -------
    PoolChoice
        ``pooled`` and per-candidate ``reasons``.
    """
    names = [str(n) for n in names]
    candidates = list(names) if candidates is None else [str(c) for c in candidates]
    bad = [c for c in candidates if c not in names]
    if bad:
        raise HbmError(f"auto_pool: candidates {bad} are not among names {names}")
    if not samples_by_specimen:
        raise HbmError("auto_pool: samples_by_specimen is empty")
    if not (0 < max_sd_ratio) or not (0 < min_fraction <= 1):
        raise HbmError(f"auto_pool: need max_sd_ratio > 0 and 0 < min_fraction <= 1, got {max_sd_ratio}, {min_fraction}")
    tr = {c: dict(transforms or {}).get(c, "identity") for c in candidates}
    model = HierarchicalModel(names, bounds, pooled=candidates, transforms=tr)
    prior_sd = np.array([prior_sd_transformed(k, lo, hi) for k, lo, hi in zip(model.kinds, model.lo, model.hi)])
    ratios = []
    for key, x in samples_by_specimen.items():
        x = np.asarray(x, float)
        if x.ndim != 2 or x.shape[1] != len(names) or x.shape[0] < 2:
            raise HbmError(f"auto_pool: samples of {key!r} must be (N>=2, {len(names)}), got {x.shape}")
        z, _ = model.to_z(x)
        ratios.append(z.std(axis=0, ddof=1) / prior_sd)
    ratios = np.array(ratios)  # (n_specimens, n_candidates)
    informative = ratios < max_sd_ratio
    n_spec = ratios.shape[0]
    need = int(np.ceil(min_fraction * n_spec - 1e-9))
    pooled, reasons = [], {}
    for k, c in enumerate(candidates):
        n_inf = int(informative[:, k].sum())
        ok = n_inf >= need
        if ok:
            pooled.append(c)
        reasons[c] = {
            "sd_ratio": ratios[:, k].tolist(), "informative": informative[:, k].tolist(),
            "n_informative": n_inf, "n_specimens": n_spec, "pooled": ok, "transform": tr[c],
            "reason": (f"{c}: posterior sd < {max_sd_ratio:.2f} x prior sd ({tr[c]} space) in {n_inf}/{n_spec} "
                       f"specimens (need {need}); median ratio {np.median(ratios[:, k]):.2f} -> "
                       + ("pooled" if ok else "not pooled (keeps its stage-1 prior)")),
        }
    if len(pooled) < min_pooled:
        # rank the rest: most informed specimens first, then the smallest median sd ratio
        rest = sorted((c for c in candidates if c not in pooled),
                      key=lambda c: (-reasons[c]["n_informative"], float(np.median(reasons[c]["sd_ratio"]))))
        for c in rest[: min_pooled - len(pooled)]:
            pooled.append(c)
            reasons[c]["pooled"] = True
            reasons[c]["reason"] = reasons[c]["reason"].replace(
                "not pooled (keeps its stage-1 prior)", f"pooled anyway: best informed of the candidates (min_pooled={min_pooled})")
    pooled = [n for n in names if n in pooled]
    return PoolChoice(pooled=pooled, reasons=reasons)
