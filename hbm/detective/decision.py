"""The verdict (step 4 of the detective, DESIGN.md §2).

One evidence number per refit -- its gain against the best base model found
(:func:`.refits.evidence_gains`) -- and no second gate on the same evidence:

* a physical effect is named when it gains more than ``DELTA_LOGZ_MIN`` nats, explains the
  misfit about as well as the best non-physical control (it leaves no more misfit windows and
  is within ``REMOVE_TOL`` nats of the control's likelihood) and beats that control in
  evidence (or, fitting at least as well, trails it only within twice the SE of the
  difference); near-ties with another physical candidate give verdict ``"group"`` with the
  experiment that would separate them;
* a physical effect that beats every control in evidence but leaves misfit a control would
  remove is named tentatively (``"partial"``): a second effect may be hidden with it, so diagnose
  adds it and re-screens, and keeps it if that round explains the rest (names an effect or a
  group, or finds nothing left) or if no generic shape replaces it (with it, alone or beside any
  control, the evidence beats the best without it by ``DELTA_LOGZ_MIN``); otherwise the
  unexplained verdict of this round stands;
* otherwise any sign of misfit -- a significant window under the fitted or the model-free
  noise, a fitted noise that disagrees with the model-free estimate (estimated under the fitted
  noise model's variance shape), white noise + a smooth misfit preferred to AR(1) noise, or a
  control that gains (> ``DELTA_LOGZ_MIN`` beside a window, > ``CONTROL_ALONE_MIN`` alone) --
  gives ``"unexplained"`` with
  where the misfit is and the best-fitting shape;
* ``"adequate"`` only when there is no such sign.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from typing import Sequence

import numpy as np

from ..effects import CONFUSABLE_GROUPS
from .protocols import describe_protocol, experiments_for, protocol_features
from .refits import primary_parameters
from .results import CandidateResult, gain
from .rules import CONTROL_ALONE_MIN, DELTA_LOGZ_MIN, REMOVE_TOL, RUNNER_UP_MARGIN

__all__ = ["Verdict", "decide", "gain"]

@dataclass(frozen=True, slots=True)
class Verdict:
    """The decision: ``verdict`` with the named effect or group, an experiment, a message, and
    for an unexplained misfit where it is (``{"axis", "range", "shape", "delta_log_evidence"}``)."""

    verdict: str
    selected: list
    group: list
    experiment: str
    message: str
    unexplained: dict | None = None
    #: for verdict ``"partial"``: the unexplained verdict that stands if the next greedy round
    #: does not account for what the named effect leaves
    fallback: "Verdict | None" = None


def misfit_signs(check_noise: dict, windows: list[dict], best_ctrl: CandidateResult | None,
                 base_noise: str, controls: Sequence[CandidateResult] = (), calibration=None,
                 physical: Sequence[CandidateResult] = ()) -> list[str]:
    """Every sign of a systematic misfit the diagnosis has, in words (empty: none).

    With a :class:`.calibration.Calibration` each statistic is a sign when it is beyond its own
    null at the family-wise level (:func:`calibrated_signs`); else the fixed rules."""
    if calibration is not None:
        return calibrated_signs(calibration, windows, base_noise, controls, physical)
    out = []
    if windows:
        out.append(f"{len(windows)} significant misfit window(s)")
    if not check_noise.get("consistent", True):
        out.append("the fitted noise disagrees with the model-free estimate")
    out += _white_sign(base_noise, controls)
    if best_ctrl is not None and gain(best_ctrl) > (DELTA_LOGZ_MIN if windows else CONTROL_ALONE_MIN):
        out.append(f"a generic shape ({best_ctrl.effect}) gains {gain(best_ctrl):.1f} nats")
    return out


def _white_sign(base_noise: str, controls: Sequence[CandidateResult]) -> list[str]:
    """An AR(1) base whose correlation white noise + a smooth misfit explains better."""
    white = max((c for c in controls if c.white_gain is not None), key=lambda c: c.white_gain, default=None)
    if base_noise == "ar1" and white is not None and white.white_gain > 0:
        return [f"the data prefer white noise + a smooth misfit ({white.effect}) to AR(1) noise "
                f"by {white.white_gain:.1f} nats"]
    return []


def calibrated_signs(cal, windows: list[dict], base_noise: str, controls: Sequence[CandidateResult],
                     physical: Sequence[CandidateResult] = ()) -> list[str]:
    """The signs of misfit of a calibrated round: each statistic beyond its null, with its strength."""
    out = []
    if windows and "windows" in cal.stats:
        out.append(f"{len(windows)} significant misfit window(s) (largest window score "
                   f"{cal.stats['windows']['observed']:.2f}× its pure-noise threshold; {cal.strength('windows')})")
    if cal.significant("noise"):
        out.append(f"the fitted noise disagrees with the model-free estimate ({cal.strength('noise')})")
    out += _white_sign(base_noise, controls)
    for kind, words in (("control", "a generic shape"), ("candidate", "the physical candidate")):
        hits = sorted((k for k, v in cal.stats.items() if v["kind"] == kind and cal.significant(k)),
                      key=lambda k: -cal.stats[k]["observed"])
        for k in hits[:2]:
            out.append(f"{words} {k} gains {cal.stats[k]['observed']:.1f} nats at its optimum ({cal.strength(k)})")
    return out


def stat_name(c: CandidateResult) -> str:
    """The name under which the calibration holds ``c``'s statistic: that of the effect the refit kept
    (a placement, e.g. an offset kept as a ``prestress``, is calibrated under its own name), else
    ``c.effect``."""
    inst = getattr(c, "effect_instance", None)
    return inst.name if inst is not None else c.effect


def named_strongly(c: CandidateResult | None, cal=None) -> bool:
    """Is physical candidate ``c``'s gain enough to name it?  Calibrated: its likelihood gain is
    beyond its null at the family-wise level and its evidence gain is positive; fixed rule: its
    gain exceeds ``DELTA_LOGZ_MIN``."""
    if c is None:
        return False
    if cal is not None:
        return bool(cal.significant(stat_name(c)) and gain(c) > 0)
    return bool(gain(c) > DELTA_LOGZ_MIN)


def adequate_message(noise: dict, windows: list[dict], best_ctrl: CandidateResult | None, cal=None) -> str:
    """The adequate verdict, naming only the checks that were made (and how they came out)."""
    if cal is not None:
        top = sorted(cal.stats, key=lambda k: cal.stats[k]["p_family"])[:2]
        parts = [f"no statistic of the verdict beyond its null at family-wise {cal.alpha:.0%} ({cal.replicates} "
                 f"replicates of {cal.null}; the strongest: "
                 + ", ".join(f"{k} {cal.stats[k]['observed']:.3g} ({cal.strength(k)})" for k in top) + ")",
                 noise.get("comparison") or ""]
        return "the model is adequate: " + ", ".join(p for p in parts if p)
    parts = ["no significant misfit window (family-wise 5 %)" if not windows else ""]
    parts.append(noise.get("comparison") or "")
    g = gain(best_ctrl)
    if best_ctrl is not None and g > DELTA_LOGZ_MIN:
        parts.append(f"no physical candidate gains more than {DELTA_LOGZ_MIN:.0f} nats; a generic shape "
                     f"({best_ctrl.effect}) gains {g:.1f} nats but shows no significant window (a shape alone "
                     f"needs {CONTROL_ALONE_MIN:.0f}: its evidence is not corrected for its free position)")
    else:
        parts.append(f"no candidate or generic shape gains more than {DELTA_LOGZ_MIN:.0f} nats of evidence")
    return "the model is adequate: " + ", ".join(p for p in parts if p)


def decide(results: list[CandidateResult], controls: list[CandidateResult], windows: list[dict],
           noise: dict, base_noise: str, data, calibration=None) -> Verdict:
    """The decision rule (module docstring); ``calibration`` (:class:`.calibration.Calibration`)
    replaces the fixed thresholds by each statistic's null on this file."""
    phys = sorted([c for c in results if c.refit], key=lambda c: -gain(c))
    ctrls = sorted([c for c in controls if c.refit], key=lambda c: -gain(c))
    best, ctrl = (phys[0] if phys else None), (ctrls[0] if ctrls else None)
    g_best = gain(best)
    signs = misfit_signs(noise, windows, ctrl, base_noise, ctrls, calibration, phys)
    if named_strongly(best, calibration):
        beats = _beats(best, ctrl)
        if beats and not _explains_like(best, ctrl):
            # it beats every generic shape in evidence but leaves misfit a shape would remove: a
            # second effect may be hidden with it (offset + viscoelasticity) -- tentative; the
            # next greedy round decides (diagnose), else the unexplained verdict stands
            return replace(_effect(best, calibration), verdict="partial",
                           fallback=_unexplained(ctrl, windows, data, best, signs, calibration))
        if beats:
            tied = [c for c in phys[1:] if named_strongly(c, calibration) and
                    g_best - gain(c) < max(RUNNER_UP_MARGIN, 2 * math.hypot(best.delta_log_evidence_se,
                                                                             c.delta_log_evidence_se))]
            if tied:
                return _group(best, tied, data)
            return _effect(best, calibration)
        return _unexplained(ctrl, windows, data, best, signs, calibration)
    if signs:
        return _unexplained(ctrl, windows, data, best, signs, calibration)
    return Verdict("adequate", [], [], "", adequate_message(noise, windows, ctrl, calibration))


