"""Compare a model with measurements, find where it fails, and name the missing effect(s).

The detective works in four steps (DESIGN.md §2), one module each:

1. **Compare** (:mod:`.fitting`) — fit the current model (CMA-ES, then TMCMC for the evidence)
   with a noise model chosen by evidence (iid, proportional or AR(1); Laplace in the noise
   parameters at each optimum) and cross-check it against a model-free, difference-based noise
   estimate (:mod:`.noise_check`).  A stress scale no passive muscle shows is reported as a
   data problem (:func:`.inputs.unit_anomaly`).
2. **Where it fails** (:mod:`.noise_check`) — posterior-predictive coverage along strain and per
   test, and strain windows in which a smoothed standardised residual is significantly
   non-zero, scanned twice: under the fitted noise and under the noise the data show (the
   model-free estimate), each calibrated by simulation at half the family-wise 5 %.
3. **What is missing** (:mod:`.screen`, :mod:`.refits`) — a cheap screen of every candidate
   effect (projected score test, local refit) and of the generic, non-physical controls
   (:mod:`.controls`: a bump, a step, a kink in strain, a slow trend in time).  The best few
   candidates and the best controls are refitted, each at its own best noise model; the base
   is then re-optimised from every refit's optimum (new parameters at their nulls) and every
   gain is measured against the best base found.
4. **Decision** (:mod:`.decision`) — an effect is named when it gains > 5 nats, explains the
   misfit about as well as the best control and beats it in evidence; near-ties give verdict
   ``"group"``; any remaining sign of misfit gives ``"unexplained"`` with where it is and its
   shape; ``"adequate"`` only without any.  After an effect is named it is added and steps 2–4
   are repeated (greedy, ``max_effects``), so two hidden effects can both be named.

:func:`extend` refits with effects added one at a time and records the error fall.
Results and their text/JSON renderings live in :mod:`.results`, thresholds in :mod:`.rules`.
"""

from __future__ import annotations

import time as _time
import warnings
from contextlib import contextmanager
from dataclasses import dataclass, replace
from typing import Mapping, Sequence

import numpy as np

try:
    import resource as _resource     # the refit workers' CPU time (Unix, like the forked workers)
except ImportError:                  # pragma: no cover - Windows
    _resource = None

from ..runtime import seeds as _seeds
from ..errors import HbmError, HbmWarning
from ..settings.rules import check_workers, usable_cores
from ..fit.specimen import edges, format_at_bounds
from ..model.core import Effect
from ..likelihood.noise import noise_model_names
from .controls import KinkMisfit, LocalMisfit, StepMisfit, TimeTrend
from .decision import Verdict, decide, gain
from .fitting import FitInterrupted, Fitter, noise_evidence
from .budget import cost_estimate, revised_estimate, stop_record, stop_reserve
from .caveats import CORRELATED_CHOICES, caveat_line, digitised_reason, verdict_caveats, white_noise_view
from .inputs import added_effects, as_data, resolve_candidates, resolve_effect, resolve_model, unit_anomaly
from .noise_check import NoiseCheck, check_noise, misfit_windows, model_free_noise, noise_prior_box
from .power import detection_power
from .refits import refit_candidates, run_in_workers
from .removal import removal_test
from .results import CandidateResult, Diagnosis, Extension, FitSummary
from .rules import DELTA_LOGZ_MIN, MAX_EFFECTS, N_CONTROL_REFITS, RUNNER_UP_MARGIN
from .screen import local_refit_screen, score_screen, screen_candidates

__all__ = ["diagnose", "extend", "place_as_diagnosed", "Diagnosis", "Extension", "CandidateResult", "FitSummary",
           "LocalMisfit", "StepMisfit", "KinkMisfit", "TimeTrend", "model_free_noise", "misfit_windows",
           "score_screen", "local_refit_screen", "DELTA_LOGZ_MIN", "RUNNER_UP_MARGIN"]

NOISE_MODELS = ("iid", "proportional", "ar1")


@contextmanager
def _stopwatch(timings: dict, key: str):
    """Record (accumulate) the wall time of the block in ``timings[key]``."""
    t0 = _time.perf_counter()
    yield
    timings[key] = timings.get(key, 0.0) + _time.perf_counter() - t0


