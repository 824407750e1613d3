"""Settings of the population layer (:class:`PopulationConfig`) and its defaults."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

from ..errors import HbmError
from ..model import COMBINATIONS

__all__ = ["PopulationConfig", "POOL_MODES", "DEFAULT_TRANSFORMS", "DEFAULT_SD_RANGE", "POOL_COMBINATIONS", "POOL_INFORMED",
           "COMBINATION_COLUMNS", "check_config"]

#: transform of each base-model parameter in the population model (see hbm.samplers.hierarchical):
#: log for strictly positive moduli spanning decades (P1, GF, GM: a log-normal population, sd
#: reads as a relative spread); logit on the box for bounded fractions/scales (VOLF, EOPT, T1,
#: T2: no truncation needed); identity (truncated normal) for THETA, whose posteriors pile up
#: against the 60° edge: logit would stretch that pile-up into a tail many units wide, far wider
#: than the population, and the importance ESS collapses (measured: 10% ESS 2-3 of 500 vs 9-190).
DEFAULT_TRANSFORMS = {"VOLF": "logit", "EOPT": "logit", "P1": "log", "T1": "logit", "T2": "logit",
                      "THETA": "identity", "GF": "log", "GM": "log"}
#: sd_k in [0.05, 1] x the width of mu_k's range.  The lower end keeps the unidentified directions
#: (VOLF, P1, T1, GF, GM individually) from drawing populations far narrower than every
#: individual posterior -- the log-uniform sd prior would otherwise put mass there, where the
#: stage-1 samples cannot represent the population (importance ESS ~ 1).
DEFAULT_SD_RANGE = (0.05, 1.0)

#: ``--pool combinations``: pool the identifiable combinations instead of the raw parameters
POOL_COMBINATIONS = "combinations"
#: ``--pool informed``: pool the model parameters that the posteriors inform (auto_pool)
POOL_INFORMED = "informed"
#: the pooling keywords of ``PopulationConfig.pooled`` (and ``hbm run --pool``); anything else is a
#: list of model parameters
POOL_MODES = ("auto", POOL_COMBINATIONS, POOL_INFORMED, "all")
#: pooled coordinates of ``--pool combinations`` (identity transform: they are logs already)
COMBINATION_COLUMNS = tuple(f"log_{c}" for c in COMBINATIONS)
#: settings that left the layer (issue 25: reference rows and the second pass, superseded by the exact
#: fallback; code at commit 287c749), folded into the reuse key at their old defaults so that a stored
#: ``hierarchical.nc`` of an unchanged run keeps its key (the exact fallback's own settings left with
#: issue 37: a layer made by it is not reused)
_RETIRED = {"reference": 0.0, "second_pass": False}
#: fields that key the reuse only when set (unset: the key of runs from before they existed)
_KEYED_WHEN_SET = ("groups", "group_by", "sampler_options")


@dataclass
class PopulationConfig:
    """Settings of the population layer (``hbm run``: ``--hier-*``, ``--pool`` and the stage-1
    settings that a fresh TMCMC run of a collapsed specimen repeats).

    Attributes
    ----------
    seed : int
        Run seed; the layer's streams are spawned from it (:mod:`hbm.population`).
    pooled : str, list of str or None
        "auto", "combinations", "informed", "all" or parameter names (:mod:`hbm.population`).
    samples : int
        Hyper-posterior draws: of the joint sampler (all its chains × kept draws, at least
        ``samples``), or the TMCMC population of the reuse layer.
    max_steps : int
        MH steps per TMCMC stage of the layer and of the refinements.
    sampler_options : dict, optional
        Further keyword arguments of the layer's TMCMC (:func:`hbm.samplers.tmcmc.tmcmc`), over
        ``max_steps``: they reach the two-level and the grouped layer and the fresh TMCMC
        refinements alike (e.g. ``{"n_steps": 12}`` for a fixed number of MH steps per stage).
    estimator : str
        Importance estimator of :func:`~hbm.samplers.hierarchical.hierarchical`.
    transforms : dict, optional
        Per-parameter transforms overriding :data:`DEFAULT_TRANSFORMS`.
    sd_range : tuple of float
        Population sd range as a fraction of mu's range.
    stage1_samples : int
        The specimens' TMCMC N (caps a refinement's N).
    noise, fix, bounds
        Stage-1 likelihood settings (:func:`hbm.likelihood.make_likelihood`), for refinements.
    retries : int
        dask retries of a refinement task.
    progress : bool
        Progress lines and bars on stderr.
    groups : dict, optional
        Specimen id -> group name (:func:`hbm.data.specimen_groups`): the three-level layer.
        None: the two-level layer.
    group_by : str, optional
        The metadata key the groups come from (``group``, ``species`` ...), for the report's words.
    exact : str or None
        "gibbs" (default): the joint posterior of the population and every specimen, each with its real
        likelihood, by batched Metropolis-within-Gibbs (:mod:`hbm.population.layer`); it needs the
        datasets and runs for a two-level layer.  None — and without datasets, or with groups —: TMCMC
        over the population reusing the stage-1 samples (:func:`hbm.samplers.hierarchical.hierarchical`,
        the hyper-evidence and the reuse diagnostics), specimens whose reuse is unreliable refined by a
        fresh TMCMC run.
    layer_chains, layer_burn, layer_keep, layer_thin : int
        The joint sampler's chains, burn-in rounds, kept draws per chain (at least ``samples`` in all)
        and rounds per kept draw.
    """

    seed: int = 0
    pooled: list | str | None = "auto"
    samples: int = 1000
    max_steps: int = 25
    sampler_options: dict | None = None
    estimator: str = "raw"
    transforms: dict | None = None
    sd_range: tuple = DEFAULT_SD_RANGE
    stage1_samples: int = 2000
    noise: str = "iid"
    fix: dict | None = None
    bounds: dict | None = None
    retries: int = 1
    progress: bool = True
    groups: dict | None = None
    group_by: str | None = None
    exact: str | None = "gibbs"
    # the shipped six: 6 chains × (300 + 3000 × 2) rounds, 0.68 M model evaluations, every hyper-parameter's
    # R-hat ≤ 1.01 and bulk ESS ≥ 400 (results/benchmarks/population_layer.md): R-hat needs long chains (its
    # excess is about the autocorrelation time over the chain's length), so few of them
    layer_chains: int = 6
    layer_burn: int = 300
    layer_keep: int = 3000
    layer_thin: int = 2

    def tmcmc_options(self) -> dict:
        """Keyword arguments of every TMCMC run of the layer: the MH step cap, then ``sampler_options``.

        Each ψ evaluation is a (n_ψ × 2d) @ (2d × Σ N_i) product: the cap keeps the layer at tens
        of seconds for six specimens.
        """
        return {"max_steps": int(self.max_steps), **dict(self.sampler_options or {})}

    def key_settings(self) -> dict:
        """The settings that decide whether a stored layer is reused (:mod:`hbm.workflow`): every field but
        ``progress`` and ``retries`` (they do not change the result)."""
        own = {k: v for k, v in dataclasses.asdict(self).items()
               if k not in ("progress", "retries") and not (k in _KEYED_WHEN_SET and v is None)}
        return {**_RETIRED, **own}


def check_config(cfg: PopulationConfig) -> None:
    """Bad settings of the joint sampler or of the sampler options (HbmError), before any computation."""
    if cfg.sampler_options is not None and not isinstance(cfg.sampler_options, dict):
        raise HbmError(f"sampler_options must be a dict of TMCMC keyword arguments, got {cfg.sampler_options!r}")
    if cfg.exact is None:
        return
    if cfg.exact != "gibbs":
        raise HbmError(f"exact must be 'gibbs' or None, got {cfg.exact!r}")
    if int(cfg.layer_chains) < 2 or int(cfg.layer_keep) < 4 or int(cfg.layer_thin) < 1 or int(cfg.layer_burn) < 0:
        raise HbmError("exact='gibbs' needs layer_chains >= 2, layer_keep >= 4, layer_thin >= 1, layer_burn >= 0")
