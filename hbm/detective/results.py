"""What the detective returns: fitted models, screened candidates, the diagnosis and the
extension, with their text and JSON renderings.

Every field a result carries is declared here (``slots=True``: nothing can be attached at
run time).  Figures are drawn by :mod:`hbm.plots.diagnose`, imported only when asked for.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from .. import plots  # plots.diagnose (matplotlib) loads when a figure is drawn
from ..fit.specimen import format_at_bounds
from ..model.core import Effect, Model
from .rules import BAND, DELTA_LOGZ_MIN, TMCMC_SE_FACTOR

__all__ = ["FitSummary", "CandidateResult", "gain", "Diagnosis", "Extension"]

NAN = float("nan")


@dataclass(slots=True)
class FitSummary:
    """One fitted model (at its chosen noise model)."""

    effects: list[str]
    noise: str
    names: list[str]
    theta_max: np.ndarray                 # free parameters at the CMA-ES optimum
    max_log_likelihood: float
    bic: float
    rmse: float
    log_evidence: float = NAN
    log_evidence_se: float = NAN
    #: log Z ± SE of the rerun with the refined settings (decisive
    #: comparisons only, :func:`hbm.detective.refits.refine_decisive`); NaN when not rerun, and
    #: reset whenever the fit is sampled again (it belongs to the chosen noise model)
    refined_log_evidence: float = NAN
    refined_log_evidence_se: float = NAN
    samples: np.ndarray | None = None     # posterior samples (n, d) of the free parameters
    coverage: float = NAN
    noise_bic: dict = field(default_factory=dict)
    #: noise model -> Laplace log-evidence score that chose it (:func:`~.fitting.noise_evidence`)
    noise_evidence: dict = field(default_factory=dict)
    wall_time: float = 0.0
    likelihood: Any = None
    model: Model | None = None
    #: noise model -> {"bic", "max_log_likelihood", "x", "lik"}: the optimum found at every
    #: noise model tried (warm starts for later fits of extended models)
    noise_fits: dict = field(default_factory=dict, repr=False)
    #: posterior-predictive band and its coverage (overall, per test, along strain), from
    #: :func:`hbm.detective.fitting.coverage`; empty when the fit was not sampled
    predictive: dict = field(default_factory=dict, repr=False)
    #: likelihood tier of the evidence run: "collapsed" (amplitudes integrated exactly, TMCMC over
    #: the nonlinear and noise parameters, :meth:`hbm.detective.fitting.Fitter.collapsed`) or "full"
    tier: str = ""
    #: one line: which tier and why
    tier_note: str = ""
    #: the collapsed run's route, evidence source and quadrature error (empty for the full tier)
    tier_info: dict = field(default_factory=dict, repr=False)
    #: likelihood evaluations of the evidence run (collapsed: basis evaluations)
    n_evaluations: int = 0

    def tier_dict(self) -> dict:
        """JSON-ready tier record of this fit's evidence run."""
        return {"tier": self.tier or None, "note": self.tier_note, "evaluations": int(self.n_evaluations),
                **jsonable(self.tier_info)}

    def interval(self, name: str, q: tuple[float, float] = (0.025, 0.975)) -> tuple[float, float]:
        """Posterior quantiles of parameter ``name`` (NaN when not sampled or not free)."""
        if self.samples is None or name not in self.names:
            return (NAN, NAN)
        col = self.samples[:, self.names.index(name)]
        return tuple(float(v) for v in np.quantile(col, q))