def _seed(seed: int, j: int) -> int:
    """Child ``j`` of the run's ``detective`` stream (:mod:`hbm.runtime.seeds`) as a small int seed (the
    optimisers add offsets and CMA-ES needs seeds below 2**32 / 7919)."""
    return int(_seeds.child(_seeds.stream(seed, "detective"), j).generate_state(1)[0] % 400_000)


def _noise_models(noise: str | None, noise_models: Sequence[str]) -> list[str]:
    """The noise models to consider: ``noise`` alone when forced."""
    if noise is None:
        return list(noise_models)
    if noise not in noise_model_names():
        raise HbmError(f"noise: unknown noise model {noise!r}; known: {', '.join(noise_model_names())}")
    return [noise]


def correlated_noises(noises: list[str], noise: str | None, correlated: str, digitised: str | None) -> list[str]:
    """The noise models offered once it is decided what correlated residuals are: without AR(1)
    when they are model error (``correlated="misfit"``, or ``"auto"`` on a digitised or
    group-mean curve), unless the user forced a noise model."""
    if correlated not in CORRELATED_CHOICES:
        raise HbmError(f"correlated: expected one of {', '.join(CORRELATED_CHOICES)}, got {correlated!r}")
    as_misfit = correlated == "misfit" or (correlated == "auto" and digitised is not None)
    if noise is None and as_misfit and len(noises) > 1:
        return [n for n in noises if n != "ar1"] or noises
    return noises


@dataclass(slots=True)
class _Step:
    """One round of steps 2–4 at the current model."""

    base: FitSummary
    check: NoiseCheck
    results: list
    controls: list
    skipped: dict
    verdict: Verdict


def _round(base: FitSummary, cands: list[Effect], fitter: Fitter, mf: dict, d, noises: list[str], top: int,
           seed: int, timings: dict) -> _Step:
    """Where it fails, what is missing, the decision -- at the current model ``base``."""
    with _stopwatch(timings, "windows"):
        check = check_noise(base, mf, d, seed)
    with _stopwatch(timings, "screen"):
        results, ctrls, skipped = screen_candidates(base, cands, check, d, fitter.log)
    with _stopwatch(timings, "refits"):
        done = refit_candidates(results, ctrls, base, fitter, noises, top, seed)
        # the windows at the best base found, and what each refit leaves
        check = check_noise(base, mf, d, seed)
        for c in done:
            c.windows_after = len(check.remaining_windows(c.fit, d))
            if not c.physical:
                x = dict(zip(c.fit.names, c.fit.theta_max))
                c.region = c.effect_instance.region(x, d)
                c.shape_detail = c.effect_instance.describe(x)
    check.noise["preference"] = _noise_preference(base, ctrls)
    verdict = decide(results, ctrls, check.windows, check.noise, base.noise, d)
    return _Step(base, check, results, ctrls, skipped, verdict)


def _ar1_absorbs_misfit(step: _Step) -> str | None:
    """Why, in words, the AR(1) noise of ``step``'s base is absorbing a misfit (None: it is not):
    the data prefer white noise + a smooth misfit control, or the fitted AR(1) noise disagrees
    with the model-free estimate (a correlation the neighbouring points do not show -- with
    two misfits at once no single control absorbs both, so the evidence test alone is blind)."""
    white = max((c for c in step.controls if c.white_gain is not None), key=lambda c: c.white_gain, default=None)
    if white is not None and white.white_gain > 0:
        return (f"the data prefer white noise + a smooth misfit ({white.effect}) to AR(1) noise "
                f"by {white.white_gain:.1f} nats")
    if not step.check.noise.get("consistent", True):
        return "the fitted AR(1) noise disagrees with the model-free noise estimate"
    return None


def _noise_preference(base: FitSummary, ctrls: list[CandidateResult]) -> str:
    """Which noise description the data prefer, in words (AR(1) vs white noise + a smooth misfit)."""
    ev = base.noise_evidence
    parts = []
    if "ar1" in ev and "iid" in ev:
        d = ev["ar1"] - ev["iid"]
        parts.append(f"AR(1) vs iid noise: Δlog Z = {d:+.1f} ({'AR(1)' if d > 0 else 'iid'} preferred)")
    white = max((c for c in ctrls if c.white_gain is not None), key=lambda c: c.white_gain, default=None)
    if white is not None:
        if white.white_gain > 0:
            parts.append(f"the data prefer white noise + a smooth misfit ({white.effect}) to AR(1) noise "
                         f"by {white.white_gain:.1f} nats")
        else:
            parts.append(f"AR(1) noise preferred to white noise + a smooth misfit ({white.effect}) by "
                         f"{-white.white_gain:.1f} nats")
    return "; ".join(parts)


