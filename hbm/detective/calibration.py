"""Calibrated decisions: each statistic the verdict uses, against its own null on this file (issue 38).

A fixed threshold (10 nats for a generic shape alone, 5 for a named effect) means a different
false-alarm rate on every design: what a shape free to sit anywhere gains by chance grows with
the number of points, the protocol, the noise and the shape's freedom (the look-elsewhere
effect).  Here the null is simulated instead: the fitted base model plus the fitted noise model
(:meth:`hbm.likelihood.noise.NoiseModel.simulate`: iid, proportional, AR(1), ...) on the file's
own strains, times and histories, ``replicates`` times, and on every replicate the statistics of
the verdict are computed exactly as on the data:

* ``windows`` -- the largest smoothed-residual window score of the two scans (fitted and
  model-free noise, :func:`.noise_check.misfit_windows`), each divided by its pure-noise
  threshold and by the row's own noise level;
* one per generic shape (:mod:`.controls`) -- its likelihood gain at its optimum over a fine
  grid of shapes (the amplitude is linear: each shape's gain is a projection);
* one per physical candidate -- its likelihood gain at the optimum of the score test's linear
  alternatives (:func:`.screen.candidate_column_sets`: nuisance grid × secant steps, signs
  constrained where the null sits on a box edge; exact over the active sets);
* ``noise`` -- the disagreement of the fitted noise with the model-free estimate,
  max(log(σ_fit/σ_mf)/log 1.5, (ρ_fit − ρ_mf)/0.3) (≥ 1 is the fixed rule's "disagrees").

Every gain is that of a Gauss–Newton refit linearised at the base optimum, in the noise-whitened
units of the screen (the base's absorbable directions projected out), with the noise level
re-estimated as a refit does -- (n/2)·log(RSS₀/RSS₁): a statistic of every row in its own noise
level (studentised), so the maximum-likelihood noise level, low by a factor (n − p)/n on few
points, does not make the data look noisier than its replicates.  The cost is a few model
Jacobians, whatever the number of replicates.  A statistic's p-value is its rank among the
replicates; the family-wise level over all of them is held by the single-step min-p adjustment
(Westfall & Young): a statistic is significant when its p-value is below the ``alpha`` quantile of
the replicates' smallest p-value.  The Monte-Carlo resolution is 1/(replicates + 1).

The candidate and control statistics run in the diagnosis's worker processes (one task each, on
replicates drawn here from the seed table's ``calibration`` stream: the result does not depend on
the worker count), and the table of statistics is cached on disk under a key of the data, the
model, the fitted optimum and every setting (:mod:`hbm.io.identity`), never reused for other
inputs.
"""

from __future__ import annotations

import json
import math
import os
import tempfile
import time as _time
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Sequence

import numpy as np

from .._version import __version__
from ..io.identity import content_key, data_key, model_key, settings_key
from ..model.core import Effect
from ..runtime import seeds as _seeds
from .controls import controls_for
from ..errors import SettingError
from .inputs import SpecimenData, added_effects
from .noise_check import (
    NoiseCheck, _window_scales, _window_z, fitted_noise_parameters, misfit_windows, model_free_noise,
    window_threshold, whitener)
from .results import FitSummary
from .rules import CALIBRATION_ALPHA, CALIBRATION_REPLICATES, CONTROL_ALONE_MIN, DELTA_LOGZ_MIN
from .screen import absorbable_basis, candidate_column_sets

__all__ = ["Calibration", "CalibrationSetting", "calibrate", "calibrated_check", "calibration_setting",
           "calibration_record", "cache_dir", "CALIBRATION_CHOICES"]

#: ``calibration=`` choices of diagnose (``--calibration``)
CALIBRATION_CHOICES = ("on", "off")
#: the fixed rule's bounds of the noise disagreement (noise_check.noise_consistent)
_SD_RATIO, _RHO_DIFF = 1.5, 0.3
#: bump when a statistic changes: old cache entries are then never read
_FORMAT = 2


