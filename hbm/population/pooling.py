"""What the population layer pools: the stage-1 data packed once, and the pooling strategies as objects.

A strategy turns the packed stage-1 data into the layer's inputs (:class:`Layout`: columns, box,
transforms, pooled names, stage-1 rows and their prior density) and knows what follows from its
choice: the updated individuals' columns, the map a fresh TMCMC refinement needs, the coordinates
of the exact fallback and how to draw a new specimen.

* :class:`ParameterPooling` -- model parameters: "informed" (those the posteriors inform,
  :func:`~hbm.samplers.hierarchical.auto_pool`), "all" or a list of names.
* :class:`CombinationPooling` -- "combinations": a population over the logs of the model's three
  mixture combinations φ (the Spyrou base: log G, log c·P1, log (1−c)·T1), its shape parameters
  (the Spyrou base: T2, THETA, + EOPT when informed), with the exact stage-1 prior density of φ
  (:mod:`hbm.identifiability.combinations`).

Parameter names, transforms and roles come from the model's spec (:mod:`hbm.model.spec`).
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Callable, Mapping, Sequence

import numpy as np

from .. import io
from ..runtime import seeds
from ..identifiability.combinations import (
    combination_box, combination_features, fibre_point, log_density, sample_conditional, support_hull, to_features)
from ..errors import HbmError
from ..model.spec import ModelSpec, base_spec
from ..samplers.hierarchical import auto_pool
from ..runtime.progress import log_progress as _log
from .config import POOL_COMBINATIONS, POOL_INFORMED, POOL_MODES, PopulationConfig, combination_columns

__all__ = ["Stage1Data", "Layout", "ParameterPooling", "CombinationPooling", "pack_results", "pooling_strategy",
           "COMBINATION_NEEDS", "combination_needs"]


def combination_needs(spec: ModelSpec) -> tuple[str, ...]:
    """The model parameters ``--pool combinations`` needs free: the mixture's five and the shape
    parameters pooled always (empty for a model without a mixture)."""
    if spec.mixture is None:
        return ()
    return spec.mixture.params + tuple(p for p in spec.shape_parameters if p not in spec.pooled_when_informed)


#: model parameters ``--pool combinations`` needs free (the default base's)
COMBINATION_NEEDS = combination_needs(base_spec())


@dataclass
class Stage1Data:
    """The specimens' stage-1 results as the layer reads them, checked and packed once.

    Attributes
    ----------
    results : mapping specimen -> SpecimenResult
    names : list of str
        The stage-1 columns (common to all specimens).
    bounds : ndarray (len(names), 2)
        The common stage-1 box.
    model_names : list of str
        The free model parameters among the columns (the noise columns are not pooled).
    transforms : dict
        Transform of each model parameter (the spec's, the configuration's overrides; "logit" where
        "log" would need a positive box).
    log_likelihood : dict or None
        The stored stage-1 log-likelihoods of every specimen's samples (None unless all have them).
    """

    results: Mapping[str, io.SpecimenResult]
    names: list
    bounds: np.ndarray
    model_names: list
    transforms: dict
    log_likelihood: dict | None
    spec: ModelSpec | None = None

    def samples(self) -> dict[str, np.ndarray]:
        """Specimen -> stage-1 samples."""
        return {sid: r.samples for sid, r in self.results.items()}

    def stage1(self, extra: Mapping[str, np.ndarray] | None = None) -> dict[str, tuple]:
        """Specimen -> (samples [+ ``extra`` columns], log Z, its SE): the layer's ``stage1`` argument."""
        return {sid: (r.samples if extra is None else np.hstack([r.samples, extra[sid]]), r.log_evidence,
                      r.log_evidence_se) for sid, r in self.results.items()}