def _tier(tier: str, likelihood: str | None, who: str) -> str:
    """The tier of ``tier=``, or of the older keyword ``likelihood=`` (deprecated: it warns)."""
    if likelihood is None:
        return tier
    warnings.warn(f"{who}(likelihood=...) is deprecated; use tier=", DeprecationWarning, stacklevel=3)
    return likelihood


def diagnose(data, *, model=None, candidates="all", fix: Mapping[str, float] | None = None,
             seed: int = 0, n_samples: int = 800, top: int = 3, progress: bool = False,
             noise_models: Sequence[str] = NOISE_MODELS, noise: str | None = None,
             sigma_bounds: tuple[float, float] | None = None, max_effects: int = MAX_EFFECTS,
             power: bool = False, removal: bool = True, max_evaluations: int | None = None,
             correlated: str = "auto", max_time: float | None = None, tier: str = "full",
             workers: int | None = None, likelihood: str | None = None) -> Diagnosis:
    """Compare a model with a specimen, locate its misfit and name the missing effect(s).

    Parameters
    ----------
    data : Specimen, xarray.Dataset or path
        The specimen (:func:`hbm.data.load_specimen`; a Dataset is converted once, a path loaded).
    model : None, str, list or Model
        Current model: ``None``/``"base"`` for the Spyrou model, ``"offset,damage"`` for the
        base model plus effects, or any :class:`hbm.Model`.
    candidates : "all", str or sequence
        Effects to screen: ids, ``"path.py:ClassName"`` strings, or :class:`hbm.Effect`
        instances (user-written effects need no edit of hbm).
    fix : dict, optional
        Parameters held fixed, ``{name: value}`` (e.g. EOPT at 0.1 for the Spyrou base).
    seed : int
        Seed of every random step (CMA-ES, TMCMC, window calibration).
    n_samples : int
        TMCMC population size of each evidence run.
    top : int
        Number of physical candidates refitted (best screen scores); the best non-physical
        control is always refitted too.
    progress : bool
        Print progress lines to stderr.
    noise_models : sequence of str
        Noise models considered (chosen by evidence at the optimum).
    noise : str, optional
        Force one noise model (``"iid"``, ``"ar1"``, ...) for every fit.
    sigma_bounds : (float, float), optional
        Prior box of the noise sd; default from the model-free estimate (×1/20 … ×20), shared
        by every fit so the evidences are comparable.
    max_effects : int
        Effects named at most (greedy: after each named effect the model is extended and
        re-screened with the same rule).
    power : bool
        Also estimate the detection limit of every library effect on this protocol and noise
        (:func:`hbm.detective.power.detection_power`; ``Diagnosis.power``).
    removal : bool
        Test whether each base part (matrix, fibers, collagen) is needed (``Diagnosis.removal``).
    max_evaluations : int, optional
        Likelihood-evaluation budget of each TMCMC evidence run (the population shrinks to what
        it affords, then a hard cap); for models far slower than the base model.
    correlated : {"auto", "noise", "misfit"}
        What correlated residuals are: ``"noise"`` offers AR(1) noise, ``"misfit"`` does not
        (model error), ``"auto"`` treats them as model error on curves marked or detected as
        digitised or group means (:func:`.caveats.digitised_reason`) and offers AR(1) otherwise.
    max_time : float, optional
        Wall seconds after which no new fit is started (a fit under way finishes): the verdict
        so far is returned with ``stopped`` saying what was left undecided and why.  ``None``:
        no limit (the command line's default is 300 s).
    tier : {"full", "auto", "collapsed"}
        Likelihood tier of every evidence run (:meth:`.fitting.Fitter.collapsed`; ``likelihood=`` is
        its older, deprecated name); default "full" (every
        fit in full space).  Not yet "auto": a collapsible candidate's converged evidence against
        a non-collapsible competitor's under-mixed full-space one tilts their comparison (library
        case mullins_3: damage 13.0 vs viscoelastic 12.2 gave "group" where "full" names damage;
        results/detective_validation.md).  "auto": where the
        model's stress is linear in at most ``COLLAPSED_MAX_COLUMNS`` amplitude columns and the
        noise keeps their integral Gaussian (iid, AR(1)), the amplitudes are integrated exactly
        and TMCMC samples only the nonlinear and noise parameters (its evidence estimates the
        same full-model evidence under the same prior, with a far smaller scatter); elsewhere
        (damage, series compliance, proportional noise, more columns) the full-space run.
        "collapsed": wherever it applies; "full": every fit in full space.  Each fit's tier is
        in the JSON (``likelihood_tier`` of the base and of every candidate).
    workers : int, optional
        Processes the candidate refits of a round run in (default: the usable cores; 1: all in
        this process).  The results do not depend on it (each refit has its own seed).

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
    noises = _noise_models(noise, noise_models)
    mf = model_free_noise(d.stress, d.segment)
    digitised = digitised_reason(getattr(d.ds, "attrs", {}), mf, d.stress)
    noises = correlated_noises(noises, noise, correlated, digitised)
    if sigma_bounds is None:
        sigma_bounds = noise_prior_box(mf, d.stress)
    workers = usable_cores() if workers is None else check_workers(workers, "workers") or 1
    tier = _tier(tier, likelihood, "diagnose")
    # no more processes than a round has refits (+ the base's rerun): the rest would sit idle
    fitter = Fitter(d, fix, seed, n_samples, sigma_bounds, progress, max_evaluations, tier,
                    min(workers, max(0, int(top)) + N_CONTROL_REFITS + 1))
    if max_time is not None:
        fitter.deadline = _time.time() + float(max_time) - stop_reserve(float(max_time))
    kids = _children_cpu()
    with fitter:             # (its worker processes stop at the end, also on an error)
        timings["estimate"] = cost_estimate(base_model, cands, fitter, noises, top, max_effects)
        fitter.log(timings["estimate"]["text"])

        with _stopwatch(timings, "base_fit"):     # 1. compare: the base fit at its best noise model
            base = fitter.fit(base_model, noises, None, _seed(seed, 0), global_restarts=2)
        fitter.log(revised_estimate(timings["estimate"], timings["base_fit"]))
        fitter.interruptible = True      # from here a fit running past the deadline stops at its next batch
        problem = unit_anomaly(d)
        rounds: list[_Step] = []
        selected: list[str] = []
        current = base
        rejected = None
        if problem is not None:
            check = check_noise(base, mf, d, _seed(seed, 1))
            rounds.append(_Step(base, check, [], [], {}, Verdict("data_problem", [], [], "", problem)))
        else:
            def run_round(cur, rem, k):
                return _round(cur, rem, fitter, mf, d, noises, top, _seed(seed, 1 + k), timings)
            rounds, selected, current = _greedy(run_round, base, list(cands), max_effects, fitter.log, fitter)
            white = rejected = (_ar1_absorbs_misfit(rounds[0])
                     if noise is None and base.noise == "ar1" and any(n != "ar1" for n in noises) else None)
            if white is not None and fitter.out_of_time():
                fitter.skip("the diagnosis under white noise", f"AR(1) noise may absorb a misfit ({white}); the "
                            "verdict so far is under AR(1) noise")
                white = rejected = None
            if white is not None:
                # the AR(1) correlation is a smooth misfit, not noise: an AR(1) fit would absorb the
                # very signal the candidates are screened on, so diagnose again under white noise
                white_noises = [n for n in noises if n != "ar1"]
                fitter.log(f"AR(1) noise absorbs a smooth misfit ({white}): diagnosing again with "
                           f"{', '.join(white_noises)}")
                try:
                    with _stopwatch(timings, "base_fit"):
                        white_base = fitter.fit(base_model, white_noises, None, _seed(seed, 0), global_restarts=2)
                except FitInterrupted:
                    white_base = None
                    fitter.skip("the diagnosis under white noise", f"AR(1) noise may absorb a misfit ({white}); its "
                                "base fit was interrupted at --max-time: the verdict so far is under AR(1) noise")
                    white = rejected = None
            if white is not None:
                noises, base = white_noises, white_base
                rounds, selected, current = _greedy(run_round, base, list(cands), max_effects, fitter.log, fitter)
                pref = rounds[0].check.noise.get("preference")
                rounds[0].check.noise["preference"] = "; ".join(
                    [f"AR(1) noise rejected: {white}; diagnosed with white noise"] + ([pref] if pref else []))
        verdict = _final_verdict(rounds, selected)
        first = rounds[0]
        edges_found = _base_at_bounds(first.base, d.name)
        extra = {}
        if removal and problem is None and fitter.out_of_time():
            fitter.skip("the removal test of the base parts", "which base parts the data need is not known")
        elif removal and problem is None:
            with _stopwatch(timings, "removal"):
                extra["removal"] = removal_test(first.base, fitter, _seed(seed, 90))
        if problem is None:
            # the noise caveat belongs to the final model: a misfit an AR(1) base absorbed and a named
            # effect explains is no caveat of the verdict
            last = rounds[-1]
            view = white_noise_view(last.base, last.controls, d, _seed(seed, 92)) if last.base.noise == "ar1" else None
            extra["caveats"] = verdict_caveats(
                n_points=d.stress.size, base=last.base, check_noise=last.check.noise, z=last.check.z,
                resid=last.check.resid, d=d, white=view, digitised=digitised, correlated=correlated,
                ar1_rejected=rejected if problem is None and noise is None else None,
                removal=extra.get("removal", []), at_bounds=edges_found, verdict=verdict.verdict)
            verdict = replace(verdict, message=verdict.message + caveat_line(extra["caveats"]))
        if fitter.undecided:
            extra["stopped"] = stop_record(fitter, max_time, t_start)
            if any(w.startswith("refit") for w, _ in fitter.undecided):
                # "adequate" claims that no candidate gains: not shown when some were never refitted
                msg = verdict.message.replace("adequate — the model is adequate", "undecided — no sign of "
                                              "misfit so far, but not every candidate was refitted").replace(
                    "no candidate or generic shape gains", "no refitted candidate or shape gains")
                if verdict.verdict == "adequate":
                    msg = "no sign of misfit so far, but not every candidate was refitted" + msg.removeprefix(
                        "the model is adequate")
                verdict = replace(verdict, verdict="undecided" if verdict.verdict == "adequate" else verdict.verdict,
                                  message=msg)
            verdict = replace(verdict, message=verdict.message + " | " + extra["stopped"]["text"])
        if power and fitter.out_of_time():
            fitter.skip("the detection-power estimate (--power)", "no detection limits")
        elif power:
            with _stopwatch(timings, "power"):
                # from the user's starting model, so every library effect gets its limit (also those
                # named here), with the noise of the final model (the starting fit's holds the misfit)
                try:
                    extra["power"] = detection_power(
                        first.base, d, cands, _seed(seed, 91), noise_fit=current,
                        run_tasks=lambda task, calls: run_in_workers(fitter, task, calls)[0])
                except FitInterrupted:
                    fitter.skip("the detection-power estimate (--power)", "interrupted at --max-time: no detection "
                                "limits")

        timings["refine"] = fitter.refine_seconds     # part of "refits": the decisive comparisons' reruns
        timings["workers"] = fitter.workers
        timings["total"] = _time.perf_counter() - t_start
        timings["cpu"] = _time.process_time() - cpu_start
        cov = first.base.predictive
        ck = first.check
        out = Diagnosis(verdict=verdict.verdict, selected=verdict.selected, group=verdict.group,
                        misfit_windows=[(w["eps_lo"], w["eps_hi"], w["sign"]) for w in ck.windows],
                        noise=ck.noise,
                        candidates=[c for c in first.results if c.refit] + [c for c in first.results if not c.refit]
                        + first.controls,
                        suggested_experiment=verdict.experiment, message=verdict.message, base=first.base,
                        coverage={k: v for k, v in cov.items() if k in ("band", "overall", "per_test", "along_strain")},
                        window_detail=[dict(w) for w in ck.windows], timings=timings, data=d, skipped=first.skipped,
                        residual_curve=ck.residual_curve(cov, d.segment), at_bounds=edges_found,
                        unexplained=verdict.unexplained, steps=[_step_record(r) for r in rounds],
                        data_problem=problem, named_candidates=_named(rounds, selected), **extra)
    # the refit workers' CPU, counted once they have exited
    out.timings["cpu"] += _children_cpu() - kids
    return out


def _children_cpu() -> float:
    """CPU seconds of this process's exited child processes (0 where the OS does not say)."""
    if _resource is None:
        return 0.0
    r = _resource.getrusage(_resource.RUSAGE_CHILDREN)
    return float(r.ru_utime + r.ru_stime)


