"""The detective across loading modes (issue 35, item 6): which collagen reading, what one mode says about
another, and lateral strains no parameter can explain.

:func:`diagnose_modes` takes a specimen whose tests are in several modes (or carry series besides the
along-fibre stress: :func:`hbm.likelihood.modes.is_multimode`) and runs:

1. **The collagen reading as a model-form candidate.**  The joint fit (:func:`hbm.fit.modes.fit_modes`) in
   every reading of :data:`hbm.model.energy3d.COLLAGEN_READINGS`, each with its log-evidence and SE.  The
   best is *named* when it beats the next by ``Δ ≥ READING_MIN_NATS`` nats **and** ``Δ ≥ READING_MIN_SE``
   combined standard errors (√(SE₁² + SE₂²)): 3 nats is a Bayes factor of 20 ("strong" on the Kass–Raftery
   scale, 2·ln B > 6), and the SE condition guards against TMCMC's evidence scatter -- on the reported SEs, which
   under-state the seed-to-seed scatter (about 2.5×, ``rules.TMCMC_SE_FACTOR``), so it is the weaker guard: in
   the benchmark below the 3 nats bound, and the rate of wrongly named readings is measured there, not derived.
   ``workflows/benchmarks/modes_reading.py`` measures the rule on generated data.  When every test is
   ``uniaxial_f`` the readings are identical (DESIGN.md §8: they differ only off the fibre axis): one fit,
   and the report says so.
2. **Leave one mode out** (≥ 2 modes): the fit on the other modes' tests, in the reading with the higher
   evidence, predicts the held-out tests: posterior-mean prediction, rmse and rmse/max|data|, the ratio of
   predicted to measured value at each test's largest |strain|, and the share of points inside the 90 %
   posterior-predictive band.  The band's noise: the training fit never saw the held-out series' kind, so
   its noise sd is the joint fit's posterior median for that kind (measurement noise, not model).
3. **Lateral strains of along-fibre tests.**  In ``uniaxial_f`` the model predicts λc = λn = λ^-1/2 for every
   parameter set, so a measured departure is physics the model lacks.  Per test, with x = ln λ:
   volume ln J = x + ln λc + ln λn = a·x against a = 0 (compressibility), ln λc − ln λn = k·x against k = 0
   (loss of transverse isotropy), and with one lateral strain only ln λ_lat = −b·x against b = ½ (either).
   Each is an exact F-test of the slope through the origin, the noise sd fitted under both laws (Gaussian,
   iid); a departure is reported at family-wise 5 % over the checks made (Bonferroni), with its
   log-likelihood ratio in nats and the fitted J at the largest strain.
4. **A verdict per mode** from the joint fit's quality per test (:meth:`hbm.fit.modes.ModesFit.quality`) and
   the held-out prediction: a test's series is *followed* unless the share of its points inside the 90 % band
   is improbably low (binomial probability of as few inside < ``BAND_ALPHA``).

Seeds: stream ``detective_modes`` of :mod:`hbm.runtime.seeds` (child k: reading k; 100 + m: the fit
without mode m; 200 + m: mode m's held-out replicates).
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Mapping

import numpy as np
from scipy import stats

from ..data.specimen import Specimen, as_specimen
from ..fit.modes import TIER_NOTE, ModesFit, fit_modes, series_fit
from ..likelihood.modes import ModesLikelihood, make_modes_likelihood
from ..model import spyrou_model
from ..model.energy3d import COLLAGEN_READINGS, DEFAULT_COLLAGEN3D
from ..model.loadcases import DEFAULT_LOAD_CASE
from ..model.spyrou import model_form
from ..runtime import seeds
from .rules import BAND

__all__ = ["ModesDiagnosis", "diagnose_modes", "compare_readings", "held_out_prediction", "lateral_checks",
           "readings_differ", "READING_MIN_NATS", "READING_MIN_SE", "LATERAL_ALPHA", "BAND_ALPHA",
           "MAX_STEPS", "TMCMC_BATCHES"]

#: the evidence margin (nats) and its size in combined SEs that name a reading
READING_MIN_NATS = 3.0
READING_MIN_SE = 3.0
#: family-wise level of the lateral-strain checks
LATERAL_ALPHA = 0.05
#: a series "misses" when the binomial probability of as few points inside its 90 % band is below this
BAND_ALPHA = 0.01
#: MH steps per TMCMC stage at most (unless ``tmcmc_options`` says otherwise): TMCMC's default cap (100)
#: took ~1600 populations per fit of a 30-point synthetic specimen (114 s CPU per diagnosis of two readings)
#: against ~160-300 with this cap (porcine ramps: log Z SE 0.3-0.6 at N = 400); a diagnosis runs 2-5 fits
MAX_STEPS = 15
#: likelihood batches (one per population) a TMCMC fit took at MAX_STEPS on the multi-mode examples (porcine
#: ramps: 256-301 at N = 400; synthetic along + across + shear: 120-190): the estimate up front
TMCMC_BATCHES = 300
#: the thesis form's own reading (no choice to compare)
AXIAL = "axial"


def _reading_name(collagen3d: str | None) -> str:
    """The name of a fit's collagen reading: the energy form's reading, or AXIAL for the thesis form (None)."""
    return collagen3d or AXIAL


def _collagen3d(reading: str) -> str | None:
    """The ``collagen3d`` argument of a fit in the named reading (None: the thesis form's own, AXIAL)."""
    return None if reading == AXIAL else reading


def readings_differ(spec: Specimen) -> bool:
    """True when a test is in a mode where the collagen readings differ (any mode but ``uniaxial_f``)."""
    return any(t.load_case != DEFAULT_LOAD_CASE for t in as_specimen(spec).tests)


def _seed(seed: int, j: int) -> int:
    return seeds.seed_int(seeds.stream(seed, "detective_modes", j))


# -- 1. the readings ------------------------------------------------------------------------------
def compare_readings(evidence: Mapping[str, tuple[float, float]]) -> dict[str, Any]:
    """Name the collagen reading by evidence.

    Parameters
    ----------
    evidence : mapping
        reading -> (log-evidence, its SE).

    Returns
    -------
    dict
        ``best``, ``second``, ``difference`` (nats), ``se`` (combined), ``named`` (the best or None) and a
        ``message``.
    """
    order = sorted(evidence, key=lambda r: -evidence[r][0])
    best = order[0]
    if len(order) == 1:
        return {"best": best, "second": None, "difference": None, "se": None, "named": None,
                "message": f"one reading fitted ({best})"}
    second = order[1]
    diff = evidence[best][0] - evidence[second][0]
    se = math.hypot(evidence[best][1], evidence[second][1])
    named = best if diff >= READING_MIN_NATS and diff >= READING_MIN_SE * se else None
    if named:
        msg = (f"the data name the {best} reading: log Z {best} - {second} = {diff:.1f} +- {se:.1f} nats "
               f"(rule: >= {READING_MIN_NATS:g} nats and >= {READING_MIN_SE:g} SE)")
    else:
        msg = (f"the data do not tell the readings apart: log Z {best} - {second} = {diff:.1f} +- {se:.1f} nats "
               f"(naming needs >= {READING_MIN_NATS:g} nats and >= {READING_MIN_SE:g} SE)")
    return {"best": best, "second": second, "difference": diff, "se": se, "named": named, "message": msg}


# -- 2. leave one mode out ------------------------------------------------------------------------
def _ratio_words(r: float, is_stress: bool, observable: str) -> str:
    if not np.isfinite(r):
        return "undefined (measured 0)"
    if r < 0:
        return f"with the wrong sign ({r:.2g}x)"
    if abs(r - 1.0) <= 0.1:
        return f"within {abs(r - 1) * 100:.2g} %"
    if not is_stress:
        return f"{r:.2g}x the measured {observable}"
    return f"{r:.2g}x too stiff" if r > 1 else f"too soft ({r:.2g}x)"


def held_out_prediction(train: ModesFit, held: ModesLikelihood, noise_sd: Mapping[str, float],
                        seed: int) -> list[dict[str, Any]]:
    """The training posterior's prediction of every series of ``held`` (tests the fit did not see).

    Parameters
    ----------
    train : ModesFit
        The fit on the other tests (same model parameters and fixed values as ``held``).
    held : ModesLikelihood
        The likelihood of the held-out tests (its noise parameters are not used).
    noise_sd : mapping
        Noise sd of each of ``held``'s kinds (natural units) for the predictive band.
    seed : int
        Seed of the predictive replicates.

    Returns
    -------
    list of dict
        Per series: test, label, mode, observable, points, ``rmse``, ``rmse_rel``, ``strain_at`` (the largest
        |strain| of the series), ``measured_at``, ``predicted_at``, ``ratio`` (predicted / measured there),
        ``inside90`` (share inside the 90 % predictive band), ``inside_model90`` (inside the band of the model
        alone, no noise).
    """
    tl = train.likelihood
    rows = np.empty((train.samples.shape[0], held.d))
    for j, n in enumerate(held.model_names):
        rows[:, j] = train.samples[:, tl.names.index(n)]
    rows[:, held.n_model:] = 1.0  # noise columns and per-test scales: unused by predict_series (scale 1)
    pred = held.predict_series(held.from_natural(rows))
    rng = np.random.default_rng(seed)
    out = []
    for s, m in zip(held.series, pred):
        mean = m.mean(axis=0)
        rep = m + noise_sd[s.kind] * rng.standard_normal(m.shape)
        lo, hi = np.quantile(rep, [(1 - BAND) / 2, (1 + BAND) / 2], axis=0)
        mlo, mhi = np.quantile(m, [(1 - BAND) / 2, (1 + BAND) / 2], axis=0)
        strain = held.data.strain[s.rows]
        k = int(np.argmax(np.abs(strain)))
        ratio = float(mean[k] / s.observed[k]) if s.observed[k] != 0 else float("nan")
        out.append({**series_fit(s, mean), "strain_at": float(strain[k]), "measured_at": float(s.observed[k]),
                    "predicted_at": float(mean[k]), "ratio": ratio, "is_stress": bool(s.is_stress),
                    "inside90": float(np.mean((s.observed >= lo) & (s.observed <= hi))),
                    "inside_model90": float(np.mean((s.observed >= mlo) & (s.observed <= mhi)))})
    return out


def _span(values, fmt: str) -> str:
    """'a' or 'a-b' (min-max) in format ``fmt``."""
    lo, hi = format(min(values), fmt), format(max(values), fmt)
    return lo if lo == hi else f"{lo}-{hi}"


def _held_sentence(mode: str, trained_on: list[str], rows: list[dict[str, Any]]) -> str:
    """'fitted on the X tests, the model predicts the Y ones 4.8-6.3x too stiff at strain -0.3 ...'."""
    parts = []
    for obs in dict.fromkeys(r["observable"] for r in rows):
        sel = [r for r in rows if r["observable"] == obs]
        ratios = np.array([r["ratio"] for r in sel])
        fin = ratios[np.isfinite(ratios)]
        where = ", ".join(dict.fromkeys(f"{r['strain_at']:+.3g}" for r in sel))
        if fin.size == ratios.size and (fin.min() > 1.1 or (fin.min() >= 0 and fin.max() < 0.9)):
            word = "too stiff" if fin.min() > 1 else "too soft"
            span = _span(fin, ".2g") + "x"
            what = f"{span} {word} at strain {where}" if sel[0]["is_stress"] else \
                f"at {span} the measured values at strain {where}"
        else:  # no common direction: test by test
            what = "per test " + "; ".join(f"{_ratio_words(r['ratio'], r['is_stress'], obs)} at strain "
                                           f"{r['strain_at']:+.3g}" for r in sel)
        parts.append(f"{obs} {what} (rmse/max {_span([r['rmse_rel'] for r in sel], '.2g')}; "
                     f"{_span([100 * r['inside90'] for r in sel], '.0f')} % of the points inside the 90 % "
                     "predictive band)")
    return f"fitted on the {', '.join(trained_on)} tests, the model predicts the {mode} ones: " + "; ".join(parts)


# -- 3. lateral strains -------------------------------------------------------------------------
def _slope_test(y: np.ndarray, x: np.ndarray) -> dict[str, float]:
    """y = k·x against y = 0: exact F-test (slope through the origin, noise sd fitted under both)."""
    n = y.size
    sxx = float(np.dot(x, x))
    k = float(np.dot(x, y) / sxx) if sxx > 0 else 0.0
    rss0 = float(np.dot(y, y))
    rss1 = float(np.sum((y - k * x) ** 2))
    if n < 3 or sxx == 0:
        return {"slope": k, "se": float("nan"), "p": float("nan"), "nats": float("nan"), "n": n}
    s2 = rss1 / (n - 1)
    se = math.sqrt(s2 / sxx) if s2 > 0 else 0.0
    f = (rss0 - rss1) / s2 if s2 > 0 else float("inf")
    p = float(stats.f.sf(f, 1, n - 1)) if np.isfinite(f) else 0.0
    nats = 0.5 * n * math.log(rss0 / rss1) if rss1 > 0 and rss0 > 0 else float("inf")
    return {"slope": k, "se": se, "p": p, "nats": nats, "n": n, "noise_sd": math.sqrt(s2)}


def lateral_checks(spec: Specimen, alpha: float = LATERAL_ALPHA) -> list[dict[str, Any]]:
    """Test the measured lateral strains of every ``uniaxial_f`` test against λ^-1/2 (module docstring, 3).

    Parameters
    ----------
    spec : Specimen
    alpha : float
        Family-wise level over all checks made.

    Returns
    -------
    list of dict
        Per check: test, label, ``check`` (``volume`` | ``isotropy`` | ``lateral_c`` | ``lateral_n``),
        points, fitted slope and SE, ``p``, ``nats`` (log-likelihood ratio), ``flagged``, a ``message``.
    """
    spec = as_specimen(spec)
    out: list[dict[str, Any]] = []
    for t in spec.tests:
        if t.load_case != DEFAULT_LOAD_CASE:
            continue
        x = np.log1p(spec.strain[t.rows])
        lat = {a: np.log1p(spec.observed[f"strain_{a}"].values[t.rows]) for a in "cn"
               if f"strain_{a}" in spec.observed}
        lat = {a: v for a, v in lat.items() if np.isfinite(v).sum() >= 3}
        name = t.label if t.label is not None else str(t.id)
        if len(lat) == 2:
            both = np.isfinite(lat["c"]) & np.isfinite(lat["n"])
            if both.sum() >= 3:
                xb = x[both]
                lnj = xb + lat["c"][both] + lat["n"][both]
                r = _slope_test(lnj, xb)
                k = int(np.argmax(np.abs(xb)))
                r.update(check="volume", J_at=float(math.exp(r["slope"] * xb[k])),
                         strain_at=float(math.expm1(xb[k])), J_measured_at=float(math.exp(lnj[k])))
                out.append({"test": t.id, "label": name, **r})
                d = lat["c"][both] - lat["n"][both]
                r = _slope_test(d, xb)
                r.update(check="isotropy", ratio_at=float(math.exp(r["slope"] * xb[k])),
                         strain_at=float(math.expm1(xb[k])))
                out.append({"test": t.id, "label": name, **r})
                continue
        for a, v in lat.items():
            ok = np.isfinite(v)
            r = _slope_test(v[ok] + 0.5 * x[ok], x[ok])
            k = int(np.argmax(np.abs(x[ok])))
            r.update(check=f"lateral_{a}", nu=0.5 - r["slope"], strain_at=float(math.expm1(x[ok][k])))
            out.append({"test": t.id, "label": name, **r})
    level = alpha / max(len(out), 1)
    for r in out:
        r["flagged"] = bool(np.isfinite(r["p"]) and r["p"] < level)
        r["message"] = _lateral_message(r, level)
    return out


def _lateral_message(r: dict[str, Any], level: float) -> str:
    strength = (f"p = {r['p']:.2g} (family-wise threshold {level:.2g}), log-likelihood ratio {r['nats']:.1f} nats, "
                f"{r['n']} points")
    at = f"at strain {r['strain_at']:+.3g}"
    if r["check"] == "volume":
        head = (f"volume not conserved (J = lambda*lambda_c*lambda_n = {r['J_at']:.4g} {at}, fitted "
                f"ln J = ({r['slope']:.3g} +- {r['se']:.2g})*ln lambda): compressibility"
                if r["flagged"] else f"volume conserved within the noise (fitted J = {r['J_at']:.4g} {at})")
    elif r["check"] == "isotropy":
        head = (f"strain_c != strain_n (lambda_c/lambda_n = {r['ratio_at']:.4g} {at}): loss of transverse isotropy"
                if r["flagged"] else f"strain_c = strain_n within the noise (lambda_c/lambda_n = "
                                     f"{r['ratio_at']:.4g} {at})")
    else:
        a = r["check"][-1]
        head = (f"strain_{a} departs from lambda^-1/2 (effective Poisson ratio {r['nu']:.3g} +- {r['se']:.2g} "
                "against 0.5): compressibility or a loss of transverse isotropy (one lateral strain cannot tell "
                "which)" if r["flagged"] else
                f"strain_{a} agrees with lambda^-1/2 (effective Poisson ratio {r['nu']:.3g} +- {r['se']:.2g})")
    return f"test {r['label']}: {head}; {strength}"


# -- 4. the verdict per mode ----------------------------------------------------------------------
def _followed(points: int, inside: float) -> tuple[bool, float]:
    """(followed, binomial probability of as few points inside a 90 % band)."""
    k = int(round(inside * points))
    p = float(stats.binom.cdf(k, points, BAND))
    return p >= BAND_ALPHA, p


@dataclass
class ModesDiagnosis:
    """The outcome of :func:`diagnose_modes` (see the module docstring for each part).

    Attributes
    ----------
    specimen_id : str
    fits : dict
        reading -> joint :class:`~hbm.fit.modes.ModesFit`.
    readings : dict
        :func:`compare_readings`, plus ``differ`` (False: every test along the fibres, one fit).
    reading : str
        The reading the held-out fits and verdicts use (the higher evidence).
    held_out : dict
        held-out mode -> {``trained_on``, ``fit`` (ModesFit), ``series`` (:func:`held_out_prediction`),
        ``message``}.
    lateral : list of dict
        :func:`lateral_checks`.
    verdicts : dict
        mode -> list of sentences.
    stopped : str or None
        Why fits were skipped (``max_time``).
    cpu_s, wall_s : float
    """

    specimen_id: str
    fits: dict
    readings: dict
    reading: str
    held_out: dict
    lateral: list
    verdicts: dict
    settings: dict
    stopped: str | None = None
    cpu_s: float = 0.0
    wall_s: float = 0.0
    paths: dict = field(default_factory=dict)

    @property
    def n_evaluations(self) -> int:
        """Log-likelihood evaluations over every fit."""
        return int(sum(f.n_evaluations for f in self.fits.values()) +
                   sum(h["fit"].n_evaluations for h in self.held_out.values() if h["fit"] is not None))

    def summary(self) -> str:
        """The text report."""
        lines = [f"{self.specimen_id}: diagnosis across loading modes ({', '.join(self.verdicts)}); TMCMC N = "
                 f"{self.settings['samples']}, at most {self.settings['tmcmc_options'].get('max_steps')} MH steps "
                 f"per stage, seed {self.settings['seed']}"]
        lines.append(f"every fit: {TIER_NOTE}")
        lines.append("collagen reading (model form):")
        for r, f in self.fits.items():
            lines.append(f"  {r:<6s} log Z {f.log_evidence:.2f} +- {f.log_evidence_se:.2f} "
                         f"({f.n_evaluations} evaluations)")
        if self.reading == AXIAL:
            lines.append("  the thesis form has its own (axial) reading only; --form energy compares cone and gst")
        elif not self.readings["differ"]:
            lines.append("  every test is along the fibres (uniaxial_f), where the readings "
                         f"({', '.join(COLLAGEN_READINGS)}) are identical: one fit, nothing to tell apart")
        else:
            lines.append("  " + self.readings["message"])
        how = ("the only one fitted" if len(self.fits) == 1 else
               "named" if self.readings.get("named") else "higher evidence, not named")
        lines.append(f"verdict per mode (joint fit and leave-one-mode-out fits in the {self.reading} reading, {how}; "
                     f"a series misses when the chance of as few points inside its 90 % band is < {BAND_ALPHA:g}; "
                     "held-out bands: the training posterior plus the joint fit's noise sd of the held-out kind):")
        for mode, sentences in self.verdicts.items():
            lines.append(f"  {mode}:")
            lines += [f"    {s}" for s in sentences]
        if self.lateral:
            lines.append("lateral strains of along-fibre tests (the model: lambda^-1/2 for every parameter set):")
            lines += [f"  {r['message']}" for r in self.lateral]
        if self.stopped:
            lines.append(f"stopped: {self.stopped}")
        lines.append(f"{self.n_evaluations} evaluations, {self.cpu_s:.1f} s CPU, {self.wall_s:.1f} s wall")
        if self.paths:
            lines.append("wrote " + ", ".join(str(p) for p in self.paths.values()))
        return "\n".join(lines)

    def to_dict(self) -> dict[str, Any]:
        """Everything of the report as JSON-able values."""
        def fit_dict(f: ModesFit) -> dict[str, Any]:
            return {"log_evidence": f.log_evidence, "log_evidence_se": f.log_evidence_se,
                    "n_evaluations": f.n_evaluations, "tests": f.quality(),
                    "posterior_mean": dict(zip(f.names, map(float, f.samples.mean(axis=0))))}
        return {"specimen": self.specimen_id, "settings": self.settings, "reading": self.reading,
                "readings": {**self.readings, "fits": {r: fit_dict(f) for r, f in self.fits.items()}},
                "held_out": {m: {"trained_on": h["trained_on"], "message": h["message"], "series": h["series"],
                                 "fit": None if h["fit"] is None else fit_dict(h["fit"])}
                             for m, h in self.held_out.items()},
                "lateral": self.lateral, "verdicts": self.verdicts, "stopped": self.stopped,
                "n_evaluations": self.n_evaluations, "cpu_s": self.cpu_s, "wall_s": self.wall_s,
                "paths": {k: str(v) for k, v in self.paths.items()}}


def _verdicts(spec: Specimen, fit: ModesFit, held_out: dict, lateral: list) -> dict[str, list[str]]:
    out: dict[str, list[str]] = {m: [] for m in spec.load_cases}
    for q in fit.quality():
        ok, p = _followed(q["points"], q["coverage90"])
        name = q["label"] if q["label"] is not None else q["test"]
        out[q["mode"]].append(
            f"test {name} {q['observable']}: {'followed' if ok else 'MISSED'} by the joint fit (rmse {q['rmse']:.3g} "
            f"{q['unit']}, rmse/max {q['rmse_rel']:.2f}, {q['coverage90'] * 100:.0f} % inside the 90 % band"
            + ("" if ok else f", chance {p:.2g}") + ")")
    for mode, h in held_out.items():
        if not h["series"]:
            continue
        ok = all(_followed(r["points"], r["inside90"])[0] for r in h["series"])
        # inside the band is all that was checked: a band the other modes leave wide holds any data
        out[mode].append(h["message"] + (": inside the other modes' 90 % predictive band (how far they "
                                         "determine it: the ratios and rmse above, not the band)" if ok else
                                         ": the other modes do not determine this one (its tests are needed)"))
    for r in lateral:
        if r["flagged"]:
            out[DEFAULT_LOAD_CASE].append("not explained by any parameter: " + r["message"])
    return out


# -- the diagnosis --------------------------------------------------------------------------------
def _plan(spec: Specimen, readings: list[str]) -> list[tuple[str, Any]]:
    fits: list[tuple[str, Any]] = [("joint", r) for r in readings]
    if len(spec.load_cases) >= 2:
        fits += [("without", m) for m in spec.load_cases]
    return fits


def diagnose_modes(data, *, model=None, samples: int = 800, seed: int = 0, fix: Mapping[str, float] | None = None,
                   max_evaluations: int | None = None, tmcmc_options: Mapping[str, Any] | None = None,
                   leave_one_out: bool = True, max_time: float | None = None, progress: bool = False,
                   out: str | Path | None = None, log=None) -> ModesDiagnosis:
    """Diagnose a specimen tested in several loading modes (module docstring).

    Parameters
    ----------
    data : Specimen or xarray.Dataset
    model : Model, optional
        The base model (default :func:`hbm.spyrou_model` in the energy form); its effects act per test where
        they are defined in 3-D (:class:`~hbm.model.modes_effects.ModeEffects`), the others are refused.  A mode
        whose tests need parameters the other modes lack (an offset of a series only it measures) gets no
        leave-one-out fit, and the diagnosis says so.
    samples, seed, fix, max_evaluations, tmcmc_options
        As for :func:`hbm.fit.modes.fit_modes`, for every fit (seeds from the ``detective_modes`` stream);
        ``tmcmc_options`` default ``{"max_steps": MAX_STEPS}``.
    leave_one_out : bool
        Run the leave-one-mode-out fits (≥ 2 modes).
    max_time : float, optional
        Wall seconds after which no new fit starts; what was skipped is in ``stopped``.
    progress : bool
        TMCMC progress bars.
    out : path, optional
        Folder for each fit's result (``joint_<reading>.nc``, ``without_<mode>.nc``;
        :func:`hbm.io.modes.write_modes_result`); the caller checks it (``hbm diagnose``).
    log : callable, optional
        ``log(str)``: a line per step, the plan and its estimate first.

    Returns
    -------
    ModesDiagnosis

    Raises
    ------
    HbmError
        Every refusal of the joint likelihoods (thesis form off the fibre axis, an effect not defined in a
        mode, unknown ``fix``),
        before any fit.
    """
    t0, c0 = time.perf_counter(), time.process_time()
    spec = as_specimen(data)
    model = spyrou_model(form="energy") if model is None else model
    say = log or (lambda s: None)
    differ = readings_differ(spec)
    readings = list(COLLAGEN_READINGS) if differ else [DEFAULT_COLLAGEN3D]
    form = model_form(model)
    if form == "thesis":  # the thesis form has its own (axial) reading only: no reading to compare
        readings = [None]  # type: ignore[list-item]
    plan = _plan(spec, readings) if leave_one_out else [("joint", r) for r in readings]
    # every likelihood first: a refusal comes before any fit
    parts: dict[str, Specimen] = {}
    for kind, what in plan:
        if kind == "without":
            keep = np.ones(spec.n_points, bool)
            for t in spec.tests:
                if t.load_case == what:
                    keep[t.rows] = False
            parts[f"without:{what}"] = spec.select(keep)
            parts[f"only:{what}"] = spec.select(~keep)
    liks = {r: make_modes_likelihood(model, spec, collagen3d=r, fix=fix) for r in readings}
    part_liks = {key: make_modes_likelihood(model, sub, collagen3d=readings[0], fix=fix) for key, sub in parts.items()}
    # a mode whose tests need parameters the others lack (an effect's per-observable offset of a series only
    # that mode measures) cannot be predicted from them: no leave-one-out fit for it, said up front
    unpredictable = {}
    for kind, what in plan:
        if kind == "without":
            missing = [n for n in part_liks[f"only:{what}"].model_names
                       if n not in part_liks[f"without:{what}"].model_names]
            if missing:
                unpredictable[what] = missing
    if unpredictable:
        plan = [p for p in plan if not (p[0] == "without" and p[1] in unpredictable)]
        say("no leave-one-out fit for " + "; ".join(f"{m} (its tests need {', '.join(n)}, which the other modes "
                                                    "do not determine)" for m, n in unpredictable.items()))
    cost = {}
    for r, lk in liks.items():  # CPU s of one population, warm (the first call builds caches)
        probe = lk.bounds[:, 0] + (lk.bounds[:, 1] - lk.bounds[:, 0]) * np.random.default_rng(0).random(
            (min(int(samples), 100), lk.d))
        lk(probe[:2])
        c = time.process_time()
        lk(probe)
        cost[r] = (time.process_time() - c) * int(samples) / probe.shape[0]
    # leave-one-out fits: the costlier reading's cost, by their share of the points
    share = {w: parts[f"without:{w}"].n_points / spec.n_points for k, w in plan if k == "without"}
    total = TMCMC_BATCHES * (sum(cost.values()) + max(cost.values()) * sum(share.values()))
    # prior draws cost more than posterior ones (cone, porcine ramps: 3-4x); the populations per fit vary
    # (TMCMC_BATCHES is typical, not a bound), so this is an estimate, not a limit
    say(f"plan: {len(plan)} TMCMC fits ({', '.join(f'{k} {_reading_name(w)}' for k, w in plan)}); estimate about "
        f"~{total / 60:.1f} min CPU (one population of {samples} evaluations at prior draws: "
        f"{', '.join(f'{_reading_name(r)} {v:.2f} s' for r, v in cost.items())}; a fit takes "
        f"~{TMCMC_BATCHES} populations)")
    folder = None if out is None else Path(out)
    tmcmc_options = {"max_steps": MAX_STEPS, **dict(tmcmc_options or {})}
    settings = {"samples": int(samples), "seed": int(seed), "fix": dict(fix or {}), "form": form,
                "max_evaluations": max_evaluations, "tmcmc_options": tmcmc_options,
                "reading_rule": {"min_nats": READING_MIN_NATS, "min_se": READING_MIN_SE},
                "lateral_alpha": LATERAL_ALPHA, "band_alpha": BAND_ALPHA}
    kw = dict(model=model, samples=samples, fix=fix, max_evaluations=max_evaluations, tmcmc_options=tmcmc_options,
              progress=progress)
    fits: dict[str, ModesFit] = {}
    paths: dict[str, Path] = {}
    stopped = None

    def late(name: str) -> bool:
        nonlocal stopped
        if max_time is not None and time.perf_counter() - t0 > max_time:
            stopped = (stopped or f"--max-time {max_time:g} s reached; not fitted:") + f" {name}"
            return True
        return False

    for k, r in enumerate(readings):
        name = f"joint_{_reading_name(r)}"
        if k and late(name):
            continue
        path = None if folder is None else folder / f"{name}.nc"
        say(f"fit {k + 1}/{len(plan)}: all tests, reading {r or 'axial (thesis form)'}")
        fits[_reading_name(r)] = fit_modes(spec, collagen3d=r, seed=_seed(seed, k), out=path,
                                       config_extra={"diagnose": name}, **kw)
        if path is not None:
            paths[name] = path
    ev = {r: (f.log_evidence, f.log_evidence_se) for r, f in fits.items()}
    cmp = {**compare_readings(ev), "differ": differ}
    reading = cmp["best"]
    best = fits[reading]
    lik_best = best.likelihood
    sigma = {kd: float(np.median(best.samples[:, lik_best.names.index(n)]))
             for kd, n in zip(lik_best.kinds, lik_best.noise_names)}
    held: dict[str, dict[str, Any]] = {}
    modes = list(spec.load_cases)
    for j, (kind, mode) in enumerate(p for p in plan if p[0] == "without"):
        name = f"without_{mode}"
        if late(name):
            continue
        m = modes.index(mode)
        trained_on = [x for x in modes if x != mode]
        say(f"fit {len(readings) + j + 1}/{len(plan)}: without the {mode} tests (reading {reading})")
        path = None if folder is None else folder / f"{name}.nc"
        f = fit_modes(parts[f"without:{mode}"], collagen3d=_collagen3d(reading),
                      seed=_seed(seed, 100 + m), out=path, config_extra={"diagnose": name}, **kw)
        if path is not None:
            paths[name] = path
        hl = make_modes_likelihood(model, parts[f"only:{mode}"], collagen3d=f.likelihood.energy.collagen3d
                                   if _collagen3d(reading) else None, fix=fix)
        rows = held_out_prediction(f, hl, sigma, _seed(seed, 200 + m))
        held[mode] = {"trained_on": trained_on, "fit": f, "series": rows,
                      "message": _held_sentence(mode, trained_on, rows)}
    for mode, missing in unpredictable.items():
        held[mode] = {"trained_on": [x for x in modes if x != mode], "fit": None, "series": [],
                      "message": f"{mode} not predicted from the other modes: its tests need {', '.join(missing)}, "
                                 "which they do not determine"}
    lateral = lateral_checks(spec)
    diag = ModesDiagnosis(spec.id, fits, cmp, reading, held, lateral, _verdicts(spec, best, held, lateral),
                          settings, stopped, time.process_time() - c0, time.perf_counter() - t0, paths)
    return diag