@dataclass(slots=True)
class CandidateResult:
    """Screen and (optionally) refit result of one candidate effect."""

    effect: str
    score: float                          # normal-equivalent z of the projected score test
    chi2: float
    dof: int
    absorbed: float                       # fraction of the signature the base model absorbs
    refit: bool = False
    physical: bool = True
    delta_log_evidence: float = NAN
    delta_log_evidence_se: float = NAN
    delta_max_log_likelihood: float = NAN
    rmse_before: float = NAN
    rmse_after: float = NAN
    noise: str | None = None
    intervals: dict = field(default_factory=dict)   # primary parameter -> (lo, hi, null)
    excludes_null: bool | None = None
    fit: FitSummary | None = None
    start: dict = field(default_factory=dict)       # refit start from the cheap local refit
    local_z: float = 0.0                            # z of the cheap local-refit screen
    local_chi2: float = 0.0
    delta_log_evidence_tmcmc: float = NAN
    delta_log_evidence_laplace: float = NAN
    evidence_method: str = ""
    #: the screened Effect itself (the refit and ``extend(auto=True)`` build models with it)
    effect_instance: Effect | None = field(default=None, repr=False)
    #: the score test's linearised estimate of the effect's parameters (a second refit start)
    score_start: dict = field(default_factory=dict, repr=False)
    #: misfit windows left after the refit (scanned with the model-free noise)
    windows_after: int | None = None
    #: where a refitted control acts: (axis, lo, hi)
    region: tuple | None = None
    #: a refitted control's own numbers in words (a ripple's period and amplitude), else ""
    shape_detail: str = ""
    #: the cheap local refit's whole optimum (base parameters included), a refit start
    local_full: dict = field(default_factory=dict, repr=False)
    #: Laplace Δlog Z of this refit at white noise against an AR(1) base (None otherwise)
    white_gain: float | None = None
    #: effects the kept refit places elsewhere than the plain model: {effect: placement used},
    #: e.g. {"offset": "prestress"} (:func:`.refits.placement_models`)
    placements: dict = field(default_factory=dict)
    #: other placements the data do not tell apart from the kept one: {"offset placed as
    #: prestress": (Δlog Z, Δmax log L) against the kept refit}
    placement_ties: dict = field(default_factory=dict)

    def to_dict(self) -> dict:
        """JSON-ready summary (one entry of ``candidates`` in ``hbm diagnose --json``)."""
        return {"effect": self.effect, "score": _num(self.score),
                "delta_log_evidence": _num(self.delta_log_evidence),
                "delta_log_evidence_se": _num(self.delta_log_evidence_se),
                "rmse_before": _num(self.rmse_before), "rmse_after": _num(self.rmse_after),
                "chi2": _num(self.chi2), "dof": int(self.dof), "absorbed": _num(self.absorbed),
                "local_refit_z": _num(self.local_z), "local_refit_chi2": _num(self.local_chi2),
                "refit": bool(self.refit), "physical": bool(self.physical),
                "delta_max_log_likelihood": _num(self.delta_max_log_likelihood),
                "noise": self.noise,
                "delta_log_evidence_tmcmc": _num(self.delta_log_evidence_tmcmc),
                "delta_log_evidence_laplace": _num(self.delta_log_evidence_laplace),
                "evidence_method": self.evidence_method,
                "intervals": {k: [_num(v) for v in t] for k, t in self.intervals.items()},
                "excludes_null": self.excludes_null,
                "windows_after": self.windows_after,
                "region": list(self.region) if self.region else None,
                "shape_detail": self.shape_detail,
                "white_noise_gain": _num(self.white_gain) if self.white_gain is not None else None,
                "placements": dict(self.placements),
                "placement_ties": {k: [_num(x) for x in v] for k, v in self.placement_ties.items()},
                "likelihood_tier": self.fit.tier_dict() if self.fit is not None else None}


def gain(c: CandidateResult | None) -> float:
    """Evidence gain, capped by the likelihood gain (a noisy evidence estimate must not
    create a gain that the best fit does not show); −inf when not refitted."""
    if c is None or not c.refit or not np.isfinite(c.delta_log_evidence):
        return -np.inf
    return min(c.delta_log_evidence, c.delta_max_log_likelihood)


