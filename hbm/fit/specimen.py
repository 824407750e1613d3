"""Fit one specimen: CMA-ES optima, TMCMC posterior with evidence, posterior predictive, Sobol.

:func:`fit_specimen` is the unit of work of the six-rat workflow (one dask task per specimen)
and of ``hbm fit``.  Every random stream is spawned from one ``SeedSequence(seed)`` so a fit is
reproducible bit for bit, wherever it runs:

=========  ======================================================
child 0    CMA-ES restarts and the bound sweep (hbm.optimize)
child 1    TMCMC (hbm.samplers.tmcmc)
child 2    posterior-predictive noise
child 3    Sobol sampling (hbm.fit.sensitivity)
=========  ======================================================
"""

from __future__ import annotations

import dataclasses
import json
import os
import time
import warnings
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Mapping, Sequence

import numpy as np

from .sensitivity import sobol as _sobol
from .._version import __version__
from ..data import as_specimen, input_line, input_summary
from ..data.prepare import prepare_record
from ..errors import HbmWarning
from ..runtime import seeds
from ..runtime.files import retire_checkpoint
from ..io import SpecimenResult, json_default, write_specimen_result
from ..likelihood.collapsed import choose_tier, fit_collapsed
from ..likelihood.core import make_likelihood
from ..likelihood.noise import get_noise
from ..model import COMBINATIONS, spyrou_model  # (COMBINATIONS: the default base's, re-exported)
from ..model.spec import DEFAULT_BASE, spec_of
from ..likelihood.prior import PriorError, load_prior
from .optimization import optimize as _cma
from ..samplers.tmcmc import tmcmc as _tmcmc
from ..settings.fit import FitRecord, FitSettings, SWEEP
from ..settings.rules import check_physical_bounds
from ..samplers.moves import needs_gradient
from .quality import (
    EDGE_MASS, EDGE_TOL, RIDGE_NOTE, _prior_line, at_bounds, chain_rhat, chains_line, edges, fit_quality,
    format_at_bounds, map_estimate, map_prediction, quality_lines, summarize, summary_table, tier_line)

__all__ = ["FitResult", "fit_specimen", "fit_posterior", "complete_fit", "summarize", "summary_table",
           "pointwise_log_likelihood", "posterior_predictive", "parse_sweep", "edges", "COMBINATIONS", "at_bounds",
           "map_estimate", "fit_quality", "format_at_bounds", "map_prediction", "quality_lines", "tier_line",
           "EDGE_TOL", "EDGE_MASS", "RIDGE_NOTE", "chain_rhat", "chains_line"]


def parse_sweep(sweep: str | tuple | None) -> tuple[str, float] | None:
    """A sweep ``"NAME:WIDTH"`` or (name, width) as (name, width); None/"" for no sweep (the rule
    of :attr:`hbm.settings.FitSettings.sweep`)."""
    if sweep is None or sweep == "" or sweep is False:
        return None
    return SWEEP.split(SWEEP.check(sweep, "sweep"))


# ----------------------------------------------------------------------------- pieces
def pointwise_log_likelihood(likelihood, theta: np.ndarray, model_stress: np.ndarray | None = None) -> np.ndarray:
    """Pointwise log-likelihood (n, p) whose row sums equal ``likelihood(theta)``.

    Delegates to the noise model (:meth:`hbm.likelihood.noise.NoiseModel.pointwise`): for AR(1) noise the
    pointwise terms are the conditional densities of the innovations p(r_t | r_{t-1}) (the exact
    factorisation of the joint Gaussian), as PSIS-LOO expects.
    """
    m = likelihood.predict(theta) if model_stress is None else model_stress
    return likelihood.noise_model.pointwise(_natural(likelihood, theta)[:, likelihood.n_model:], m)


def _natural(likelihood, theta) -> np.ndarray:
    """Working rows -> natural units (likelihoods without priors: unchanged)."""
    conv = getattr(likelihood, "to_natural", None)
    return np.asarray(theta, float) if conv is None else conv(theta)


