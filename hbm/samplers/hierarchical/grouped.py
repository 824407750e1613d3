"""Three-level hierarchical layer over per-specimen TMCMC posteriors: population → group → specimen.

Specimens often come in groups the data name (a ``# group:`` line, or any metadata key such as
species, muscle or protocol): treating frog, mouse and human bundles as exchangeable draws of one
population mixes two kinds of variability.  This module adds the group level to the two-level
layer of :mod:`hbm.samplers.hierarchical`, in the *same* transformed coordinates and with the
*same* per-specimen estimator (sample reuse), so the only new thing is the group means.

Model (per pooled parameter k, transformed coordinate z = g_k(θ_k) of the two-level layer)
-------------------------------------------------------------------------------------------
::

    mu_k                          ~ Uniform[mu_lo_k, mu_hi_k]           (as the two-level layer)
    sd_between_k, sd_within_k     ~ the two-level sd hyperprior, each   (log-uniform or half-normal
                                                                          on sd_range × width of mu)
    m_gk | mu_k, sd_between_k     ~ Normal(mu_k, sd_between_k²) truncated to [mu_lo_k, mu_hi_k]
    z_ik | m_g(i)k, sd_within_k   ~ Normal(m_g(i)k, sd_within_k²) truncated to the transformed box
                                    (the two-level specimen density with mu → m_g(i), sd → sd_within)

independently over k (no full covariance).  A group mean is the centre of a sub-population, so it
is confined to the range where the two-level layer lets a population centre lie (mu's range).

Sampling: inverse-CDF coordinates of the group means
----------------------------------------------------
TMCMC runs over x = (mu, log sd_between, log sd_within, u) with u_gk ∈ [0, 1] and
m_gk = F⁻¹(u_gk; mu_k, sd_between_k) the quantile function of the truncated normal above (a
non-centred parametrisation).  u uniform on [0, 1] ⇔ m_gk ~ N_trunc(mu_k, sd_between_k) exactly,
so the uniform TMCMC reference on the box *is* the prior of (ψ, m): the target is just

    Σ_i log p̂(d_i | m_g(i), sd_within) = Σ_i log mean_j r_ij(m_g(i), sd_within)

with the two-level importance ratios r_ij (:meth:`HierarchicalModel.coefficients` and
:meth:`HierarchicalModel.log_ratio_stats`, one matrix product per group over the whole ψ
population), and the TMCMC log-evidence plus Σ_i log Z_i is the hyper-evidence
log p(all data | three-level family), comparable with the two-level layer's (the half-normal sd
prior adds its correction as there).  The per-specimen ESS, updated individuals (per-draw normalised
weights averaged over draws) and fresh-TMCMC refinement (:meth:`GroupedResult.view`) work as in the
two-level layer with each specimen's own (m_g(i), sd_within).

Measured on the two-group toy of ``tests/test_grouped.py`` (d = 2, three specimens per group):
centred coordinates (m_g uniform on mu's range, the truncated normal a tempered term of the target)
cost the same and ended with a TMCMC log-evidence 5 nats below the inverse-CDF coordinates
(under-converged), so only the latter are offered.  When the data pin the group means, the
posterior of (mu, sd_between, u) is a thin curved sheet and the number of MH steps per stage
matters: 12 fixed steps gave evidences 1–3 nats low and wider intervals than the adaptive default.

Outputs answer "do the groups differ?": draws of the group means, of their pairwise differences
(:meth:`GroupedResult.group_differences`: median, interval and the posterior probability of the
sign) and the split of the spread into between-group and within-group parts
(:meth:`GroupedResult.variance_split`).  A new specimen has two predictives: of a known group
(``group_predictive``) and of a new group (``predictive``: m_new ~ N_trunc(mu, sd_between)).

This module is sampler-layer code: it knows nothing about muscles.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Any, Callable, Mapping, Sequence

import numpy as np

from ...errors import HbmError
from ..truncnorm import ppf
from .model import HierarchicalModel, draw_population
from .posterior import fit_layer
from .result import HierarchicalResult, thin_rows
from .reuse import ReuseEstimator, check_box, pack_stage1

__all__ = ["GroupedModel", "GroupedResult", "grouped_hierarchical", "group_differences",
           "variance_split"]


class GroupedModel:
    """Hyperparameters, sampler box and coordinates of the three-level model (module docstring).

    Parameters
    ----------
    names, bounds, pooled, transforms, sd_prior, sd_range, mu_bounds, logit_range
        As :class:`~hbm.samplers.hierarchical.HierarchicalModel` (which is built from them and
        gives the specimen level); no ``full_cov`` and no ``fix``.
    groups : sequence of str
        The group names, in order (at least two).
    """

    def __init__(self, names: Sequence[str], bounds, groups: Sequence[str], *, pooled: Sequence[str] | None = None,
                 transforms: Mapping[str, str] | None = None, sd_prior: str = "loguniform",
                 sd_range: tuple[float, float] = (1e-3, 1.0), mu_bounds: Mapping[str, tuple[float, float]] | None = None,
                 logit_range: float = 8.0) -> None:
        self.base = HierarchicalModel(names, bounds, pooled=pooled, transforms=transforms, sd_prior=sd_prior,
                                      sd_range=sd_range, mu_bounds=mu_bounds, logit_range=logit_range)
        self.groups = [str(g) for g in groups]
        if len(self.groups) < 2 or len(set(self.groups)) != len(self.groups):
            raise HbmError(f"grouped hierarchical: need at least two distinct groups, got {self.groups}")
        b = self.base
        self.d, self.G, self.names = b.d, len(self.groups), list(b.names)
        d = self.d
        # sampler box: mu, sd_between, sd_within in the two-level conventions; u in [0, 1]
        sbox = b.full_box[d : 2 * d]
        self.box = np.vstack([b.full_box[:d], sbox, sbox, np.tile([0.0, 1.0], (self.G * d, 1))])
        self.hyper_names = ([f"mu_{p}" for p in self.names] + [f"sd_{p}" for p in self.names]
                            + [f"sd_between_{p}" for p in self.names] + [f"sd_within_{p}" for p in self.names])

    def _sd(self, s: np.ndarray) -> np.ndarray:
        return np.exp(s) if self.base.sd_prior == "loguniform" else s

    def split(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Sampler coordinates (n, 3d + G·d) -> mu (n, d), sd_between, sd_within (n, d), means (n, G, d).

        mu and the means are in transformed units; the sds are sds (not logs).
        """
        x = np.atleast_2d(np.asarray(x, float))
        d, G = self.d, self.G
        if x.shape[1] != (3 + G) * d:
            raise HbmError(f"grouped hierarchical: expected {(3 + G) * d} sampler coordinates, got {x.shape[1]}")
        mu, sdb, sdw = x[:, :d], self._sd(x[:, d : 2 * d]), self._sd(x[:, 2 * d : 3 * d])
        u = x[:, 3 * d :].reshape(-1, G, d)
        m = ppf(u, mu[:, None, :], sdb[:, None, :], self.base.mu_lo, self.base.mu_hi)
        return mu, sdb, sdw, m

    def specimen_raw(self, x: np.ndarray, g: int | None = None) -> np.ndarray | list[np.ndarray]:
        """Two-level raw coordinates (m_g, sd_within) of group ``g``'s specimens, for every row of ``x``
        (``g=None``: the list over all groups, the quantile map evaluated once)."""
        x = np.atleast_2d(np.asarray(x, float))
        _, _, _, m = self.split(x)
        raws = [np.concatenate([m[:, k, :], x[:, 2 * self.d : 3 * self.d]], axis=1) for k in range(self.G)]
        return raws if g is None else raws[g]

    def from_z(self, z: np.ndarray) -> np.ndarray:
        """Inverse transform of the pooled columns (the two-level model's)."""
        return self.base.from_z(z)

    def natural(self, x: np.ndarray) -> np.ndarray:
        """(mu, total sd, sd_between, sd_within) named by ``hyper_names``; total sd = √(sd_b² + sd_w²)."""
        mu, sdb, sdw, _ = self.split(x)
        return np.concatenate([mu, np.sqrt(sdb**2 + sdw**2), sdb, sdw], axis=1)

    def log_hyperprior_correction(self, x: np.ndarray) -> np.ndarray:
        """log hyperprior minus log uniform density on the box, for both sds (0 if log-uniform)."""
        d = self.d
        x = np.atleast_2d(np.asarray(x, float))
        return sum(self.base.log_hyperprior_correction(np.concatenate([x[:, :d], x[:, s : s + d]], axis=1))
                   for s in (d, 2 * d))


