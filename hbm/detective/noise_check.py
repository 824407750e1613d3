"""How noisy are the data, and where does the fitted model fail (steps 1 and 2 of the detective).

* :func:`model_free_noise` — (σ, ρ) from differences of the data alone, no model involved;
* :func:`noise_prior_box` — the prior box of the noise sd shared by every fit of a diagnosis;
* :func:`simulate_ar1` / :func:`whitener` — the AR(1) noise process and its inverse;
* :func:`misfit_windows` — the scan for strain windows with a significant smoothed residual;
* :func:`check_noise` — the step: the fitted noise against the model-free estimate, then the
  windows, calibrated with the noise the data show.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy import stats as _stats

from ..likelihood.noise import make_noise
from .inputs import SpecimenData
from .results import FitSummary, jsonable
from .rules import WINDOW_ALPHA

__all__ = ["model_free_noise", "noise_prior_box", "simulate_ar1", "whitener", "misfit_windows",
           "NoiseCheck", "check_noise"]


# =========================================================================================
# model-free noise estimate (difference based)
# =========================================================================================
# third-order difference: annihilates quadratic trends, so a smooth curve contributes little
_DIFF = np.array([1.0, -3.0, 3.0, -1.0]) / np.sqrt(20.0)


def _diff_var_factor(rho: float, lag: int) -> float:
    """Var(Σ a_j y_{i+j·lag}) / σ² for AR(1) noise with coefficient rho."""
    j = np.arange(_DIFF.size)
    return float(_DIFF @ _AR1.autocorrelation((1.0, rho), lag * np.abs(j[:, None] - j[None, :])) @ _DIFF)


def model_free_noise(stress: np.ndarray, segment: np.ndarray | None = None, max_lag: int = 4,
                     scale: np.ndarray | None = None) -> dict:
    """Noise sd and lag-1 autocorrelation from differences of the data alone.

    Third-order differences (which annihilate quadratic trends, so the smooth curve
    contributes little) at lags k = 1..``max_lag`` within each sampling segment have mean
    squares m_k = σ²·v_k(ρ) under AR(1) noise, v_k known in closed form.  (σ², ρ) are fitted to
    log m_k by least squares (σ² profiled, ρ on a grid): a Gasser/Rice-type difference
    estimator extended to AR(1).  The largest 5 % of squared differences are trimmed (with
    the matching correction) so that kinks (load reversals, onsets) do not dominate.
    Independent of any model, hence unaffected by a misfit that a fitted AR(1) might soak up.

    ``scale`` (optional, per point, > 0) is the *shape* of a heteroscedastic noise sd (e.g. the
    fitted proportional noise's sd / its median): each difference is divided by the scale at
    its centre, so the estimate is of the sd at scale 1 -- under the noise model's variance
    structure.  Without it the estimate is a root-mean-square sd, which exceeds the median sd
    of a proportional noise several-fold on curves spanning a decade of stress.

    ``stress`` may also be (replicates, n): every row is estimated at once (the calibration's
    null replicates, :mod:`.calibration`), each as it would be alone (to rounding).

    Returns
    -------
    dict with ``sigma``, ``rho`` and ``sigma_iid`` (σ from lag 1 assuming ρ = 0): floats, or
    arrays (replicates,) for a 2-D ``stress``.
    """
    y = np.asarray(stress, float)
    one = y.ndim == 1
    y = np.atleast_2d(y)
    n = y.shape[-1]
    seg = np.zeros(n, int) if segment is None else np.asarray(segment)
    w = np.ones(n) if scale is None else np.asarray(scale, float)
    lags, ms = [], []
    for lag in range(1, max_lag + 1):
        vals = []
        for s in np.unique(seg):
            ys, ws = y[:, seg == s], w[seg == s]
            m = ys.shape[-1] - 3 * lag
            if m <= 0:
                continue
            # the scale at the difference's centre (the mean of its two middle points)
            centre = 0.5 * (ws[lag: lag + m] + ws[2 * lag: 2 * lag + m])
            vals.append(sum(_DIFF[j] * ys[:, j * lag: j * lag + m] for j in range(4)) / centre)
        v = np.concatenate(vals, axis=-1) if vals else np.zeros((y.shape[0], 0))
        if v.shape[-1] < 8:
            break
        v2 = np.sort(v * v, axis=-1)[:, : max(1, int(0.95 * v.shape[-1]))]
        lags.append(lag)
        ms.append(v2.mean(axis=-1) / _TRIM_FACTOR)
    nan = np.full(y.shape[0], np.nan)
    sigma, rho, sigma_iid = nan.copy(), nan.copy(), nan.copy()
    if ms:
        ms_a = np.stack(ms, axis=-1)                       # (rows, lags)
        ok = ms_a[:, 0] > 0
        lm = np.log(np.where(ok[:, None], ms_a, 1.0))
        lv = _diff_var_table(tuple(lags))                  # (grid, lags)
        ls2 = np.mean(lm[:, None, :] - lv[None], axis=-1)  # (rows, grid): σ² profiled
        sse = np.sum((lm[:, None, :] - lv[None] - ls2[..., None]) ** 2, axis=-1)
        k = np.argmin(sse, axis=-1)                        # (the first of equal minima, as a loop)
        rows = np.arange(y.shape[0])
        # (scalar math per row: a 1-D estimate stays bitwise what it was)
        sigma = np.array([math.sqrt(math.exp(v)) if o else np.nan for v, o in zip(ls2[rows, k], ok)])
        rho = np.where(ok, _RHO_GRID[k], np.nan)
        sigma_iid = np.array([math.sqrt(v) if o else np.nan for v, o in zip(ms_a[:, 0], ok)])
    if one:
        return {"sigma": float(sigma[0]), "rho": float(rho[0]), "sigma_iid": float(sigma_iid[0])}
    return {"sigma": sigma, "rho": rho, "sigma_iid": sigma_iid}


#: ρ grid of the model-free estimate; E[x² | x² below its 95 % quantile] / E[x²] for a Gaussian x
_RHO_GRID = np.linspace(-0.5, 0.97, 148)
_TRIM_FACTOR = float(_stats.chi2.cdf(_stats.chi2.ppf(0.95, 1), 3) / 0.95)
_VAR_TABLES: dict[tuple[int, ...], np.ndarray] = {}


def _diff_var_table(lags: tuple[int, ...]) -> np.ndarray:
    """log v_k(ρ) on the ρ grid for the given lags (grid, lags), computed once."""
    if lags not in _VAR_TABLES:
        _VAR_TABLES[lags] = np.log([[_diff_var_factor(r, k) for k in lags] for r in _RHO_GRID])
    return _VAR_TABLES[lags]


def noise_prior_box(model_free: dict, stress: np.ndarray) -> tuple[float, float]:
    """Prior box of the noise sd: the model-free σ ×1/20 … ×20 (a fallback from the stress
    range when σ is unavailable).  Shared by every fit so that evidences are comparable."""
    s0 = model_free["sigma"] if np.isfinite(model_free["sigma"]) and model_free["sigma"] > 0 \
        else 1e-3 * max(np.ptp(stress), 1e-6)
    return (s0 / 20.0, s0 * 20.0)


# =========================================================================================
# the AR(1) noise process and its whitening
# =========================================================================================
#: the AR(1) noise model, for its autocorrelation rho**|lag| (hbm.likelihood.noise)
_AR1 = make_noise("ar1", history_starts=np.array([True]))  # autocorrelation needs no curve


def _single_history(n: int) -> np.ndarray:
    starts = np.zeros(int(n), bool)
    starts[0] = True
    return starts


def simulate_ar1(rng: np.random.Generator, shape: tuple[int, ...], rho: float) -> np.ndarray:
    """Stationary AR(1) noise with unit marginal variance along the last axis of ``shape``
    (rows × points): :meth:`hbm.likelihood.noise.AR1Noise.standard_draws`, the one implementation.

    x_0 = e_0, x_t = ρ·x_{t−1} + √(1 − ρ²)·e_t with e iid N(0, 1) drawn from ``rng`` (one
    ``standard_normal`` call, also for ρ = 0, so the stream does not depend on ρ).
    :func:`whitener` inverts it exactly.
    """
    rows, n = int(np.prod(shape[:-1], dtype=int)), int(shape[-1])
    draws = make_noise("ar1", history_starts=_single_history(n)).standard_draws(rng, (1.0, float(rho)), n=rows)
    return draws.reshape(shape)


def whitener(sd: np.ndarray, rho: float, first: np.ndarray):
    """Function mapping (n,) or (n, k) arrays to noise-whitened units
    (:meth:`hbm.likelihood.noise.AR1Noise.whiten` with the given marginal sd).

    Divides by the marginal sd, then for AR(1) takes innovations (u_t = (z_t − ρ z_{t−1})/√(1−ρ²),
    u = z where the process restarts, ``first``), which makes the noise iid N(0, 1).
    """
    return _Whitener(np.asarray(sd, float), float(rho), np.asarray(first, bool))


class _Whitener:
    """:func:`whitener`'s function as a small object (it crosses to worker processes pickled)."""

    def __init__(self, sd: np.ndarray, rho: float, first: np.ndarray):
        self.sd, self.rho, self.first = sd, rho, first
        self.noise = make_noise("ar1", history_starts=first)

    def __call__(self, a):
        return self.noise.whiten(a, (np.nan, self.rho), sd=self.sd)


# =========================================================================================
# misfit windows
# =========================================================================================
def _window_scales(n: int) -> list[int]:
    scales, w = [], 5
    while w <= max(5, n // 2):
        scales.append(w)
        w = int(round(w * 1.6))
    return scales


def _window_z(z: np.ndarray, rho: float, scales: list[int]) -> list[tuple[int, np.ndarray]]:
    """Standardised moving means of z (..., n) for each window length, under AR(1) rho."""
    out = []
    cs = np.concatenate([np.zeros(z.shape[:-1] + (1,)), np.cumsum(z, axis=-1)], axis=-1)
    for w in scales:
        if w > z.shape[-1]:
            continue
        k = np.arange(1, w)
        var = (w + 2.0 * np.sum((w - k) * _AR1.autocorrelation((1.0, rho), k))) / (w * w)  # var of a w-point mean
        m = (cs[..., w:] - cs[..., :-w]) / w
        out.append((w, m / math.sqrt(var)))
    return out


def misfit_windows(z: np.ndarray, strain: np.ndarray, segment: np.ndarray, rho: float, *,
                   alpha: float = WINDOW_ALPHA, n_sim: int = 400, seed: int = 0,
                   test: np.ndarray | None = None, threshold: float | None = None) -> tuple[list[dict], float]:
    """Strain windows where the smoothed standardised residual is significantly non-zero.

    Parameters
    ----------
    z : array (n,)
        Residuals divided by the marginal noise sd (not whitened: the smoothing averages the
        correlated noise and its variance is computed for AR(1) ``rho``).
    strain, segment : arrays (n,)
        Strain of each point and the sampling segment (noise correlation runs within).
    rho : float
        Lag-1 noise autocorrelation (0 for iid).  The effective sample size of a w-point
        window is smaller for rho > 0; the variance formula accounts for it.
    alpha : float
        Family-wise false-alarm rate over all windows, scales and segments; the threshold is
        the (1 − alpha) quantile of the maximum |z| of simulated AR(1) noise scanned the same way.
    n_sim : int
        Simulated noise series per segment.
    seed : int
        Seed of the simulation.
    test : array (n,), optional
        Test ids (reported per window; the segment id otherwise).
    threshold : float, optional
        A threshold calibrated before for the same sampling and ``rho`` (skips the simulation).

    Returns
    -------
    windows : list of dict
        ``eps_lo, eps_hi, sign, z, test, i0, i1`` (merged overlapping windows of equal sign).
    threshold : float
    """
    rho = float(np.clip(rho, -0.95, 0.99))
    segs = [np.flatnonzero(segment == s) for s in np.unique(segment)]
    thr = window_threshold(segs, rho, alpha, n_sim, seed) if threshold is None else float(threshold)
    found = []
    for idx in segs:
        n = idx.size
        if n < 5:
            continue
        for w, zz in _window_z(z[idx], rho, _window_scales(n)):
            for i in np.flatnonzero(np.abs(zz) > thr):
                found.append((idx[i], idx[i + w - 1], int(np.sign(zz[i])), float(zz[i]), int(segment[idx[i]])))
    # merge overlapping windows of the same sign in the same segment; keep the strongest z
    found.sort(key=lambda t: (t[4], t[2], t[0]))
    merged: list[list] = []
    for a, b, s, zval, sg in found:
        if merged and merged[-1][4] == sg and merged[-1][2] == s and a <= merged[-1][1]:
            m = merged[-1]
            m[1] = max(m[1], b)
            if abs(zval) > abs(m[3]):
                m[3] = zval
        else:
            merged.append([a, b, s, zval, sg])
    out = []
    for a, b, s, zval, sg in merged:
        e = strain[a: b + 1]
        t = test[a] if test is not None else sg
        out.append({"eps_lo": float(e.min()), "eps_hi": float(e.max()), "sign": s, "z": zval,
                    "test": jsonable(t), "i0": int(a), "i1": int(b)})
    out.sort(key=lambda d: -abs(d["z"]))
    return out, thr


def window_threshold(segs: list[np.ndarray], rho: float, alpha: float, n_sim: int, seed: int) -> float:
    """(1 − alpha) quantile of the scan's maximum |z| over simulated AR(1) noise (vectorised
    over ``n_sim`` replicates), for segments of the given index arrays."""
    rng = np.random.default_rng(seed)
    sim_max = np.zeros(n_sim)
    for idx in segs:
        n = idx.size
        if n < 5:
            continue
        for _, zz in _window_z(simulate_ar1(rng, (n_sim, n), rho), rho, _window_scales(n)):
            sim_max = np.maximum(sim_max, np.abs(zz).max(axis=-1))
    return float(np.quantile(sim_max, 1 - alpha)) if np.any(sim_max > 0) else float("inf")


def smoothed_residual(z: np.ndarray, segment: np.ndarray, width: int) -> np.ndarray:
    """Moving average of z within segments (for plotting)."""
    out = np.empty_like(z)
    for s in np.unique(segment):
        idx = np.flatnonzero(segment == s)
        w = max(1, min(width, idx.size))
        k = np.ones(w) / w
        num = np.convolve(z[idx], k, mode="same")
        den = np.convolve(np.ones(idx.size), k, mode="same")
        out[idx] = num / den
    return out


# =========================================================================================
# the step
# =========================================================================================
@dataclass(slots=True)
class NoiseCheck:
    """The base fit's residuals, the noise they are judged against, and the misfit windows."""

    noise: dict            # what Diagnosis.noise reports (fitted, model-free, which one is used)
    pred: np.ndarray       # prediction of the base fit at its optimum
    resid: np.ndarray      # data − prediction
    sd: np.ndarray         # marginal noise sd per point the data show (model-free level, fitted shape)
    rho: float             # lag-1 noise correlation the data show (model-free)
    z: np.ndarray          # resid / sd
    windows: list          # misfit windows of both scans (dicts of :func:`misfit_windows`), strongest first
    threshold: float       # family-wise threshold of the model-free scan
    alpha: float = WINDOW_ALPHA

    def residual_curve(self, predictive: dict, segment: np.ndarray) -> dict:
        """What the diagnosis figure draws: prediction, residuals, smoothed z and the band."""
        smooth_w = max(5, self.z.size // 20)
        return {"pred": self.pred, "resid": self.resid, "z": self.z, "threshold": self.threshold,
                "smoothed": smoothed_residual(self.z, segment, smooth_w),
                "lower": predictive["lower"], "upper": predictive["upper"], "rho_window": self.rho}

    def remaining_windows(self, fit: FitSummary, d: SpecimenData) -> list[dict]:
        """Misfit windows of another fit's residuals, scanned like the model-free scan."""
        pred = np.asarray(fit.likelihood.predict(fit.theta_max[None, :]))[0]
        w, _ = misfit_windows((d.stress - pred) / self.sd, d.strain, d.segment, self.rho, test=d.test,
                              threshold=self.threshold)
        return w


def fitted_noise_parameters(lik, x) -> dict:
    """The noise parameters (not the model's) of the free vector ``x`` of ``lik``."""
    return {n: float(v) for n, v in zip(lik.names, np.asarray(x, float)) if n not in lik.model.parameter_names}


def noise_consistent(sig_fit: float, rho_fit: float, mf: dict) -> bool:
    """Is the fitted noise free of signs of a systematic misfit?

    One-sided: a misfit inflates the fitted sd (above ×1.5 the model-free σ) or correlates the
    residuals (fitted ρ more than 0.3 above the model-free ρ).  The reverse -- a fit *less*
    noisy than the model-free estimate -- happens on coarse, strongly curved samplings, where
    third differences keep some of the curve; it is no sign of misfit.
    """
    if not np.isfinite(mf["sigma"]) or not mf["sigma"] > 0:
        return True
    return bool(sig_fit / mf["sigma"] < 1.5 and rho_fit - mf["rho"] < 0.3)


def noise_comparison(sig_fit: float, rho_fit: float, mf: dict) -> str:
    """The fitted noise against the model-free estimate, in words that claim only what was
    compared: "undefined" when the estimate could not be formed, the ratio otherwise."""
    if not np.isfinite(mf.get("sigma", np.nan)) or not mf["sigma"] > 0:
        return "no model-free noise estimate (too few points per segment): the fitted noise is not cross-checked"
    ratio = sig_fit / mf["sigma"]
    under = f", under {mf['under']}" if mf.get("under") else ""
    if 1 / 1.5 <= ratio <= 1.5 and abs(rho_fit - mf["rho"]) < 0.3:
        return (f"fitted noise sd {sig_fit:.3g} agrees with the model-free estimate {mf['sigma']:.3g}{under} "
                f"(ratio {ratio:.2f}; rho {rho_fit:.2f} vs {mf['rho']:.2f})")
    below = ("; a fit less noisy than the difference estimate is no sign of misfit (the differences of a "
             "coarsely sampled, curved record keep some curve)" if ratio < 1 / 1.5 else "")
    return (f"fitted noise sd {sig_fit:.3g} vs model-free estimate {mf['sigma']:.3g}{under} (ratio {ratio:.2f}; "
            f"rho {rho_fit:.2f} vs {mf['rho']:.2f}){below}")


def check_noise(base: FitSummary, model_free: dict, d: SpecimenData, seed: int,
                alpha: float = WINDOW_ALPHA) -> NoiseCheck:
    """Cross-check the fitted noise with the model-free estimate, then scan for misfit windows.

    Two scans, each at family-wise rate ``alpha``/2: under the chosen (fitted) noise model, and
    under the noise the *data* show -- the model-free level and ρ where they are below the fit's
    (white noise unless the differences show correlation; the fitted shape of a
    heteroscedastic sd).  A fitted AR(1)
    that soaks up a real misfit therefore cannot hide it: the second scan still sees it.  The
    screen whitens with the model-free noise too.
    """
    lik = base.likelihood
    noise_par = fitted_noise_parameters(lik, base.theta_max)
    sd = np.asarray(lik.noise_sd(base.theta_max[None, :]))[0]
    if lik.noise_model.robust:
        # a heavy-tailed noise chosen on purpose: an outlying row gets the sd of its weight, so the
        # windows and the screens are as robust as the fit (hbm.likelihood.student_t)
        q = lik.to_natural(base.theta_max[None, :])[:, lik.n_model:]
        resid0 = d.stress - np.asarray(lik.predict(base.theta_max[None, :]))[0]
        sd = np.asarray(lik.noise_model.effective_sd(q, resid0[None, :]))[0]
    rho_fit = float(noise_par.get("rho", 0.0))
    mf = model_free
    noise = {"model": base.noise, **noise_par, "bic": base.noise_bic, "model_free": mf,
             "evidence": dict(base.noise_evidence)}
    sig_fit = float(np.median(sd))
    if np.ptp(sd) > 1e-6 * max(sig_fit, 1e-300):
        # a heteroscedastic noise model: estimate the model-free level under its variance shape,
        # so that a fitted sd is compared with the same quantity (the sd at the median scale)
        mf = {**model_free_noise(d.stress, d.segment, scale=sd / max(sig_fit, 1e-300)),
              "under": f"the fitted {base.noise} variance shape"}
        noise["model_free_scaled"] = mf
    consistent = noise_consistent(sig_fit, rho_fit, mf)
    noise["consistent"] = consistent
    noise["comparison"] = noise_comparison(sig_fit, rho_fit, mf)
    if not consistent:
        noise["note"] = ("fitted noise differs from the model-free estimate (sd {:.3g} vs {:.3g}, rho {:.2f} vs "
                         "{:.2f}): a systematic misfit is probably inflating/correlating the residuals"
                         .format(sig_fit, mf["sigma"], rho_fit, mf["rho"]))
    pred = np.asarray(lik.predict(base.theta_max[None, :]))[0]
    resid = d.stress - pred
    if np.isfinite(mf["sigma"]) and mf["sigma"] > 0:
        # the noise cannot exceed what the residuals show: a model-free estimate above the fit's
        # is contaminated by curvature (coarse sampling), so the smaller of the two is used
        rho_mf = float(np.clip(min(mf["rho"], rho_fit), 0.0, 0.95))
        sd_mf = sd * (min(mf["sigma"], sig_fit) / max(sig_fit, 1e-300))
    else:
        rho_mf, sd_mf = rho_fit, sd
    noise["windows_use"] = {"source": "fit and model-free", "sigma": float(np.median(sd_mf)), "rho": rho_mf}
    w_fit, _ = misfit_windows(resid / sd, d.strain, d.segment, rho_fit, alpha=alpha / 2, seed=seed, test=d.test)
    zres = resid / sd_mf
    w_mf, thr = misfit_windows(zres, d.strain, d.segment, rho_mf, alpha=alpha / 2, seed=seed + 1, test=d.test)
    for w in w_fit:
        w["noise"] = "fitted"
    for w in w_mf:
        w["noise"] = "model-free"
    windows = sorted(w_fit + w_mf, key=lambda w: -abs(w["z"]))
    return NoiseCheck(noise=noise, pred=pred, resid=resid, sd=sd_mf, rho=rho_mf, z=zres, windows=windows,
                      threshold=thr, alpha=alpha)