def posterior_predictive(likelihood, theta: np.ndarray, seed, model_stress: np.ndarray | None = None
                         ) -> tuple[np.ndarray, np.ndarray]:
    """(noise-free prediction, noisy replicate), both (n, p), one replicate per posterior draw.

    The noise is drawn by the noise model (:meth:`hbm.likelihood.noise.NoiseModel.simulate`, AR(1)
    correlation included) from ``numpy.random.default_rng(seed)``; ``model_stress`` must be the
    prediction at ``theta`` when given.  ``theta`` is in the likelihood's working coordinates
    (as :func:`pointwise_log_likelihood`).
    """
    rng = np.random.default_rng(seed)
    m = likelihood.predict(theta) if model_stress is None else model_stress
    return m, m + likelihood.noise_model.simulate(rng, _natural(likelihood, theta)[:, likelihood.n_model:], m)


def _normalise_optima(res: Any, names: Sequence[str], kind: str) -> list[dict]:
    """Optima from hbm.optimize in the JSON form {"params": {...}, "objective": f, "kind": ...}."""
    items = getattr(res, "optima", None)
    if items is None and isinstance(res, Mapping):
        items = res.get("optima")
    if items is None:
        items = [res]
    out = []
    for o in items:
        if isinstance(o, Mapping):
            d = dict(o)
        elif hasattr(o, "to_dict"):
            d = dict(o.to_dict())
        else:
            d = {k: getattr(o, k) for k in ("params", "objective", "theta", "x", "window") if hasattr(o, k)}
        params = d.get("params")
        if params is None:
            x = d.get("theta", d.get("x"))
            params = {n: float(v) for n, v in zip(names, np.asarray(x, float))}
        entry = {"params": {k: float(v) for k, v in dict(params).items()},
                 "objective": float(d.get("objective", d.get("f", np.nan))), "kind": kind}
        win = d.get("window")
        if win is not None and len(win) == 2:
            entry["window_lower"], entry["window_upper"] = float(win[0]), float(win[1])
        for k in ("window_lower", "window_upper"):
            if k in d:
                entry[k] = float(d[k])
        out.append(entry)
    return out


def run_optima(likelihood, *, restarts: int, seed: int, sweep: tuple[str, float] | None, **options) -> list[dict]:
    """CMA-ES restarts (+ an optional bound sweep) through :func:`hbm.fit.optimization.optimize`."""
    names = list(likelihood.names)
    optima = _normalise_optima(_cma(likelihood, restarts=restarts, seed=seed, **options), names, "restart")
    if sweep is not None:
        sw = _cma(likelihood, restarts=1, seed=seed + 1, sweep=sweep, **options)
        optima += _normalise_optima(sw, names, "sweep")
    return optima


def run_sobol(model, data, *, n: int, seed: int, fix=None, bounds=None, qoi: str = "log_integrated_stress") -> dict:
    """Sobol indices over the prior box (:func:`hbm.fit.sensitivity.sobol`) as a plain dict for io.

    The QoI is log W (the energy on a log scale): its estimator is stable at N = 1024 where the
    raw energy's is not (see :mod:`hbm.fit.sensitivity`).
    """
    res = _sobol(model, data=data, n=n, seed=seed, fix=fix, bounds=bounds, qoi=qoi, per_point=True)
    out: dict[str, Any] = {k: {str(a): float(b) for a, b in getattr(res, k).items()}
                           for k in ("S1", "ST", "S1_conf", "ST_conf")}
    out["relevance"] = {str(a): str(b) for a, b in res.relevance.items()}
    if res.per_point is not None:
        for key in ("S1", "ST"):
            arr = np.asarray(res.per_point[key], float)  # (n_points, D)
            out[f"{key}_point"] = {nm: arr[:, j] for j, nm in enumerate(res.names)}
    out["qoi"] = str(res.qoi)
    out["n"] = int(res.n)
    out["n_evaluations"] = int(res.n_evaluations)
    out.update(res.settings)  # SALib settings: attributes of the file's sobol group
    return out