@dataclass(slots=True)
class Calibration:
    """The calibrated statistics of one greedy round.

    ``stats`` maps a statistic's name (``"windows"``, ``"noise"``, a control's or a candidate's
    name) to ``{"kind", "observed", "p", "p_family", "critical", "unit"}``: the observed value, its
    p-value among the replicates, its family-wise adjusted p-value and the value it must exceed to
    be significant at family-wise ``alpha``.
    """

    replicates: int
    alpha: float
    stats: dict
    p_family: float                # the smallest family-wise p-value (the verdict's)
    window_thresholds: dict        # scan -> calibrated threshold of its window z
    null: str                      # the simulated null, in words
    cached: bool = False
    key: str = ""
    seconds: float = 0.0
    order: list = field(default_factory=list)

    def significant(self, name: str) -> bool:
        """Is statistic ``name`` beyond its null at the family-wise level?  (False if absent.)"""
        s = self.stats.get(name)
        return bool(s is not None and s["p_family"] <= self.alpha)

    def strength(self, name: str) -> str:
        """Statistic ``name``'s calibrated strength in words, e.g. "p = 0.004, family-wise 0.03"."""
        s = self.stats.get(name)
        if s is None:
            return "not calibrated"
        return f"calibrated p {_p_text(s['p'], self.replicates)}, family-wise {_p_text(s['p_family'], self.replicates)}"

    def to_dict(self) -> dict:
        return {"method": "calibrated", "replicates": self.replicates, "alpha": self.alpha, "null": self.null,
                "p_family": self.p_family, "resolution": 1.0 / (self.replicates + 1),
                "window_thresholds": dict(self.window_thresholds), "cached": self.cached, "key": self.key,
                "statistics": {k: dict(self.stats[k]) for k in self.order}}

    def text(self) -> str:
        """The report's table: each statistic, its observed value, p-values and critical value."""
        lines = [f"calibration: {self.replicates} null replicates ({self.null}); family-wise {self.alpha:.0%} "
                 f"(Monte-Carlo resolution {1 / (self.replicates + 1):.4f}){' [cached]' if self.cached else ''}",
                 f"  {'statistic':<20}{'observed':>10}{'critical':>10}{'p':>9}{'family-wise p':>15}"]
        for k in self.order:
            s = self.stats[k]
            lines.append(f"  {k:<20}{s['observed']:>10.3g}{s['critical']:>10.3g}"
                         f"{_p_text(s['p'], self.replicates):>9}{_p_text(s['p_family'], self.replicates):>15}"
                         f"  {s['unit']}{'  *' if s['p_family'] <= self.alpha else ''}")
        return "\n".join(lines)


def _p_text(p: float, n: int) -> str:
    return f"<{1 / (n + 1):.3g}" if p <= 1.0 / (n + 1) + 1e-15 else f"{p:.3g}"


# =========================================================================================
# the statistics, on the observed row and every replicate row at once
# =========================================================================================
def _scan_max(z: np.ndarray, segment: np.ndarray, rho: float) -> np.ndarray:
    """The largest |window z| of :func:`.noise_check.misfit_windows`' scan, per row of ``z``."""
    rho = float(np.clip(rho, -0.95, 0.99))
    out = np.zeros(z.shape[0])
    for s in np.unique(segment):
        idx = np.flatnonzero(segment == s)
        if idx.size < 5:
            continue
        for _, zz in _window_z(z[:, idx], rho, _window_scales(idx.size)):
            out = np.maximum(out, np.abs(zz).max(axis=-1))
    return out


def _control_gain(ctl, d: SpecimenData, whiten, U: np.ndarray, Rw: np.ndarray) -> np.ndarray:
    """A control's likelihood gain at its optimum over its dense shape grid, per row of ``Rw``."""
    grid = ctl.dense_grid()
    q = {k: np.array([g[k] for g in grid])[:, None] for k in grid[0]}
    F = np.asarray(ctl.shape(d.loading, q), float) * np.ones((len(grid), d.stress.size))
    Fw = whiten(F.T)
    Fp = Fw - U @ (U.T @ Fw)
    nn = np.sum(Fp * Fp, axis=0)
    ok = nn > 1e-12 * max(float(nn.max(initial=0.0)), 1e-300)
    if not ok.any():
        return np.zeros(Rw.shape[0])
    return np.max(0.5 * (Rw @ Fp[:, ok]) ** 2 / nn[ok], axis=1)


