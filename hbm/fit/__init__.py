"""Fitting one specimen: :func:`fit_specimen` (CMA-ES optima, TMCMC posterior with evidence, posterior
predictive, Sobol) in :mod:`.specimen`, with what a fit says (:mod:`.quality`), the optimiser
(:mod:`.optimization`) and the sensitivity analysis (:mod:`.sensitivity`)."""

from ..runtime.lazy import attach

# hbm.fit.optimization or .sensitivity alone do not load the whole fit (hbm.runtime.lazy)
__getattr__, __dir__ = attach(__name__, {
    ".specimen": ["COMBINATIONS", "EDGE_MASS", "EDGE_TOL", "RIDGE_NOTE", "FitResult", "at_bounds", "chain_rhat",
                  "chains_line", "edges", "fit_quality", "fit_specimen", "format_at_bounds", "map_estimate",
                  "map_prediction", "parse_sweep", "pointwise_log_likelihood", "posterior_predictive",
                  "quality_lines", "summarize", "summary_table", "tier_line"],
})

__all__ = ["FitResult", "fit_specimen", "summarize", "summary_table", "pointwise_log_likelihood",
           "posterior_predictive", "parse_sweep", "edges", "COMBINATIONS", "at_bounds", "map_estimate", "fit_quality",
           "format_at_bounds", "map_prediction", "quality_lines", "tier_line", "EDGE_TOL", "EDGE_MASS",
           "RIDGE_NOTE", "chain_rhat", "chains_line"]
