"""Compare a model with measurements, find where it fails, and name the missing effect.

The detective works in four steps (DESIGN.md §2), one module each:

1. **Compare** (:mod:`.fitting`) — fit the current model (CMA-ES, then TMCMC for the evidence)
   with a noise model chosen from the data (iid, proportional or AR(1), by BIC at the optimum)
   and cross-check it against a model-free, difference-based noise estimate (:mod:`.noise_check`).
2. **Where it fails** (:mod:`.noise_check`) — posterior-predictive coverage along strain and per
   test, and strain windows in which a smoothed standardised residual is significantly
   non-zero.  The window threshold is calibrated by simulating the fitted noise process (AR(1)
   included), so the scan over many windows and scales keeps a 5 % family-wise false-alarm rate.
3. **What is missing** (:mod:`.screen`, :mod:`.refits`) — a cheap score screen of every candidate
   effect: the sensitivity of the stress to the candidate's parameters at their null values,
   with the part the base model can absorb (its Jacobian at the fit) projected out, in
   noise-whitened units.  The best few candidates plus a generic, non-physical local-misfit
   control (:class:`LocalMisfit`, a Gaussian bump in strain) are refitted, each at its own best
   noise model (iid vs AR(1)).  Δlog-evidence: Laplace in the new parameters at the CMA-ES
   optimum (the decision statistic, reproducible) next to the TMCMC difference ± SE (reported;
   at the affordable population sizes it scatters by several nats on this model).
4. **Decision** (:mod:`.decision`) — an effect is named only when its evidence gain is large
   (Δlog Z > 5), it beats the runner-up clearly, and its parameter interval excludes the null;
   near-ties inside a known confusable group give verdict ``"group"`` with the experiment that
   would separate them; a misfit only the control explains is ``"unexplained"``; otherwise
   ``"adequate"``.

:func:`extend` refits with effects added one at a time and records the error fall.
Results and their text/JSON renderings live in :mod:`.results`, thresholds in :mod:`.rules`.
"""

from __future__ import annotations

import time as _time
import warnings
from contextlib import contextmanager
from typing import Mapping, Sequence

import numpy as np

from ..errors import HbmError, HbmWarning
from ..fit import edges, format_at_bounds
from ..model.core import Effect
from .decision import decide
from .fitting import Fitter
from .inputs import added_effects, as_data, resolve_candidates, resolve_effect, resolve_model
from .noise_check import check_noise, misfit_windows, model_free_noise, noise_prior_box
from .refits import refit_candidates
from .results import CandidateResult, Diagnosis, Extension, FitSummary
from .rules import CONTROL_MARGIN, DELTA_LOGZ_MIN, RUNNER_UP_MARGIN
from .screen import LocalMisfit, local_refit_screen, score_screen, screen_candidates

__all__ = ["diagnose", "extend", "Diagnosis", "Extension", "CandidateResult", "FitSummary",
           "LocalMisfit", "model_free_noise", "misfit_windows", "score_screen", "local_refit_screen",
           "DELTA_LOGZ_MIN", "RUNNER_UP_MARGIN", "CONTROL_MARGIN"]

NOISE_MODELS = ("iid", "proportional", "ar1")


@contextmanager
def _stopwatch(timings: dict, key: str):
    """Record the wall time of the block in ``timings[key]``."""
    t0 = _time.perf_counter()
    yield
    timings[key] = _time.perf_counter() - t0