def control_optimum(ctl, d: SpecimenData, whiten, U: np.ndarray, rw0: np.ndarray) -> dict[str, float]:
    """The shape of ``ctl``'s dense grid that fits the data's whitened residual ``rw0`` best, with
    its amplitude (MPa: whitening is linear, so the whitened fit's coefficient is the raw one)."""
    grid = ctl.dense_grid()
    q = {k: np.array([g[k] for g in grid])[:, None] for k in grid[0]}
    F = np.asarray(ctl.shape(d.loading, q), float) * np.ones((len(grid), d.stress.size))
    Fw = whiten(F.T)
    Fp = Fw - U @ (U.T @ Fw)
    nn = np.maximum(np.sum(Fp * Fp, axis=0), 1e-300)
    proj = rw0 @ Fp
    k = int(np.argmax(proj ** 2 / nn))
    return {ctl.amp: float(proj[k] / nn[k]), **grid[k]}


def _bounded_gain(A: np.ndarray, lb: np.ndarray, ub: np.ndarray, Rw: np.ndarray) -> np.ndarray:
    """Largest ½·(drop of ‖r‖²) of a linear fit of columns ``A`` with sign bounds, per row.

    Exact: the bounded least-squares optimum is the unconstrained fit on one subset of the
    columns (the rest at 0) whose coefficients obey the signs, so the best such subset is it."""
    k = A.shape[1]
    best = np.zeros(Rw.shape[0])
    for mask in range(1, 2 ** k):
        cols = [j for j in range(k) if mask >> j & 1]
        As = A[:, cols]
        beta = Rw @ np.linalg.pinv(As).T                      # (rows, |S|)
        ok = np.all((beta >= lb[cols] - 1e-12) & (beta <= ub[cols] + 1e-12), axis=1)
        Q, _ = np.linalg.qr(As)
        g = 0.5 * np.sum((Rw @ Q) ** 2, axis=1)
        best = np.where(ok & (g > best), g, best)
    return best


def _candidate_gain(e: Effect, model, theta_model: np.ndarray, d: SpecimenData, whiten, U: np.ndarray,
                    Rw: np.ndarray, ref: float) -> np.ndarray:
    """A physical candidate's likelihood gain at the optimum of the score test's alternatives, per row."""
    best = np.zeros(Rw.shape[0])
    for cs in candidate_column_sets(model, theta_model, e, whiten, d, U, ref):
        if cs["A"] is not None:
            best = np.maximum(best, _bounded_gain(cs["A"], cs["lb"], cs["ub"], Rw))
    return best


def _gain_task(kind: str, obj, model, theta_model, d, whiten, U, Rw, ref) -> np.ndarray:
    """One statistic's rows (a worker task: depends only on its arguments)."""
    g = _control_gain(obj, d, whiten, U, Rw) if kind == "control" else \
        _candidate_gain(obj, model, theta_model, d, whiten, U, Rw, ref)
    # rounding is no gain: a statistic that is 0 on every replicate must not be "significant" at 1e-15
    return np.where(g > 1e-9, g, 0.0)


def _lag1(z: np.ndarray, first: np.ndarray) -> np.ndarray:
    """Lag-1 autocorrelation of each row of ``z`` within histories (pairs not across a restart)."""
    pair = ~np.asarray(first, bool)[1:]
    a, b = z[:, :-1][:, pair], z[:, 1:][:, pair]
    return np.sum(a * b, axis=1) / np.maximum(np.sqrt(np.sum(a * a, axis=1) * np.sum(b * b, axis=1)), 1e-300)