# ----------------------------------------------------------------------------- driver
@dataclass
class FitResult:
    """Outcome of :func:`fit_specimen`.

    Attributes
    ----------
    result : SpecimenResult
        What is (or would be) stored in the netCDF file.
    path : Path or None
        Written file, if ``out`` was given.
    likelihood : Likelihood
        The specimen's likelihood (free parameter names, bounds, predict ...).
    tmcmc : TMCMCResult or None
        With the collapsed likelihood: the run over the nonlinear parameters (stages, evidence),
        its ``samples``/``log_likelihood`` replaced by the completed rows of every free parameter.
    timings : dict
        Seconds per phase: ``cmaes``, ``tmcmc``, ``predictive``, ``sobol``, ``write``, ``total``.
    """

    result: SpecimenResult
    path: Path | None
    likelihood: Any
    tmcmc: Any = None
    timings: dict = field(default_factory=dict)

    @property
    def samples(self) -> np.ndarray:
        return self.result.samples

    @property
    def names(self) -> list[str]:
        return self.result.names

    @property
    def log_evidence(self) -> float:
        return self.result.log_evidence

    @property
    def log_evidence_se(self) -> float:
        return self.result.log_evidence_se

    def summary(self, prob: float = 0.9) -> dict:
        return summarize(self.result, prob=prob)

    def table(self, prob: float = 0.9) -> str:
        return summary_table(self.result, prob=prob)

    def quality(self, data=None, prob: float = 0.9) -> dict[str, Any]:
        """:func:`fit_quality` of this fit (with its likelihood)."""
        return fit_quality(self, data, prob=prob)

    def map(self) -> dict[str, float]:
        """:func:`map_estimate`: the best fit as a usable parameter set."""
        return map_estimate(self.result)

    def report(self, prob: float = 0.9) -> str:
        """Text report: fit quality, noise, MAP, combinations, evidence and edge warnings FIRST,
        then one line on why raw-parameter means are not a parameter set, then the raw table."""
        r = self.result
        head = [f"specimen {r.specimen_id}: {r.n_samples} posterior samples"]
        stored = FitRecord.from_attrs(r.config)
        if stored.input:
            head.append(input_line(stored.input))
        raw = summarize(r, prob=prob)
        pc = int(round(prob * 100))
        rows = [RIDGE_NOTE, f"{'parameter':<14}{'mean':>12}{'sd':>12}{f'{pc}% lower':>12}{f'{pc}% upper':>12}"]
        rows += [f"{k:<14}{v['mean']:>12.5g}{v['sd']:>12.4g}{v['lower']:>12.5g}{v['upper']:>12.5g}"
                 for k, v in raw.items() if k not in spec_of(r).combination_names]
        if r.fixed:
            rows.append("fixed: " + ", ".join(f"{k}={v:g}" for k, v in r.fixed.items()))
        rows.append(_prior_line(r))
        return "\n".join(head + quality_lines(self.quality(prob=prob)) + [tier_line(r), chains_line(r)] + rows)

    def to_json(self, prob: float = 0.9) -> dict[str, Any]:
        """One JSON-able dict: :func:`fit_quality` plus identification of the run.

        Keys include ``rmse``, ``rmse_rel`` (fraction of peak |stress|), ``coverage90``,
        ``log_evidence``, ``log_evidence_se``, ``map`` (name -> value), ``combinations``,
        ``at_bounds`` (list of {parameter, side, edge, fraction, map_at_edge}), ``noise``,
        ``prior``, ``names``, ``n_samples``, ``summary`` (raw-parameter statistics) and ``path``.
        """
        q = self.quality(prob=prob)
        r = self.result
        stored = FitRecord.from_attrs(r.config)
        q.update({"names": list(r.names), "n_samples": r.n_samples, "fixed": dict(r.fixed),
                  "summary": {k: v for k, v in summarize(r, prob=prob).items()
                              if k not in spec_of(r).combination_names},
                  "input": stored.input, "likelihood_tier": stored.tier_used, "likelihood_note": stored.tier_note,
                  "chains": {"n_chains": r.chains.n_chains, "method": r.chains.method, "note": r.chains.note,
                             "max_rhat": max((chain_rhat(r, r.samples[:, j]) for j in range(len(r.names))),
                                             default=float("nan"))},
                  "path": None if self.path is None else str(self.path)})
        return json.loads(json.dumps(q, default=json_default))


