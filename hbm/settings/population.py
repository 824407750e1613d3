"""The settings of the population layer (:class:`PopulationSettings`, ``hbm run``'s ``--hier-*`` and
``--pool``; :func:`hbm.population.run_population` takes them)."""

from __future__ import annotations

from typing import Any, ClassVar, Mapping

from ..errors import SettingError
from .fields import Settings, record, setting
from .rules import NON_NEGATIVE_INT, POSITIVE_INT, SEED, ChoiceRule, IntRule, RealRule

__all__ = ["PopulationSettings", "DEFAULT_SD_RANGE", "JOINT_SD_RANGE",
           "POOL_COMBINATIONS", "POOL_INFORMED", "POOL_MODES"]

#: the reuse layer's sd_k range, [0.05, 1] x the width of mu_k's range.  The lower end keeps the unidentified
#: directions (VOLF, P1, T1, GF, GM individually) from drawing populations far narrower than every
#: individual posterior -- the log-uniform sd prior would otherwise put mass there, where the
#: stage-1 samples cannot represent the population (importance ESS ~ 1).
DEFAULT_SD_RANGE = (0.05, 1.0)
#: the joint sampler's (the default layer's), [0.01, 1] x mu_k's range: it evaluates every specimen's likelihood, so
#: it needs no such floor, and 0.05 lay above real spreads (0.69 in log (1-c)*T1, 0.80 in logit T2: a
#: population of sd 0.5 there was excluded and missed at every size; results/benchmarks/population_layer.md)
JOINT_SD_RANGE = (0.01, 1.0)
#: ``--pool combinations``: pool the identifiable combinations instead of the raw parameters
POOL_COMBINATIONS = "combinations"
#: ``--pool informed``: pool the model parameters that the posteriors inform (auto_pool)
POOL_INFORMED = "informed"
#: the pooling keywords of ``PopulationSettings.pooled`` (and ``hbm run --pool``); anything else is a
#: list of model parameters
POOL_MODES = ("auto", POOL_COMBINATIONS, POOL_INFORMED, "all")

_EXACT = ChoiceRule(lambda: ("gibbs",), "joint sampler (or None)")
_ESTIMATOR = ChoiceRule(lambda: ("raw", "kernel"), "importance estimator")


@record
class PopulationSettings(Settings):
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
        Per-parameter transforms overriding the model's (its spec's population transforms).
    sd_range : tuple of float, optional
        Population sd range as a fraction of mu's range (None: :data:`JOINT_SD_RANGE` for the joint sampler,
        :data:`DEFAULT_SD_RANGE` for the reuse layer; :meth:`sd_bounds`).
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
    layer_extend : float
        Chains not converged after ``layer_keep`` draws (the layer's R-hat and ESS targets) go on, half of
        ``layer_keep`` at a time, until they are or they hold ``layer_extend`` times the planned draws;
        1: never extend.
    """

    #: settings that left the layer (issue 25: reference rows and the second pass, superseded by the
    #: exact fallback; code at commit 287c749), folded into the reuse key at their old defaults so
    #: that a stored ``hierarchical.nc`` of an unchanged run keeps its key
    RETIRED: ClassVar[Mapping[str, Any]] = {"reference": 0.0, "second_pass": False}
    #: an unset setting keys the layer too (as None), except those declared ``omit_default``
    KEY_UNSET: ClassVar[bool] = True
    KEY_VERSION: ClassVar[bool] = False

    seed: Any = setting(0, rule=SEED, help="run seed")
    pooled: Any = setting("auto", help="what gets a population distribution (auto, combinations, informed, all, "
                                       "or parameter names)")
    samples: int = setting(1000, rule=POSITIVE_INT, help="hyper-posterior draws (TMCMC population of the layer)")
    max_steps: int = setting(25, rule=POSITIVE_INT, help="MH steps per TMCMC stage of the layer")
    sampler_options: dict | None = setting(None, omit_default=True,
                                           help="further keyword arguments of the layer's TMCMC")
    estimator: str = setting("raw", rule=_ESTIMATOR, help="importance estimator of p(d_i|psi): raw or kernel")
    transforms: dict | None = setting(None, help="per-parameter population transforms over the model's")
    sd_range: tuple | None = setting(None, help="population sd range as a fraction of mu's range (None: the "
                                                "layer's own, JOINT_SD_RANGE or DEFAULT_SD_RANGE)")
    stage1_samples: int = setting(2000, rule=POSITIVE_INT, help="the specimens' TMCMC N")
    noise: str = setting("iid", help="stage-1 noise model (for refinements)")
    fix: dict | None = setting(None, help="stage-1 fixed parameters (for refinements)")
    bounds: dict | None = setting(None, help="stage-1 narrowed boxes (for refinements)")
    retries: int = setting(1, rule=NON_NEGATIVE_INT, keyed=False, help="dask retries of a refinement task")
    progress: bool = setting(True, keyed=False, help="progress lines and bars on stderr")
    groups: dict | None = setting(None, omit_default=True, help="specimen id -> group name: the three-level layer")
    group_by: str | None = setting(None, omit_default=True, help="the metadata key the groups come from")
    exact: str | None = setting("gibbs", rule=_EXACT, help="the joint sampler of the population and every "
                                                            "specimen (gibbs), or None: reuse the stage-1 samples")
    # the shipped six: 6 chains × (300 + 3000 × 2) rounds, 0.68 M model evaluations, every hyper-parameter's
    # R-hat ≤ 1.01 and bulk ESS ≥ 400 (results/benchmarks/population_layer.md): R-hat needs long chains (its
    # excess is about the autocorrelation time over the chain's length), so few of them
    layer_chains: int = setting(6, rule=IntRule(2), help="chains of the joint sampler")
    layer_burn: int = setting(300, rule=NON_NEGATIVE_INT, help="burn-in rounds of the joint sampler")
    layer_keep: int = setting(3000, rule=IntRule(4), help="kept draws per chain of the joint sampler")
    layer_thin: int = setting(2, rule=POSITIVE_INT, help="rounds per kept draw of the joint sampler")
    # chains that have not converged at the planned length go on, half of it at a time, up to this many times
    # the planned kept draws (results/benchmarks/population_layer.md: the 96-specimen population's EOPT)
    layer_extend: float = setting(3.0, rule=RealRule(1.0), help="the joint sampler's chains go on until converged, "
                                                                 "up to this many times the planned draws (1: never)")

    def __post_init__(self) -> None:
        super().__post_init__()
        if self.sampler_options is not None and not isinstance(self.sampler_options, Mapping):
            raise SettingError(f"sampler_options must be a dict of TMCMC keyword arguments, got "
                               f"{self.sampler_options!r}")

    def sd_bounds(self, joint: bool) -> tuple:
        """The sd range of the joint sampler (``joint``) or of the reuse layer: ``sd_range`` if set."""
        if self.sd_range is not None:
            return tuple(float(v) for v in self.sd_range)
        return JOINT_SD_RANGE if joint else DEFAULT_SD_RANGE

    def tmcmc_options(self) -> dict:
        """Keyword arguments of every TMCMC run of the layer: the MH step cap, then ``sampler_options``.

        Each ψ evaluation is a (n_ψ × 2d) @ (2d × Σ N_i) product: the cap keeps the layer at tens
        of seconds for six specimens.
        """
        return {"max_steps": int(self.max_steps), **dict(self.sampler_options or {})}