@dataclass
class GroupedResult(HierarchicalResult):
    """Output of :func:`grouped_hierarchical`: a :class:`~hbm.samplers.hierarchical.HierarchicalResult`
    with the group level added.

    The inherited attributes mean the same (``hyper_samples``: ``mu_<P>``, ``sd_<P>`` = total sd
    √(sd_between² + sd_within²), ``sd_between_<P>``, ``sd_within_<P>``; ``predictive``: a new
    specimen of a *new* group; ``model`` is the :class:`GroupedModel`; ``raw_samples`` are in its
    sampler coordinates), so code written for the two-level result reads this one.

    Attributes
    ----------
    groups : list of str
        Group names (order of the group axis).
    specimen_group : dict specimen -> group
    group_means : ndarray (n, G, d)
        Draws of the group means m_g, transformed units.
    group_predictive : ndarray (n, G, d)
        A new specimen of each known group (pooled columns, θ space).
    new_group_raw : ndarray (n, 2d)
        (m_new, sd_within) of a new group per draw, two-level raw coordinates (the predictive's
        population; used by :meth:`population_log_density`).
    """

    groups: list = field(default_factory=list)
    specimen_group: dict = field(default_factory=dict)
    group_means: np.ndarray | None = None
    group_predictive: np.ndarray | None = None
    new_group_raw: np.ndarray | None = None

    def population_log_density(self, theta: np.ndarray, n_hyper: int = 500, seed=0) -> np.ndarray:
        """log predictive density of a new specimen of a new group (pooled columns): the mixture of
        N(m_new, sd_within) over (a thinned subset of) the draws of :attr:`new_group_raw`."""
        return self.model.base.log_density(theta, thin_rows(self.new_group_raw, n_hyper, seed))

    def group_differences(self, prob: float = 0.9) -> list[dict]:
        """Posterior of every pairwise group-mean difference m_b − m_a (transformed units), per parameter.

        Returns
        -------
        list of dict
            One per (pair, parameter): ``a``, ``b`` (group names, pairs in group order),
            ``parameter``, ``median``, ``lo``, ``hi`` (central ``prob`` interval) and
            ``p_positive`` = P(m_b > m_a | all data).
        """
        return group_differences(self.group_means, self.groups, self.names, prob)

    def variance_split(self, prob: float = 0.9) -> dict[str, dict[str, float]]:
        """Per parameter: medians and intervals of sd_between, sd_within and the between-group
        fraction of the variance, sd_b² / (sd_b² + sd_w²) (transformed units)."""
        return variance_split(self.hyper_samples, self.hyper_names, self.names, prob)

    def view(self, specimen: str) -> HierarchicalResult:
        """The two-level result seen by one specimen: population (m_g(i), sd_within).

        For :func:`~hbm.samplers.hierarchical.refine_individual`: its leave-one-out mixture over
        these draws is p(θ_i | all data) of the three-level model (the draws of (m_g(i), sd_within)
        are marginals of the joint posterior, and p̂(d_i|·) depends on them only).
        """
        if specimen not in self.specimens:
            raise HbmError(f"grouped hierarchical: unknown specimen {specimen!r}; have {self.specimens}")
        g = self.groups.index(self.specimen_group[specimen])
        raw = self.model.specimen_raw(self.raw_samples, g)
        b = self.model.base
        return HierarchicalResult(
            hyper_samples=b.natural(raw), hyper_names=list(b.hyper_names), names=list(self.names),
            all_names=list(self.all_names), bounds=self.bounds, transforms=dict(self.transforms),
            specimens=list(self.specimens), predictive=self.group_predictive[:, g, :], timings={}, model=b,
            raw_samples=raw, options=dict(self.options),
            **self.layer_fields(ess_trace=[], warnings=list(self.warnings), reuse={}))