def _named(rounds: list[_Step], selected: list[str]) -> list[CandidateResult]:
    """The candidate result of each named effect, in order (round k named ``selected[k]``)."""
    return [next(c for c in rounds[k].results if c.effect == name) for k, name in enumerate(selected)]


def _step_record(r: _Step) -> dict:
    named = next((c for c in r.results if r.verdict.selected and c.effect == r.verdict.selected[0]), None)
    return {"model": added_effects(r.base.model), "verdict": r.verdict.verdict, "selected": r.verdict.selected,
            "group": r.verdict.group, "message": r.verdict.message,
            "windows": [(w["eps_lo"], w["eps_hi"], w["sign"]) for w in r.check.windows],
            "candidates": {c.effect: round(float(gain(c)), 2) for c in r.results + r.controls if c.refit},
            "placements": dict(named.placements) if named is not None else {},
            "placement_ties": dict(named.placement_ties) if named is not None else {}}


def _greedy(run_round, base: FitSummary, cands: list, max_effects: int, log=lambda msg: None,
            fitter: Fitter | None = None):
    """Steps 2–4 at the base model, then again after each named effect.

    ``run_round(current_fit, remaining_candidates, k)`` returns a :class:`_Step`.  A tentatively
    named effect (verdict ``"partial"``) is added and kept if the next round settles what it
    left (:func:`_settles`), or if no generic shape replaces it -- with it the best evidence
    (alone or with any control) beats the best without it by more than ``DELTA_LOGZ_MIN``
    (:func:`gain_beyond_controls`): two hidden effects whose interplay leaves a small rest (an
    offset that relaxes with the tissue) are both named, and the rest is reported as unexplained.
    Otherwise the rounds after it are dropped and its round's unexplained verdict stands.

    Returns
    -------
    (rounds, selected, current) : the rounds kept, the named effects in order, the final fit.
    """
    rounds: list[_Step] = []
    selected: list[str] = []
    current, remaining = base, list(cands)
    tentative: int | None = None          # index of the round whose effect awaits the next round
    for k in range(max(0, int(max_effects)) + 1):
        st, why = None, "what the named effect leaves is not screened"
        if not (k > 0 and fitter is not None and fitter.out_of_time()):
            try:
                st = run_round(current, remaining, k)
            except FitInterrupted:
                if k == 0:        # (its refits are guarded one by one: only a bug gets here)
                    raise
                why = "interrupted at --max-time: " + why
        if st is None:
            named = selected[-1] if selected else "?"
            fitter.skip(f"greedy round {k} (with {named} added)", why + (
                f"; {named} stays tentative: the verdict of the round that named it stands"
                if tentative is not None else ""))
            if tentative is not None:
                rounds[tentative].verdict = rounds[tentative].verdict.fallback
                return rounds, selected[:-1], rounds[tentative].base
            break
        rounds.append(st)
        if tentative is not None:
            t = rounds[tentative]
            beyond = gain_beyond_controls(t, st)
            if not _settles(st.verdict) and not beyond > DELTA_LOGZ_MIN:
                # the next round does not explain the rest, and a generic shape does as well
                # without the effect as with it: the effect may be absorbing an unknown misfit
                log(f"{selected[-1]} alone leaves misfit the next round does not explain, and it gains "
                    f"{beyond:.1f} nats beside the best generic shape: not named")
                t.verdict = t.verdict.fallback
                return rounds[:tentative + 1], selected[:-1], t.base
            msg = t.verdict.message
            if not _settles(st.verdict):
                # a second, unexplained misfit: the effect is needed all the same
                msg += f" (needed beside the best generic shape too: +{beyond:.1f} nats)"
            t.verdict = replace(t.verdict, verdict="effect", fallback=None, message=msg)
            tentative = None
        if st.verdict.verdict == "partial":
            if len(selected) >= max_effects:
                st.verdict = st.verdict.fallback
                break
            tentative = len(rounds) - 1
        elif st.verdict.verdict != "effect" or len(selected) >= max_effects:
            break
        chosen = next(c for c in st.results if c.effect == st.verdict.selected[0])
        selected.append(chosen.effect)
        log(f"named {chosen.effect}{' (tentatively)' if tentative is not None else ''}: adding it and re-screening")
        current, remaining = chosen.fit, [e for e in remaining if e.name != chosen.effect]
    return rounds, selected, current