#: above this many points the cost of a fit is measured and said before it starts
LARGE_CURVE = 2000
#: TMCMC likelihood evaluations per population member at the default settings (2.43e6 for
#: N = 2000 on the benchmark posterior, results/benchmarks/evaluations_to_accuracy.md)
EVALUATIONS_PER_SAMPLE = 1200


def check_data_size(sid: str, lik, samples: int, max_evaluations: int | None = None) -> None:
    """Warn (:class:`~hbm.errors.HbmWarning`) before a fit whose data size makes its result weak
    or its cost large.

    * Fewer points than twice the free parameters: the posterior of most parameters is the
      prior box; only the identified combinations and the evidence speak for the data.
    * More than :data:`LARGE_CURVE` points: the cost of one evaluation is measured on the
      likelihood itself (no random numbers) and the TMCMC fit's expected time said, with the
      remedies, when it exceeds two minutes.
    """
    n, free = int(lik.n_points), len(lik.names)
    if n < 2 * free:
        warnings.warn(f"{sid}: {n} points for {free} free parameters: most parameters are set by the prior "
                      "box, not the data; read the identified combinations and the evidence", HbmWarning,
                      stacklevel=2)
    if n <= LARGE_CURVE:
        return
    rows = np.tile(lik.from_unit(np.full(free, 0.5)), (64, 1))
    t = time.perf_counter()
    lik(rows)
    per_row = (time.perf_counter() - t) / 64
    evaluations = EVALUATIONS_PER_SAMPLE * int(samples)
    if max_evaluations is not None:
        evaluations = min(evaluations, int(max_evaluations))
    if per_row * evaluations > 120.0:
        warnings.warn(f"{sid}: {n} points: one evaluation costs {1e3 * per_row:.2g} ms, the TMCMC fit about "
                      f"{per_row * evaluations / 60:.0f} min (~{evaluations:.2g} evaluations); a dense record is "
                      "fitted as bin means of its readings unless --reduce off (hbm.data.reduction), neighbouring "
                      "points are rarely independent (the ar1 noise), and --max-evaluations caps the cost",
                      HbmWarning, stacklevel=2)


def prepared_record(data, sid: str, noise: str, reduce: str | None, artefacts: str | None):
    """The record a fit uses (:func:`hbm.data.prepare.prepare_record`): a dense one reduced, artefact
    rows dropped on request; rows flagged and kept are named in one :class:`~hbm.errors.HbmWarning`."""
    prep = prepare_record(data, reduce=reduce or "auto", artefacts=artefacts or "flag")
    if prep.artefacts:
        keep = (f"kept: the {noise} noise is heavy-tailed and down-weights them" if get_noise(noise).robust else
                "kept, and they pull the fit: drop them with --drop-artefacts (artefacts='drop'; recorded in the "
                "result) or fit robustly with --noise student_t")
        warnings.warn(f"{sid}: rows that are not the tissue: {prep.artefact_text()}; {keep}", HbmWarning,
                      stacklevel=3)
    return prep.data


def _base_name(model) -> str | None:
    """The registered base of ``model`` when it is not the default base (stored in the result file)."""
    spec = getattr(model, "spec", None)
    return spec.name if spec is not None and spec.name != DEFAULT_BASE else None


