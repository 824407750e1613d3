"""Fresh TMCMC of one specimen's updated posterior, for a specimen whose reused samples are unreliable."""

from __future__ import annotations

from typing import Any, Callable

import numpy as np

from ...errors import HbmError
from ..tmcmc import tmcmc as _tmcmc
from .result import HierarchicalResult

__all__ = ["refine_individual"]


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

    Returns
    -------
    TMCMCResult
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
    return res