def pack_results(results: Mapping[str, io.SpecimenResult], model, cfg: PopulationConfig) -> Stage1Data:
    """Check that the specimens share parameters, boxes and uniform priors, and pack them (:class:`Stage1Data`)."""
    first = next(iter(results.values()))
    names = list(first.names)
    for sid, r in results.items():
        if list(r.names) != names or not np.allclose(r.bounds, first.bounds):
            raise HbmError(f"hierarchical: specimen {sid} was fitted with other parameters/boxes than "
                           f"{first.specimen_id}; re-run all specimens with the same settings")
        # stage-1 posteriors are reweighted by their prior, taken as uniform on the box
        logu = [n for n, p in (getattr(r, "prior", None) or {}).items() if p.get("form", "uniform") != "uniform"]
        if logu:
            raise HbmError(f"hierarchical: specimen {sid} was fitted with a non-uniform prior on "
                           f"{', '.join(logu)}; the population layer needs uniform stage-1 priors")
    model_names = [n for n in names if n in model.parameter_names]
    spec = getattr(model, "spec", None) or base_spec()
    transforms = {n: spec.transform(n) for n in model_names}
    transforms.update({k: v for k, v in dict(cfg.transforms or {}).items() if k in model_names})
    for n in model_names:  # log needs a positive box
        if transforms[n] == "log" and first.bounds[names.index(n), 0] <= 0:
            transforms[n] = "logit"
    # stage-1 log-likelihoods for the coverage diagnostic (its likelihood extrapolation), when stored
    ll = {sid: np.asarray(r.log_likelihood, float) for sid, r in results.items()
          if getattr(r, "log_likelihood", None) is not None and len(r.log_likelihood) == len(r.samples)}
    return Stage1Data(results, names, first.bounds, model_names, transforms, ll if len(ll) == len(results) else None,
                      spec)


@dataclass
class Layout:
    """The layer's inputs chosen by a pooling strategy.

    ``names``/``bounds``: the layer's columns and box (the stage-1 columns, plus derived ones);
    ``stage1``: specimen -> (rows, log Z, SE); ``log_prior``: the stage-1 prior log density of the
    pooled columns of every row (None: the uniform box, or not computed yet: ``prior`` computes it,
    :meth:`with_prior`); ``attrs``: what ``hierarchical.nc`` records about the choice
    (``transforms``, ``pooled``, ``pool_reasons``, ``mode``).
    """

    names: list
    bounds: np.ndarray
    transforms: dict
    pooled: list
    stage1: dict
    log_prior: dict | None
    attrs: dict
    prior: Callable[[], dict] | None = None

    def with_prior(self) -> "Layout":
        """The layout with ``log_prior`` computed (the reuse layer needs it; the joint sampler does not:
        the exact density of the combinations costs ~30 µs per stage-1 row)."""
        if self.prior is None:
            return self
        return dataclasses.replace(self, log_prior=self.prior(), prior=None)


#: the joint sampler pools a parameter that at least this many specimens inform, whatever fraction of the
#: specimens that is (auto-pool's half otherwise).  The half was made for the reuse layer, whose importance
#: weights collapse on columns the data leave at their prior; the joint sampler evaluates every specimen's
#: likelihood.  Ten informed values estimate a spread to ~24 % (1/sqrt(2·9)); at 96 synthetic specimens whose
#: EOPT varies (informed in 24), pooling it brought the generator's coverage from 6/10 to 12/12
#: (results/benchmarks/population_layer.md).  Up to 20 specimens the half is at most ten: nothing changes there.
JOINT_POOL_INFORMED = 10


def joint_needed(joint: bool) -> int | None:
    """auto-pool's ``max_needed`` for the layer that will run (None: the reuse layer's half)."""
    return JOINT_POOL_INFORMED if joint else None


def pooling_strategy(pooled, data: Stage1Data):
    """The strategy of ``PopulationConfig.pooled``: "auto" (default: "combinations" when the model has a
    mixture and its parameters (:func:`combination_needs`) are free, otherwise "informed"),
    "combinations", "informed", "all" or names."""
    if (isinstance(pooled, (list, tuple)) and len(pooled) == 1
            and pooled[0] in POOL_MODES):
        pooled = pooled[0]  # the CLI splits --pool on commas
    if pooled in (None, "auto"):
        needs = combination_needs(data.spec)
        pooled = POOL_COMBINATIONS if needs and all(n in data.model_names for n in needs) else POOL_INFORMED
    return CombinationPooling() if pooled == POOL_COMBINATIONS else ParameterPooling(pooled)


