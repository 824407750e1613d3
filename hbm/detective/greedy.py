"""The greedy rounds of a diagnosis: steps 2–4 at the current model, repeated after each named
effect (:func:`_greedy`), and the verdict over the rounds (:func:`_final_verdict`)."""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from .calibration import Calibration
from .decision import Verdict, gain
from .fitting import FitInterrupted, Fitter
from .inputs import added_effects
from .noise_check import NoiseCheck
from .results import CandidateResult, FitSummary
from .rules import DELTA_LOGZ_MIN

__all__ = ["gain_beyond_controls"]


@dataclass(slots=True)
class _Step:
    """One round of steps 2–4 at the current model."""

    base: FitSummary
    check: NoiseCheck
    results: list
    controls: list
    skipped: dict
    verdict: Verdict
    calibration: Calibration | None = None


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