def group_differences(means: np.ndarray, groups: Sequence[str], names: Sequence[str], prob: float = 0.9) -> list[dict]:
    """Pairwise differences m_b − m_a of group-mean draws ``means`` (n, G, d); see
    :meth:`GroupedResult.group_differences`."""
    means = np.asarray(means, float)
    q = [(1 - prob) / 2, 0.5, (1 + prob) / 2]
    out = []
    for a in range(len(groups)):
        for b in range(a + 1, len(groups)):
            diff = means[:, b, :] - means[:, a, :]  # (n, d): all parameters at once
            lo, med, hi = np.quantile(diff, q, axis=0)
            pos = np.mean(diff > 0, axis=0)
            out += [{"a": groups[a], "b": groups[b], "parameter": p, "median": float(med[k]), "lo": float(lo[k]),
                     "hi": float(hi[k]), "p_positive": float(pos[k])} for k, p in enumerate(names)]
    return out


def variance_split(hyper: np.ndarray, hyper_names: Sequence[str], names: Sequence[str],
                   prob: float = 0.9) -> dict[str, dict[str, float]]:
    """Between/within-group sds and the between fraction of the variance; see
    :meth:`GroupedResult.variance_split`."""
    hyper = np.asarray(hyper, float)
    hn = list(hyper_names)
    q = [(1 - prob) / 2, 0.5, (1 + prob) / 2]
    out = {}
    for p in names:
        sb, sw = hyper[:, hn.index(f"sd_between_{p}")], hyper[:, hn.index(f"sd_within_{p}")]
        row = {}
        for key, v in (("sd_between", sb), ("sd_within", sw), ("between_fraction", sb**2 / (sb**2 + sw**2))):
            lo, med, hi = np.quantile(v, q)
            row.update({key: float(med), f"{key}_lo": float(lo), f"{key}_hi": float(hi)})
        out[p] = row
    return out