# =========================================================================================
# the calibration
# =========================================================================================
def cache_dir() -> Path | None:
    """Folder of the calibration cache: ``$HBM_CACHE_DIR/calibration`` (default
    ``~/.cache/hbm/calibration``); ``HBM_CACHE_DIR=off`` disables the cache."""
    root = os.environ.get("HBM_CACHE_DIR")
    if root is not None and root.strip().lower() in ("off", "none", ""):
        return None
    return Path(root or Path.home() / ".cache" / "hbm") / "calibration"


def _cache_key(base: FitSummary, check: NoiseCheck, d: SpecimenData, names: list[str], extra: dict) -> str:
    settings = {"format": _FORMAT, "version": __version__, "theta": np.asarray(base.theta_max, float),
                "names": list(base.names), "noise": base.noise, "statistics": names,
                "whitening": {"sd": np.asarray(check.sd, float), "rho": float(check.rho)}, **extra}
    return content_key({"data": data_key(d.ds), "model": model_key(base.model), "settings": settings_key(settings)})


def _cache_read(key: str, names: list[str]) -> np.ndarray | None:
    folder = cache_dir()
    path = folder / f"{key}.npz" if folder is not None else None
    if path is None or not path.is_file():
        return None
    try:
        with np.load(path, allow_pickle=False) as z:
            if json.loads(str(z["names"])) != names:
                return None
            return np.asarray(z["table"], float)
    except (OSError, ValueError, KeyError):     # a damaged entry is recomputed
        return None


def _cache_write(key: str, names: list[str], table: np.ndarray) -> None:
    folder = cache_dir()
    if folder is None:
        return
    try:
        folder.mkdir(parents=True, exist_ok=True)
        # written whole, then renamed: a concurrent reader never sees half a file
        fd, tmp = tempfile.mkstemp(dir=folder, suffix=".npz.tmp")
        with os.fdopen(fd, "wb") as fh:
            np.savez(fh, table=table, names=json.dumps(names))
        os.replace(tmp, folder / f"{key}.npz")
    except OSError:      # a read-only home: the calibration is recomputed next time
        pass


