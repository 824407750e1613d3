"""The verdict (step 4 of the detective, DESIGN.md §2).

An effect is named only when its evidence gain is large (Δlog Z > ``DELTA_LOGZ_MIN``), it beats
the runner-up clearly and its parameter leaves the null; near-ties give verdict ``"group"``
with the experiment that would separate them; a misfit only the control explains is
``"unexplained"``; otherwise ``"adequate"``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Sequence

import numpy as np

from ..effects import CONFUSABLE_GROUPS, SEPARATING_EXPERIMENT
from .refits import primary_parameters
from .results import CandidateResult
from .rules import CONTROL_MARGIN, DELTA_LOGZ_MIN, RUNNER_UP_MARGIN

__all__ = ["Verdict", "decide"]

#: suggested when no known group covers the tied candidates
_GENERIC_EXPERIMENT = ("a protocol that exercises the effects differently: several strain rates and a relaxation "
                       "hold (viscoelasticity), load-unload-reload cycles (damage), a pinned reference length (slack)")


@dataclass(frozen=True, slots=True)
class Verdict:
    """The decision: ``verdict`` with the named effect or group, an experiment, a message."""

    verdict: str
    selected: list
    group: list
    experiment: str
    message: str


def _gain(c: CandidateResult) -> float:
    """Evidence gain, capped by the likelihood gain (a noisy evidence estimate must not
    create a gain that the best fit does not show); −inf when not refitted."""
    if not c.refit or not np.isfinite(c.delta_log_evidence):
        return -np.inf
    return min(c.delta_log_evidence, c.delta_max_log_likelihood)


def decide(results: list[CandidateResult], ctrl: CandidateResult, windows: list[dict]) -> Verdict:
    """The decision rule of DESIGN.md §2 (see the module docstring)."""
    # a candidate whose parameter interval does not exclude its null cannot be named
    phys = sorted([c for c in results if c.refit and c.excludes_null is not False], key=lambda c: -_gain(c))
    vague = [c for c in results if c.refit and c.excludes_null is False and _gain(c) > DELTA_LOGZ_MIN]
    g_ctrl = _gain(ctrl)
    best = phys[0] if phys else None
    g_best = _gain(best) if best else -np.inf
    if max(g_best, g_ctrl) <= DELTA_LOGZ_MIN:
        return _adequate(vague, windows)
    if best is None or g_ctrl - g_best > CONTROL_MARGIN or g_best <= DELTA_LOGZ_MIN:
        return _unexplained(ctrl, windows)
    # near-ties with the best physical candidate
    tied = [c for c in phys[1:] if _gain(c) > DELTA_LOGZ_MIN and
            g_best - _gain(c) < max(RUNNER_UP_MARGIN, 2 * math.hypot(best.delta_log_evidence_se,
                                                                      c.delta_log_evidence_se))]
    if tied:
        return _group(best, tied)
    iv = "; ".join(f"{k} ∈ [{v[0]:.3g}, {v[1]:.3g}] (null {v[2]:.3g})" for k, v in best.intervals.items()
                   if k in primary_parameters(best.effect_instance))
    return Verdict("effect", [best.effect], [], "",
                   f"missing effect: {best.effect} (Δlog Z = {best.delta_log_evidence:.1f} ± "
                   f"{best.delta_log_evidence_se:.1f}, RMSE {best.rmse_before:.3g} → {best.rmse_after:.3g} MPa; "
                   f"{iv})")


def _adequate(vague: list[CandidateResult], windows: list[dict]) -> Verdict:
    msg = "the model is adequate: no candidate gains more than {:.0f} nats of evidence".format(DELTA_LOGZ_MIN)
    if vague:
        msg += (" with its parameter away from the null ("
                + ", ".join(c.effect for c in vague) + " improve the fit but their interval includes the null)")
    if windows:
        win = "; ".join(f"[{w['eps_lo']:.3f}, {w['eps_hi']:.3f}]" for w in windows[:3])
        msg += f" (weak residual structure in eps ∈ {win} that no effect explains decisively)"
    return Verdict("adequate", [], [], "", msg)


def _unexplained(ctrl: CandidateResult, windows: list[dict]) -> Verdict:
    # a window description for the unexplained case: the control's bump ± 2 widths
    a, b = _control_window(ctrl, windows)
    return Verdict("unexplained", [], [], "a protocol probing the window (e.g. load-unload cycles or a relaxation "
                   "hold ending inside it) and a user-written candidate effect for that strain range",
                   f"unexplained misfit in ε ∈ [{a:.3f}, {b:.3f}] (no physical candidate explains it; "
                   f"generic control Δlog Z = {ctrl.delta_log_evidence:.1f})")


def _group(best: CandidateResult, tied: list[CandidateResult]) -> Verdict:
    members = [best.effect] + [c.effect for c in tied]
    # name the known confusable group of the best candidate too
    known = [tuple(g) for g in CONFUSABLE_GROUPS if best.effect in g]
    return Verdict("group", [], members, _experiment_for(members),
                   f"{', '.join(members)} explain the misfit about equally (Δlog Z "
                   + ", ".join(f"{_gain(c):.1f}" for c in [best] + tied) + ")"
                   + (f"; known confusable group: {', '.join(known[0])}" if known else ""))


def _experiment_for(group: Sequence[str]) -> str:
    """The experiment of the known group containing ``group`` (else of the one overlapping
    it most; else a generic protocol)."""
    gs = set(group)
    best, best_overlap = "", 0
    for members, text in SEPARATING_EXPERIMENT.items():
        overlap = len(members & gs)
        if members >= gs and overlap:
            return str(text)
        if overlap > best_overlap:
            best, best_overlap = str(text), overlap
    return best or _GENERIC_EXPERIMENT


def _control_window(ctrl: CandidateResult, windows: list[dict]) -> tuple[float, float]:
    """Where the control's bump sits (centre ± 2 widths, inside the data), else the strongest window."""
    if ctrl.fit is not None:
        names = ctrl.fit.names
        x = ctrl.fit.theta_max
        if "BUMP_C" in names and "BUMP_W" in names:
            c, w = x[names.index("BUMP_C")], x[names.index("BUMP_W")]
            lo, hi = c - 2 * w, c + 2 * w
            centre = ctrl.effect_instance.parameters[1]
            return float(max(lo, centre.lower)), float(min(hi, centre.upper))
    if windows:
        return windows[0]["eps_lo"], windows[0]["eps_hi"]
    return float("nan"), float("nan")