def gain_beyond_controls(prev: _Step, nxt: _Step) -> float:
    """Evidence the effect named in round ``prev`` adds when a generic shape may be present too.

    The best log-evidence with the effect (the model of round ``nxt``, alone or with any control
    refitted there) minus the best without it (round ``prev``'s model, alone or with any control
    refitted there), capped like :func:`.decision.gain` by the same difference of maximum
    log-likelihoods (a noisy evidence must not create a gain the best fits do not show).  Large:
    no generic shape replaces the effect -- it is needed even if a second, unexplained misfit is
    hidden with it.  −inf when either round has no evidence.
    """
    def best(st: _Step) -> tuple[float, float]:
        fits = [getattr(st.base, "log_evidence", np.nan), getattr(st.base, "max_log_likelihood", np.nan)]
        out = [tuple(fits)] + [(c.fit.log_evidence, c.fit.max_log_likelihood) for c in st.controls
                               if c.refit and c.fit is not None]
        out = [o for o in out if np.isfinite(o[0]) and np.isfinite(o[1])]
        return max(out, default=(np.nan, np.nan))
    (z0, l0), (z1, l1) = best(prev), best(nxt)
    if not (np.isfinite(z0) and np.isfinite(z1)):
        return -np.inf
    return float(min(z1 - z0, l1 - l0))