def _effect(best: CandidateResult, cal=None) -> Verdict:
    iv = "; ".join(f"{k} ∈ [{v[0]:.3g}, {v[1]:.3g}] (null {v[2]:.3g})" for k, v in best.intervals.items()
                   if k in primary_parameters(best.effect_instance))
    k = stat_name(best)
    strength = "" if cal is None or k not in cal.stats else (
        f"likelihood gain {cal.stats[k]['observed']:.1f} nats at the screen's optimum, {cal.strength(k)}; ")
    return Verdict("effect", [best.effect], [], "",
                   f"missing effect: {best.effect}{placement_words(best)} (Δlog Z = {best.delta_log_evidence:.1f} ± "
                   f"{best.delta_log_evidence_se:.1f}, {strength}RMSE {best.rmse_before:.3g} → "
                   f"{best.rmse_after:.3g} MPa; {iv})")


def placement_words(c: CandidateResult) -> str:
    """Where the kept refit placed the candidate or an effect of the model, in words ("" if as is)."""
    effects = c.fit.model.effects if c.fit is not None and c.fit.model is not None else ()
    from_effects = {e.name: e for e in effects}
    parts = []
    for old, new in c.placements.items():
        what = from_effects.get(new)
        desc = f": {what.description}" if what is not None and what.description else ""
        parts.append(f"{'' if old == c.effect else 'with the ' + old + ' '}placed as {new}{desc}")
    for what, (dz, dl) in c.placement_ties.items():
        parts.append(f"placement not told apart by the data (with the {what}: Δlog Z {dz:+.1f}, "
                     f"Δmax log L {dl:+.1f})")
    return f", {'; '.join(parts)}" if parts else ""