def diagnose(data, *, model=None, candidates="all", fix: Mapping[str, float] | None = None,
             seed: int = 0, n_samples: int = 800, top: int = 3, progress: bool = False,
             noise_models: Sequence[str] = NOISE_MODELS,
             sigma_bounds: tuple[float, float] | None = None) -> Diagnosis:
    """Compare a model with a specimen, locate its misfit and name the missing effect.

    Parameters
    ----------
    data : xarray.Dataset or path
        Specimen with ``strain``, ``stress`` and optional ``time``/``test`` (see
        :func:`hbm.data.load_specimen`).
    model : None, str, list or Model
        Current model: ``None``/``"base"`` for the Spyrou model, ``"offset,damage"`` for the
        base model plus effects, or any :class:`hbm.Model`.
    candidates : "all", str or sequence
        Effects to screen: ids, ``"path.py:ClassName"`` strings, or :class:`hbm.Effect`
        instances (user-written effects need no edit of hbm).
    fix : dict, optional
        Parameters held fixed, e.g. ``{"EOPT": 0.1}``.
    seed : int
        Seed of every random step (CMA-ES, TMCMC, window calibration).
    n_samples : int
        TMCMC population size of each evidence run.
    top : int
        Number of physical candidates refitted (best screen scores); the local-misfit control
        is always refitted too.
    progress : bool
        Print progress lines to stderr.
    noise_models : sequence of str
        Noise models considered for the base fit (chosen by BIC at the optimum).
    sigma_bounds : (float, float), optional
        Prior box of the noise sd; default from the model-free estimate (×1/20 … ×20), shared
        by every fit so the evidences are comparable.

    Returns
    -------
    Diagnosis
    """
    t_start, cpu_start = _time.perf_counter(), _time.process_time()
    timings: dict[str, float] = {}
    d = as_data(data)
    base_model = resolve_model(model)
    cands = resolve_candidates(candidates, base_model)
    fix = _checked_fix(fix, base_model.parameter_names)
    mf = model_free_noise(d.stress, d.segment)
    if sigma_bounds is None:
        sigma_bounds = noise_prior_box(mf, d.stress)
    fitter = Fitter(d, fix, seed, n_samples, sigma_bounds, progress)

    with _stopwatch(timings, "base_fit"):     # 1. compare: the base fit at its best noise model
        base = fitter.fit(base_model, list(noise_models), None, seed, global_restarts=2)
    with _stopwatch(timings, "windows"):      # 2. where it fails
        check = check_noise(base, mf, d, seed)
    with _stopwatch(timings, "screen"):       # 3. what is missing: screen ...
        results, ctrl, skipped = screen_candidates(base, cands, check, d, fitter.log)
    with _stopwatch(timings, "refits"):       # ... and refit the best
        refit_candidates(results, ctrl, base, fitter, noise_models, top, seed)
    verdict = decide(results, ctrl, check.windows)  # 4. decision
    edges_found = _base_at_bounds(base, d.name)

    timings["total"] = _time.perf_counter() - t_start
    timings["cpu"] = _time.process_time() - cpu_start
    cov = base.predictive
    return Diagnosis(verdict=verdict.verdict, selected=verdict.selected, group=verdict.group,
                     misfit_windows=[(w["eps_lo"], w["eps_hi"], w["sign"]) for w in check.windows],
                     noise=check.noise,
                     candidates=[c for c in results if c.refit] + [c for c in results if not c.refit] + [ctrl],
                     suggested_experiment=verdict.experiment, message=verdict.message, base=base,
                     coverage={k: v for k, v in cov.items() if k in ("band", "overall", "per_test", "along_strain")},
                     window_detail=[dict(w) for w in check.windows], timings=timings, data=d, skipped=skipped,
                     residual_curve=check.residual_curve(cov, d.segment), at_bounds=edges_found)


def _base_at_bounds(base: FitSummary, name: str) -> list[dict]:
    """Base-model parameters on a box edge (best fit or > 20 % of the posterior), each also a
    one-line :class:`~hbm.errors.HbmWarning`: the verdict is conditional on that box."""
    model_names = set(base.model.parameter_names) if base.model is not None else set(base.names)
    lik_box = np.asarray(base.likelihood.bounds, float) if base.likelihood is not None else None
    if lik_box is None:
        return []
    boxes = {n: {"lo": float(lik_box[i, 0]), "hi": float(lik_box[i, 1]), "form": "uniform"}
             for i, n in enumerate(base.names) if n in model_names}
    found = edges(base.names, boxes, base.theta_max, base.samples)
    for line in format_at_bounds(found):
        warnings.warn(f"{name}: base fit: {line.removeprefix('warning: ')}", HbmWarning, stacklevel=3)
    return found