def fit_specimen(data, *, model=None, settings: FitSettings | None = None,
                 checkpoint_dir: str | os.PathLike | None = None, out: str | os.PathLike | None = None,
                 progress: bool = True, config_extra: Mapping[str, Any] | None = None,
                 on_phase: Callable[[str], None] | None = None, **options: Any) -> FitResult:
    """CMA-ES optima, TMCMC posterior, posterior predictive and (optionally) Sobol for one specimen.

    Parameters
    ----------
    data : Specimen or xarray.Dataset
        A specimen (:func:`hbm.data.load_specimen`; a Dataset is converted once); its ``id`` names it.
    model : Model, optional
        Default :func:`hbm.spyrou_model`.
    settings : FitSettings, optional
        The fit's settings (:class:`hbm.settings.FitSettings`: ``samples``, ``move``, ``noise``,
        ``tier``, ``fix``, ``bounds``, ``seed``, ``restarts``, ``sweep``, ``sobol_n``, ``maxfevals``,
        ``optimize_options``, ``sigma_bounds``, ``tmcmc_options``, ``max_evaluations``, ``prior``);
        default the record's defaults.
    **options
        Settings as keywords instead (or over ``settings``), e.g. ``samples=4000, move="manifold"``;
        the older names ``kernel=`` (the move) and ``likelihood=`` (the tier) still work and warn.
        Highlights: ``move`` -- a TMCMC move of :data:`hbm.samplers.moves.MOVES` ("manifold" uses
        the likelihood's gradient and Fisher information); ``noise`` -- the noise model
        (:func:`hbm.likelihood.make_likelihood`); ``fix``/``bounds`` -- parameters held fixed /
        narrowed prior boxes (inside the prior's box; to widen the thesis box pass
        ``prior=resolve_prior(model, file, bounds)``); ``seed`` -- the root seed (int or
        SeedSequence), the four phases get spawned children (module docstring); ``sweep`` --
        ``"PARAM:WIDTH"`` or (name, width), the thesis §3.1 bound sweep tracing a manifold;
        ``sobol_n`` -- Sobol base sample size (None or 0 skips Sobol); ``maxfevals`` /
        ``optimize_options`` -- CMA-ES budget (default 5000 evaluations per run: the optima only
        seed figures and the manifold) and further options of :func:`hbm.fit.optimization.optimize`;
        ``sigma_bounds`` -- box of the first noise parameter (the workflow uses one box for all
        specimens so the hierarchical layer sees a common stage-1 prior); ``prior`` -- user prior
        (:mod:`hbm.likelihood.prior`; default the thesis box, uniform: bitwise the outputs of a fit
        without it; loguniform parameters are sampled in log coordinates, the stored posterior,
        optima, predictive and Sobol box are in natural units); ``max_evaluations`` -- cap on TMCMC
        log-likelihood evaluations; ``tier`` -- the likelihood tier
        (:func:`hbm.likelihood.collapsed.choose_tier`): "auto" (default) samples only the nonlinear
        and noise parameters on the likelihood with the linear amplitudes integrated out exactly
        where the model's stress is linear in them and the noise keeps their integral Gaussian
        (:func:`hbm.likelihood.collapsed.fit_collapsed`: a 500-particle TMCMC run and an
        importance-sampling finish, or N = ``samples`` with at most 10 MH steps per stage when the
        finish is refused or ``tmcmc_options`` are given), then draws the amplitudes given each
        posterior sample -- the stored posterior holds every free parameter as with the full
        likelihood; "full": the sampler over all parameters; the tier used and why are stored
        (``FitRecord.tier_used``/``tier_note``), evaluation counts count basis evaluations as model
        evaluations; ``reduce`` -- "auto" (default) fits a record above
        :data:`hbm.data.reduction.DENSE_POINTS` rows as bin means of its readings
        (:mod:`hbm.data.reduction`), "off" row by row; ``artefacts`` -- rows the artefact screen
        flags (:mod:`hbm.data.artefacts`) are named in an :class:`~hbm.errors.HbmWarning` and kept
        ("flag", the default), or dropped with a record in the result ("drop").
    checkpoint_dir : path, optional
        TMCMC checkpoint ``<dir>/<id>.npz``: an interrupted fit resumes from its last stage.
        Removed once the result file is written.  It is resumed whatever made it: pass a folder
        keyed by the fit's content (:func:`hbm.io.identity.checkpoint_dir` of :func:`hbm.io.identity.fit_key`,
        as ``hbm fit`` and ``hbm run`` do) so that one of other data or settings is never resumed.
    out : path, optional
        Write the result netCDF here (atomically; ``complete`` flag last).
    progress : bool
        tqdm bar per TMCMC stage.
    config_extra : dict, optional
        Extra JSON-able entries for the stored ``config`` attribute (e.g. a settings hash).
    on_phase : callable, optional
        Called with the phase name when a phase starts (progress reporting).

    Returns
    -------
    FitResult
        ``result.prior`` and ``result.at_bounds`` (box-edge warnings, :func:`at_bounds`) are
        stored in the file too.

    Raises
    ------
    SettingError
        A setting its rule refuses (:mod:`hbm.settings.rules`), before any computation.
    """
    t_start = time.perf_counter()
    f = _prepare_fit(data, model, settings, options)
    phase = on_phase or (lambda name: None)
    timings: dict[str, float] = {}
    if f.s.restarts > 0:
        phase("cmaes")
    optima = _optima(f, timings)
    phase("tmcmc")
    post = _posterior(f, checkpoint_dir, progress, timings)
    phase("predictive")
    res = _result(f, post, optima, config_extra, timings)
    if f.s.sobol_n:
        phase("sobol")
    res.sobol = _sobol_phase(f, timings)
    return _finish(f, res, post, out, timings, t_start)