def _beats(c: CandidateResult, ctrl: CandidateResult | None) -> bool:
    """Does physical candidate ``c`` beat the best control in evidence?  Yes when it gains more;
    also when it fits at least as well (maximum likelihood) and trails only within twice the SE
    of the difference -- a generic shape must not win on the noise of two evidence estimates."""
    if ctrl is None or not ctrl.refit or gain(c) >= gain(ctrl):
        return True
    tie = gain(ctrl) - gain(c) <= 2 * math.hypot(c.delta_log_evidence_se, ctrl.delta_log_evidence_se)
    return bool(tie and c.delta_max_log_likelihood >= ctrl.delta_max_log_likelihood)


def _explains_like(c: CandidateResult, ctrl: CandidateResult | None) -> bool:
    """Does physical candidate ``c`` remove the misfit about as well as the best control?"""
    if ctrl is None or not ctrl.refit:
        return True
    fewer = (c.windows_after or 0) <= (ctrl.windows_after or 0) or not c.windows_after
    close = c.delta_max_log_likelihood >= ctrl.delta_max_log_likelihood - REMOVE_TOL
    return bool(fewer and close)


def _gain_words(c: CandidateResult) -> str:
    """The gain the decision used, in words matching the table's Δlog Z column: when the
    likelihood gain caps the evidence estimate, both numbers are named."""
    if gain(c) < c.delta_log_evidence:
        return (f"gain {gain(c):.1f} nats (its Δlog Z {c.delta_log_evidence:.1f} capped by its "
                "maximum-likelihood gain)")
    return f"Δlog Z = {gain(c):.1f}"