def _checked_fix(fix: Mapping[str, float] | None, names: Sequence[str]) -> dict[str, float]:
    fix = dict(fix or {})
    unknown = [k for k in fix if k not in names]
    if unknown:
        raise HbmError(f"--fix: unknown parameter(s) {unknown}; the model has {list(names)}")
    return fix


def extend(data, add: Sequence = (), *, auto: bool = False, model=None, candidates="all",
           fix: Mapping[str, float] | None = None, seed: int = 0, n_samples: int = 800,
           top: int = 3, progress: bool = False, max_steps: int = 4,
           noise_models: Sequence[str] = NOISE_MODELS) -> Extension:
    """Refit with effects added one at a time and record the error fall.

    Parameters
    ----------
    data : xarray.Dataset or path
        The specimen.
    add : sequence
        Effects to add in this order (ids, ``"path.py:ClassName"`` or Effect instances).
    auto : bool
        Greedy: after the given effects, repeatedly :func:`diagnose` the current model and add
        the effect it names (verdict ``"effect"``), until nothing passes the decision rule or
        ``max_steps`` effects were added.
    model, candidates, fix, seed, n_samples, top, progress, noise_models
        As in :func:`diagnose`.

    Returns
    -------
    Extension
        ``steps[0]`` is the starting model; each further step adds one effect, with RMSE,
        log-evidence ± SE and predictive coverage.
    """
    t_start = _time.perf_counter()
    d = as_data(data)
    current = resolve_model(model)
    fix = dict(fix or {})
    adds = _effects_to_add(add)
    if not adds and not auto:
        raise HbmError("extend: give effects to add (--add EFFECT[,EFFECT...]) or auto=True (--auto)")
    mf = model_free_noise(d.stress, d.segment)
    fitter = Fitter(d, fix, seed, n_samples, noise_prior_box(mf, d.stress), progress)
    steps = [fitter.fit(current, list(noise_models), None, seed, global_restarts=2)]
    decisions: list = []

    def add_step(e: Effect, k: int, start: Mapping[str, float] | None = None):
        nonlocal current
        mc = current.with_effects(e)
        starts = fitter.warm_starts(steps[-1], mc, noise_models,
                                    [{q.name: q.null for q in e.parameters}] + ([start] if start else []))
        steps.append(fitter.fit(mc, list(noise_models), starts, seed + 1000 * k))
        current = mc

    for k, e in enumerate(adds):               # the given effects, in order
        if e.name in current.effect_names:
            raise HbmError(f"extend: effect {e.name!r} is already in the model {current.effect_names}")
        add_step(e, k + 1)
    k = len(adds)
    while auto and k < max_steps:              # then greedily what diagnose names
        dg = diagnose(d.ds, model=current, candidates=candidates, fix=fix, seed=seed + 17 * (k + 1),
                      n_samples=n_samples, top=top, progress=progress, noise_models=noise_models)
        decisions.append({"model": added_effects(current), "verdict": dg.verdict,
                          "selected": dg.selected, "group": dg.group, "message": dg.message})
        if dg.verdict != "effect":
            break
        chosen = next(c for c in dg.candidates if c.effect == dg.selected[0])
        k += 1
        add_step(chosen.effect_instance, k, start=dict(zip(chosen.fit.names, chosen.fit.theta_max)))
    return Extension(steps=steps, decisions=decisions, data=d,
                     timings={"total": _time.perf_counter() - t_start}, noise=mf)


def _effects_to_add(add) -> list[Effect]:
    """``add`` ("a,b", one Effect, or a sequence of ids/specs/Effects) as Effect instances."""
    if isinstance(add, str):
        add = [a for a in add.split(",") if a.strip()]
    elif isinstance(add, Effect):
        add = [add]
    return [resolve_effect(a.strip() if isinstance(a, str) else a) for a in add]