def _membership(specs: Sequence[str], specimen_group: Mapping[str, str]) -> tuple[list[str], np.ndarray]:
    """Group names (order of first appearance in sorted order) and each specimen's group index."""
    missing = [s for s in specs if s not in specimen_group or not str(specimen_group[s]).strip()]
    if missing:
        raise HbmError(f"grouped hierarchical: no group for specimens {missing}")
    labels = [str(specimen_group[s]).strip() for s in specs]
    groups = sorted(set(labels))
    if len(groups) < 2:
        raise HbmError(f"grouped hierarchical: every specimen is in group {groups[0]!r}; a group level needs at "
                       "least two groups (use the two-level layer)")
    return groups, np.array([groups.index(g) for g in labels])


def _explain(key: str, s: dict, hyper: bool, threshold: float) -> str:
    """The warning of a collapsed ESS of one specimen under its group's population."""
    which = "p(d|m_g, sd_within) and its updated posterior" if hyper else "its updated posterior"
    return (f"grouped hierarchical: importance ESS of specimen {key!r} collapsed for {which} (10% quantile "
            f"{min(s['q10'], s['raw_q10']):.1f} of {s['n']} stage-1 samples < {threshold:g}): refine it with "
            f"hbm.samplers.hierarchical.refine_individual(result.view({key!r}), ...)")