@dataclass(slots=True)
class Diagnosis:
    """Result of :func:`hbm.diagnose`.

    Attributes
    ----------
    verdict : str
        ``"adequate"``, ``"effect"``, ``"group"``, ``"unexplained"``, ``"data_problem"`` or, when
        ``max_time`` stopped it before every candidate was refitted and no misfit showed, ``"undecided"``.
    selected : list of str
        The named effect (verdict ``"effect"``).
    group : list of str
        Near-tied candidates (verdict ``"group"``).
    misfit_windows : list of (eps_lo, eps_hi, sign)
        Strain windows with a significant smoothed standardised residual.
    noise : dict
        Chosen noise model, its parameters, BIC of each noise model and the model-free estimate.
    candidates : list of CandidateResult
        Every screened candidate (refitted ones carry Δlog Z), best first; the control last.
    suggested_experiment : str
        What would separate a confusable group (or locate an unexplained misfit).
    message : str
        One-line verdict for people.
    base : FitSummary
        The fit of the current model.
    coverage : dict
        Posterior-predictive coverage: ``band``, ``overall``, ``per_test``, ``along_strain``.
    window_detail : list of dict
        Each misfit window with its z, test and index range.
    timings : dict
        Wall seconds per step, ``total`` and ``cpu``.
    data : SpecimenData
        The specimen's arrays (for the figure).
    residual_curve : dict
        Prediction, residuals, standardised and smoothed residuals, band (for the figure).
    skipped : dict
        Candidate -> why it could not be screened (e.g. no time column).
    at_bounds : list of dict
        Base-model parameters whose best fit or posterior sits on a box edge
        (:func:`hbm.fit.edges`): the verdict is conditional on that box.
    unexplained : dict or None
        For an unexplained misfit: ``axis`` (strain or time), ``range``, best-fitting ``shape``.
    steps : list of dict
        The greedy rounds: model, verdict, message, windows and gains at each.
    data_problem : str or None
        A data problem found before any physics (e.g. a stress file in kPa).
    removal : list of dict
        Removal test of each base part (:func:`hbm.detective.removal.removal_test`).
    power : dict or None
        Detection limits of the library effects on this protocol
        (:func:`hbm.detective.power.detection_power`).
    """

    verdict: str
    selected: list
    group: list
    misfit_windows: list
    noise: dict
    candidates: list
    suggested_experiment: str
    message: str
    base: FitSummary
    coverage: dict
    window_detail: list
    timings: dict
    data: Any = None
    residual_curve: dict = field(default_factory=dict)
    skipped: dict = field(default_factory=dict)
    at_bounds: list = field(default_factory=list)
    unexplained: dict | None = None
    steps: list = field(default_factory=list)
    data_problem: str | None = None
    removal: list = field(default_factory=list)
    power: dict | None = None
    #: what the verdict can and cannot tell (:func:`hbm.detective.caveats.verdict_caveats`)
    caveats: list = field(default_factory=list)
    #: why the diagnosis stopped early (``max_time`` reached), and what was left undecided
    stopped: dict | None = None
    #: what decided the verdict (issue 38): ``method`` "calibrated" with each greedy round's calibrated
    #: statistics (:class:`hbm.detective.calibration.Calibration` as dicts) or "fixed"; ``text``
    calibration: dict = field(default_factory=dict)
    #: the candidate result of each named effect, in order, each from the round that named it
    #: (``hbm extend --auto`` tabulates their fits and gains)
    named_candidates: list = field(default_factory=list, repr=False)
    #: what was done to the record before the diagnosis: artefact rows flagged or dropped, a dense
    #: record reduced (:func:`hbm.detective.records.record_dict`); None for a record taken as it is
    record: dict | None = None

    @property
    def named_fits(self) -> list:
        """The refit of each named effect, in order."""
        return [c.fit for c in self.named_candidates]

    def to_dict(self) -> dict:
        """The JSON object of ``hbm diagnose --json`` (issue 5 shape plus detail keys)."""
        return {
            "verdict": self.verdict,
            "selected": list(self.selected),
            "group": list(self.group),
            "misfit_windows": [[_num(a), _num(b), int(s)] for a, b, s in self.misfit_windows],
            "noise": jsonable(self.noise),
            "candidates": [c.to_dict() for c in self.candidates],
            "suggested_experiment": self.suggested_experiment,
            "message": self.message,
            "base": {"effects": self.base.effects, "noise": self.base.noise,
                     "rmse": _num(self.base.rmse), "log_evidence": _num(self.base.log_evidence),
                     "log_evidence_se": _num(self.base.log_evidence_se),
                     "max_log_likelihood": _num(self.base.max_log_likelihood),
                     "likelihood_tier": self.base.tier_dict(),
                     "theta": {n: _num(v) for n, v in zip(self.base.names, self.base.theta_max)}},
            "coverage": jsonable(self.coverage),
            "misfit_window_detail": jsonable(self.window_detail),
            "timings": jsonable(self.timings),
            "skipped_candidates": dict(self.skipped),
            "at_bounds": jsonable(self.at_bounds),
            "unexplained_window": jsonable(self.unexplained),
            "steps": jsonable(self.steps),
            "data_problem": self.data_problem,
            "removal": jsonable(self.removal),
            "caveats": jsonable([{k: v for k, v in c.items()} for c in self.caveats]),
            "stopped": jsonable(self.stopped),
            "power": jsonable({k: v for k, v in self.power.items() if k != "text"}) if self.power else None,
            "calibration": jsonable({k: v for k, v in self.calibration.items() if k != "text"}),
            **({"record": jsonable(self.record)} if self.record else {}),
        }

    def to_json(self) -> str:
        return json.dumps(self.to_dict())

    def summary(self) -> str:
        """Human-readable report (what ``hbm diagnose`` prints)."""
        b = self.base
        lines = [f"model: {' + '.join(b.effects) or 'base'}   noise: {_noise_text(self.noise)}",
                 f"fit: RMSE {b.rmse:.4g} MPa (at the optimum under {b.noise} noise, the noise model chosen here; "
                 f"other noise models give other optima), log Z {b.log_evidence:.2f} ± {b.log_evidence_se:.2f}, "
                 f"{int(BAND * 100)}% predictive coverage {self.coverage.get('overall', NAN):.2f}"]
        lines += [f"base fit: {line.removeprefix('warning: ')}" for line in format_at_bounds(self.at_bounds)]
        if self.noise.get("comparison"):
            cal = self.noise.get("calibrated") or {}
            if cal.get("noise"):
                st = cal["noise"]
                flag = (f"  (disagreement {st['observed']:.2f}, 1 = the fixed rule's bound; calibrated family-wise p "
                        f"{st['p_family']:.3g}{': a sign of misfit' if st['p_family'] <= cal['alpha'] else ''})")
            else:
                flag = "" if self.noise.get("consistent", True) else "  (DISAGREES: a sign of misfit)"
            lines.append("noise check: " + self.noise["comparison"] + flag)
        if self.misfit_windows:
            lines.append("misfit windows (smoothed standardised residual, family-wise 5%):")
            for d in self.window_detail:
                lines.append(f"  eps in [{d['eps_lo']:.4f}, {d['eps_hi']:.4f}] test {d['test']}: "
                             f"{'model too low (data above)' if d['sign'] > 0 else 'model too high (data below)'}"
                             f", z = {d['z']:.1f}")
        else:
            lines.append("misfit windows: none")
        lines.append("")
        lines.append("Δlog Z: Laplace difference against the best base (a dense record: narrow, Gaussian posteriors, "
                     "no sampling SE); intervals: Laplace posterior 95 %" if b.tier == "laplace" else
                     "Δlog Z: TMCMC difference against the best base, SE calibrated to the seed-to-seed scatter "
                     "(Laplace: the screen's estimate); intervals: TMCMC posterior 95 %")
        lines.append(f"{'candidate':<20}{'score z':>8}{'local z':>8}{'absorbed':>9}{'dlogZ ± SE':>15}"
                     f"{'Laplace':>9}{'RMSE before':>12}{'after':>11}  noise  interval of new parameter")
        any_unsampled = False
        for c in self.candidates:
            # the curvature (Laplace) intervals stay in the JSON: beside the TMCMC ones they mislead
            # (local curvature at the optimum, up to 10x narrower where the posterior is skewed)
            unsampled = c.refit and c.evidence_method == "laplace"
            iv = "; ".join((f"{k} [{v[0]:.3g}, {v[1]:.3g}]" if np.isfinite(v[0]) and np.isfinite(v[1]) else
                            f"{k} undefined (flat or at a box edge)") + f" (null {v[2]:.3g})"
                           for k, v in c.intervals.items() if k.endswith("(Laplace)") == unsampled)
            if c.refit:
                tm = (f"{c.delta_log_evidence:.1f} ± {c.delta_log_evidence_se:.1f}" if not unsampled else
                      f"{c.delta_log_evidence:.1f} (L)†")
                any_unsampled |= unsampled
                lines.append(f"{c.effect:<20}{c.score:>8.2f}{c.local_z:>8.2f}{c.absorbed:>9.2f}{tm:>15}"
                             f"{c.delta_log_evidence_laplace:>9.1f}{c.rmse_before:>12.4g}{c.rmse_after:>11.4g}  "
                             f"{c.noise or '':<6} {iv}")
            else:
                lines.append(f"{c.effect:<20}{c.score:>8.2f}{c.local_z:>8.2f}{c.absorbed:>9.2f}{'—':>15}{'':>9}"
                             f"{c.rmse_before:>12.4g}{'':>11}")
        if any_unsampled:
            lines.append("†: no evidence run -- its likelihood gain at the optimum cannot reach the "
                         f"{DELTA_LOGZ_MIN:g}-nat threshold, so the run could not change the verdict; Δlog Z is the "
                         "Laplace estimate and the interval the curvature one")
        if self.noise.get("preference"):
            lines.append(f"noise: {self.noise['preference']}")
        if len(self.steps) > 1:
            lines.append("greedy rounds (each named effect added, then re-screened):")
            for k, st in enumerate(self.steps):
                lines.append(f"  {k}: model {' + '.join(st['model']) or 'base'}: {st['verdict']} — {st['message']}")
        for r in self.removal:
            if not r["needed"]:
                lines.append(f"removal test: the data do not need the {r['part']} part (removing "
                             f"{', '.join(r['removed'])} changes log Z by {r['delta_log_evidence']:+.1f})")
        if self.removal and all(r["needed"] for r in self.removal):
            lines.append("removal test: every base part is needed ("
                         + ", ".join(f"{r['part']} {r['delta_log_evidence']:+.1f}" for r in self.removal) + ")")
        if self.calibration.get("text"):
            lines.append(self.calibration["text"])
        if self.stopped:
            lines.append(self.stopped["text"])
        lines.append("")
        lines.append(f"verdict: {self.verdict} — {self.message}")
        if self.suggested_experiment:
            lines.append(f"suggested experiment: {self.suggested_experiment}")
        if self.power:
            lines += ["", self.power_text()]
        t = self.timings.get("total")
        if t is not None:
            lines.append(f"(wall time {t:.1f} s, CPU time {self.timings.get('cpu', NAN):.1f} s)")
        return "\n".join(lines)

    def __str__(self) -> str:
        return self.summary()

    def power_text(self) -> str:
        """The detection-limit section (``hbm diagnose --power``); empty without a power run."""
        return self.power.get("text", "") if self.power else ""

    def plot(self, path):
        """Write the diagnosis figure (data, fit, band, residuals with windows) to ``path``."""
        return _figures().plot_diagnosis(self, path, evidence_threshold=DELTA_LOGZ_MIN)


