"""Hierarchical Bayesian layer over per-specimen TMCMC posteriors (two-stage, sample reuse).

Each specimen's stage-1 posterior samples (drawn under a uniform prior) are reused to estimate
p(d_i | ψ) for a population ψ of its parameters, and TMCMC samples the hyper-posterior on the
sum of their logs; or the joint posterior of the population and every specimen is sampled with
the specimens' real likelihoods (:mod:`.batched`).  By concept:

* :mod:`.model` -- the population model (transforms, hyperprior, the vectorised importance
  ratios as a matrix product), :func:`draw_population` of a new specimen;
* :mod:`.reuse` -- the one estimator of p(d_i | ψ) (raw or kernel-smoothed ratios) and the
  updated individuals, on the stage-1 data packed once (:func:`~.reuse.pack_stage1`);
* :mod:`.diagnostics` -- ESS summary and flags, evidence parts, what the reused samples cannot
  represent (PSIS k̂, mass beyond the samples) and the per-specimen verdict;
* :mod:`.posterior` -- TMCMC over ψ and the post-sampling steps shared by both drivers;
* :mod:`.two_level` (:func:`hierarchical`) and :mod:`.grouped` (:func:`grouped_hierarchical`,
  population → group → specimen) -- the drivers;
* :mod:`.pooling` -- which parameters to pool (:func:`auto_pool`);
* :mod:`.refine` -- fresh TMCMC of one specimen's updated posterior (:func:`refine_individual`);
* :mod:`.batched` -- the joint sampler of the population and every specimen with its real
  likelihood (batched Metropolis-within-Gibbs, issue 37): the specimens' moves a shard at a time
  (:mod:`.shards`, in this process or as dask actors), their linear amplitudes by importance
  particles (:mod:`.amplitudes`), R-hat/ESS (:mod:`.convergence`);
* :mod:`.psis` -- Pareto-smoothed importance sampling k̂;
* :mod:`.result` -- :class:`HierarchicalResult` (the products of TMCMC over ψ that it shares with
  :mod:`.posterior`'s ``LayerFit``: :class:`~.result.LayerProducts`).

This package is sampler-layer code: it knows nothing about muscles.
"""

from .diagnostics import reuse_diagnostics, reuse_unreliable
from .grouped import (
    GroupedModel, GroupedResult, group_differences, grouped_hierarchical, variance_split)
from ..convergence import rhat_ess
from .batched import BatchedResult, HyperLevel, PooledFeatures, ShardSpec, batched_gibbs, one_population
from .model import TRANSFORMS, HierarchicalModel, draw_population, kernel_bandwidth
from .pooling import PoolChoice, auto_pool, prior_sd_transformed
from ..psis import K_HAT_THRESHOLD, pareto_khat
from .refine import refine_individual
from .result import HierarchicalResult
from .reuse import ESTIMATORS
from .two_level import hierarchical

__all__ = [
    "HierarchicalResult", "HierarchicalModel", "hierarchical", "refine_individual",
    "kernel_bandwidth", "auto_pool", "PoolChoice", "prior_sd_transformed", "TRANSFORMS", "ESTIMATORS",
    "reuse_diagnostics", "reuse_unreliable", "draw_population",
    "GroupedModel", "GroupedResult", "grouped_hierarchical", "group_differences", "variance_split",
    "BatchedResult", "HyperLevel", "PooledFeatures", "ShardSpec", "batched_gibbs", "one_population", "rhat_ess",
    "K_HAT_THRESHOLD", "pareto_khat",
]