def calibrate(base: FitSummary, check: NoiseCheck, candidates: Sequence[Effect], d: SpecimenData, seed: int,
              round_index: int = 0, replicates: int = CALIBRATION_REPLICATES, alpha: float = CALIBRATION_ALPHA,
              run_tasks=None) -> Calibration:
    """Simulate the null of ``base`` on this file and calibrate every statistic of the verdict.

    Parameters
    ----------
    base : FitSummary
        The fitted model (its optimum and its noise model generate the replicates).
    check : NoiseCheck
        The noise check at ``base`` (its residual, and the model-free whitening of the screen).
    candidates : sequence of Effect
        The physical candidates screened in this round.
    d : SpecimenData
        The specimen: its strains, times and histories are the design of every replicate.
    seed, round_index : int
        The run's root seed and the greedy round: the replicates come from the seed table's
        ``calibration`` stream ``round_index``.
    replicates : int
        Null replicates (the Monte-Carlo resolution of a p-value is 1/(replicates + 1)).
    alpha : float
        Family-wise level over all statistics.
    run_tasks : callable, optional
        ``run_tasks(task, calls)`` returns ``[task(*c) for c in calls]``, e.g. in the diagnosis's
        workers (one task per candidate or control).

    Returns
    -------
    Calibration
    """
    t0 = _time.perf_counter()
    lik, model = base.likelihood, base.model
    theta_model = np.asarray(lik.model_theta(base.theta_max[None, :]))[0]
    free = [n for n in lik.names if n in model.parameter_names]
    whiten = whitener(check.sd, check.rho, d.ar_first)
    U, Jb = absorbable_basis(model, theta_model, free, whiten, d)
    ctrls = controls_for(d)
    usable = []
    for e in candidates:
        try:
            mc = model.with_effects(e)
            mc.stress(d.loading, mc.null_theta(theta_model))
            usable.append(e)
        except Exception:     # noqa: BLE001 -- not applicable here (e.g. no time column): screened out too
            continue
    noise_par = fitted_noise_parameters(lik, base.theta_max)
    sd_fit = np.asarray(lik.noise_sd(base.theta_max[None, :]))[0]
    rho_fit = float(noise_par.get("rho", 0.0))
    sig_fit = float(np.median(sd_fit))
    hetero = np.ptp(sd_fit) > 1e-6 * max(sig_fit, 1e-300)
    names = ["windows", "noise"] + [c.name for c in ctrls] + [e.name for e in usable]
    kinds = ["windows", "noise"] + ["control"] * len(ctrls) + ["candidate"] * len(usable)
    key = _cache_key(base, check, d, names, {"seed": int(seed), "round": int(round_index),
                                              "replicates": int(replicates)})
    segs = [np.flatnonzero(d.segment == s) for s in np.unique(d.segment)]
    # the pure-noise thresholds of the two scans only scale the window statistic (it is calibrated)
    c_fit = window_threshold(segs, rho_fit, 0.05, 200, 0)
    c_mf = window_threshold(segs, check.rho, 0.05, 200, 0)
    # the data's own noise level in the screen's whitened units (the windows' threshold scales with it)
    rw0 = whiten(check.resid)
    rw0 = rw0 - U @ (U.T @ rw0)
    scale0 = math.sqrt(float(rw0 @ rw0) / max(d.stress.size - U.shape[1], 1))
    table = _cache_read(key, names)
    cached = table is not None
    if table is None:
        rng = _seeds.rng(seed, "calibration", round_index)
        nat = lik.to_natural(base.theta_max[None, :])
        q = np.repeat(nat[:, lik.n_model:], replicates, axis=0)
        pred = np.asarray(lik.predict(base.theta_max[None, :]))[0]
        noise = lik.noise_model.simulate(rng, q, np.repeat(pred[None, :], replicates, axis=0)
                                         if lik.noise_model.needs_model_stress else None)
        # row 0 the data, then the replicates: every statistic computed by one code path
        # linearised refit of the base on each replicate (generalised least squares, screen whitening),
        # along the directions the fit resolves (U's cutoff: a direction the data barely determine is
        # left in the data's residual by the optimiser, so it is left in the replicates' too)
        beta = np.linalg.pinv(whiten(Jb), rcond=1e-9) @ whiten(noise.T)
        R = np.vstack([check.resid[None, :], noise - (Jb @ beta).T])
        Rw = whiten(R.T).T
        Rw = Rw - (Rw @ U) @ U.T
        ref = float(np.linalg.norm(Rw[0]))
        # each row's own noise level (studentised): an ML noise level is low by (n - p)/n on few
        # points, which would make the data look noisier than every replicate
        S = np.sum(Rw * Rw, axis=1)
        scale = np.sqrt(S / max(d.stress.size - U.shape[1], 1))
        calls = [("control", c, model, theta_model, d, whiten, U, Rw, ref) for c in ctrls] + \
                [("candidate", e, model, theta_model, d, whiten, U, Rw, ref) for e in usable]
        gains = run_tasks(_gain_task, calls) if run_tasks is not None else [_gain_task(*c) for c in calls]
        # a gain with the noise level re-estimated, as a refit's Δmax log L: (n/2)·log(RSS0/RSS1)
        gains = [0.5 * d.stress.size * np.log(S / np.maximum(S - 2.0 * g, 1e-300 * S + 1e-300)) for g in gains]
        # windows: both scans, each over its pure-noise threshold, in the row's own noise level
        T_w = np.maximum(_scan_max(R / sd_fit, d.segment, rho_fit) / c_fit,
                         _scan_max(R / check.sd, d.segment, check.rho) / c_mf) / np.maximum(scale, 1e-300)
        # noise: the fitted noise (its level re-estimated on each replicate's residual) against the
        # model-free estimate of each replicate curve
        Y = np.vstack([d.stress[None, :], pred[None, :] + noise])
        mf = model_free_noise(Y, d.segment, scale=sd_fit / sig_fit if hetero else None)
        wfit = whitener(sd_fit, rho_fit, d.ar_first)
        s = np.sqrt(np.mean(wfit(R.T).T ** 2, axis=1))
        sig_rows = sig_fit * s / max(float(s[0]), 1e-300)
        if base.noise == "ar1":
            r1 = _lag1(R / sd_fit, d.ar_first)
            rho_rows = rho_fit + (r1 - r1[0])
        else:
            rho_rows = np.zeros(Y.shape[0])
        with np.errstate(divide="ignore", invalid="ignore"):
            T_n = np.maximum(np.log(sig_rows / mf["sigma"]) / math.log(_SD_RATIO), (rho_rows - mf["rho"]) / _RHO_DIFF)
        T_n = np.where(np.isfinite(T_n), T_n, -np.inf)
        table = np.column_stack([T_w, T_n] + list(gains))
        _cache_write(key, names, table)
    stats, p_fam = _pvalues(table, alpha)
    units = {"windows": "window z / pure-noise threshold (studentised)", "noise": "sd and rho disagreement (1: fixed rule)"}
    out = {}
    for j, (nm, kd) in enumerate(zip(names, kinds)):
        if kd == "noise" and not np.isfinite(table[0, j]):
            continue     # no model-free estimate (too few points per segment)
        out[nm] = {"kind": kd, "observed": float(table[0, j]), "p": stats[j][0], "p_family": stats[j][1],
                   "critical": stats[j][2], "unit": units.get(nm, "nats (likelihood gain at the optimum)")}
    for c in ctrls:
        # where the data's best shape of each control acts (the verdict locates a significant one
        # that was not refitted, e.g. a ripple's period)
        x = control_optimum(c, d, whiten, U, rw0)
        axis, lo, hi = c.region(x, d)
        out[c.name].update(optimum=x, region=[axis, lo, hi], detail=c.describe(x),
                           shape=c.description.split(": ")[-1])
    crit_w = out["windows"]["critical"]
    # the replicates draw from the fitted noise model itself (NoiseModel.simulate): t variates for
    # student_t, Gaussian bin means of sd/sqrt(count) for a reduced dense record (BinnedNoise)
    binned = getattr(lik.noise_model, "counts", None) is not None
    null = (f"the fitted {' + '.join(getattr(base, 'effects', []) or ['base'])} model with its fitted "
            f"{base.noise} noise on this file's strains, times and histories"
            + (" (bin means: each with the sd of its readings' mean)" if binned else ""))
    return Calibration(replicates=int(replicates), alpha=float(alpha), stats=out,
                       p_family=float(min(s["p_family"] for s in out.values())),
                       window_thresholds={"fitted": float(c_fit * crit_w * scale0),
                                          "model-free": float(c_mf * crit_w * scale0)},
                       null=null, cached=cached, key=key, seconds=_time.perf_counter() - t0, order=list(out))


