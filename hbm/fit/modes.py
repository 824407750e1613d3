"""Fit a specimen tested in several loading modes (issue 35, items 4 and 7).

:func:`fit_modes` samples the joint likelihood of :mod:`hbm.likelihood.modes` with TMCMC (full tier: the
amplitude collapse is exact only along the fibres, see the likelihood's docstring), then evaluates every
series at the posterior: pointwise log-likelihood, a posterior-predictive replicate per draw and the fit
quality per test, and what the tests identify (:mod:`hbm.identifiability.modes`: a Fisher analysis at
the highest-likelihood draw).  :func:`hbm.io.modes.write_modes_result` stores one observed variable per
measured observable.  Seeds come from the seed table (:mod:`hbm.runtime.seeds`): the TMCMC and predictive phases.
"""

from __future__ import annotations

import time
import warnings
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Mapping

import numpy as np

from .._version import __version__
from ..data.specimen import as_specimen
from ..errors import HbmError, HbmWarning
from ..identifiability.modes import ModesIdentifiability, fit_point, linearised_identifiability
from ..io.modes import write_modes_result
from ..likelihood.modes import ModesLikelihood, make_modes_likelihood
from ..model import spyrou_model
from ..model.spec import spec_of
from ..runtime import seeds
from ..runtime.files import retire_checkpoint
from ..samplers.tmcmc import tmcmc

__all__ = ["ModesFit", "fit_modes", "TIER_NOTE", "series_fit"]

#: why the multi-mode fit samples every parameter (stated in every report and result file)
TIER_NOTE = ("full tier: the tests are not all along-fibre stress, and the linear-amplitude collapse is exact only "
             "there (uniaxial_c's free lateral stretch depends on the amplitudes; the prescribed-F modes' collapse "
             "is not implemented)")


@dataclass
class ModesFit:
    """The outcome of :func:`fit_modes`.

    Attributes
    ----------
    likelihood : ModesLikelihood
    samples : ndarray (n, d)
        Posterior draws in natural units (columns ``likelihood.names``).
    log_likelihood : ndarray (n,)
    log_evidence, log_evidence_se : float
    predictions : list of ndarray (n, n_values)
        The model's value of every series (parallel to ``likelihood.series``) at each draw.
    replicates : list of ndarray (n, n_values)
        One posterior-predictive replicate per draw.
    pointwise : list of ndarray (n, n_values)
        Log-density of every measured value at each draw.
    n_evaluations : int
        Log-likelihood evaluations (one per particle and call; each solves every test).
    stages : list
    seeds : dict
    timings : dict
    path : Path or None
    identifiability : ModesIdentifiability or None
        What the tests identify, linearised at the highest-likelihood draw (None when not computed).
    """

    likelihood: ModesLikelihood
    samples: np.ndarray
    log_likelihood: np.ndarray
    log_evidence: float
    log_evidence_se: float
    predictions: list
    replicates: list
    pointwise: list
    n_evaluations: int
    stages: list
    seeds: dict
    timings: dict = field(default_factory=dict)
    path: Path | None = None
    identifiability: ModesIdentifiability | None = None

    @property
    def names(self) -> tuple[str, ...]:
        return self.likelihood.names

    def interval(self, values: np.ndarray, level: float = 0.9) -> tuple[float, float]:
        """The central ``level`` interval of ``values`` over the draws."""
        a = (1 - level) / 2
        return tuple(np.quantile(values, [a, 1 - a]))  # type: ignore[return-value]

    def combinations(self) -> dict[str, np.ndarray]:
        """The base model's identifiable combinations (:attr:`hbm.model.spec.ModelSpec.combinations`) at each
        draw, where all their parameters are in the samples or fixed."""
        lik = self.likelihood
        cols = {n: self.samples[:, j] for j, n in enumerate(lik.names)}
        cols.update({n: np.full(self.samples.shape[0], v) for n, v in lik.fixed.items()})
        return {c.name: np.asarray(c.compute(cols), float) for c in spec_of(lik.model).combinations
                if all(p in cols for p in c.parameters)}

    def quality(self) -> list[dict[str, Any]]:
        """Per series: test, mode, observable, points, RMSE of the posterior-mean prediction, RMSE relative
        to the largest |value| of the series, and the share of points inside the 90 % predictive band."""
        out = []
        for s, m, r in zip(self.likelihood.series, self.predictions, self.replicates):
            lo, hi = np.quantile(r, [0.05, 0.95], axis=0)
            out.append({**series_fit(s, m.mean(axis=0)),
                        "coverage90": float(np.mean((s.observed >= lo) & (s.observed <= hi)))})
        return out

    def report(self) -> str:
        """The text summary: tier and why, reading, parameters, then each test's mode and fit quality."""
        lik = self.likelihood
        lines = [f"{lik.label}: {len(lik.data.tests)} test(s) in modes "
                 f"{', '.join(dict.fromkeys(t.load_case for t in lik.data.tests))}; {lik.energy.label}",
                 f"tier: {TIER_NOTE}",
                 f"log-evidence {self.log_evidence:.2f} +- {self.log_evidence_se:.2f} "
                 f"({self.n_evaluations} evaluations, {len(self.stages)} stages)",
                 "posterior: mean, sd, 90 % interval (natural units)"]
        for j, n in enumerate(self.names):
            v = self.samples[:, j]
            lo, hi = self.interval(v)
            lines.append(f"  {n:<28s} {v.mean():<11.4g} {v.std():<11.3g} [{lo:.4g}, {hi:.4g}]")
        for name, v in self.combinations().items():
            lo, hi = self.interval(v)
            lines.append(f"  {name:<28s} {v.mean():<11.4g} {v.std():<11.3g} [{lo:.4g}, {hi:.4g}]")
        lines.append("fit per test (posterior-mean prediction; rmse in the observable's unit, rel = / max|data|; "
                     "cov90 = share inside the 90 % predictive band):")
        for q in self.quality():
            name = q["label"] if q["label"] is not None else q["test"]
            lines.append(f"  test {name} [{q['mode']}] {q['observable']}: {q['points']} points, rmse "
                         f"{q['rmse']:.3g} {q['unit']} (rel {q['rmse_rel']:.3f}), cov90 {q['coverage90']:.2f}")
        if self.identifiability is not None:
            lines += self.identifiability.report_lines()
        return "\n".join(lines)