def grouped_hierarchical(
    stage1: Mapping[str, tuple], names: Sequence[str], bounds, specimen_group: Mapping[str, str], *,
    transforms: Mapping[str, str] | None = None, pooled: Sequence[str] | None = None,
    log_prior: Mapping[str, np.ndarray] | None = None, estimator: str = "raw", bandwidth: str | float = "silverman",
    n_samples: int = 2000, seed=None, progress: bool = True, sampler: Callable | None = None,
    tmcmc_options: Mapping[str, Any] | None = None, sd_prior: str = "loguniform",
    sd_range: tuple[float, float] = (1e-3, 1.0), mu_bounds: Mapping[str, tuple[float, float]] | None = None,
    logit_range: float = 8.0, ess_threshold: float = 50.0, n_updated: int | None = None, n_hyper_updated: int = 1000,
    chunk_bytes: float = 4e6, log_likelihood: Mapping[str, np.ndarray] | None = None,
) -> GroupedResult:
    """Three-level hyper-posterior, hyper-evidence, group means, updated individuals and predictives.

    Parameters
    ----------
    stage1, names, bounds, transforms, pooled, log_prior, estimator, bandwidth, n_samples, seed,
    progress, sampler, tmcmc_options, sd_prior, sd_range, mu_bounds, logit_range, ess_threshold,
    n_updated, n_hyper_updated, chunk_bytes, log_likelihood
        As :func:`hbm.samplers.hierarchical.hierarchical` (no ``full_cov``, ``fix``, ``thin``,
        row weights).  ``log_likelihood`` (the stage-1 rows' log-likelihoods) lets the reuse
        diagnostics extrapolate the likelihood beyond the samples with its edge slope.
    specimen_group : mapping specimen -> group name
        The group of every specimen of ``stage1``; at least two groups.

    Returns
    -------
    GroupedResult

    Raises
    ------
    HbmError
        A specimen without a group, a single group, or the two-level layer's input errors.
    """
    t0 = time.perf_counter()
    names = [str(n) for n in names]
    label = "grouped hierarchical"
    data = pack_stage1(stage1, names, None, log_prior=log_prior, log_likelihood=log_likelihood, label=label)
    groups, gidx = _membership(data.specimens, specimen_group)
    model = GroupedModel(names, bounds, groups, pooled=pooled, transforms=transforms, sd_prior=sd_prior,
                         sd_range=sd_range, mu_bounds=mu_bounds, logit_range=logit_range)
    base = model.base
    check_box(data, names, base.all_bounds, label)
    est = ReuseEstimator(base, data, estimator=estimator, bandwidth=bandwidth, chunk_bytes=chunk_bytes, label=label)
    s_tmcmc, s_upd, s_pred = np.random.SeedSequence(
        seed if not isinstance(seed, np.random.Generator) else seed.integers(2**63)).spawn(3)
    t1 = time.perf_counter()
    fit = fit_layer(est, model.box, model.specimen_raw, model.log_hyperprior_correction, gidx, (s_tmcmc, s_upd),
                    n_samples=n_samples, progress=progress, sampler=sampler, tmcmc_options=tmcmc_options,
                    ess_threshold=ess_threshold, n_updated=n_updated, n_hyper_updated=n_hyper_updated,
                    explain=lambda k, s, h: _explain(k, s, h, ess_threshold))
    x = fit.x
    t2 = time.perf_counter()
    rng_p = np.random.default_rng(s_pred)
    n = x.shape[0]
    mu, sdb = x[:, : model.d], model._sd(x[:, model.d : 2 * model.d])
    # a new group: m_new ~ N_trunc(mu, sd_between), then a specimen ~ N(m_new, sd_within)
    m_new = ppf(rng_p.random(mu.shape), mu, sdb, base.mu_lo, base.mu_hi)
    new_raw = np.concatenate([m_new, x[:, 2 * model.d : 3 * model.d]], axis=1)
    predictive = draw_population(base, new_raw, n, rng_p)
    group_pred = np.stack([draw_population(base, raw, n, rng_p) for raw in fit.raws], axis=1)
    t3 = time.perf_counter()
    return GroupedResult(
        hyper_samples=model.natural(x), hyper_names=list(model.hyper_names), names=list(model.names),
        all_names=names, bounds=base.all_bounds.copy(), transforms=dict(base.transforms), specimens=data.specimens,
        groups=groups, specimen_group={s: groups[g] for s, g in zip(data.specimens, gidx)},
        group_means=model.split(x)[3], group_predictive=group_pred, new_group_raw=new_raw, predictive=predictive,
        model=model, raw_samples=x, **fit.result_fields(t1 - t0, t3 - t2),
        options={"n_samples": int(n_samples), "sd_prior": sd_prior, "sd_range": list(sd_range),
                 "ess_threshold": ess_threshold, "logit_range": logit_range, "mu_lo": base.mu_lo.tolist(),
                 "mu_hi": base.mu_hi.tolist(), "estimator": estimator, "log_prior": log_prior is not None,
                 "groups": list(groups), "levels": "population -> group -> specimen"},
    )