def _pvalues(table: np.ndarray, alpha: float) -> tuple[list[tuple[float, float, float]], float]:
    """Per statistic (column): p-value of row 0 (the data) among all rows, its single-step min-p
    family-wise adjusted p-value, and the critical value (significant when observed > it).

    The data and the replicates are exchangeable under the null, so every row's p-value is its
    rank among all n + 1 rows, and the data's family-wise p-value is the share of rows whose
    smallest p-value is at most the data's: P(family-wise p <= alpha) <= alpha exactly, also at
    the resolution 1/(n + 1) (the data beating every replicate of one of m statistics has
    family-wise p about m/(n + 1), not 1/(n + 1)).

    Returns the list and the largest per-statistic p-value significant at ``alpha``."""
    n1 = table.shape[0]
    srt = np.sort(table, axis=0)
    ge = n1 - np.stack([np.searchsorted(srt[:, j], table[:, j], side="left") for j in range(table.shape[1])], axis=1)
    P = ge / n1                                   # each row's p-value per statistic (itself counted)
    min_p = np.min(P, axis=1)
    cand = np.sort(min_p)
    ok = np.arange(1, n1 + 1) / n1 <= alpha
    p_star = float(cand[ok][-1]) if ok.any() else 0.0
    null = np.sort(table[1:], axis=0)
    n = n1 - 1
    k = int(math.floor(p_star * n1 - 1 + 1e-9))   # significant iff #{replicates >= observed} <= k
    out = []
    for j in range(table.shape[1]):
        p = float(P[0, j])
        p_f = float(np.mean(min_p <= p + 1e-15))
        crit = float(null[n - 1 - k, j]) if 0 <= k < n else float("inf")
        out.append((p, p_f, crit))
    return out, p_star


