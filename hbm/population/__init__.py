"""The population layer of a multi-specimen fit: the hierarchical model over fitted specimens.

:func:`run_population` takes the specimens' stage-1 results (:class:`hbm.io.SpecimenResult`,
from :func:`hbm.fit.fit_specimen` or ``<out>/specimens/*.nc``), their datasets and the model,
and samples the joint posterior of the population and every specimen with its real likelihood
(:mod:`.layer`, the default ``exact="gibbs"``: batched Metropolis-within-Gibbs,
:func:`hbm.samplers.hierarchical.batched_gibbs`), or — without the datasets, with groups, or with
``exact=None`` — fits :func:`hbm.samplers.hierarchical.hierarchical` over the population reusing the
stage-1 samples; the result goes to ``<out>/hierarchical.nc``.  It is phase 2 of ``hbm run``
(:mod:`hbm.workflow`); with a dask client of two workers or more the joint sampler's shards of
specimens run on them (the draws are the same), and the reuse layer's fresh TMCMC refinements of
collapsed specimens run as tasks.  By concept:

* :mod:`.config` -- :class:`PopulationConfig` (``sampler_options`` reaches every TMCMC run of
  the layer) and the defaults;
* :mod:`.pooling` -- the stage-1 data packed once and the pooling strategies as objects;
* :mod:`.batch`, :mod:`.layer` -- the specimens' likelihoods a shard at a time and the joint sampler;
* :mod:`.fallbacks` -- the reuse layer's fresh TMCMC refinements;
* :mod:`.driver` -- the one driver: pool → sample (joint, or reuse + refinements) → new-specimen draw
  → write.

Pooling (``PopulationConfig.pooled``): "combinations" (a population over log G, log c·P1,
log (1−c)·T1, T2, THETA — what a uniaxial curve identifies — with the exact stage-1 prior
density of the combinations, :mod:`hbm.identifiability.combinations`), "informed" (the model parameters that
the posteriors inform, :func:`~hbm.samplers.hierarchical.auto_pool`), "all", a list of names,
or "auto" (default: "combinations" when VOLF, P1, T1, GF, GM, T2, THETA are free, otherwise
"informed").

Groups (``PopulationConfig.groups``, from ``# group:`` lines or ``hbm run --group-by KEY``): a
population → group → specimen layer (:func:`hbm.samplers.hierarchical.grouped_hierarchical`) in
the same transformed coordinates and with every pooling mode; its group-level draws go to
``hierarchical.nc`` too.  Without groups the two-level layer runs.

Reuse diagnostics (issue 15, the reuse layer only): per specimen PSIS k̂ and the mass beyond the
stage-1 samples (:func:`~hbm.samplers.hierarchical.reuse_diagnostics`, in ``hierarchical.nc`` and the
report); a specimen flagged unreliable, or whose ESS collapsed, gets a fresh TMCMC run (:mod:`.fallbacks`).

Seeds: the streams ``layer`` and ``layer_specimen`` k of the joint sampler; ``hierarchical``
(``grouped`` with groups), ``refine`` k of the reuse layer; ``new_specimen`` of
:mod:`hbm.runtime.seeds`.
"""

from .config import (
    COMBINATION_COLUMNS, DEFAULT_SD_RANGE, DEFAULT_TRANSFORMS, JOINT_SD_RANGE, POOL_COMBINATIONS, POOL_INFORMED,
    POOL_MODES, PopulationConfig)
from .driver import run_population
from .layer import ESS_TARGET, RHAT_SPECIMEN, RHAT_TARGET, shards_on_workers
from .pooling import COMBINATION_NEEDS, JOINT_POOL_INFORMED

__all__ = ["PopulationConfig", "run_population", "DEFAULT_TRANSFORMS", "DEFAULT_SD_RANGE", "JOINT_SD_RANGE",
           "POOL_COMBINATIONS", "POOL_INFORMED", "POOL_MODES", "COMBINATION_COLUMNS", "COMBINATION_NEEDS",
           "JOINT_POOL_INFORMED", "layer_rules", "shards_on_workers"]


def layer_rules() -> dict:
    """The layer's built-in rules that no setting records (the joint sampler's sd floor, pooling count and the
    convergence targets its chains run to): part of a stored layer's reuse key, so a layer computed under other
    rules is computed again."""
    return {"joint_sd_range": [float(v) for v in JOINT_SD_RANGE], "joint_pool_informed": int(JOINT_POOL_INFORMED),
            "convergence": [float(RHAT_TARGET), float(ESS_TARGET), float(RHAT_SPECIMEN)]}
