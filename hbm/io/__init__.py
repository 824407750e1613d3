"""Results <-> netCDF.  The only module of hbm that knows netCDF group and variable names.

Per-specimen file ``<out>/specimens/<id>.nc`` (ArviZ ``InferenceData`` layout, one netCDF4
file with groups, written with :class:`xarray.DataTree`):

``posterior``             (chain, draw): one variable per free parameter, noise parameters
                          (``sigma`` ...) included.  The chains are TMCMC's islands (or the
                          importance finish's batches), independent up to the shared adaptation
                          (:mod:`hbm.samplers.chains`); one chain when they were pooled.  Attributes
                          ``chains`` (tmcmc_islands, importance_batches or pooled), ``chains_note``
                          (what they are, or why there is one: then R-hat is NaN),
                          ``chains_spread_log_evidence``/``chains_tolerance_log_evidence`` (nats).
                          Files of older versions hold one chain and no such attributes.
``sample_stats``          (chain, stage): one float64 variable per field of the sampler's
                          :class:`~hbm.samplers.tmcmc.StageInfo` (``beta``,
                          ``log_evidence_increment``, ``acceptance_rate``, ``cov_weights``,
                          ``ess``, ``evaluations``, ``n_steps``, ``proposal_scale``, ...;
                          NaN where a stage did not report it, ``capped`` as 0/1); (chain,):
                          ``log_marginal_likelihood`` and ``log_marginal_likelihood_se`` (the
                          whole population's, the same for every chain; stage rows too);
                          (chain, draw): ``log_likelihood_sum`` (total log-likelihood per draw).
                          The stage axis never shares the ``draw`` dimension.
``log_likelihood``        (chain, draw, point): pointwise log-likelihood ``stress``.
``posterior_predictive``  (chain, draw, point): ``stress`` (noisy replicate) and
                          ``stress_model`` (noise-free model prediction).
``observed_data``         (point): ``stress`` with coordinates ``strain`` (and ``time``, ``test``).
``constant_data``         (parameter): prior box ``prior_lower``, ``prior_upper``.
``optima``                (optimum): CMA-ES optima, one variable per parameter + ``objective``
                          (+ ``window_lower``/``window_upper`` of a bound sweep, ``kind``).
``sobol``                 (parameter[, point]): ``S1``, ``ST``, ``S1_conf``, ``ST_conf``,
                          ``relevance`` (+ per-point ``S1_point``/``ST_point``).

Root attributes: ``specimen_id``, ``model``, ``effects`` (JSON list), ``config`` (JSON),
``seed`` (int), ``hbm_version``, ``timings`` (JSON), ``prior`` (JSON ``{name: {"lo", "hi",
"form"}}``: the prior each free parameter was sampled under, natural units), ``at_bounds`` (JSON
list of ``{"parameter", "side", "edge", "fraction", "map_at_edge"}``, see
:func:`hbm.fit.at_bounds`), ``complete`` (int, set to 1 last, after every group is on disk).  netCDF attributes cannot hold bool/None/dict, hence ints and JSON.

Hierarchical file ``<out>/hierarchical.nc``: ``posterior`` (chain, draw) with ``mu_<P>`` and
``sd_<P>`` (hyper-parameters), ``updated`` (chain, draw, specimen) one variable per parameter
(the updated individual posteriors), ``sample_stats`` (chain, stage) + hyper-evidence,
``new_specimen`` (chain, draw) the predictive of a new specimen, ``diagnostics`` (specimen):
importance ESS; root attrs as above.  A grouped layer (population → group → specimen) adds
``sd_between_<P>``, ``sd_within_<P>`` to ``posterior`` (``sd_<P>`` is then their root sum of squares)
and a ``groups`` group: (chain, draw, group) ``mean_<P>`` (group means, transformed units) and
``new_specimen_<P>`` (a new specimen of each group), (specimen) ``specimen_group``; attrs ``key``
(the metadata key grouped by) and ``extra`` (JSON).

``<out>/manifolds.nc``: group per specimen-independent table (specimen, grid) of spline
manifolds and identified combinations (see :func:`write_population_summary`).
"""

from ..runtime.lazy import attach

# xarray and netCDF load when a result is read or written, not with the package (hbm.runtime.lazy)
__getattr__, __dir__ = attach(__name__, {
    ".common": ["is_complete", "json_default", "read_attrs"],
    ".specimen": ["SpecimenResult", "read_specimen_result", "specimen_path", "to_inference_data",
                  "write_specimen_result"],
    ".population": ["HierarchicalFile", "read_hierarchical", "read_population_summary", "write_hierarchical",
                    "write_population_summary"],
    ".organ": ["ORGAN_SOURCES", "OrganFile", "read_organ", "write_organ"],
})

__all__ = ["SpecimenResult", "HierarchicalFile", "write_specimen_result", "read_specimen_result",
           "is_complete", "read_attrs", "write_hierarchical", "read_hierarchical", "write_population_summary",
           "read_population_summary", "to_inference_data", "specimen_path", "json_default", "OrganFile", "write_organ",
           "read_organ", "ORGAN_SOURCES"]