def fit_posterior(data, *, model=None, settings: FitSettings | None = None,
                  checkpoint_dir: str | os.PathLike | None = None,
                  config_extra: Mapping[str, Any] | None = None) -> SpecimenResult:
    """The first part of :func:`fit_specimen`: the TMCMC posterior and its predictive, no optima, no Sobol.

    What a population layer needs of a specimen, early: ``hbm run`` starts its layer on these while the
    optima and Sobol indices (:func:`complete_fit`) run beside it.  Nothing is written but the TMCMC
    checkpoint; the result is the one :func:`fit_specimen` stores with ``optima`` and ``sobol`` None and no
    edge warnings yet (``at_bounds``: they read the optima).
    Arguments as :func:`fit_specimen`'s.
    """
    f = _prepare_fit(data, model, settings, {})
    timings: dict[str, float] = {}
    post = _posterior(f, checkpoint_dir, False, timings)
    res = _result(f, post, None, config_extra, timings)
    res.timings = dict(timings)
    return res


def complete_fit(posterior: SpecimenResult, data, *, model=None, settings: FitSettings | None = None,
                 checkpoint_dir: str | os.PathLike | None = None,
                 out: str | os.PathLike | None = None) -> FitResult:
    """The rest of :func:`fit_specimen` after :func:`fit_posterior`: CMA-ES optima, the sweep, Sobol; writes.

    With the same data, model and settings the file is the one :func:`fit_specimen` writes (each phase
    has its own stream of the seed table, so their order does not matter); the checkpoint is retired
    once it is written.  ``FitResult.tmcmc`` is None (the stages are in the result).
    """
    t_start = time.perf_counter()
    f = _prepare_fit(data, model, settings, {})
    timings = {k: v for k, v in (posterior.timings or {}).items() if k in ("tmcmc", "predictive")}
    res = dataclasses.replace(posterior, optima=_optima(f, timings))
    res.sobol = _sobol_phase(f, timings)
    ckpt = None if checkpoint_dir is None else Path(checkpoint_dir) / f"{f.data.id}.npz"
    return _finish(f, res, {"ckpt": ckpt, "tr": None}, out, timings, t_start)


@dataclass
class _Fit:
    """A fit's inputs once checked: settings, the prepared record, its likelihood and tier, the phase seeds."""

    model: Any
    s: FitSettings
    data: Any
    prior: Any
    lik: Any
    collapsed: Any
    tier_note: str | None
    phase_seeds: tuple
    sweep: tuple | None


