"""The result of the two-level hierarchical layer (:func:`hbm.samplers.hierarchical.hierarchical`)."""

from __future__ import annotations

from dataclasses import dataclass, field, fields
from typing import Any

import numpy as np

from ...errors import HbmError
from .model import HierarchicalModel

__all__ = ["LayerProducts", "HierarchicalResult", "thin_rows"]


@dataclass(kw_only=True)
class LayerProducts:
    """What TMCMC over ψ on the reuse estimator yields, the same for every driver.

    The one home of these attributes: :class:`HierarchicalResult` (and so the grouped result)
    carries them, and so does the sampling step both drivers share
    (:class:`~hbm.samplers.hierarchical.posterior.LayerFit`).

    Attributes
    ----------
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
    warnings : list of str
    sampler_result : object
        The TMCMC result over the free hyperparameters.
    reuse : dict specimen -> dict
        What the reused stage-1 samples cannot represent and the verdict
        (:func:`~hbm.samplers.hierarchical.diagnostics.reuse_diagnostics`,
        :func:`~hbm.samplers.hierarchical.diagnostics.reuse_unreliable`); empty when not computed.
    """

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
    warnings: list
    sampler_result: Any
    reuse: dict = field(default_factory=dict)

    def layer_fields(self, **changes) -> dict:
        """These attributes as keyword arguments of another result (``changes`` replace some)."""
        return {**{f.name: getattr(self, f.name) for f in fields(LayerProducts)}, **changes}


@dataclass
class HierarchicalResult(LayerProducts):
    """Output of :func:`hierarchical`.

    The attributes of :class:`LayerProducts` (hyper-evidence, ESS and its flags, updated
    individuals, reuse diagnostics, the TMCMC result), and:

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
    predictive : ndarray (n, d)
        Posterior predictive of a new, unseen specimen (pooled columns).
    timings : dict
    model : HierarchicalModel
    raw_samples : ndarray (n, 2d+q)
        Hyper draws in sampler coordinates (used by :func:`refine_individual`).
    options : dict
        The settings of the run (stored with the result).
    """

    hyper_samples: np.ndarray
    hyper_names: list
    names: list
    all_names: list
    bounds: np.ndarray
    transforms: dict
    specimens: list
    predictive: np.ndarray
    timings: dict
    model: HierarchicalModel
    raw_samples: np.ndarray
    options: dict = field(default_factory=dict)

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
        raw = thin_rows(self.raw_samples, n_hyper, seed)
        return self.model.log_density(theta, raw)


def thin_rows(a: np.ndarray, n: int, seed) -> np.ndarray:
    """At most ``n`` rows of ``a``: a seeded random subset in row order (all rows if there are few)."""
    if a.shape[0] <= n:
        return a
    rng = np.random.default_rng(seed)
    return a[np.sort(rng.choice(a.shape[0], n, replace=False))]