def _significant_shape(cal, ctrl: CandidateResult | None) -> dict | None:
    """The calibrated verdict's shape: the most significant control, located at its grid optimum,
    when it is not the refitted best control (None: the refit says it, or nothing is significant)."""
    if cal is None:
        return None
    hits = [k for k, v in cal.stats.items() if v["kind"] == "control" and cal.significant(k) and "region" in v]
    if not hits:
        return None
    k = min(hits, key=lambda k: (cal.stats[k]["p_family"], -cal.stats[k]["observed"]))
    if ctrl is not None and ctrl.refit and ctrl.effect == k and ctrl.region is not None and gain(ctrl) > 0:
        return None
    v = cal.stats[k]
    return {"axis": v["region"][0], "range": [v["region"][1], v["region"][2]],
            "shape": v["shape"] + (f", {v['detail']}" if v["detail"] else ""), "control": k,
            "delta_log_evidence": None, "likelihood_gain": v["observed"],
            "words": f"likelihood gain {v['observed']:.1f} nats, {cal.strength(k)}"}


def _unexplained(ctrl: CandidateResult | None, windows: list[dict], data, best: CandidateResult | None,
                 signs: list[str], cal=None) -> Verdict:
    """Unexplained misfit: where (the best control's region -- or, calibrated, the most significant
    shape's -- else the strongest window) and its shape."""
    where = _significant_shape(cal, ctrl)
    if where is not None:
        pass
    elif ctrl is not None and ctrl.refit and ctrl.region is not None and gain(ctrl) > 0:
        axis, lo, hi = ctrl.region
        shape = ctrl.effect_instance.description.split(": ")[-1]
        where = {"axis": axis, "range": [lo, hi], "shape": shape + (f", {ctrl.shape_detail}" if ctrl.shape_detail else ""),
                 "control": ctrl.effect, "delta_log_evidence": float(gain(ctrl))}
    elif windows:
        w = windows[0]
        where = {"axis": "strain", "range": [w["eps_lo"], w["eps_hi"]], "shape": "smoothed residual window",
                 "control": None, "delta_log_evidence": None}
    if where is None:
        lo, hi = float(np.min(data.strain)), float(np.max(data.strain))
        where = {"axis": "strain", "range": [lo, hi], "shape": "over the whole range", "control": None,
                 "delta_log_evidence": None}
    sym = "ε" if where["axis"] == "strain" else "t"
    unit = "" if where["axis"] == "strain" else " s"
    msg = (f"unexplained misfit in {sym} ∈ [{where['range'][0]:.3g}, {where['range'][1]:.3g}]{unit}"
           f" (best-fitting shape: {where['shape']}"
           + (f", Δlog Z = {where['delta_log_evidence']:.1f}" if where["delta_log_evidence"] is not None else "")
           + (f", {where.pop('words')}" if "words" in where else "") + ")")
    if best is not None and best.refit:
        msg += f"; best physical candidate {best.effect} {_gain_words(best)} does not explain it as well"
    if signs:
        msg += "; evidence of misfit: " + ", ".join(signs)
    return Verdict("unexplained", [], [], "a protocol probing that range (e.g. load-unload cycles or a relaxation "
                   "hold ending inside it) and a user-written candidate effect for it", msg, where)


def _group(best: CandidateResult, tied: list[CandidateResult], data) -> Verdict:
    members = [best.effect] + [c.effect for c in tied]
    # name the known confusable group of the best candidate too
    known = [tuple(g) for g in CONFUSABLE_GROUPS if best.effect in g]
    feats = protocol_features(data)
    return Verdict("group", [], members, experiments_for(members, feats) + f"; this file: {describe_protocol(feats)}",
                   f"{', '.join(members)} explain the misfit about equally (Δlog Z "
                   + ", ".join(f"{gain(c):.1f}" for c in [best] + tied) + ")"
                   + (f"; known confusable group: {', '.join(known[0])}" if known else ""))


def shape_preferred(controls: list[CandidateResult], windows: list[dict], data, reason: str, cal=None) -> Verdict:
    """The verdict when AR(1) noise was rejected because the data prefer white noise + a misfit
    shape, and nothing else is significant: what was found, with its calibrated strength --
    never "adequate" beside that finding."""
    ctrls = sorted([c for c in controls if c.refit], key=lambda c: -gain(c))
    ctrl = ctrls[0] if ctrls else None
    signs = [f"AR(1) noise rejected: {reason}"]
    if ctrl is not None and cal is not None and stat_name(ctrl) in cal.stats:
        k = stat_name(ctrl)
        signs.append(f"under white noise {ctrl.effect} gains {cal.stats[k]['observed']:.1f} nats at its "
                     f"optimum ({cal.strength(k)}; not significant alone at family-wise {cal.alpha:.0%})")
    return _unexplained(ctrl, windows, data, None, signs, cal)