def _prepare_fit(data, model, settings: FitSettings | None, options: Mapping[str, Any]) -> _Fit:
    """Check the settings and build the likelihood (before any long computation)."""
    model = spyrou_model() if model is None else model
    s = FitSettings(**options) if settings is None else (settings.replace(**options) if options else settings)
    check_physical_bounds(s.bounds, spec_of(model).physical_range)
    data = as_specimen(data)
    sid = data.id
    data = prepared_record(data, sid, s.noise, s.reduce, s.artefacts)
    prior = load_prior(s.prior)
    lik = make_likelihood(model, data, noise=s.noise, fix=s.fix, bounds=s.bounds, sigma_bounds=s.sigma_bounds,
                          prior=prior)
    check_data_size(sid, lik, s.samples, s.max_evaluations)
    collapsed, tier_note = choose_tier(lik, s.tier, move=s.move)  # before any long computation
    phase_seeds = tuple(seeds.child_ints(s.seed, len(seeds.PHASES)))  # the phase streams of hbm.runtime.seeds
    sweep_t = s.sweep_pair
    if sweep_t is not None and sweep_t[0] in lik.names and lik.forms[lik.index(sweep_t[0])] == "loguniform":
        # the sweep's windows are cut in the optimiser's (log) coordinates; a width in natural
        # units would be misread there
        raise PriorError(f"sweep: {sweep_t[0]} has a loguniform prior; sweep a uniform parameter")
    return _Fit(model=model, s=s, data=data, prior=prior, lik=lik, collapsed=collapsed, tier_note=tier_note,
                phase_seeds=phase_seeds, sweep=sweep_t)


def _optima(f: _Fit, timings: dict) -> list | None:
    """CMA-ES restarts and the bound sweep (None without restarts)."""
    if f.s.restarts <= 0:
        return None
    t = time.perf_counter()
    optima = run_optima(f.lik, restarts=f.s.restarts, seed=f.phase_seeds[0], sweep=f.sweep, **f.s.cma_options())
    timings["cmaes"] = time.perf_counter() - t
    return optima


def _posterior(f: _Fit, checkpoint_dir, progress: bool, timings: dict) -> dict:
    """The TMCMC phase: posterior rows in sampler coordinates, their log-likelihood, evidence, checkpoint."""
    s, lik = f.s, f.lik
    t = time.perf_counter()
    ckpt = None
    if checkpoint_dir is not None:
        ckpt = Path(checkpoint_dir) / f"{f.data.id}.npz"
        ckpt.parent.mkdir(parents=True, exist_ok=True)
    opts = dict(s.tmcmc_options or {})
    if s.max_evaluations is not None:
        opts["max_evaluations"] = int(s.max_evaluations)
    if needs_gradient(s.move):
        opts.setdefault("gradient_fim", lik.gradient_fim)
    collapsed_info = None
    s_tm = f.phase_seeds[1]
    if f.collapsed is not None:  # sample φ only; the amplitudes are integrated, then drawn given φ
        cf = fit_collapsed(f.collapsed, int(s.samples), seed=s_tm, checkpoint=ckpt, progress=progress, **opts)
        y, log_lik, n_evaluations = cf.samples, cf.log_likelihood, cf.n_evaluations
        # FitResult.tmcmc: the φ run's stages and evidence, with the completed full rows as samples
        tr = dataclasses.replace(cf.tmcmc, samples=y, log_likelihood=log_lik, chains=cf.chains)
        log_z, log_z_se, collapsed_info = cf.log_evidence, cf.log_evidence_se, cf.info
    else:
        tr = _tmcmc(lik, lik.bounds, int(s.samples), seed=s_tm, move=s.move, checkpoint=ckpt,
                    progress=progress, **opts)
        y, log_lik, n_evaluations = tr.samples, tr.log_likelihood, tr.n_evaluations
        log_z, log_z_se = tr.log_evidence, tr.log_evidence_se
    timings["tmcmc"] = time.perf_counter() - t
    return {"tr": tr, "y": y, "log_lik": log_lik, "n_evaluations": n_evaluations, "log_z": log_z,
            "log_z_se": log_z_se, "collapsed_info": collapsed_info, "ckpt": ckpt}


