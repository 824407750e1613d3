"""Transitional MCMC (Ching & Chen 2007) with log-evidence, a manifold (mMALA) kernel and resumable runs.

The sampler is split blackjax-style into a pure core and a driver:

* :func:`init` draws the stage-0 population from the uniform prior on a box and evaluates it;
* :func:`step` performs one tempering stage (choose the next β by a bracketed root find on the
  coefficient of variation of the incremental weights, accumulate the log-evidence, resample,
  move the population with vectorised Metropolis–Hastings) and returns ``(state, info)`` with
  ``info`` a :class:`StageInfo` (whose fields are also the stored per-stage schema of :mod:`hbm.io`);
* :func:`tmcmc` loops over stages with a tqdm progress bar and an atomic checkpoint after
  every stage, and returns a :class:`TMCMCResult`; :func:`checkpoint_progress` reads the
  stage and β of such a checkpoint (progress display of running fits).

Every random number comes from a numpy ``Generator`` whose ``bit_generator.state`` is part of the
:class:`TMCMCState`, so a run resumed from a checkpoint is bitwise identical to an uninterrupted one.

The log-likelihood is always called with a whole ``(m, d)`` population and must return ``(m,)``;
NaN is treated as −inf.  Proposals that leave the prior box are rejected without evaluation.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import math
import os
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Mapping, NamedTuple, Optional, Protocol, get_type_hints, runtime_checkable

import numpy as np
from scipy.optimize import brentq
from scipy.special import logsumexp

from ..errors import HbmError
from ..utils import atomic_path
from .local_proposal import fit_local_metric, local_step, nearest_reference

LogLikelihood = Callable[[np.ndarray], np.ndarray]
GradientFIM = Callable[[np.ndarray], "tuple[np.ndarray, np.ndarray]"]


@runtime_checkable
class Bijection(Protocol):
    """Sampling coordinates u = g(θ) of the random walk, replacing the default logit transform.

    The samplers know nothing of the model: a caller that knows the model's degeneracies (e.g.
    :class:`hbm.combinations.CombinationCoordinates`) passes an object with

    * ``name`` : str — identifies the map in checkpoint fingerprints;
    * ``support`` : array (d, 2) — the box of u that g maps the prior box onto (±inf allowed);
      proposals outside it are rejected without evaluating the likelihood;
    * ``forward(theta)`` : (n, d) → u (n, d);
    * ``inverse(u)`` : (n, d) → (θ (n, d), log|det ∂θ/∂u| (n,)).

    The prior of θ is uniform on the box, so the log-density of u is the log-Jacobian up to a
    constant: the MH ratio uses it and the tempered target (hence log Ẑ) is unchanged.
    """

    name: str
    support: np.ndarray

    def forward(self, theta: np.ndarray) -> np.ndarray: ...

    def inverse(self, u: np.ndarray) -> "tuple[np.ndarray, np.ndarray]": ...

_CHECKPOINT_VERSION = 1

#: Default population size: on the 9-parameter muscle benchmark (DESIGN.md §6) N = 2000 with the
#: default adaptive steps and CoV target 1.0 reaches a median |log Ẑ − gold| ≈ 0.1 and posterior
#: means within a median ~0.17 gold sd in ~4.1–4.5 s of CPU (20 seeds; CoV target 1.5: 0.19,
#: 0.24 sd with one seed in 20 at 1.03 sd, 3.1 s); see workflows/benchmarks/README.md.
DEFAULT_N_SAMPLES = 2000

#: Default CoV target per kernel.  Random walk: 1.0.  ``cov_target=1.5`` saves ~31 % CPU on the
#: muscle benchmark (10 instead of 15 stages) but doubles the median evidence error (0.10 → 0.19
#: nats) and put one seed in 20 1.03 gold sd off in a posterior mean; the evidence feeds model
#: choice (``hbm diagnose``), so accuracy wins the default.  Manifold: 1.0 (at 1.5 its error on
#: the 9-D Gaussian validation exceeded the random walk's).
DEFAULT_COV_TARGET = {"rw": 1.0, "manifold": 1.0}


# ----------------------------------------------------------------------------------------
# configuration, state, result
# ----------------------------------------------------------------------------------------
@dataclass(frozen=True)
class TMCMCConfig:
    """Settings of one TMCMC run (everything that changes the random stream or the answer).

    Attributes
    ----------
    n_samples : int
        Population size N.
    kernel : {"rw", "manifold"}
        Random walk with the weighted population covariance, or simplified mMALA with the
        tempered Fisher metric (``gradient_fim`` required).
    cov_target : float or None
        Target coefficient of variation of the incremental weights (1 ⇔ ESS = N/2, 1.5 ⇔ ESS =
        0.31·N); None = :data:`DEFAULT_COV_TARGET` of the kernel (resolved on construction).
    proposal_scale : float
        Initial scale of the random-walk proposal relative to the population covariance
        (adapted toward ``target_acceptance`` when ``adapt_scale``).
    n_steps : int or None
        Metropolis steps per stage; ``None`` = adaptive: keep stepping until every coordinate's
        correlation with the stage-start population is ≤ ``mixing_target`` (between
        ``min_steps`` and ``max_steps``).
    max_stages : int
        Stage cap; the last allowed stage jumps to β = 1 (flagged in the stage info).
    min_dbeta : float
        Smallest β increment (keeps the loop moving when the CoV target cannot be met).
    target_acceptance : float
        Acceptance rate the random-walk scale is adapted to (0.3 measured best on the muscle
        benchmark; 0.2 was worse).
    target_acceptance_manifold : float
        Acceptance rate the manifold step size ε is adapted to (≈ 0.57 is MALA's optimum).
    resampling : {"systematic", "multinomial"}
        Resampling scheme between stages.
    ridge : float
        Manifold kernel regulariser: G = β·F + ridge·Σ⁻¹ with Σ the weighted population covariance
        (keeps G invertible along non-identifiable directions).
    transform : {"logit", "none"}
        Coordinates of the random walk.  "logit" (default) walks in u = logit((θ − lo)/(hi − lo))
        with the logistic prior density of u in the MH ratio: proposals never leave the box and
        multiplicative ridges (T1 ∝ 1/(1 − VOLF), A·exp(T2·x)) become nearly straight, which is
        what made the muscle benchmark accurate at ~100× less cost.  The manifold kernel always
        works in box coordinates.  A ``bijection`` passed to :func:`tmcmc` / :func:`step`
        replaces this transform by the caller's coordinates (:class:`Bijection`).
    n_islands : int
        K contiguous blocks of particles resampled separately (sharing β and proposal shape);
        the spread of their evidences gives ``log_evidence_se`` including the error of incomplete
        mixing.  The final stage pools them (each weighted by its evidence).  K = 1 (or N < 80)
        falls back to the per-stage delta-method SE.
    de_fraction : float
        Probability that a particle proposes a differential-evolution move (ter Braak 2006) instead
        of the random walk at each MH step: u' = u + γ·(P_a − P_b) + de_noise·L z with P the
        stage-start population (held fixed during the stage) and a ≠ b particles not descended
        from the particle's own ancestor, so the kernel is symmetric and exact.  0 (default)
        leaves the random-walk stream untouched.  On the muscle benchmark (0.5, 1.0) it did not
        reduce the steps per stage (the late stages stay at ``max_steps``) and made log Ẑ less
        accurate (median error 0.2 with 0.5, ~0.6 with 1.0, vs 0.1 without).  DE pairs span the
        islands, so the island SE can be optimistic with DE moves.
    de_gamma : float or None
        DE step factor γ; None = 2.38/√(2d) (optimal for Gaussian targets).
    de_jump : float
        Probability that a DE proposal uses γ = 1 (jumps between modes).
    de_noise : float
        Scale of the Gaussian jitter added to a DE move, relative to the population covariance.
    mixing : {"max_corr", "pca", "ll_rank", "max_corr_ll"}
        Decorrelation measure of the adaptive step count: largest |correlation| between stage-start
        and current positions over the sampling coordinates ("max_corr", default), over the
        stage-start principal axes ("pca"), of the log-likelihood ranks ("ll_rank"), or over
        coordinates and log-likelihood rank ("max_corr_ll").
    mixing_every : int
        Evaluate the mixing measure every k steps only (after ``min_steps``).
    max_evaluations : int or None
        Hard cap on log-likelihood evaluations (particles, including the N of the initial
        population).  A stage's MH loop stops before a step that could exceed it, and once fewer
        than N evaluations remain the next stage jumps to β = 1 without moves; the result is then
        flagged ``budget_exhausted``.  The SE then comes from the crude forced last stage and is
        only a lower bound: on the muscle benchmark a 120k budget on the frugal preset gave log Ẑ
        errors of 26–37 nats with SE ≤ 1.  None = no cap.
    recycle : bool
        Keep the population of every stage (after its moves) and estimate the evidence and the
        posterior from all of them at once with the multistate bridge / MBAR equations
        (Z_t = Σ_i L_i^β_t / Σ_s N_s L_i^β_s / Z_s; the recycling of "persistent sampling",
        Karamanis et al. 2025); the SE is the spread of the same estimate over the islands, which
        are then also kept apart in the final stage.  False (default) = the classical product of
        per-stage mean weights and the last population only.
    proposal : {"rw", "mixture", "local"}
        Move kernel of the random walk: "rw" (default) the Gaussian random walk with the
        population covariance; "mixture" a mixture kernel that with probability
        ``independence_fraction`` proposes independently from a multivariate-t mixture fitted
        by EM to the stage-start population (full covariance per cluster, in the sampling
        coordinates), else the random walk; "local" the random walk with the covariance of the
        ``local_neighbours`` stage-start particles nearest to the current point
        (:mod:`hbm.samplers.local_proposal`; needs ``transform="logit"``).  Needs ``kernel="rw"``.
        On the muscle benchmark "local" cut the whitened Fisher information of the thin
        direction from ~7600 to ~30–60 but decorrelated the early, broad stages worse than the
        global walk; N = 1000 with 50 steps per stage (5e5 evaluations) was 1.3–2.6 nats low.
    mixture_components : int
        Largest number of clusters of the fitted mixture (clusters with fewer than d + 2 members
        are dropped).
    independence_fraction : float
        Probability of the independence proposal per particle and step (``proposal="mixture"``).
    mixture_df : float
        Degrees of freedom of the t components (heavy tails keep the independence sampler
        geometrically ergodic where the fit is too narrow).
    local_neighbours : int
        Neighbours whose covariance a point uses with ``proposal="local"`` (at least d + 1).
    local_ridge : float
        Multiple of the global covariance added to every neighbourhood covariance; must stay
        well below the squared ratio of the thinnest local to the global width (1e-2 hid the
        muscle benchmark's thin direction entirely; 1e-4 did not).
    persistent : bool
        Persistent sampling (needs ``recycle``): every stage resamples its N particles from the
        pool of *all* stored populations, weighted to the new β by the MBAR mixture density
        (L_i^β / Σ_s N_s L_i^β_s / Z_s), instead of from the last population only, and chooses
        β so that the pool's ESS at β is ``persistent_ess``·N (capped at pool/(1 + cov_target²)
        while the pool is small).  With an ESS target above N the resampled particles are
        nearly all distinct and come from several stages' lineages (less degeneracy per MH
        step; the idea of pocoMC's persistent sampling, Karamanis et al. 2025).  Islands
        resample from their own part of the pool, so their recycled evidences stay independent
        and give the SE.  Measured on the muscle benchmark (N = 1000, ≤ 30 steps per stage):
        target 2·N took 28 stages, 8.4e5 evaluations, log Ẑ 0.69 high; target 0.5·N 13 stages,
        3.9e5 evaluations, 1.46 low — no better than the plain recycling there, and the MBAR
        solve of the growing pool every stage costs CPU (~30–120 s per run).
    persistent_ess : float
        Pool ESS target per particle of ``persistent``.
    """

    n_samples: int
    kernel: str = "rw"
    cov_target: Optional[float] = None
    proposal_scale: float = 0.2
    n_steps: Optional[int] = None
    min_steps: int = 2
    max_steps: int = 100
    mixing_target: float = 0.1
    max_stages: int = 100
    min_dbeta: float = 1e-9
    target_acceptance: float = 0.3
    target_acceptance_manifold: float = 0.57
    adapt_scale: bool = True
    resampling: str = "systematic"
    ridge: float = 0.1
    transform: str = "logit"
    n_islands: int = 4
    de_fraction: float = 0.0
    de_gamma: Optional[float] = None
    de_jump: float = 0.1
    de_noise: float = 0.05
    mixing: str = "max_corr"
    mixing_every: int = 1
    max_evaluations: Optional[int] = None
    recycle: bool = False
    proposal: str = "rw"
    mixture_components: int = 4
    independence_fraction: float = 0.5
    mixture_df: float = 5.0
    local_neighbours: int = 30
    local_ridge: float = 0.01
    persistent: bool = False
    persistent_ess: float = 2.0

    def __post_init__(self) -> None:
        if self.cov_target is None:  # kernel-dependent default (frozen dataclass: set once here)
            object.__setattr__(self, "cov_target", DEFAULT_COV_TARGET.get(self.kernel, 1.0))

    def validate(self) -> None:
        if int(self.n_samples) < 4:
            raise HbmError(f"tmcmc: n_samples must be >= 4, got {self.n_samples}")
        if self.kernel not in ("rw", "manifold"):
            raise HbmError(f"tmcmc: kernel must be 'rw' or 'manifold', got {self.kernel!r}")
        if not (self.cov_target > 0 and math.isfinite(self.cov_target)):
            raise HbmError(f"tmcmc: cov_target must be a positive number, got {self.cov_target}")
        if not self.proposal_scale > 0:
            raise HbmError(f"tmcmc: proposal_scale must be > 0, got {self.proposal_scale}")
        if self.n_steps is not None and int(self.n_steps) < 1:
            raise HbmError(f"tmcmc: n_steps must be >= 1 or None (adaptive), got {self.n_steps}")
        if int(self.max_stages) < 1:
            raise HbmError(f"tmcmc: max_stages must be >= 1, got {self.max_stages}")
        if self.transform not in ("none", "logit"):
            raise HbmError(f"tmcmc: transform must be 'none' or 'logit', got {self.transform!r}")
        if self.resampling not in ("systematic", "multinomial"):
            raise HbmError(f"tmcmc: resampling must be 'systematic' or 'multinomial', got {self.resampling!r}")
        if not 0 < self.target_acceptance < 1:
            raise HbmError(f"tmcmc: target_acceptance must be in (0, 1), got {self.target_acceptance}")
        if int(self.min_steps) < 1 or int(self.max_steps) < int(self.min_steps):
            raise HbmError("tmcmc: need 1 <= min_steps <= max_steps")
        if not 0.0 <= self.de_fraction <= 1.0:
            raise HbmError(f"tmcmc: de_fraction must be in [0, 1], got {self.de_fraction}")
        if self.de_gamma is not None and not self.de_gamma > 0:
            raise HbmError(f"tmcmc: de_gamma must be > 0 or None, got {self.de_gamma}")
        if not 0.0 <= self.de_jump <= 1.0:
            raise HbmError(f"tmcmc: de_jump must be in [0, 1], got {self.de_jump}")
        if not self.de_noise >= 0:
            raise HbmError(f"tmcmc: de_noise must be >= 0, got {self.de_noise}")
        if self.mixing not in _MIXING:
            raise HbmError(f"tmcmc: mixing must be one of {sorted(_MIXING)}, got {self.mixing!r}")
        if int(self.mixing_every) < 1:
            raise HbmError(f"tmcmc: mixing_every must be >= 1, got {self.mixing_every}")
        if self.max_evaluations is not None and int(self.max_evaluations) < int(self.n_samples):
            raise HbmError(f"tmcmc: max_evaluations ({self.max_evaluations}) must be >= n_samples "
                           f"({self.n_samples}): the initial population alone costs N evaluations")
        if self.proposal not in ("rw", "mixture", "local"):
            raise HbmError(f"tmcmc: proposal must be 'rw', 'mixture' or 'local', got {self.proposal!r}")
        if self.proposal != "rw" and self.kernel != "rw":
            raise HbmError(f"tmcmc: proposal={self.proposal!r} needs kernel='rw'")
        if self.proposal == "local" and self.transform != "logit":
            raise HbmError("tmcmc: proposal='local' needs transform='logit' (its steps are unbounded)")
        if int(self.local_neighbours) < 2:
            raise HbmError(f"tmcmc: local_neighbours must be >= 2, got {self.local_neighbours}")
        if self.persistent and not self.recycle:
            raise HbmError("tmcmc: persistent=True needs recycle=True (the pool is the recycled history)")
        if not self.persistent_ess > 0:
            raise HbmError(f"tmcmc: persistent_ess must be > 0, got {self.persistent_ess}")
        if not self.local_ridge > 0:
            raise HbmError(f"tmcmc: local_ridge must be > 0, got {self.local_ridge}")
        if int(self.mixture_components) < 1:
            raise HbmError(f"tmcmc: mixture_components must be >= 1, got {self.mixture_components}")
        if not 0.0 <= self.independence_fraction <= 1.0:
            raise HbmError(f"tmcmc: independence_fraction must be in [0, 1], got {self.independence_fraction}")
        if not self.mixture_df > 0:
            raise HbmError(f"tmcmc: mixture_df must be > 0, got {self.mixture_df}")


#: Fields added to :class:`TMCMCConfig` after checkpoint version 1: left out of the checkpoint
#: fingerprint while at their defaults, so checkpoints of older runs still resume.
_LATE_FIELDS = {"max_evaluations": None, "recycle": False, "proposal": "rw", "mixture_components": 4,
                "independence_fraction": 0.5, "mixture_df": 5.0, "local_neighbours": 30, "local_ridge": 0.01,
                "persistent": False, "persistent_ess": 2.0}

#: Named settings for :func:`tmcmc` (``preset=``); explicit arguments override them.
#: "frugal" (experimental): a smaller population whose stages are all recycled into the evidence
#: and posterior (MBAR), moved by a fitted t-mixture independence proposal mixed with a
#: cluster-local random walk, at most 30 steps per stage.  On the muscle benchmark it spends ~8x
#: fewer evaluations than the defaults (3.2e5 vs 2.4e6) but is NOT as accurate there (log Ẑ
#: median 2.9 nats low, its island SE ~0.2 does not cover that; results/benchmarks/
#: evaluations_to_accuracy.md); on the 9-D Gaussian / banana checks mean |error| 0.16 / 0.08.
#: "lean": the default random walk at N = 1500 and CoV target 1.5 — on the muscle benchmark half
#: the default's evaluations (1.25e6 vs 2.43e6) for the same share of runs reaching |log Ẑ error| ≤ 0.3
#: and worst posterior-mean error ≤ 0.3 gold sd (3/5 each, SE covering the error 5/5), but one seed
#: in five put a posterior mean 1.1 gold sd off (results/benchmarks/evaluations_to_accuracy.md).
PRESETS: dict[str, dict[str, Any]] = {
    "default": {},
    "lean": {"n_samples": 1500, "cov_target": 1.5},
    "frugal": {"n_samples": 1000, "recycle": True, "proposal": "mixture", "n_islands": 8,
               "cov_target": 1.5, "mixing_target": 0.1, "max_steps": 30, "mixture_components": 8,
               "independence_fraction": 0.3},
}


class TMCMCState(NamedTuple):
    """Everything needed to continue a run (pure data; see :func:`step`).

    Attributes
    ----------
    samples : ndarray (n, d)
        Current population (equally weighted at the current ``beta``).
    log_likelihood : ndarray (n,)
        Log-likelihood of each particle (−inf allowed at β = 0 only).
    island_log_evidence : ndarray (K,)
        Accumulated log-evidence of each island (contiguous blocks of particles that are
        resampled separately); their spread gives the within-run standard error.
    beta : float
        Current tempering exponent.
    log_evidence : float
        Pooled log-evidence, log mean_k Ẑ_k (one island: Σ_j log mean w_j).
    log_evidence_var : float
        Accumulated per-stage delta-method variance Σ_j CoV_j²/N (used when K < 4).
    stage : int
        Number of completed stages.
    scale : float
        Current random-walk scale (relative to the population covariance).
    epsilon : float
        Current manifold step size.
    n_evaluations : int
        Log-likelihood evaluations so far (particles, not calls).
    rng_state : dict
        ``Generator.bit_generator.state`` (PCG64).
    history_samples, history_log_likelihood : ndarray (T·n, d), (T·n,) or None
        With ``recycle``: the populations of all stages so far (stage 0 = the prior draws), in
        stage order, in box coordinates, and their log-likelihoods.
    history_beta : ndarray (T,) or None
        β of each stored population.
    budget_bound : bool
        ``max_evaluations`` cut a stage's moves short or forced the jump to β = 1.
    """

    samples: np.ndarray
    log_likelihood: np.ndarray
    island_log_evidence: np.ndarray
    beta: float
    log_evidence: float
    log_evidence_var: float
    stage: int
    scale: float
    epsilon: float
    n_evaluations: int
    rng_state: dict
    history_samples: Optional[np.ndarray] = None
    history_log_likelihood: Optional[np.ndarray] = None
    history_beta: Optional[np.ndarray] = None
    budget_bound: bool = False


class StageInfo(NamedTuple):
    """Diagnostics of one tempering stage, as returned by :func:`step`.

    The fields are also the per-stage storage schema: :mod:`hbm.io` writes one
    ``(chain, stage)`` variable per field, named after it, so a field added here is stored
    without touching the writer.

    Attributes
    ----------
    beta : float
        Tempering exponent reached by the stage.
    dbeta : float
        β increment of the stage.
    log_evidence_increment : float
        log mean of the incremental weights (pooled over the islands).
    log_evidence_increment_var : float
        Delta-method variance CoV²/N of the increment.
    cov_weights : float
        Coefficient of variation of the incremental weights (the quantity the β root find targets).
    ess : float
        Effective sample size of the incremental weights.
    acceptance_rate : float
        Mean MH acceptance over the stage's steps.
    de_acceptance : float
        Acceptance of the differential-evolution proposals, or of the fitted-mixture independence
        proposals with ``proposal="mixture"`` (NaN without such moves).
    proposal_scale : float
        Random-walk scale (relative to the population covariance) after the stage's adaptation.
    epsilon : float
        Manifold step size after adaptation (NaN for the random walk).
    n_steps : int
        MH steps taken.
    evaluations : int
        Log-likelihood evaluations (particles) of the MH steps.
    mixing : float
        Final value of the decorrelation measure (``TMCMCConfig.mixing``).
    metric_ok : float
        Manifold kernel: share of particles whose metric was positive definite (NaN for the
        random walk).
    capped : bool
        The stage cap forced the jump to β = 1.
    """

    beta: float
    dbeta: float
    log_evidence_increment: float
    log_evidence_increment_var: float
    cov_weights: float
    ess: float
    acceptance_rate: float
    de_acceptance: float
    proposal_scale: float
    epsilon: float
    n_steps: int
    evaluations: int
    mixing: float
    metric_ok: float
    capped: bool

    @classmethod
    def from_record(cls, record: Mapping[str, Any]) -> StageInfo:
        """Rebuild from a stored row of numbers (netCDF floats, checkpoint JSON).

        Fields missing from ``record`` are NaN (files written before the field existed); int
        and bool fields get their type back where the stored value is finite.  Keys that are
        not fields are ignored.
        """
        vals = {}
        for name, typ in _STAGE_TYPES.items():
            v = float(record.get(name, math.nan))
            vals[name] = typ(v) if typ in (int, bool) and math.isfinite(v) else v
        return cls(**vals)


#: field -> type of :class:`StageInfo` (resolved once; annotations are strings under PEP 563)
_STAGE_TYPES = get_type_hints(StageInfo)

#: stage keys of checkpoints written before :class:`StageInfo` (renamed fields)
_LEGACY_STAGE_KEYS = {"cov": "cov_weights", "scale": "proposal_scale"}


@dataclass
class TMCMCResult:
    """Outcome of :func:`tmcmc`.

    Attributes
    ----------
    samples : ndarray (n, d)
        Equally weighted posterior population.
    log_likelihood : ndarray (n,)
    log_evidence, log_evidence_se : float
        log p(data) under the uniform prior on the box, and its within-run standard error.
    stages : list of StageInfo
        Per-stage diagnostics, one per completed stage.
    n_evaluations : int
        Total log-likelihood evaluations (particles).
    wall_time : float
        Seconds spent in this call (excluding previous sessions of a resumed run).
    likelihood_time : float
        Seconds spent inside ``log_likelihood`` (and ``gradient_fim``) during this call.
    config : TMCMCConfig
    resumed_from_stage : int
        Stage a resumed run started from (0 = fresh).
    budget_exhausted : bool
        ``max_evaluations`` bound the run (moves cut short or the jump to β = 1 forced): the
        answer is what that budget buys, with its (larger) SE.
    log_evidence_classic : float
        The product-of-mean-weights estimate (equal to ``log_evidence`` unless ``recycle``).
    """

    samples: np.ndarray
    log_likelihood: np.ndarray
    log_evidence: float
    log_evidence_se: float
    stages: list[StageInfo]
    n_evaluations: int
    wall_time: float
    likelihood_time: float
    config: TMCMCConfig
    resumed_from_stage: int = 0
    budget_exhausted: bool = False
    log_evidence_classic: float = math.nan

    @property
    def n_stages(self) -> int:
        return len(self.stages)

    @property
    def beta(self) -> np.ndarray:
        return np.array([s.beta for s in self.stages])


# ----------------------------------------------------------------------------------------
# small numerical helpers
# ----------------------------------------------------------------------------------------
def _rng_from_state(rng_state: dict) -> np.random.Generator:
    bg = np.random.PCG64()
    bg.state = rng_state
    return np.random.Generator(bg)


def _eval(log_likelihood: LogLikelihood, x: np.ndarray) -> np.ndarray:
    """Call the user's log-likelihood on (m, d) and sanitise: NaN/+inf → −inf, shape checked."""
    if x.shape[0] == 0:
        return np.empty(0)
    out = np.asarray(log_likelihood(x), dtype=float)
    if out.shape != (x.shape[0],):
        raise HbmError(f"tmcmc: log_likelihood returned shape {out.shape}, expected ({x.shape[0]},)")
    return np.where(np.isnan(out) | (out == np.inf), -np.inf, out)


def _in_box(x: np.ndarray, bounds: np.ndarray) -> np.ndarray:
    return np.all((x >= bounds[:, 0]) & (x <= bounds[:, 1]), axis=1)


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


def _resample(w: np.ndarray, n: int, rng: np.random.Generator, scheme: str) -> np.ndarray:
    """Indices of n draws proportional to w (systematic: one uniform, lowest variance)."""
    c = np.cumsum(w)
    c /= c[-1]
    if scheme == "systematic":
        u = (rng.random() + np.arange(n)) / n
    else:
        u = rng.random(n)
    return np.minimum(np.searchsorted(c, u, side="right"), len(w) - 1)


def _islands(n: int, k: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Contiguous blocks: start index, size and island id of every particle."""
    starts = (np.arange(k) * n) // k
    sizes = np.diff(np.append(starts, n))
    return starts, sizes, np.repeat(np.arange(k), sizes)


def _log_mean_exp(a: np.ndarray) -> float:
    return float(logsumexp(a) - math.log(len(a)))


def _resample_islands(logw, m_k, starts, sizes, isl, rng, scheme) -> np.ndarray:
    """Resample each island from its own weights (vectorised over islands)."""
    w = np.exp(logw - m_k[isl])
    tot = np.add.reduceat(w, starts)
    cum = np.cumsum(w / tot[isl])
    offset = np.concatenate([[0.0], cum[starts[1:] - 1]])
    cw = cum - offset[isl] + isl  # island k occupies (k, k + 1]
    n = len(logw)
    if scheme == "systematic":
        rank = np.arange(n) - starts[isl]
        u = isl + (rng.random(len(starts))[isl] + rank) / sizes[isl]
    else:
        u = isl + rng.random(n)
    idx = np.searchsorted(cw, u, side="right")
    return np.clip(idx, starts[isl], starts[isl] + sizes[isl] - 1)


def _resample_pool(w, n, starts, sizes, isl, rng, scheme) -> np.ndarray:
    """Indices into a pool of stacked populations (blocks of n, islands contiguous in each block):
    island k draws its ``sizes[k]`` particles from its own rows of every block (one loop over the
    few islands, vectorised inside)."""
    isl_pool = np.tile(isl, len(w) // n)
    idx = np.empty(n, dtype=np.int64)
    for k, (s0, m) in enumerate(zip(starts, sizes)):
        rows = np.flatnonzero(isl_pool == k)
        idx[s0:s0 + m] = rows[_resample(w[rows], int(m), rng, scheme)]
    return idx


def _weighted_cov(x: np.ndarray, w: np.ndarray, bounds: np.ndarray) -> np.ndarray:
    """Weighted covariance with a tiny box-relative floor so it is always positive definite."""
    w = w / w.sum()
    mu = w @ x
    xc = x - mu
    cov = (xc * w[:, None]).T @ xc
    width = bounds[:, 1] - bounds[:, 0]
    cov = 0.5 * (cov + cov.T) + np.diag((1e-10 * width) ** 2)
    return cov


def _safe_cholesky(cov: np.ndarray) -> np.ndarray:
    jitter = 0.0
    scale = float(np.mean(np.diag(cov)))
    for _ in range(12):
        try:
            return np.linalg.cholesky(cov + jitter * np.eye(len(cov)))
        except np.linalg.LinAlgError:
            jitter = max(jitter * 10.0, 1e-12 * scale)
    return np.diag(np.sqrt(np.maximum(np.diag(cov), 1e-300)))


def _batched_cholesky(g: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Cholesky factors of a stack (n, d, d) and a mask of the matrices where it succeeded.

    numpy raises for the whole batch if one matrix fails, so the failing ones are located by
    their smallest eigenvalue and replaced by the identity (caller falls back for them).
    """
    n, d, _ = g.shape
    ok = np.all(np.isfinite(g), axis=(1, 2))
    g = np.where(ok[:, None, None], g, np.eye(d))
    try:
        return np.linalg.cholesky(g), ok
    except np.linalg.LinAlgError:
        pass
    sym = 0.5 * (g + np.swapaxes(g, 1, 2))
    lam_min = np.linalg.eigvalsh(sym)[:, 0]
    lam_max = np.abs(np.linalg.eigvalsh(sym)[:, -1])
    good = lam_min > 1e-12 * np.maximum(lam_max, 1e-300)
    ok &= good
    g = np.where(ok[:, None, None], sym, np.eye(d))
    try:
        return np.linalg.cholesky(g), ok
    except np.linalg.LinAlgError:  # pragma: no cover - borderline matrices: test one by one
        chol = np.empty_like(g)
        for i in range(n):  # rare fallback path only, not the hot loop
            try:
                chol[i] = np.linalg.cholesky(g[i])
            except np.linalg.LinAlgError:
                ok[i] = False
                chol[i] = np.eye(d)
        return chol, ok


def _free_cov(x: np.ndarray, w: np.ndarray) -> np.ndarray:
    """Weighted covariance in unbounded sampling coordinates, with a relative floor."""
    wn = w / w.sum()
    xc = x - wn @ x
    sigma = (xc * wn[:, None]).T @ xc
    # floor: a degenerate weight vector (one survivor) must not freeze the walk
    return 0.5 * (sigma + sigma.T) + np.diag(1e-9 * x.var(axis=0) + 1e-12)


def _check_bijection(bijection: Optional[Bijection], config: TMCMCConfig, d: int) -> None:
    """Reject a bijection the kernel cannot use (checked once per stage: cheap)."""
    if bijection is None:
        return
    if not isinstance(bijection, Bijection):
        raise HbmError("tmcmc: bijection needs name, support, forward(theta) and inverse(u)")
    if config.kernel != "rw":
        raise HbmError("tmcmc: a bijection needs kernel='rw' (the manifold kernel works in box coordinates)")
    sup = np.asarray(bijection.support, float)
    if sup.shape != (d, 2) or np.any(sup[:, 0] >= sup[:, 1]):
        raise HbmError(f"tmcmc: bijection support must be a (d, 2) box with lo < hi, got shape {sup.shape}")
    if config.proposal == "local" and np.isfinite(sup).any():
        raise HbmError("tmcmc: proposal='local' needs a bijection onto all of R^d (its steps are unbounded)")


class LogitCoordinates:
    """The default sampling coordinates (``transform="logit"``) as a :class:`Bijection`.

    Passing it as ``bijection`` reproduces the default run bitwise; it is the reference that
    other coordinates are compared with (e.g. the geometry measurement of the benchmark).
    """

    name = "logit"

    def __init__(self, bounds):
        self.bounds = _check_bounds(bounds)
        self.support = np.array([[-np.inf, np.inf]] * len(self.bounds))

    def forward(self, theta: np.ndarray) -> np.ndarray:
        return _to_logit(np.asarray(theta, float), self.bounds)

    def inverse(self, u: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        return _from_logit(np.asarray(u, float), self.bounds, True)


def _to_logit(x: np.ndarray, bounds: np.ndarray) -> np.ndarray:
    """Box → R^d: u = log(f / (1 − f)), f = (x − lo)/(hi − lo) (kept finite at the faces)."""
    f = np.clip((x - bounds[:, 0]) / (bounds[:, 1] - bounds[:, 0]), 1e-15, 1.0 - 1e-15)
    return np.log(f) - np.log1p(-f)


def _from_logit(u: np.ndarray, bounds: np.ndarray, with_log_prior: bool = False):
    """Inverse of :func:`_to_logit`; optionally also the log density of u under the uniform prior.

    x uniform on the box ⇔ each u_i standard logistic: log p(u) = Σ log f(1 − f)
    = −Σ|u_i| − 2·log Π(1 + e^{−|u_i|}) (one log per particle instead of one per coordinate; the
    product lies in [1, 2^d], so it is formed directly for d ≤ 500).
    """
    a = np.abs(u)
    e = np.exp(-a)  # stable logistic: never overflows
    r = 1.0 / (1.0 + e)
    f = np.where(u >= 0, r, e * r)
    x = bounds[:, 0] + f * (bounds[:, 1] - bounds[:, 0])
    if not with_log_prior:
        return x
    if u.shape[1] <= 500:
        return x, -np.sum(a, axis=1) - 2.0 * np.log(np.prod(1.0 + e, axis=1))
    return x, np.sum(-a - 2.0 * np.log1p(e), axis=1)


class _Mixing:
    """Decorrelation of the current population from the stage start (precomputes the start side)."""

    def __init__(self, kind: str, start: np.ndarray, ll: np.ndarray):
        self.kind = kind
        if kind == "max_corr":
            a = start - start.mean(axis=0)
        elif kind == "pca":
            # principal axes of the stage-start population: the slow direction of a ridge is the
            # largest-variance one; correlation per axis instead of per raw coordinate
            c = np.cov(start, rowvar=False).reshape(start.shape[1], start.shape[1])
            _, vec = np.linalg.eigh(c)
            self.vec = vec
            a = (start - start.mean(axis=0)) @ vec
        elif kind == "ll_rank":
            a = _ranks(ll)[:, None]
        elif kind == "max_corr_ll":
            a = np.column_stack([start - start.mean(axis=0), _ranks(ll)])
        a = a - a.mean(axis=0)
        norm = np.sqrt(np.einsum("ij,ij->j", a, a))
        self.a = a / np.where(norm > 0, norm, 1.0)

    def __call__(self, x: np.ndarray, ll: np.ndarray) -> float:
        if self.kind == "max_corr":
            b = x
        elif self.kind == "pca":
            b = x @ self.vec
        elif self.kind == "ll_rank":
            b = _ranks(ll)[:, None]
        else:
            b = np.column_stack([x, _ranks(ll)])
        b = b - b.mean(axis=0)
        num = np.einsum("ij,ij->j", self.a, b)
        den = np.sqrt(np.einsum("ij,ij->j", b, b))
        r = np.where(den > 0, num / np.where(den > 0, den, 1.0), 0.0)
        return float(np.max(np.abs(r)))


def _ranks(v: np.ndarray) -> np.ndarray:
    """Ranks 0..n−1 of v (−inf/NaN lowest, ties in index order)."""
    v = np.where(np.isfinite(v), v, -1e300)
    r = np.empty(len(v))
    r[np.argsort(v, kind="stable")] = np.arange(len(v))
    return r


_MIXING = ("max_corr", "pca", "ll_rank", "max_corr_ll")


# ----------------------------------------------------------------------------------------
# Metropolis–Hastings kernels (vectorised over the population)
# ----------------------------------------------------------------------------------------
def _pairs_excluding_self(n: int, m: int, rng: np.random.Generator, rows: np.ndarray):
    """Two distinct indices a ≠ b in [0, n), both ≠ rows[i], uniform over ordered pairs."""
    a = rng.integers(0, n - 1, m)
    a += a >= rows
    b = rng.integers(0, n - 2, m)
    lo, hi = np.minimum(rows, a), np.maximum(rows, a)
    b += b >= lo
    b += b >= hi
    return a, b


def _rw_de_step(x, ll, lp, beta, chol, scale, bounds, evaluate, rng, pop, anc, de_fraction, gamma,
                de_jump, de_noise):
    """One MH step of the whole population mixing random-walk and differential-evolution moves.

    Each particle independently (probability ``de_fraction``, a choice that does not depend on its
    position, so the step is a mixture of MH kernels each leaving the tempered target invariant)
    proposes the differential-evolution move (ter Braak 2006)

        u' = u + γ·(P_a − P_b) + de_noise·L z,

    with P the stage-start population held fixed during the stage and a ≠ b two other particles
    drawn uniformly among those not descended from the same ancestor as the particle itself
    (``anc``: ancestor index of every particle after resampling) — the increment distribution is
    then symmetric and does not depend on u or on u's own start, so the plain Metropolis ratio is
    exact; γ = 1 with probability ``de_jump`` (jumps between modes).  Otherwise (or when no valid
    pair is found in a few vectorised redraws) the Gaussian random walk u' = u + scale·L z.

    ``evaluate(u)`` returns (log-likelihood, log-prior density of the sampling coordinates); ``lp``
    is that log-prior at the current points.  With ``de_fraction == 0`` the random stream is the
    plain random walk's.  Returns (x, ll, lp, accepted, is_de, n_evaluations).
    """
    n, d = x.shape
    zl = rng.standard_normal((n, d)) @ chol.T
    log_u = np.log(rng.random(n))
    prop = x + scale * zl
    is_de = np.zeros(n, dtype=bool)
    if de_fraction > 0 and n >= 4:
        rows = np.flatnonzero(rng.random(n) < de_fraction)
        a = np.empty(len(rows), dtype=np.int64)
        b = np.empty(len(rows), dtype=np.int64)
        todo = np.arange(len(rows))
        for _ in range(8):  # vectorised redraws of the few pairs hitting a relative of the particle
            if not len(todo):
                break
            ai, bi = _pairs_excluding_self(n, len(todo), rng, rows[todo])
            a[todo], b[todo] = ai, bi
            own = anc[rows[todo]]
            bad = (anc[ai] == own) | (anc[bi] == own) | (anc[ai] == anc[bi])
            todo = todo[bad]
        ok = np.ones(len(rows), dtype=bool)
        ok[todo] = False  # no valid pair found: this particle keeps its random-walk proposal
        rows, a, b = rows[ok], a[ok], b[ok]
        g = np.where(rng.random(len(rows)) < de_jump, 1.0, gamma)
        prop[rows] = x[rows] + g[:, None] * (pop[a] - pop[b]) + de_noise * zl[rows]
        is_de[rows] = True
    inside = _in_box(prop, bounds) if bounds is not None else None
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
    accept = ok_prop & ((log_ratio >= log_u) | ~np.isfinite(ll))
    x = np.where(accept[:, None], prop, x)
    ll = np.where(accept, ll_prop, ll)
    lp = np.where(accept, lp_prop, lp)
    return x, ll, lp, accept, is_de, n_eval


def _manifold_parts(grad, fim, beta, ridge_prec, eps):
    """Mean shift, Cholesky of G and validity for mMALA with G = β·F + ridge (per particle)."""
    g = beta * fim + ridge_prec[None, :, :]
    chol, ok = _batched_cholesky(g)
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


def _manifold_step(x, ll, grad, fim, beta, eps, ridge_prec, chol_rw, scale, bounds,
                   log_likelihood, gradient_fim, rng):
    """One simplified-mMALA MH step with the correct reverse density (metric at θ').

    Particles whose metric fails at θ use the random walk; the reverse density of each proposal
    uses whichever proposal the rule would pick at θ', so the MH ratio stays exact.
    """
    n, d = x.shape
    shift, chol, logdet, ok = _manifold_parts(grad, fim, beta, ridge_prec, eps)
    z = rng.standard_normal((n, d))
    # manifold draw: θ + shift + sqrt(ε)·L⁻ᵀ z  (covariance ε·G⁻¹)
    step_m = shift + math.sqrt(eps) * np.linalg.solve(np.swapaxes(chol, 1, 2), z[:, :, None])[:, :, 0]
    step_rw = scale * (z @ chol_rw.T)
    prop = x + np.where(ok[:, None], step_m, step_rw)
    log_u = np.log(rng.random(n))
    inside = _in_box(prop, bounds)
    ll_p = np.full(n, -np.inf)
    grad_p = np.zeros((n, d))
    fim_p = np.zeros((n, d, d))
    if inside.any():
        ll_p[inside] = _eval(log_likelihood, prop[inside])
        gi, fi = gradient_fim(prop[inside])
        grad_p[inside] = np.asarray(gi, dtype=float)
        fim_p[inside] = np.asarray(fi, dtype=float)
    finite = inside & np.isfinite(ll_p)
    logdet_rw = 2.0 * np.sum(np.log(np.diag(chol_rw)))
    # forward densities
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
    x = np.where(accept[:, None], prop, x)
    ll = np.where(accept, ll_p, ll)
    grad = np.where(accept[:, None], grad_p, grad)
    fim = np.where(accept[:, None, None], fim_p, fim)
    return x, ll, grad, fim, accept, int(inside.sum()), float(np.mean(ok))


# ----------------------------------------------------------------------------------------
# fitted t-mixture independence proposal (proposal="mixture")
# ----------------------------------------------------------------------------------------
class _TMixture(NamedTuple):
    """Fitted mixture: log weights (k,), means (k, d), Cholesky factors of the cluster covariances
    (k, d, d) and their log-determinants; the independence proposal uses t components with these
    covariances (scale (ν − 2)/ν · C, i.e. ``t_shift`` added to the log-determinant)."""

    log_weights: np.ndarray
    means: np.ndarray
    chols: np.ndarray
    logdets: np.ndarray
    df: float
    t_factor: float


def _mvn_logpdf_components(x: np.ndarray, means: np.ndarray, chols: np.ndarray, logdets: np.ndarray,
                           df: Optional[float] = None) -> np.ndarray:
    """(n, k) log densities of every point under every Gaussian (df None) or t component."""
    n, d = x.shape
    out = np.empty((n, len(means)))
    for c in range(len(means)):  # k ≤ a handful of clusters; vectorised over the n particles
        z = np.linalg.solve(chols[c], (x - means[c]).T)
        m2 = np.einsum("ij,ij->j", z, z)
        if df is None:
            out[:, c] = -0.5 * m2 - 0.5 * logdets[c] - 0.5 * d * math.log(2 * math.pi)
        else:
            out[:, c] = (math.lgamma(0.5 * (df + d)) - math.lgamma(0.5 * df) - 0.5 * d * math.log(df * math.pi)
                         - 0.5 * logdets[c] - 0.5 * (df + d) * np.log1p(m2 / df))
    return out


def _fit_mixture(u: np.ndarray, k: int, df: float, sigma: np.ndarray, rng: np.random.Generator,
                 n_iter: int = 25) -> _TMixture:
    """Gaussian-mixture EM on the (equally weighted) population; the scales become t components.

    Starts from k distinct particles as means and the population covariance ``sigma``; every
    covariance keeps a 1e-3·sigma ridge (duplicates after resampling must not collapse a
    cluster), and clusters with fewer than d + 2 members are dropped.
    """
    n, d = u.shape
    k = max(1, min(k, n // (d + 2)))
    means = u[rng.choice(n, size=k, replace=False)]
    covs = np.repeat(sigma[None], k, axis=0)
    logw = np.full(k, -math.log(k))
    ridge = 1e-3 * sigma
    for _ in range(n_iter if k > 1 else 0):
        chols = np.stack([_safe_cholesky(c) for c in covs])
        logdets = 2.0 * np.sum(np.log(np.diagonal(chols, axis1=1, axis2=2)), axis=1)
        lr = logw + _mvn_logpdf_components(u, means, chols, logdets)
        r = np.exp(lr - logsumexp(lr, axis=1, keepdims=True))
        nk = r.sum(axis=0)
        keep = nk >= d + 2
        if not keep.any():
            break
        r, nk = r[:, keep], nk[keep]
        means = (r.T @ u) / nk[:, None]
        covs = np.stack([((u - means[c]) * r[:, c:c + 1]).T @ (u - means[c]) / nk[c] + ridge
                         for c in range(len(nk))])
        logw = np.log(nk / nk.sum())
    if k == 1:
        means = u.mean(axis=0, keepdims=True)
    chols = np.stack([_safe_cholesky(0.5 * (c + c.T)) for c in covs])
    logdets = 2.0 * np.sum(np.log(np.diagonal(chols, axis1=1, axis2=2)), axis=1)
    # t scale with the fitted covariance: S = (ν − 2)/ν · C for ν > 2 (else C itself)
    return _TMixture(logw, means, chols, logdets, float(df), (df - 2.0) / df if df > 2 else 1.0)


def _mixture_logpdf(mix: _TMixture, x: np.ndarray) -> np.ndarray:
    """(log q_t(x) of the t-mixture, (n, k) log responsibilities of the Gaussian clusters)."""
    f = mix.t_factor
    d = x.shape[1]
    lt = _mvn_logpdf_components(x, mix.means, mix.chols * math.sqrt(f), mix.logdets + d * math.log(f), mix.df)
    lg = mix.log_weights + _mvn_logpdf_components(x, mix.means, mix.chols, mix.logdets)
    return logsumexp(mix.log_weights + lt, axis=1), lg - logsumexp(lg, axis=1, keepdims=True)


def _mixture_sample(mix: _TMixture, m: int, rng: np.random.Generator) -> np.ndarray:
    d = mix.means.shape[1]
    comp = np.searchsorted(np.cumsum(np.exp(mix.log_weights)), rng.random(m) * np.exp(mix.log_weights).sum())
    comp = np.minimum(comp, len(mix.means) - 1)
    z = rng.standard_normal((m, d))
    g = rng.chisquare(mix.df, m) / mix.df
    return mix.means[comp] + math.sqrt(mix.t_factor) * np.einsum("nij,nj->ni", mix.chols[comp], z) / np.sqrt(g)[:, None]


def _local_rw_logq(step: np.ndarray, log_resp: np.ndarray, mix: _TMixture, scale: float) -> np.ndarray:
    """log Σ_c r_c(u) N(step; 0, scale²·C_c): density of a local random-walk step from u."""
    d = step.shape[1]
    zero = np.zeros_like(mix.means)
    return logsumexp(log_resp + _mvn_logpdf_components(step, zero, scale * mix.chols,
                                                       mix.logdets + 2 * d * math.log(scale)), axis=1)


def _mixture_step(x, ll, lp, lq, beta, scale, bounds, evaluate, rng, mix, frac):
    """One MH step mixing the fitted independence proposal (probability ``frac``) and a local random walk.

    The local random walk draws a cluster c from the particle's responsibilities r_c(u) and steps
    with scale²·C_c (the covariance of that cluster: curved ridges are followed piecewise); its
    proposal density Σ_c r_c(u) N(u' − u; 0, scale²C_c) is not symmetric, so the ratio carries
    the reverse density with the responsibilities at u'.  The kernel choice does not depend on the
    position, so each particle's step is a mixture of two kernels that both leave the tempered
    target invariant; the independence move's ratio carries q(u)/q(u').  ``lq`` = (log q, log
    responsibilities) at the current points.  Returns (x, ll, lp, lq, accepted, is_independence,
    n_evaluations).
    """
    n, d = x.shape
    lq_x, lr_x = lq
    is_ind = rng.random(n) < frac
    cum = np.cumsum(np.exp(lr_x), axis=1)
    comp = np.minimum((cum < rng.random(n)[:, None] * cum[:, -1:]).sum(axis=1), len(mix.means) - 1)
    prop = x + scale * np.einsum("nij,nj->ni", mix.chols[comp], rng.standard_normal((n, d)))
    m = int(is_ind.sum())
    if m:
        prop[is_ind] = _mixture_sample(mix, m, rng)
    log_u = np.log(rng.random(n))
    inside = _in_box(prop, bounds) if bounds is not None else np.ones(n, dtype=bool)
    ll_prop, lp_prop = np.full(n, -np.inf), np.zeros(n)
    ll_prop[inside], lp_prop[inside] = evaluate(prop[inside])
    lq_p, lr_p = _mixture_logpdf(mix, prop)
    rw = ~is_ind
    corr = np.zeros(n)
    corr[is_ind] = lq_x[is_ind] - lq_p[is_ind]
    if rw.any():
        step = prop[rw] - x[rw]
        corr[rw] = _local_rw_logq(-step, lr_p[rw], mix, scale) - _local_rw_logq(step, lr_x[rw], mix, scale)
    with np.errstate(invalid="ignore"):
        log_ratio = beta * (ll_prop - ll) + (lp_prop - lp) + corr
    accept = inside & np.isfinite(ll_prop) & ((log_ratio >= log_u) | ~np.isfinite(ll))
    x = np.where(accept[:, None], prop, x)
    lq_new = (np.where(accept, lq_p, lq_x), np.where(accept[:, None], lr_p, lr_x))
    return (x, np.where(accept, ll_prop, ll), np.where(accept, lp_prop, lp), lq_new, accept, is_ind,
            int(inside.sum()))


# ----------------------------------------------------------------------------------------
# recycling: evidence and posterior from the populations of all stages (MBAR)
# ----------------------------------------------------------------------------------------
def _tempered(ll: np.ndarray, betas: np.ndarray) -> np.ndarray:
    """(M, T) matrix β_t·L_i with 0·(−inf) = 0 (the prior stage weighs every draw alike)."""
    with np.errstate(invalid="ignore"):
        b = betas[None, :] * ll[:, None]
    return np.where(betas[None, :] == 0.0, 0.0, b)


def mbar_log_evidence(log_likelihood: np.ndarray, betas: np.ndarray, counts: np.ndarray,
                      tol: float = 1e-10, max_iter: int = 5000) -> np.ndarray:
    """Log normalising constants of the tempered posteriors from all their samples at once.

    Parameters
    ----------
    log_likelihood : ndarray (M,)
        Log-likelihoods of the pooled samples: ``counts[0]`` draws of the first distribution,
        then ``counts[1]`` of the second, ...
    betas : ndarray (T,)
        Tempering exponents of the distributions p_t ∝ prior·L^β_t; ``betas[0]`` must be 0.
    counts : ndarray (T,)
        Samples per distribution.

    Returns
    -------
    ndarray (T,)
        log Z_t with log Z_0 = 0: the self-consistent solution of
        Z_t = Σ_i L_i^β_t / Σ_s N_s L_i^β_s / Z_s (multistate bridge sampling / MBAR, Meng & Wong
        1996, Shirts & Chodera 2008), by fixed-point iteration started from the sequential
        importance-sampling estimate.
    """
    ll = np.asarray(log_likelihood, dtype=float)
    betas = np.asarray(betas, dtype=float)
    counts = np.asarray(counts, dtype=int)
    if betas[0] != 0.0:
        raise HbmError("mbar_log_evidence: the first distribution must be the prior (beta 0)")
    b = _tempered(ll, betas)
    log_n = np.log(counts)
    ends = np.cumsum(counts)
    f = np.zeros(len(betas))
    for t in range(1, len(betas)):  # start: the product of mean incremental weights
        prev = b[ends[t - 1] - counts[t - 1]:ends[t - 1], t] - b[ends[t - 1] - counts[t - 1]:ends[t - 1], t - 1]
        f[t] = f[t - 1] + _log_mean_exp(prev)
    for _ in range(max_iter):
        log_den = logsumexp(b - f + log_n, axis=1)
        f_new = logsumexp(b - log_den[:, None], axis=0)
        f_new -= f_new[0]
        done = np.max(np.abs(f_new - f)) < tol
        f = f_new
        if done:
            break
    return f


def _recycled_weights(ll: np.ndarray, betas: np.ndarray, counts: np.ndarray, log_z: np.ndarray,
                      beta: float = 1.0) -> np.ndarray:
    """Normalised importance weights of the pooled samples for the target at ``beta``."""
    b = _tempered(ll, betas)
    log_den = logsumexp(b - log_z + np.log(counts), axis=1)
    lw = _tempered(ll, np.array([beta]))[:, 0] - log_den
    w = np.exp(lw - lw.max())
    return w / w.sum()


def _recycled_result(state: TMCMCState, config: TMCMCConfig, bounds: np.ndarray):
    """(log Ẑ, SE, posterior samples, their log-likelihoods) from all stored stages.

    The SE is the spread over the islands of the same recycled estimate from each island's own
    particles (the islands are resampled apart in every stage, so these are independent runs
    sharing β and proposal shape): Var(log mean Ẑ_k) ≈ var_k(Ẑ_k / mean Ẑ)/K.
    """
    hx, hll, betas = state.history_samples, state.history_log_likelihood, state.history_beta
    n = len(state.samples)
    t = len(betas)
    counts = np.full(t, n)
    log_z = mbar_log_evidence(hll, betas, counts)
    k = len(state.island_log_evidence)
    se = math.sqrt(max(float(state.log_evidence_var), 0.0))
    if k >= 2:
        starts, sizes, isl = _islands(n, k)
        isl_all = np.tile(isl, t)
        zk = np.array([mbar_log_evidence(hll[isl_all == j], betas, np.full(t, sizes[j]))[-1] for j in range(k)])
        if np.isfinite(zk).all():
            r = np.exp(zk - zk.max())
            r = r / r.mean()
            se = float(math.sqrt(np.var(r, ddof=1) / k))
    w = _recycled_weights(hll, betas, counts, log_z)
    # the run's own stream after its last stage: reproducible, and resumed runs agree
    idx = _resample(w, n, _rng_from_state(state.rng_state), "systematic")
    return float(log_z[-1]), se, hx[idx], hll[idx]


def _pool_ess(lw: np.ndarray) -> float:
    w = np.exp(lw - lw.max())
    return float(w.sum() ** 2 / (w * w).sum())


def _persistent_beta(hll: np.ndarray, hbeta: np.ndarray, n: int, beta0: float, config: TMCMCConfig,
                     force: bool) -> tuple[float, bool, np.ndarray]:
    """Next β of persistent sampling: pool ESS at β = target (bisection on log Δβ); pool log weights."""
    counts = np.full(len(hbeta), n)
    f = mbar_log_evidence(hll, hbeta, counts)
    base = logsumexp(_tempered(hll, hbeta) - f + np.log(counts), axis=1)
    tempered = lambda b: _tempered(hll, np.array([b]))[:, 0] - base  # noqa: E731
    target = min(float(config.persistent_ess) * n, len(hll) / (1.0 + float(config.cov_target) ** 2))
    if force or _pool_ess(tempered(1.0)) >= target:
        return 1.0, bool(force), tempered(1.0)
    lo, hi = math.log(float(config.min_dbeta)), math.log(1.0 - beta0)
    if _pool_ess(tempered(beta0 + math.exp(lo))) < target:
        b = beta0 + math.exp(lo)
        return b, False, tempered(b)
    for _ in range(60):  # ESS falls with β beyond the newest stage: bisection in log Δβ
        mid = 0.5 * (lo + hi)
        if _pool_ess(tempered(beta0 + math.exp(mid))) >= target:
            lo = mid
        else:
            hi = mid
        if hi - lo < 1e-6:
            break
    b = beta0 + math.exp(lo)
    return b, False, tempered(b)


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
    bounds = _check_bounds(bounds)
    config.validate()
    if isinstance(seed, np.random.Generator):
        raise HbmError("tmcmc: pass an int seed (the generator state is stored in checkpoints)")
    rng = np.random.Generator(np.random.PCG64(seed))
    n, d = int(config.n_samples), len(bounds)
    x = bounds[:, 0] + rng.random((n, d)) * (bounds[:, 1] - bounds[:, 0])
    ll = _eval(log_likelihood, x)
    if not np.isfinite(ll).any():
        raise HbmError("tmcmc: the log-likelihood is -inf/NaN for every prior draw; "
                       "check the bounds and the likelihood")
    eps0 = 1.0
    k = max(1, min(int(config.n_islands), n // 20))
    hist = (x.copy(), ll.copy(), np.zeros(1)) if config.recycle else (None, None, None)
    return TMCMCState(x, ll, np.zeros(k), 0.0, 0.0, 0.0, 0, float(config.proposal_scale), eps0, n,
                      rng.bit_generator.state, *hist)


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
        θ (n, d) → (∇ log L (n, d), Fisher information (n, d, d)); required for the manifold kernel.
    bijection : Bijection, optional
        Sampling coordinates of the random walk (instead of ``config.transform``); see
        :class:`Bijection`.  None (default) leaves the run unchanged.

    Returns
    -------
    state : TMCMCState
    info : StageInfo
        Per-stage diagnostics.
    """
    bounds = _check_bounds(bounds)
    _check_bijection(bijection, config, len(bounds))
    if state.beta >= 1.0:
        raise HbmError("tmcmc: the run is already at beta = 1")
    rng = _rng_from_state(state.rng_state)
    x, ll = state.samples, state.log_likelihood
    n, d = x.shape

    # 1. next β from the CoV of the incremental weights (root find, min step, stage cap)
    force = state.stage + 1 >= int(config.max_stages)
    # evaluations this stage may still spend (None = unlimited); below one MH step's worth
    # (n) no move is affordable, so the stage jumps straight to β = 1
    remaining = None if config.max_evaluations is None else int(config.max_evaluations) - int(state.n_evaluations)
    budget_hit = bool(state.budget_bound)
    if remaining is not None and remaining < n:
        force, budget_hit = True, True
    if config.persistent:
        b_new, capped, lw_pool = _persistent_beta(state.history_log_likelihood, state.history_beta, n,
                                                  state.beta, config, force)
        dbeta = b_new - state.beta
    else:
        dbeta, capped = _next_beta(ll, state.beta, config.cov_target, config.min_dbeta, force)
    beta = 1.0 if state.beta + dbeta >= 1.0 - 1e-12 else state.beta + dbeta
    dbeta = beta - state.beta
    with np.errstate(invalid="ignore"):
        logw = np.where(np.isfinite(ll), dbeta * ll, -np.inf)
    w = np.exp(logw - logw.max())
    r = w / w.mean()  # normalised weights, mean 1
    cov = float(r.std())
    ess = float(n / (1.0 + cov * cov))
    var_inc = cov * cov / n  # delta method for log mean w with iid particles
    # islands: per-island evidence increments (their spread is the honest within-run SE)
    k_isl = len(state.island_log_evidence)
    starts, sizes, isl = _islands(n, k_isl)
    m_k = np.maximum.reduceat(logw, starts)
    with np.errstate(invalid="ignore", divide="ignore"):
        s_k = np.add.reduceat(np.exp(logw - np.where(np.isfinite(m_k), m_k, 0.0)[isl]), starts)
        inc_k = np.where(np.isfinite(m_k), m_k + np.log(s_k), -np.inf) - np.log(sizes)
    island_prev = state.island_log_evidence
    island_new = island_prev + inc_k
    log_z_new = _log_mean_exp(island_new)
    if config.persistent:
        # running estimate Z_β = Σ_i L_i^β / Σ_s N_s L_i^β_s / Z_s over the pool (the final answer
        # is the MBAR solution of all stages, _recycled_result); the pool replaces the population
        log_z_new = float(logsumexp(lw_pool))
        island_new = np.full(k_isl, log_z_new)
        var_inc = 0.0
        x, ll = state.history_samples, state.history_log_likelihood
        w = np.exp(lw_pool - lw_pool.max())
        ess = _pool_ess(lw_pool)
    log_mean_w = log_z_new - state.log_evidence

    # 2. resample and prepare the proposal (weighted covariance at the new β)
    use_bij = bijection is not None
    use_logit = config.transform == "logit" and config.kernel == "rw" and not use_bij
    if use_logit:
        # random walk in unconstrained logit coordinates: the uniform prior becomes a product of
        # logistic densities, multiplicative ridges (T1 ~ 1/(1−c), A·e^{T2·x}) become nearly straight
        x = _to_logit(x, bounds)
        sigma = _free_cov(x, w)
        box = None

        def evaluate(u):
            theta, lp_u = _from_logit(u, bounds, True)
            return _eval(log_likelihood, theta), lp_u
    elif use_bij:
        # the caller's coordinates: log-Jacobian as the prior density of u, its support as the box
        x = bijection.forward(x)
        sigma = _free_cov(x, w)
        sup = np.asarray(bijection.support, float)
        box = sup if np.isfinite(sup).any() else None

        def evaluate(u):
            theta, lp_u = bijection.inverse(u)
            return _eval(log_likelihood, theta), lp_u
    else:
        box = bounds
        sigma = _weighted_cov(x, w, bounds)

        def evaluate(u):
            return _eval(log_likelihood, u), np.zeros(len(u))
    chol_rw = _safe_cholesky(sigma)
    if config.persistent:
        idx = _resample_pool(w, n, starts, sizes, isl, rng, config.resampling)
    elif k_isl == 1:
        idx = _resample(w, n, rng, config.resampling)
    elif (beta >= 1.0 and not config.recycle) or not np.isfinite(m_k).all():
        # (recycling keeps the islands apart to the end: their recycled evidences are the SE)
        # final stage (or a dead island): pool the islands, each weighted by its evidence so far;
        # after this the islands are no longer independent, so it happens once at the end only
        with np.errstate(invalid="ignore"):
            lw = np.where(np.isfinite(logw), island_prev[isl] - np.log(sizes)[isl] + logw, -np.inf)
        idx = _resample(np.exp(lw - lw.max()), n, rng, config.resampling)
    else:
        idx = _resample_islands(logw, m_k, starts, sizes, isl, rng, config.resampling)
    x, ll = x[idx], ll[idx]
    if use_bij:
        lp = bijection.inverse(x)[1]
    else:
        lp = _from_logit(x, bounds, True)[1] if use_logit else np.zeros(n)
    start = x.copy()

    # 3. Metropolis–Hastings moves
    scale, eps = float(state.scale), float(state.epsilon)
    n_eval = 0
    acc_total, n_done, mix, mix_at = 0.0, 0, 1.0, -1
    fixed = config.n_steps is not None
    max_steps = int(config.n_steps) if fixed else int(config.max_steps)
    min_steps = int(config.n_steps) if fixed else int(config.min_steps)
    metric_ok = float("nan")
    if config.kernel == "manifold":
        if gradient_fim is None:
            raise HbmError("tmcmc: kernel='manifold' needs gradient_fim")
        g0, f0 = gradient_fim(x)
        grad, fim = np.asarray(g0, dtype=float).copy(), np.asarray(f0, dtype=float).copy()
        ridge_prec = config.ridge * np.linalg.inv(sigma)
        ridge_prec = 0.5 * (ridge_prec + ridge_prec.T)
        oks = []
    mixer = _Mixing(config.mixing, start, ll)
    mixture = None
    if config.proposal == "mixture":
        mixture = _fit_mixture(start, int(config.mixture_components), float(config.mixture_df), sigma, rng)
        lq = _mixture_logpdf(mixture, x)
    local = None
    if config.proposal == "local":
        local = fit_local_metric(start, sigma, int(config.local_neighbours), float(config.local_ridge))
        near = nearest_reference(local, x)
    gamma = config.de_gamma if config.de_gamma is not None else 2.38 / math.sqrt(2.0 * d)
    acc_de: list = []
    for k in range(max_steps):
        if remaining is not None and n_eval + n > remaining:
            budget_hit = True  # the next step could exceed the budget: stop moving here
            break
        if local is not None:
            x, ll, lp, near, acc, ne = local_step(x, ll, lp, near, beta, scale, evaluate, rng, local)
            acc_rw = acc
        elif mixture is not None:
            x, ll, lp, lq, acc, is_de, ne = _mixture_step(x, ll, lp, lq, beta, scale, box, evaluate,
                                                          rng, mixture, config.independence_fraction)
            acc_rw = acc[~is_de]
            if is_de.any():
                acc_de.append(float(acc[is_de].mean()))
        elif config.kernel == "rw":
            x, ll, lp, acc, is_de, ne = _rw_de_step(x, ll, lp, beta, chol_rw, scale, box, evaluate, rng,
                                                    start, idx, config.de_fraction, gamma,
                                                    config.de_jump, config.de_noise)
            acc_rw = acc[~is_de]
            if is_de.any():
                acc_de.append(float(acc[is_de].mean()))
        else:
            x, ll, grad, fim, acc, ne, okf = _manifold_step(
                x, ll, grad, fim, beta, eps, ridge_prec, chol_rw, scale, bounds,
                log_likelihood, gradient_fim, rng)
            oks.append(okf)
        n_eval += ne
        a = float(acc.mean())
        acc_total += a
        n_done += 1
        if config.adapt_scale:
            # multiplicative adaptation of the population-level step toward the target acceptance
            if config.kernel == "rw":
                if len(acc_rw):
                    a_rw = float(acc_rw.mean())
                    factor = math.exp(0.5 * (a_rw - config.target_acceptance) / max(config.target_acceptance, 0.1))
                    scale = float(np.clip(scale * factor, 1e-4, 10.0))
            else:
                ta = config.target_acceptance_manifold
                eps = float(np.clip(eps * math.exp((a - ta) / max(ta, 0.1)), 1e-8, 1e3))
        if not fixed and k + 1 >= min_steps and (k + 1 - min_steps) % int(config.mixing_every) == 0:
            mix, mix_at = mixer(x, ll), n_done
            if mix <= config.mixing_target:
                break
    if mix_at != n_done:
        mix = mixer(x, ll)
    if config.kernel == "manifold":
        metric_ok = float(np.mean(oks)) if oks else float("nan")
    if use_logit:
        x = _from_logit(x, bounds)
    elif use_bij:
        x = bijection.inverse(x)[0]

    hist = (None, None, None)
    if config.recycle:
        hist = (np.concatenate([state.history_samples, x]), np.concatenate([state.history_log_likelihood, ll]),
                np.append(state.history_beta, beta))
    new = TMCMCState(x, ll, island_new, beta, log_z_new,
                     state.log_evidence_var + var_inc, state.stage + 1, scale, eps,
                     state.n_evaluations + n_eval, rng.bit_generator.state, *hist, budget_hit)
    info = StageInfo(
        beta=float(beta), dbeta=float(dbeta), log_evidence_increment=float(log_mean_w),
        log_evidence_increment_var=float(var_inc), cov_weights=float(cov), ess=float(ess),
        acceptance_rate=acc_total / max(n_done, 1),
        de_acceptance=float(np.mean(acc_de)) if acc_de else float("nan"), proposal_scale=scale,
        epsilon=eps if config.kernel == "manifold" else float("nan"), n_steps=n_done,
        evaluations=int(n_eval), mixing=float(mix), metric_ok=metric_ok, capped=bool(capped))
    return new, info


def _check_bounds(bounds) -> np.ndarray:
    b = np.asarray(bounds, dtype=float)
    if b.ndim != 2 or b.shape[1] != 2 or b.shape[0] < 1:
        raise HbmError(f"tmcmc: bounds must have shape (d, 2), got {b.shape}")
    if not np.all(np.isfinite(b)) or np.any(b[:, 1] <= b[:, 0]):
        raise HbmError("tmcmc: bounds must be finite with lower < upper in every row")
    return b


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


# ----------------------------------------------------------------------------------------
# checkpoints
# ----------------------------------------------------------------------------------------
def _fingerprint(config: TMCMCConfig, bounds: np.ndarray, seed, bijection: Optional[str] = None) -> str:
    cfg = {k: v for k, v in dataclasses.asdict(config).items()
           if not (k in _LATE_FIELDS and v == _LATE_FIELDS[k])}
    payload = {"config": cfg, "bounds": bounds.tolist(), "seed": repr(seed),
               "version": _CHECKPOINT_VERSION}
    if bijection is not None:  # absent without one: older checkpoints still resume
        payload["bijection"] = bijection
    return hashlib.sha256(json.dumps(payload, sort_keys=True).encode()).hexdigest()


def _save_checkpoint(path: Path, state: TMCMCState, stages: list[StageInfo], fingerprint: str,
                     settings: dict) -> None:
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as fh:  # file handle: np.savez would append ".npz" to a name
            np.savez(fh, samples=state.samples, log_likelihood=state.log_likelihood,
                     island_log_evidence=state.island_log_evidence,
                     scalars=np.array([state.beta, state.log_evidence, state.log_evidence_var,
                                       state.scale, state.epsilon]),
                     counters=np.array([state.stage, state.n_evaluations, int(state.budget_bound)],
                                       dtype=np.int64),
                     **({} if state.history_beta is None else
                        {"history_samples": state.history_samples,
                         "history_log_likelihood": state.history_log_likelihood,
                         "history_beta": state.history_beta}),
                     meta=np.array(json.dumps({"rng_state": state.rng_state,
                                               "stages": [s._asdict() for s in stages],
                                               "fingerprint": fingerprint, "settings": settings})))


def _load_checkpoint(path: Path, fingerprint: str) -> tuple[TMCMCState, list[StageInfo]]:
    try:
        with np.load(path, allow_pickle=False) as z:
            meta = json.loads(str(z["meta"]))
            sc, ct = z["scalars"], z["counters"]
            hist = tuple(z[k].copy() if k in z.files else None
                         for k in ("history_samples", "history_log_likelihood", "history_beta"))
            state = TMCMCState(z["samples"].copy(), z["log_likelihood"].copy(), z["island_log_evidence"].copy(),
                               float(sc[0]), float(sc[1]), float(sc[2]), int(ct[0]), float(sc[3]),
                               float(sc[4]), int(ct[1]), meta["rng_state"], *hist,
                               bool(ct[2]) if len(ct) > 2 else False)
    except Exception as exc:  # corrupt / foreign file
        raise HbmError(f"tmcmc: cannot read checkpoint {path}: {exc}") from None
    if meta.get("fingerprint") != fingerprint:
        raise HbmError(f"tmcmc: checkpoint {path} was made with different settings "
                       f"({meta.get('settings')}); delete it or use another path")
    stages = [StageInfo.from_record({_LEGACY_STAGE_KEYS.get(k, k): v for k, v in rec.items()})
              for rec in meta["stages"]]
    return state, stages


def checkpoint_progress(path: str | os.PathLike) -> Optional[tuple[int, float]]:
    """Progress recorded in a checkpoint written by :func:`tmcmc`.

    Parameters
    ----------
    path : path
        The ``checkpoint`` file of a (possibly running) :func:`tmcmc` call.

    Returns
    -------
    (stage, beta) or None
        Completed stages and the tempering exponent reached; None if the file is absent or
        unreadable (e.g. being replaced at this moment, or not a checkpoint).
    """
    try:
        with np.load(Path(path), allow_pickle=False) as z:
            return int(z["counters"][0]), float(z["scalars"][0])
    except Exception:  # absent, mid-replacement or foreign: no progress to report
        return None


# ----------------------------------------------------------------------------------------
# driver
# ----------------------------------------------------------------------------------------
def tmcmc(log_likelihood: LogLikelihood, bounds, n_samples: Optional[int] = None, *, seed,
          kernel: str = "rw", gradient_fim: Optional[GradientFIM] = None,
          cov_target: Optional[float] = None,
          proposal_scale: float = 0.2, n_steps: Optional[int] = None, max_stages: int = 100,
          checkpoint: Optional[str | os.PathLike] = None, progress: bool = True,
          max_evaluations: Optional[int] = None, preset: Optional[str] = None,
          bijection: Optional[Bijection] = None, **options: Any) -> TMCMCResult:
    """Transitional MCMC from the uniform prior on ``bounds`` to the posterior, with log-evidence.

    Parameters
    ----------
    log_likelihood : callable
        θ (n, d) → log-likelihood (n,); NaN is treated as −inf.  Called with whole populations.
    bounds : array_like (d, 2)
        Uniform prior box.
    n_samples : int or None
        Population size N; None = the preset's, else :data:`DEFAULT_N_SAMPLES`.
    seed : int
        Seed of the PCG64 generator (required: runs are reproducible and resumable).
    kernel : {"rw", "manifold"}
        Random walk (population covariance, adapted scale) or simplified mMALA.
    gradient_fim : callable, optional
        θ (n, d) → (gradient (n, d), Fisher information (n, d, d)) of the log-likelihood;
        required for ``kernel="manifold"``.
    cov_target : float or None
        Target CoV of the incremental weights per stage (1 ⇔ ESS ≈ N/2); None = the kernel's
        default (:data:`DEFAULT_COV_TARGET`: 1.0 for both kernels).
    proposal_scale : float
        Initial random-walk scale relative to the weighted population covariance.
    n_steps : int or None
        MH steps per stage; None = adaptive by the mixing diagnostic (see :class:`TMCMCConfig`).
    max_stages : int
        Stage cap (the last stage jumps to β = 1 and is flagged ``capped``).
    checkpoint : path, optional
        ``.npz`` file written atomically after every stage; if it exists, the run resumes from it
        (same settings required, else :class:`HbmError`).
    progress : bool
        tqdm progress bar on stderr.
    max_evaluations : int or None
        Hard cap on log-likelihood evaluations (rows passed to ``log_likelihood``), including the
        initial N; see :class:`TMCMCConfig`.  ``result.budget_exhausted`` says whether it bound
        the run.
    preset : str or None
        Named settings of :data:`PRESETS` ("default", "lean", "frugal") used as defaults for the
        population size, ``cov_target`` and the options; explicit arguments override them.
    bijection : Bijection or None
        Sampling coordinates of the random walk replacing the logit transform (see
        :class:`Bijection`; e.g. :class:`hbm.combinations.CombinationCoordinates` for the muscle
        model).  None (default): the run is unchanged.
    **options
        Further :class:`TMCMCConfig` fields (transform, n_islands, min_steps, max_steps,
        mixing_target, mixing, mixing_every, target_acceptance, target_acceptance_manifold,
        adapt_scale, resampling, min_dbeta, ridge, de_fraction, de_gamma, de_jump, de_noise,
        recycle, proposal, mixture_components, independence_fraction, mixture_df, local_neighbours,
        local_ridge).

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
    if max_evaluations is not None:
        options["max_evaluations"] = int(max_evaluations)
    unknown = set(options) - {f.name for f in dataclasses.fields(TMCMCConfig)}
    if unknown:
        raise HbmError(f"tmcmc: unknown options {sorted(unknown)}")
    config = TMCMCConfig(n_samples=int(n_samples), kernel=kernel, cov_target=None if cov_target is None else float(cov_target),
                         proposal_scale=float(proposal_scale),
                         n_steps=None if n_steps is None else int(n_steps),
                         max_stages=int(max_stages), **options)
    config.validate()
    b = _check_bounds(bounds)
    if kernel == "manifold" and gradient_fim is None:
        raise HbmError("tmcmc: kernel='manifold' needs gradient_fim")
    if seed is None or isinstance(seed, np.random.Generator):
        raise HbmError("tmcmc: seed must be an int (reproducible, resumable runs)")
    _check_bijection(bijection, config, len(b))

    timer = [0.0]

    def ll_timed(x):
        t = time.perf_counter()
        try:
            return log_likelihood(x)
        finally:
            timer[0] += time.perf_counter() - t

    gf_timed = None
    if gradient_fim is not None:
        def gf_timed(x):
            t = time.perf_counter()
            try:
                return gradient_fim(x)
            finally:
                timer[0] += time.perf_counter() - t

    fp = _fingerprint(config, b, seed, None if bijection is None else str(bijection.name))
    settings = {"n_samples": config.n_samples, "kernel": kernel, "seed": repr(seed), "d": len(b)}
    path = Path(checkpoint) if checkpoint is not None else None
    stages: list[StageInfo] = []
    resumed = 0
    if path is not None and path.exists():
        state, stages = _load_checkpoint(path, fp)
        resumed = state.stage
        if state.samples.shape != (config.n_samples, len(b)):
            raise HbmError(f"tmcmc: checkpoint {path} holds a population of shape "
                           f"{state.samples.shape}, expected {(config.n_samples, len(b))}")
    else:
        state = init(ll_timed, b, config, seed)
        if path is not None:
            _save_checkpoint(path, state, stages, fp, settings)

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
                _save_checkpoint(path, state, stages, fp, settings)
            if bar is not None:
                bar.update(int(1000 * state.beta) - bar.n)
                bar.set_postfix_str(f"stage {state.stage} β={state.beta:.3g} "
                                    f"logZ={state.log_evidence:.2f} acc={info.acceptance_rate:.2f} "
                                    f"steps={info.n_steps}")
    finally:
        if bar is not None:
            bar.close()
    samples, ll, log_z, se = state.samples, state.log_likelihood, float(state.log_evidence), _evidence_se(state)
    if config.recycle:
        log_z, se, samples, ll = _recycled_result(state, config, b)
    return TMCMCResult(
        samples=samples, log_likelihood=ll,
        log_evidence=log_z,
        log_evidence_se=se,
        stages=stages, n_evaluations=int(state.n_evaluations),
        wall_time=time.perf_counter() - t0, likelihood_time=timer[0], config=config,
        resumed_from_stage=resumed, budget_exhausted=bool(state.budget_bound),
        log_evidence_classic=float(state.log_evidence))