@dataclass(slots=True)
class Extension:
    """Result of :func:`hbm.extend`: one :class:`FitSummary` per step, the base model first."""

    steps: list
    decisions: list = field(default_factory=list)
    data: Any = None
    timings: dict = field(default_factory=dict)
    #: model-free noise estimate of the data (``sigma``, ``rho``, ``sigma_iid``): the noise
    #: level the error should fall to (the figure's reference line)
    noise: dict = field(default_factory=dict)
    #: the diagnosis of ``auto`` stopped at ``max_time`` (what it left undecided), else None
    stopped: dict | None = None
    #: per step after the first: the evidence gain over the previous step,
    #: ``{"delta_log_evidence", "delta_log_evidence_se", "evidence_method"}`` -- for the effects
    #: ``auto`` added, the diagnosis's own numbers (its refined reruns where it made them)
    gains: list = field(default_factory=list)
    #: how the given steps' noise model was chosen (one line each), e.g. an AR(1) rejected by
    #: diagnose's guard
    notes: list = field(default_factory=list)

    def step_gain(self, i: int) -> dict | None:
        """Step ``i``'s gain over step ``i - 1`` (None for the first step)."""
        if i == 0:
            return None
        if i - 1 < len(self.gains) and self.gains[i - 1] is not None:
            return self.gains[i - 1]
        a, b = self.steps[i - 1], self.steps[i]
        return {"delta_log_evidence": b.log_evidence - a.log_evidence,
                "delta_log_evidence_se": TMCMC_SE_FACTOR * math.hypot(a.log_evidence_se, b.log_evidence_se),
                "evidence_method": "tmcmc"}

    def to_dict(self) -> dict:
        return {"steps": [{"effects": list(s.effects), "rmse": _num(s.rmse),
                           "log_evidence": _num(s.log_evidence),
                           "log_evidence_se": _num(s.log_evidence_se),
                           "coverage": _num(s.coverage), "noise": s.noise,
                           "max_log_likelihood": _num(s.max_log_likelihood),
                           "likelihood_tier": s.tier_dict(),
                           "gain_over_previous": jsonable(self.step_gain(i))} for i, s in enumerate(self.steps)],
                "decisions": jsonable(self.decisions), "stopped": jsonable(self.stopped), "notes": list(self.notes)}

    def to_json(self) -> str:
        return json.dumps(self.to_dict())

    def table(self) -> str:
        """The error-fall table."""
        rows = [f"{'step':<5}{'effects':<40}{'noise':<13}{'RMSE':>10}{'log Z':>10}{'± SE':>7}"
                f"{'dlogZ(prev) ± SE':>18}{'coverage':>10}"]
        refined = False
        for i, s in enumerate(self.steps):
            eff = "+".join(s.effects) if s.effects else "(base)"
            g = self.step_gain(i)
            dz = "" if g is None else f"{g['delta_log_evidence']:.1f} ± {g['delta_log_evidence_se']:.1f}" + (
                "*" if g["evidence_method"] == "tmcmc-refined" else "")
            refined |= bool(g and g["evidence_method"] == "tmcmc-refined")
            rows.append(f"{i:<5}{eff:<40}{s.noise:<13}{s.rmse:>10.4g}{s.log_evidence:>10.2f}"
                        f"{s.log_evidence_se:>7.2f}{dz:>18}{s.coverage:>10.2f}")
        rows.append("dlogZ(prev): evidence gain over the previous step, SE calibrated to the seed-to-seed scatter"
                    + ("; *: from the refined evidence reruns of the diagnosis (log Z column: standard runs)"
                       if refined else ""))
        rows += list(self.notes)
        if self.stopped:
            rows.append(self.stopped["text"])
        return "\n".join(rows)

    def __str__(self) -> str:
        return self.table()

    def plot(self, path):
        """Write the error-fall figure (fits per step, RMSE, log Z, coverage) to ``path``."""
        return _figures().plot_extension(self, path, noise_sd=self.noise.get("sigma"))


def _figures():
    """:mod:`hbm.plots.diagnose`, imported when a figure is drawn."""
    # matplotlib is heavy and optional: the detective itself never needs it (hbm.plots is lazy)
    return plots.diagnose


def _num(x):
    try:
        x = float(x)
    except (TypeError, ValueError):
        return None
    return x if math.isfinite(x) else None


def jsonable(x):
    """``x`` with numpy scalars/arrays turned into Python numbers/lists and NaN into None."""
    if isinstance(x, dict):
        return {str(k): jsonable(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [jsonable(v) for v in x]
    if isinstance(x, (np.integer,)):
        return int(x)
    if isinstance(x, (bool, np.bool_)):
        return bool(x)
    if isinstance(x, (float, np.floating)):
        return _num(x)
    if isinstance(x, np.ndarray):
        return jsonable(x.tolist())
    return x


def _noise_text(noise: dict) -> str:
    m = noise.get("model", "?")
    parts = [m] + [f"{k} {noise[k]:.3g}" for k in ("sigma", "sigma_rel", "rho") if noise.get(k) is not None]
    return ", ".join(parts)