def _result(f: _Fit, post: dict, optima: list | None, config_extra: Mapping[str, Any] | None,
            timings: dict) -> SpecimenResult:
    """The posterior predictive and the result record (Sobol filled in by its phase)."""
    s, lik, data, tr = f.s, f.lik, f.data, post["tr"]
    s_opt, s_tm, s_pred, s_sob = f.phase_seeds
    t = time.perf_counter()
    y = np.asarray(post["y"], float)  # sampler (working) coordinates
    theta = lik.to_natural(y)  # what the user sees: natural units
    m = lik.predict(y)
    pll = pointwise_log_likelihood(lik, y, m)
    pred_model, pred = posterior_predictive(lik, y, s_pred, m)
    timings["predictive"] = time.perf_counter() - t
    seed = s.seed
    stored = FitRecord(
        settings=s.replace(prior=f.prior), seeds={"cmaes": s_opt, "tmcmc": s_tm, "predictive": s_pred, "sobol": s_sob},
        n_evaluations=int(post["n_evaluations"]), n_stages=len(tr.stages),
        tier_used="full" if f.collapsed is None else "collapsed", tier_note=f.tier_note, source_file=data.source_file,
        input=input_summary(data), collapsed=post["collapsed_info"],
        seed_spawn_key=tuple(map(int, seed.spawn_key)) if isinstance(seed, np.random.SeedSequence) else None,
        extra=dict(config_extra or {}))
    return SpecimenResult(
        specimen_id=data.id, names=list(lik.names), samples=theta, log_likelihood=np.asarray(post["log_lik"], float),
        log_evidence=float(post["log_z"]), log_evidence_se=float(post["log_z_se"]),
        bounds=np.asarray(lik.natural_bounds, float), stages=list(tr.stages), data=data,
        pointwise_log_likelihood=pll, predictive=pred, predictive_model=pred_model, optima=optima, sobol=None,
        model=f.model.name, effects=list(f.model.effect_names), config=stored.to_attrs(),
        base_model=_base_name(f.model),
        seed=int(seed.entropy) if isinstance(seed, np.random.SeedSequence) else int(seed),
        fixed=dict(lik.fixed), version=__version__,
        prior={n: lik.prior[n].to_dict() for n in lik.names},
        parameter_info={q.name: (q.unit, q.meaning) for q in getattr(f.model, "parameters", ())},
        chains=tr.chains)


def _sobol_phase(f: _Fit, timings: dict) -> dict | None:
    """Sobol indices over the prior box (None when ``sobol_n`` is 0)."""
    s, lik = f.s, f.lik
    if not s.sobol_n:
        return None
    t = time.perf_counter()
    sbounds = s.bounds
    if f.prior is not None:  # the Sobol input box is the prior's natural box
        sbounds = {n: tuple(map(float, lik.natural_bounds[j])) for j, n in enumerate(lik.model_names)}
    sob = run_sobol(f.model, f.data, n=int(s.sobol_n), seed=f.phase_seeds[3], fix=s.fix, bounds=sbounds)
    timings["sobol"] = time.perf_counter() - t
    return sob


def _finish(f: _Fit, res: SpecimenResult, post: dict, out, timings: dict, t_start: float) -> FitResult:
    """Edge warnings; write the file (atomically) and retire the checkpoint."""
    res.at_bounds = at_bounds(res)
    path = None
    if out is not None:
        t = time.perf_counter()
        res.timings = dict(timings)
        path = write_specimen_result(res, out)
        timings["write"] = time.perf_counter() - t
        retire_checkpoint(post["ckpt"])
    timings["total"] = time.perf_counter() - t_start
    res.timings = dict(timings)
    return FitResult(result=res, path=path, likelihood=f.lik, tmcmc=post["tr"], timings=timings)