class PlainCoordinates:
    """Coordinates of the exact fallback when the pooled columns are stage-1 columns: y = θ."""

    def __init__(self, bounds: np.ndarray, names: Sequence[str]) -> None:
        self.box, self.names_y = np.asarray(bounds, float), list(names)

    def y_of(self, theta: np.ndarray) -> np.ndarray:
        return np.asarray(theta, float)

    def theta_of(self, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        return y, np.ones(y.shape[0], bool)

    def columns(self, y: np.ndarray) -> tuple[np.ndarray, None]:
        return y, None  # the model's uniform box prior of the pooled columns

    def draw_theta(self, y: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        return y


class ParameterPooling:
    """Pool model parameters: "informed", "all" or a list of names (the stage-1 columns as they are)."""

    augment = None  # a refinement runs on the layer's own columns

    def __init__(self, mode) -> None:
        self.mode = mode

    def layout(self, data: Stage1Data, cfg: PopulationConfig, joint: bool = False) -> Layout:
        mode, model_names, pool_reasons = self.mode, list(data.model_names), None
        if mode == POOL_INFORMED:  # informed in half of the specimens (joint sampler: in ten at most)
            choice = auto_pool(data.samples(), data.names, data.bounds, data.transforms, candidates=model_names,
                               max_needed=joint_needed(joint))
            pool_reasons = {k: v["reason"] for k, v in choice.reasons.items()}
            model_names = choice.pooled
            _log(f"pooled (informed): {', '.join(model_names)}", cfg.progress)
        elif mode and mode != "all":
            if isinstance(mode, str):
                mode = [mode]
            bad = [p for p in mode if p not in model_names]
            if bad:
                raise HbmError(f"--pool: {', '.join(bad)} not among the free model parameters "
                               f"{', '.join(model_names)} (or auto, combinations, informed, all)")
            model_names = [n for n in model_names if n in mode]
        transforms = {n: data.transforms[n] for n in model_names}
        self.coords = PlainCoordinates(data.bounds, data.names)
        return Layout(data.names, data.bounds, transforms, model_names, data.stage1(), None,
                      {"transforms": transforms, "pooled": model_names, "pool_reasons": pool_reasons,
                       "mode": mode if isinstance(mode, str) else "list"})

    def updated(self, h) -> dict[str, np.ndarray]:
        """The updated individuals' stage-1 columns."""
        return {sid: np.asarray(h.updated[sid]) for sid in h.specimens}

    def new_specimen(self, h, cfg: PopulationConfig) -> tuple[np.ndarray, list, dict]:
        """A new specimen's pooled columns: the layer's predictive."""
        return h.predictive, list(h.names), {}


class CombinationAugment:
    """θ (stage-1 columns) -> (θ + φ columns, stage-1 prior log density of the pooled columns).

    The map behind ``--pool combinations``, for the fresh-TMCMC fallback of collapsed specimens
    (:func:`hbm.samplers.hierarchical.refine_individual`); a class so that dask can ship it.
    """

    def __init__(self, names: Sequence[str], bounds: np.ndarray, log_u: float, roles=None) -> None:
        self.names, self.bounds, self.log_u = list(names), np.asarray(bounds, float), float(log_u)
        self.roles = roles or base_spec().mixture

    def __call__(self, theta: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        f = to_features(self.names, theta, roles=self.roles)
        ok = np.all(f > 0, axis=1)  # an amplitude exactly 0 has no log feature (prior mass 0)
        phi = np.log(np.where(ok[:, None], f, 1.0))
        lp = np.full(theta.shape[0], -np.inf)
        if ok.any():
            lp[ok] = log_density(phi[ok], self.bounds, self.names, roles=self.roles) + self.log_u
        return np.hstack([theta, phi]), lp


class PhiCoordinates:
    """Coordinates of the exact fallback for ``--pool combinations``: y = (φ, the other stage-1 columns).

    The likelihood depends on (VOLF, P1, T1, GF, GM) only through φ = (log G, log c·P1,
    log (1−c)·T1), so the joint posterior is sampled in y: with p(θ|ψ) = p_pop(x|ψ)·p0(θ)/p0(x)
    the fibre of θ over y integrates to p(y|ψ) ∝ p_pop(x(y)|ψ) on the support of p0(φ), i.e. the
    stage-1 density p0(φ) cancels and is never evaluated (it costs 10× the likelihood).  The
    likelihood is evaluated at one deterministic point of the fibre (:meth:`theta_of`); the
    output θ are drawn from the box prior given φ (:func:`hbm.identifiability.combinations.sample_conditional`),
    which is the joint posterior's own conditional.
    """

    def __init__(self, names: Sequence[str], bounds: np.ndarray, hull: np.ndarray, log_u: float,
                 roles=None) -> None:
        self.names, self.bounds, self.log_u = list(names), np.asarray(bounds, float), float(log_u)
        self.roles = roles = roles or base_spec().mixture   # the mixture of the model's spec (default base's)
        self.comb = [self.names.index(p) for p in roles.params]
        self.other = [j for j, n in enumerate(self.names) if n not in roles.params]
        self.box = np.vstack([np.asarray(hull, float), self.bounds[self.other]])
        # built once: theta_of is in the sampler's inner loop
        self.cbox = combination_box(self.bounds, self.names, roles=roles)
        self.names_y = list(combination_columns(roles)) + [self.names[j] for j in self.other]

    def y_of(self, theta: np.ndarray) -> np.ndarray:
        theta = np.asarray(theta, float)
        return np.column_stack([np.log(to_features(self.names, theta, roles=self.roles)), theta[:, self.other]])

    def theta_of(self, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """A θ with combinations φ = y[:, :3] (:func:`hbm.identifiability.combinations.fibre_point`) and whether one exists."""
        parts, ok = fibre_point(y[:, :3], self.bounds, self.names, box=self.cbox, roles=self.roles)
        theta = np.empty((y.shape[0], len(self.names)))
        theta[:, self.comb] = parts
        theta[:, self.other] = y[:, 3:]
        return theta, ok

    def columns(self, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        # log_prior: the uniform densities of the other pooled columns only -- p0(φ) cancels (class docstring)
        return np.hstack([self.theta_of(y)[0], y[:, :3]]), np.full(y.shape[0], self.log_u)

    def draw_theta(self, y: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        theta = np.empty((y.shape[0], len(self.names)))
        theta[:, self.comb] = sample_conditional(y[:, :3], self.bounds, rng, self.names, roles=self.roles)
        theta[:, self.other] = y[:, 3:]
        return theta


class CombinationPooling:
    """``--pool combinations``: a population over φ = (log G, log c·P1, log (1−c)·T1), T2, THETA
    (+ EOPT when ``auto_pool`` would pool it), with the exact stage-1 prior density of φ.

    The φ columns are appended to the stage-1 samples (the other columns ride along), their
    stage-1 prior log density goes in as ``log_prior`` (see :mod:`hbm.identifiability.combinations`), and a new
    specimen's (VOLF, P1, T1, GF, GM) are drawn from the box prior conditioned on its φ; its
    unpooled model parameters (EOPT if not pooled) from their stage-1 (uniform) prior, as the
    population model leaves them.  A specimen whose importance ESS collapses gets a fresh TMCMC
    run of p(θ_i | all data) over its own parameters, with the population density of φ(θ)
    divided by the stage-1 prior density of φ (:class:`CombinationAugment`).
    """

    mode = POOL_COMBINATIONS

    def layout(self, data: Stage1Data, cfg: PopulationConfig, joint: bool = False) -> Layout:
        names, bounds, model_names, spec = data.names, np.asarray(data.bounds, float), data.model_names, data.spec
        if spec is None or spec.mixture is None:
            raise HbmError("--pool combinations needs a model whose spec declares a mixture of its combinations; "
                           "use --pool informed")
        roles = spec.mixture
        missing = [p for p in combination_needs(spec) if p not in model_names]
        if missing:
            raise HbmError(f"--pool combinations needs free parameters {', '.join(missing)} (fixed or absent); "
                           f"use --pool informed")
        choice = auto_pool(data.samples(), names, bounds, data.transforms, candidates=model_names,
                           max_needed=joint_needed(joint))
        self.extra = extra = [n for n in model_names if n in spec.shape_parameters
                              and (n not in spec.pooled_when_informed or n in choice.pooled)]
        # φ of every stage-1 row; its prior density only when the reuse layer asks (the joint sampler does not)
        phis = {sid: combination_features(names, r.samples, bounds, roles=roles, density=False)[0]
                for sid, r in data.results.items()}
        # box of the φ columns: the support hull of the combinations (a zero lower end, an amplitude from 0,
        # is floored; widened if a sample lies below the floor so every sample is inside)
        hull = np.log(support_hull(bounds, names, roles=roles))
        allphi = np.concatenate(list(phis.values()))
        hull[:, 0] = np.minimum(hull[:, 0], allphi.min(axis=0) - 1e-9)
        hull[:, 1] = np.maximum(hull[:, 1], allphi.max(axis=0) + 1e-9)
        columns = list(combination_columns(roles))
        aug_names = list(names) + columns
        aug_bounds = np.vstack([bounds, hull])
        pooled = columns + extra
        tr = {**{c: "identity" for c in columns}, **{n: data.transforms[n] for n in extra}}
        # stage-1 prior of the pooled columns: p0(φ) × uniform densities of the other pooled columns
        log_u = -float(sum(np.log(np.ptp(bounds[names.index(n)])) for n in extra))
        reasons = {k: v["reason"] for k, v in choice.reasons.items()}
        reasons["combinations"] = ("--pool combinations: population over "
                                   + ", ".join(f"log {c}" for c in roles.names)
                                   + f" (exact stage-1 prior density) and {', '.join(extra)}")
        _log(f"pooled (combinations): {', '.join(pooled)}", cfg.progress)
        self.names, self.bounds, self.model_names, self.roles = list(names), bounds, list(model_names), roles
        self.augment = CombinationAugment(names, bounds, log_u, roles)
        self.coords = PhiCoordinates(names, bounds, hull, log_u, roles)
        cbox = combination_box(bounds, names, roles=roles)

        def prior() -> dict:  # p0(φ) × the uniform densities of the other pooled columns, per stage-1 row
            return {sid: log_density(phis[sid], cbox) + log_u for sid in data.results}

        return Layout(aug_names, aug_bounds, tr, pooled, data.stage1(phis), None,
                      {"transforms": tr, "pooled": pooled, "pool_reasons": reasons, "mode": POOL_COMBINATIONS},
                      prior=prior)

    def updated(self, h) -> dict[str, np.ndarray]:
        """The updated individuals' stage-1 columns (the φ columns dropped)."""
        return {s: np.asarray(h.updated[s])[:, : len(self.names)] for s in h.specimens}

    def new_specimen(self, h, cfg: PopulationConfig) -> tuple[np.ndarray, list, dict]:
        """Pooled columns from the predictive, the mixture's five parameters | φ from the box prior, unpooled
        model parameters from their uniform stage-1 prior (stream ``new_specimen``)."""
        names, bounds, roles = self.names, self.bounds, self.roles
        rng = seeds.rng(int(cfg.seed), "new_specimen")
        pred = np.asarray(h.predictive)
        # The normal population lives on the hull box of φ, but p0 (hence a real specimen) lives on a
        # smaller region (e.g. c·P1/P1_hi + (1−c)·T1/T1_hi ≤ 1): predictive draws outside it have no
        # parameters and are rejected (rejection sampling of the population restricted to the support).
        # The likelihood ignores that truncation mass Z_S(ψ); the rejected fraction, E_ψ[1 − Z_S(ψ)],
        # bounds its effect and goes into the attributes.
        inside = np.isfinite(log_density(pred[:, :3], bounds, names, roles=roles))
        outside_fraction = float(1.0 - inside.mean())
        if not inside.any():
            raise HbmError("--pool combinations: every new-specimen draw lies outside the prior support of the "
                           "combinations; the population is not usable")
        pred = pred[inside]
        parts = sample_conditional(pred[:, :3], bounds, rng, names, roles=roles)
        derived_cols = {p: parts[:, k] for k, p in enumerate(roles.params)}
        for n in self.model_names:
            if n not in derived_cols and n not in self.extra:
                lo, hi = bounds[names.index(n)]
                derived_cols[n] = rng.uniform(lo, hi, pred.shape[0])
        derived = [n for n in self.model_names if n in derived_cols]
        new = np.column_stack([pred] + [derived_cols[n] for n in derived])
        return new, list(h.names) + derived, {"derived": derived, "outside_support_fraction": outside_fraction}