def series_fit(series, mean: np.ndarray) -> dict[str, Any]:
    """One series against a prediction ``mean`` (its points): test, label, mode, observable, unit, points,
    RMSE in the observable's unit and relative to the series' largest |value| (the rows of
    :meth:`ModesFit.quality` and of the held-out prediction, :func:`hbm.detective.modes.held_out_prediction`)."""
    rmse = float(np.sqrt(np.mean((mean - series.observed) ** 2)))
    return {"test": series.test.id, "label": series.test.label, "mode": series.test.load_case,
            "observable": series.observable, "unit": "MPa" if series.is_stress else "-",
            "points": int(series.rows.size), "rmse": rmse,
            "rmse_rel": rmse / float(np.max(np.abs(series.observed)) or 1.0)}


def fit_modes(data, *, model=None, collagen3d: str | None = None, samples: int = 2000, seed: int = 0,
              test_scale: bool = False, fix: Mapping[str, float] | None = None,
              bounds: Mapping[str, tuple[float, float]] | None = None, prior=None,
              max_evaluations: int | None = None, tmcmc_options: Mapping[str, Any] | None = None,
              progress: bool = True, out: str | Path | None = None,
              config_extra: Mapping[str, Any] | None = None,
              checkpoint_dir: str | Path | None = None) -> ModesFit:
    """TMCMC posterior of a specimen's tests in their loading modes, with evidence and per-series checks.

    Parameters
    ----------
    data : Specimen or xarray.Dataset
        Tests with modes (:func:`hbm.data.load_specimen` of a file with a ``mode`` column).
    model : Model, optional
        Default :func:`hbm.spyrou_model` in the energy form (the thesis form is refused outside
        ``uniaxial_f``).
    collagen3d : {"cone", "gst"}, optional
        The collagen reading (default cone); recorded in the result.
    samples : int
        TMCMC population size.
    seed : int
        Root seed: the TMCMC and predictive phases get the children of :data:`hbm.runtime.seeds.PHASES`.
    test_scale : bool
        A per-test stress scale with prior N(1, 0.05²) (:mod:`hbm.likelihood.modes`).
    fix, bounds, prior
        As for :func:`hbm.likelihood.make_likelihood`.
    max_evaluations : int, optional
        Cap on log-likelihood evaluations.
    tmcmc_options : dict, optional
        Further options of :func:`hbm.samplers.tmcmc.tmcmc` (``max_steps``, ``cov_target`` ...).
    progress : bool
    out : path, optional
        Write the result netCDF (:func:`hbm.io.modes.write_modes_result`).
    config_extra : dict, optional
        Extra JSON-able entries of the stored configuration.
    checkpoint_dir : path, optional
        TMCMC checkpoint ``<dir>/<id>.npz``: an interrupted fit resumes from its last stage.  The caller keys
        the folder by the fit's content (:func:`hbm.io.identity.fit_key`); the result file supersedes it.

    Returns
    -------
    ModesFit

    Raises
    ------
    HbmError
        Every refusal of :func:`hbm.likelihood.modes.make_modes_likelihood`, before any computation.
    """
    t0 = time.perf_counter()
    model = spyrou_model(form="energy") if model is None else model
    spec = as_specimen(data)
    lik = make_modes_likelihood(model, spec, collagen3d=collagen3d, fix=fix, bounds=bounds, prior=prior,
                                test_scale=test_scale)
    _, s_tm, s_pred, _ = seeds.child_ints(seed, len(seeds.PHASES))
    opts = dict(tmcmc_options or {})
    if max_evaluations is not None:
        opts["max_evaluations"] = int(max_evaluations)
    ckpt = None
    if checkpoint_dir is not None:
        ckpt = Path(checkpoint_dir) / f"{spec.id}.npz"
        ckpt.parent.mkdir(parents=True, exist_ok=True)
    tr = tmcmc(lik, lik.bounds, int(samples), seed=s_tm, progress=progress, checkpoint=ckpt, **opts)
    timings = {"tmcmc": time.perf_counter() - t0}
    if tr.budget_exhausted:
        warnings.warn(f"{spec.id}: the evaluation cap ({max_evaluations}) bound the TMCMC run: the last stage jumped "
                      "to the posterior, whose draws, intervals and evidence are not converged; raise "
                      "--max-evaluations", HbmWarning, stacklevel=2)
    t = time.perf_counter()
    y = np.asarray(tr.samples, float)
    pred = lik.predict_series(y)
    pointwise = lik.pointwise(y, pred)
    rng = np.random.default_rng(s_pred)
    sig = lik.to_natural(y)[:, lik.n_model: lik.n_model + len(lik.kinds)]
    replicates = [m + sig[:, lik.kinds.index(s.kind)][:, None] * rng.standard_normal(m.shape)
                  for s, m in zip(lik.series, pred)]
    timings["predictive"] = time.perf_counter() - t
    fit = ModesFit(lik, lik.to_natural(y), np.asarray(tr.log_likelihood, float), float(tr.log_evidence),
                   float(tr.log_evidence_se), pred, replicates, pointwise, int(tr.n_evaluations), list(tr.stages),
                   {"tmcmc": s_tm, "predictive": s_pred})
    t = time.perf_counter()
    fit.identifiability = _identifiability(fit)
    timings["identifiability"] = time.perf_counter() - t
    if out is not None:
        t = time.perf_counter()
        config = {"samples": int(samples), "seed": int(seed), "collagen3d": lik.energy.collagen3d,
                  "form": lik.energy.form, "test_scale": bool(test_scale), "tier": TIER_NOTE,
                  "fix": dict(fix or {}), "version": __version__, **dict(config_extra or {})}
        fit.path = write_modes_result(fit, out, config)
        timings["write"] = time.perf_counter() - t
        retire_checkpoint(ckpt)
    timings["total"] = time.perf_counter() - t0
    fit.timings = timings
    return fit


def _identifiability(fit: ModesFit) -> ModesIdentifiability | None:
    """The Fisher analysis of the fit's tests at its highest-likelihood draw, compared with the posterior;
    None (with a warning) when a model solve fails at the point (the rest of the fit stands)."""
    lik = fit.likelihood
    row, where = fit_point(lik, fit.samples, fit.log_likelihood)
    try:
        ident = linearised_identifiability(lik, row, point_label=where)
    except HbmError as e:
        warnings.warn(f"{lik.label}: what the tests identify was not computed ({e})", HbmWarning, stacklevel=3)
        return None
    cols = {n: fit.samples[:, j] for j, n in enumerate(lik.names)}
    ident.compare_posterior({**cols, **fit.combinations()})
    return ident