def _settles(verdict: Verdict) -> bool:
    """Does the round after a tentatively named effect account for what that effect left?
    Yes when it names a further effect or group that explains it, or finds no misfit left."""
    return verdict.verdict in ("effect", "group", "adequate")


def _final_verdict(rounds: list[_Step], selected: list[str]) -> Verdict:
    """The verdict over the greedy rounds: the named effects in order, and what is left."""
    last = rounds[-1].verdict
    if not selected:
        return last
    msgs = [r.verdict.message for r in rounds if r.verdict.verdict == "effect"]
    msg = "; then ".join(msgs)
    if last.verdict != "effect":
        msg += f". With {' + '.join(selected)} added: {last.verdict} — {last.message}"
    return Verdict("effect", list(selected), list(last.group), last.experiment, msg, last.unexplained)


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
        # (stacklevel: this function <- _diagnose <- diagnose <- the caller's line)
        warnings.warn(f"{name}: base fit: {line.removeprefix('warning: ')}", HbmWarning, stacklevel=4)
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
           noise_models: Sequence[str] = NOISE_MODELS, noise: str | None = None,
           max_evaluations: int | None = None, correlated: str = "auto",
           max_time: float | None = None, tier: str = "full", workers: int | None = None,
           likelihood: str | None = None) -> Extension:
    """Refit with effects added one at a time and record the error fall.

    One noise-model choice for the whole table, so that its Δlog Z are those of
    :func:`diagnose`: the effects named by ``auto`` are the diagnosis's own fits (its base, after
    its guard against AR(1) noise absorbing a misfit, and each round's named refit), and the
    given effects (``add``) are compared at one noise model, the one the most complete model
    chooses, after diagnose's guard: where that is AR(1), the most complete model's round of
    generic shapes is refitted and AR(1) is rejected when white noise + a smooth misfit is
    preferred or the AR(1) fit disagrees with the model-free noise (an unlisted effect's misfit
    soaked up by AR(1) noise would hide the given effect's gain: −0.3 nats under AR(1) against
    +11.4 under white noise for a real offset beside unlisted relaxation).  ``notes`` says which.

    Parameters
    ----------
    data : Specimen, xarray.Dataset or path
        The specimen.
    add : sequence
        Effects to add in this order (ids, ``"path.py:ClassName"`` or Effect instances).
    auto : bool
        Greedy: after the given effects, :func:`diagnose` the current model (which adds what it
        names and re-screens, with the same rule at each step) and add its ``selected`` effects
        in order, at most ``max_steps`` effects in all.
    model, candidates, fix, seed, n_samples, top, progress, noise_models, noise, max_evaluations, correlated, max_time, tier, workers
        As in :func:`diagnose` (``likelihood=``: the tier's older, deprecated name).

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
    noise_models = _noise_models(noise, noise_models)
    if not adds and not auto:
        raise HbmError("extend: give effects to add (--add EFFECT[,EFFECT...]) or auto=True (--auto)")
    mf = model_free_noise(d.stress, d.segment)
    noise_models = correlated_noises(noise_models, noise, correlated,
                                     digitised_reason(getattr(d.ds, "attrs", {}), mf, d.stress))
    tier = _tier(tier, likelihood, "extend")
    fitter = Fitter(d, fix, seed, n_samples, noise_prior_box(mf, d.stress), progress, max_evaluations, tier)
    steps: list[FitSummary] = []
    decisions: list = []
    notes: list[str] = []
    if adds:
        steps.append(fitter.fit(current, list(noise_models), None, _seed(seed, 0), global_restarts=2))
        for k, e in enumerate(adds):               # the given effects, in order
            if e.name in current.effect_names:
                raise HbmError(f"extend: effect {e.name!r} is already in the model {current.effect_names}")
            mc = current.with_effects(e)
            starts = fitter.warm_starts(steps[-1], mc, noise_models, [{q.name: q.null for q in e.parameters}])
            steps.append(fitter.fit(mc, list(noise_models), starts, _seed(seed, 1 + k)))
            current = mc
        common = steps[-1].noise
        noise_note = f"every given step compared at {common} noise (the most complete model's choice)"
        if common == "ar1" and noise is None and any(n != "ar1" for n in noise_models):
            # diagnose's guard, on the most complete model: its round with no candidate refits the
            # best generic shapes, and AR(1) is rejected where white noise + a smooth misfit is
            # preferred or the AR(1) fit disagrees with the model-free noise -- the noise the
            # diagnosis of that model would use, so both commands report one Δlog Z
            why = _ar1_absorbs_misfit(_round(steps[-1], [], fitter, mf, d, list(noise_models), 0,
                                             _seed(seed, 60), {}))
            if why is not None:
                white = {k: v for k, v in steps[-1].noise_fits.items() if k != "ar1"}
                common = max(white, key=lambda k: noise_evidence(white[k], steps[-1].model.parameter_names))
                noise_note = (f"AR(1) noise rejected ({why}): every given step compared at {common} noise, as "
                              "diagnose would")
        for k, fs in enumerate(steps):
            fitter.use_noise(fs, common, _seed(seed, 1 + k))
        fitter.log("extend: " + noise_note)
        notes.append(noise_note)
    stopped = None
    if auto and len(adds) < max_steps:         # then what diagnose names, greedily, in its order
        dg = diagnose(d.ds, model=current, candidates=candidates, fix=fix, seed=seed + 17,
                      n_samples=n_samples, top=top, progress=progress, noise_models=noise_models,
                      noise=noise, max_effects=max_steps - len(adds), removal=False,
                      max_evaluations=max_evaluations, correlated=correlated, max_time=max_time,
                      tier=tier, workers=workers)
        decisions.extend({"model": st["model"], "verdict": st["verdict"], "selected": st["selected"],
                          "group": st["group"], "message": st["message"]} for st in dg.steps)
        # the diagnosis's own fits: the same model as the last given step, fitted (and its noise
        # chosen, with the guard) by the diagnosis, then each named effect's refit
        gains = [None] * len(steps)
        steps = steps[:-1] + [dg.base] + list(dg.named_fits)
        gains += [{"delta_log_evidence": c.delta_log_evidence, "delta_log_evidence_se": c.delta_log_evidence_se,
                   "evidence_method": c.evidence_method} for c in dg.named_candidates]
        stopped = dg.stopped
    else:
        gains = []
    return Extension(steps=steps, decisions=decisions, data=d, gains=gains,
                     timings={"total": _time.perf_counter() - t_start}, noise=mf, stopped=stopped, notes=notes)


def place_as_diagnosed(model, name: str, moves: Mapping[str, str]):
    """Apply a named effect's placements (a diagnosis step's ``"placements"``) before adding it.

    Returns the model with every effect it already has moved as the diagnosis moved it (a
    load-cell offset that became a pre-stress once a viscoelastic effect came in), and the id
    of the placement to add for ``name`` itself.
    """
    for old, new in moves.items():
        if old != name and old in model.effect_names:
            model = model.replacing(old, resolve_effect(new))
    return model, moves.get(name, name)


def _effects_to_add(add) -> list[Effect]:
    """``add`` ("a,b", one Effect, or a sequence of ids/specs/Effects) as Effect instances."""
    if isinstance(add, str):
        add = [a for a in add.split(",") if a.strip()]
    elif isinstance(add, Effect):
        add = [add]
    return [resolve_effect(a.strip() if isinstance(a, str) else a) for a in add]