def calibrated_check(check: NoiseCheck, cal: Calibration, base: FitSummary, d: SpecimenData) -> NoiseCheck:
    """The noise check with its two window scans at the calibrated thresholds (a window is
    significant exactly when the window statistic is, family-wise)."""
    lik = base.likelihood
    sd_fit = np.asarray(lik.noise_sd(base.theta_max[None, :]))[0]
    rho_fit = float(fitted_noise_parameters(lik, base.theta_max).get("rho", 0.0))
    w_fit, _ = misfit_windows(check.resid / sd_fit, d.strain, d.segment, rho_fit, test=d.test,
                              threshold=cal.window_thresholds["fitted"])
    w_mf, thr = misfit_windows(check.z, d.strain, d.segment, check.rho, test=d.test,
                               threshold=cal.window_thresholds["model-free"])
    for w in w_fit:
        w["noise"] = "fitted"
    for w in w_mf:
        w["noise"] = "model-free"
    noise = dict(check.noise)
    noise["calibrated"] = {"alpha": cal.alpha, **{k: cal.stats[k] for k in ("noise",) if k in cal.stats}}
    return replace(check, windows=sorted(w_fit + w_mf, key=lambda w: -abs(w["z"])), threshold=thr,
                   alpha=cal.alpha, noise=noise)


# =========================================================================================
# the setting of a diagnosis, and what its report says
# =========================================================================================
@dataclass(frozen=True, slots=True)
class CalibrationSetting:
    """How a diagnosis's rounds are calibrated: the run's root seed and the null replicates per
    round (``None`` in its place: the fixed thresholds)."""

    seed: int
    replicates: int


def calibration_setting(calibration: str, replicates: int, seed: int) -> CalibrationSetting | None:
    """``diagnose(calibration=..., replicates=...)`` checked (before any fit)."""
    if calibration not in CALIBRATION_CHOICES:
        raise SettingError(f"calibration: expected one of {', '.join(CALIBRATION_CHOICES)}, got {calibration!r}")
    if calibration == "off":
        return None
    if isinstance(replicates, bool) or not isinstance(replicates, (int, np.integer)) or replicates < 40:
        raise SettingError(f"replicates: expected an integer >= 40 (below, nothing can be significant at 5 %: a p-value is at least 2/(replicates + 1) family-wise), got {replicates!r}")
    return CalibrationSetting(int(seed), int(replicates))


def calibration_record(rounds: list[tuple[FitSummary, Calibration | None]], on: bool = True) -> dict:
    """What decided the verdict (``Diagnosis.calibration``): each greedy round's calibrated
    statistics (``rounds``: its base fit and calibration), or the fixed thresholds (``on``
    False: calibration switched off)."""
    cals = [c for _, c in rounds]
    if on and not any(c is not None for c in cals):
        return {"method": "none", "text": "no round was calibrated (a data problem is reported before any physics)"}
    if not any(c is not None for c in cals):
        return {"method": "fixed", "text": "decided by the fixed thresholds (calibration off): a generic shape "
                f"alone needs {CONTROL_ALONE_MIN:.0f} nats, a named effect {DELTA_LOGZ_MIN:.0f}, each window scan "
                "5 % family-wise"}
    text = [(f"round {k} (model {' + '.join(added_effects(b.model)) or 'base'}): " if len(cals) > 1 else "")
            + c.text() for k, (b, c) in enumerate(rounds) if c is not None]
    return {"method": "calibrated", "rounds": [c.to_dict() if c is not None else None for c in cals],
            "text": "\n".join(text)}
