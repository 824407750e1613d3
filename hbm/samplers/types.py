"""The data of a TMCMC run: settings, state between stages, per-stage diagnostics, result.

:class:`TMCMCConfig` holds what changes the random stream or the answer (the move's own settings
live in its :class:`~hbm.samplers.moves.Move` object); :class:`TMCMCState` everything needed to
continue a run (it is what a checkpoint stores); :class:`StageInfo` one stage's diagnostics (and
the stored per-stage schema of :mod:`hbm.io`); :class:`TMCMCResult` the outcome of the driver.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Callable, Mapping, NamedTuple, Optional, Union, get_type_hints

import numpy as np

from ..errors import HbmError
from .chains import POOLED, Chains
from .moves import Move, get_move
from .resampling import SCHEMES

__all__ = ["DEFAULT_N_SAMPLES", "DEFAULT_COV_TARGET", "LogLikelihood", "GradientFIM", "TMCMCConfig",
           "TMCMCState", "StageInfo", "TMCMCResult"]

LogLikelihood = Callable[[np.ndarray], np.ndarray]
GradientFIM = Callable[[np.ndarray], "tuple[np.ndarray, np.ndarray]"]

#: Default population size: on the 9-parameter muscle benchmark (DESIGN.md §6) N = 2000 with the
#: default adaptive steps and CoV target 1.0 reaches a median |log Ẑ − gold| ≈ 0.1 and posterior
#: means within a median ~0.17 gold sd in ~4.1–4.5 s of CPU (20 seeds; CoV target 1.5: 0.19,
#: 0.24 sd with one seed in 20 at 1.03 sd, 3.1 s); see workflows/benchmarks/README.md.
DEFAULT_N_SAMPLES = 2000

#: Default CoV target of every move: 1.0.  ``cov_target=1.5`` saves ~31 % CPU on the muscle
#: benchmark (10 instead of 15 stages) but doubles the median evidence error (0.10 → 0.19 nats)
#: and put one seed in 20 1.03 gold sd off in a posterior mean; the evidence feeds model choice
#: (``hbm diagnose``), so accuracy wins the default.  Manifold: at 1.5 its error on the 9-D
#: Gaussian validation exceeded the random walk's.
DEFAULT_COV_TARGET = 1.0


@dataclass(frozen=True)
class TMCMCConfig:
    """Settings of one TMCMC run (everything that changes the random stream or the answer).

    Attributes
    ----------
    n_samples : int
        Population size N.
    move : str or Move
        Metropolis–Hastings move: a name of :data:`hbm.samplers.moves.MOVES` ("rw" random walk
        with the weighted population covariance, "manifold" simplified mMALA with the tempered
        Fisher metric — ``gradient_fim`` required —, "local" the random walk with neighbourhood
        covariances) or a :class:`~hbm.samplers.moves.Move` object (e.g. ``Manifold(ridge=1e-3)``);
        stored as the object.
    cov_target : float or None
        Target coefficient of variation of the incremental weights (1 ⇔ ESS = N/2, 1.5 ⇔ ESS =
        0.31·N); None = :data:`DEFAULT_COV_TARGET` (resolved on construction).
    proposal_scale : float
        Initial scale of the random-walk proposal relative to the population covariance
        (adapted toward ``target_acceptance`` when ``adapt_scale``).
    n_steps : int or None
        Metropolis steps per stage; ``None`` = adaptive: keep stepping until every coordinate's
        correlation with the stage-start population is ≤ ``mixing_target`` (between
        ``min_steps`` and ``max_steps``).
    min_steps, max_steps : int
        Bounds of the adaptive step count.
    mixing_target : float
        Largest |correlation| of a sampling coordinate with its stage-start value that ends a stage.
    max_stages : int
        Stage cap; the last allowed stage jumps to β = 1 (flagged in the stage info).
    min_dbeta : float
        Smallest β increment (keeps the loop moving when the CoV target cannot be met).
    target_acceptance : float
        Acceptance rate the random-walk scale is adapted to (0.3 measured best on the muscle
        benchmark; 0.2 was worse).  The manifold move has its own target.
    adapt_scale : bool
        Adapt the step size (scale or ε) after every MH step.
    resampling : {"systematic", "multinomial"}
        Resampling scheme between stages.
    transform : {"logit", "none"}
        Coordinates of the random walk.  "logit" (default) walks in u = logit((θ − lo)/(hi − lo))
        with the logistic prior density of u in the MH ratio: proposals never leave the box and
        multiplicative ridges (T1 ∝ 1/(1 − VOLF), A·exp(T2·x)) become nearly straight, which is
        what made the muscle benchmark accurate at ~100× less cost.  The manifold move always
        works in box coordinates.  A ``bijection`` passed to :func:`~hbm.samplers.tmcmc.tmcmc` /
        :func:`~hbm.samplers.tmcmc.step` replaces this transform by the caller's coordinates.
    n_islands : int
        K contiguous blocks of particles resampled separately (sharing β and proposal shape);
        the spread of their evidences gives ``log_evidence_se`` including the error of incomplete
        mixing.  K = 1 (or N < 80) falls back to the per-stage delta-method SE.  At the final stage
        see ``final_resampling``.
    max_evaluations : int or None
        Hard cap on log-likelihood evaluations (particles, including the N of the initial
        population).  A stage's MH loop stops before a step that could exceed it, and once fewer
        than N evaluations remain the next stage jumps to β = 1 without moves; the result is then
        flagged ``budget_exhausted``.  The SE then comes from the crude forced last stage and is
        only a lower bound.  None = no cap.
    final_resampling : {"islands", "pooled"}
        Resampling at β = 1.  "islands" (default): each island from its own particles, so the
        final population is K chains of N/K draws (R-hat; :mod:`hbm.samplers.chains`) -- unless
        the islands' log-evidences differ by more than their noise (or N is not a multiple of K),
        when they are pooled as with "pooled": one resampling of all particles, each island
        weighted by its evidence (the code before chains were stored).  Not part of the checkpoint
        fingerprint: it changes nothing before β = 1 and the state records what the last stage did.
    """

    n_samples: int
    move: Union[str, Move] = "rw"
    cov_target: Optional[float] = None
    proposal_scale: float = 0.2
    n_steps: Optional[int] = None
    min_steps: int = 2
    max_steps: int = 100
    mixing_target: float = 0.1
    max_stages: int = 100
    min_dbeta: float = 1e-9
    target_acceptance: float = 0.3
    adapt_scale: bool = True
    resampling: str = "systematic"
    transform: str = "logit"
    n_islands: int = 4
    max_evaluations: Optional[int] = None
    final_resampling: str = "islands"

    def __post_init__(self) -> None:
        # frozen dataclass: defaults that need resolving are set once here
        if self.cov_target is None:
            object.__setattr__(self, "cov_target", DEFAULT_COV_TARGET)
        object.__setattr__(self, "move", get_move(self.move))

    def validate(self) -> None:
        """Raise :class:`HbmError` naming the first setting out of range."""
        if int(self.n_samples) < 4:
            raise HbmError(f"tmcmc: n_samples must be >= 4, got {self.n_samples}")
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
        if self.resampling not in SCHEMES:
            raise HbmError(f"tmcmc: resampling must be 'systematic' or 'multinomial', got {self.resampling!r}")
        if not 0 < self.target_acceptance < 1:
            raise HbmError(f"tmcmc: target_acceptance must be in (0, 1), got {self.target_acceptance}")
        if int(self.min_steps) < 1 or int(self.max_steps) < int(self.min_steps):
            raise HbmError("tmcmc: need 1 <= min_steps <= max_steps")
        if self.max_evaluations is not None and int(self.max_evaluations) < int(self.n_samples):
            raise HbmError(f"tmcmc: max_evaluations ({self.max_evaluations}) must be >= n_samples "
                           f"({self.n_samples}): the initial population alone costs N evaluations")
        if self.final_resampling not in ("islands", "pooled"):
            raise HbmError(f"tmcmc: final_resampling must be 'islands' or 'pooled', got {self.final_resampling!r}")
        if self.move.unbounded and self.transform != "logit":
            raise HbmError(f"tmcmc: move {self.move.name!r} needs transform='logit' (its steps are unbounded)")


class TMCMCState(NamedTuple):
    """Everything needed to continue a run (pure data; see :func:`hbm.samplers.tmcmc.step`).

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
    budget_bound : bool
        ``max_evaluations`` cut a stage's moves short or forced the jump to β = 1.
    n_chains : int
        0 before β = 1; then the islands kept as chains by the final resampling (K), or 1 when
        it pooled them.
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
    budget_bound: bool = False
    n_chains: int = 0


class StageInfo(NamedTuple):
    """Diagnostics of one tempering stage, as returned by :func:`hbm.samplers.tmcmc.step`.

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
    proposal_scale : float
        Random-walk scale (relative to the population covariance) after the stage's adaptation.
    epsilon : float
        Manifold step size after adaptation (NaN for the random walk).
    n_steps : int
        MH steps taken.
    evaluations : int
        Log-likelihood evaluations (particles) of the MH steps.
    mixing : float
        Final largest |correlation| of a sampling coordinate with its stage-start value.
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


@dataclass
class TMCMCResult:
    """Outcome of :func:`hbm.samplers.tmcmc.tmcmc`.

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
    chains : Chains
        How ``samples`` splits into chains (chain-major blocks): the islands, or one pooled
        chain and why (:mod:`hbm.samplers.chains`).
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
    chains: Chains = POOLED

    @property
    def n_stages(self) -> int:
        return len(self.stages)

    @property
    def beta(self) -> np.ndarray:
        return np.array([s.beta for s in self.stages])

