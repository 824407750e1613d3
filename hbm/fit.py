"""Fit one specimen: CMA-ES optima, TMCMC posterior with evidence, posterior predictive, Sobol.

:func:`fit_specimen` is the unit of work of the six-rat workflow (one dask task per specimen)
and of ``hbm fit``.  Every random stream is spawned from one ``SeedSequence(seed)`` so a fit is
reproducible bit for bit, wherever it runs:

=========  ======================================================
child 0    CMA-ES restarts and the bound sweep (hbm.optimize)
child 1    TMCMC (hbm.samplers.tmcmc)
child 2    posterior-predictive noise
child 3    Sobol sampling (hbm.sensitivity)
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

from . import sensitivity as _sens
from ._version import __version__
from .data import input_line, input_summary
from .errors import HbmError, HbmWarning
from . import seeds
from .io import SpecimenResult, json_default, write_specimen_result
from .collapse import choose_tier, fit_collapsed
from .likelihood import make_likelihood
from .model import COMBINATIONS, identifiable_combinations, spyrou_model
from .model.spyrou import PHYSICAL_RANGE
from .noise import get_noise
from .prior import Prior, PriorError, load_prior
from .optimization import optimize as _cma
from .samplers.tmcmc import tmcmc as _tmcmc
from .validation import check_physical_bounds, check_seed

__all__ = ["FitResult", "fit_specimen", "summarize", "summary_table", "pointwise_log_likelihood",
           "posterior_predictive", "parse_sweep", "edges", "COMBINATIONS", "at_bounds", "map_estimate", "fit_quality",
           "format_at_bounds", "map_prediction", "quality_lines", "tier_line", "EDGE_TOL", "EDGE_MASS",
           "RIDGE_NOTE"]

#: a value lies "at" a box edge within this fraction of the box width (log width for loguniform)
EDGE_TOL = 0.02
#: posterior mass near one edge above which the edge is reported
EDGE_MASS = 0.2
#: why the raw-parameter table is not a parameter set (printed right above it)
RIDGE_NOTE = ("raw parameters: posterior means are NOT a parameter set -- along non-identified directions the "
              "posterior is a curved ridge whose means lie off it; use the MAP or the combinations above")



def parse_sweep(sweep: str | tuple | None) -> tuple[str, float] | None:
    """``"VOLF:0.05"`` -> ("VOLF", 0.05)."""
    if sweep is None or sweep == "" or sweep is False:
        return None
    if isinstance(sweep, (tuple, list)):
        name, width = sweep
    else:
        name, _, width = str(sweep).partition(":")
        if not width:
            raise HbmError(f"sweep: expected PARAM:WIDTH (e.g. VOLF:0.05), got {sweep!r}")
    try:
        width = float(width)
    except ValueError:
        raise HbmError(f"sweep: width must be a number, got {width!r}") from None
    if not width > 0:
        raise HbmError(f"sweep: width must be > 0, got {width}")
    return str(name), width


# ----------------------------------------------------------------------------- pieces
def pointwise_log_likelihood(likelihood, theta: np.ndarray, model_stress: np.ndarray | None = None) -> np.ndarray:
    """Pointwise log-likelihood (n, p) whose row sums equal ``likelihood(theta)``.

    Delegates to the noise model (:meth:`hbm.noise.NoiseModel.pointwise`): for AR(1) noise the
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

    The noise is drawn by the noise model (:meth:`hbm.noise.NoiseModel.simulate`, AR(1)
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
    """CMA-ES restarts (+ an optional bound sweep) through :func:`hbm.optimization.optimize`."""
    names = list(likelihood.names)
    optima = _normalise_optima(_cma(likelihood, restarts=restarts, seed=seed, **options), names, "restart")
    if sweep is not None:
        sw = _cma(likelihood, restarts=1, seed=seed + 1, sweep=sweep, **options)
        optima += _normalise_optima(sw, names, "sweep")
    return optima


def run_sobol(model, data, *, n: int, seed: int, fix=None, bounds=None, qoi: str = "log_integrated_stress") -> dict:
    """Sobol indices over the prior box (:func:`hbm.sensitivity.sobol`) as a plain dict for io.

    The QoI is log W (the energy on a log scale): its estimator is stable at N = 1024 where the
    raw energy's is not (see :mod:`hbm.sensitivity`).
    """
    res = _sens.sobol(model, data=data, n=n, seed=seed, fix=fix, bounds=bounds, qoi=qoi, per_point=True)
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


# ----------------------------------------------------------------------------- summaries
def summarize(result: SpecimenResult, *, prob: float = 0.9) -> dict[str, dict[str, float]]:
    """Posterior mean, sd and central ``prob`` interval per free parameter and combination.

    Returns
    -------
    dict
        ``{name: {"mean", "sd", "lower", "upper", "median"}}``; parameters first, then the
        identifiable combinations (when the model has VOLF, P1, T1, GF, GM).
    """
    cols = result.as_dict()
    q = [(1 - prob) / 2, 0.5, (1 + prob) / 2]
    out: dict[str, dict[str, float]] = {}

    def stats(x):
        lo, med, hi = np.quantile(x, q)
        return {"mean": float(np.mean(x)), "sd": float(np.std(x, ddof=1)) if x.size > 1 else 0.0,
                "lower": float(lo), "median": float(med), "upper": float(hi)}

    for nm in result.names:
        out[nm] = stats(cols[nm])
    needed = ("VOLF", "P1", "T1", "GF", "GM")
    if all(k in cols for k in needed):
        names = list(cols)
        combos = identifiable_combinations(names, np.column_stack([cols[k] for k in names]))
        for k in COMBINATIONS:
            if k in combos:
                out[k] = stats(np.asarray(combos[k], float))
    return out


def summary_table(result: SpecimenResult, *, prob: float = 0.9) -> str:
    """Plain-text table of :func:`summarize` plus the log-evidence, the prior and box-edge warnings."""
    result = _spec(result)
    s = summarize(result, prob=prob)
    pc = int(round(prob * 100))
    lines = [f"specimen {result.specimen_id}: {result.n_samples} posterior samples, "
             f"log-evidence {result.log_evidence:.3f} ± {result.log_evidence_se:.3f}",
             f"{'quantity':<14}{'mean':>12}{'sd':>12}{f'{pc}% lower':>12}{f'{pc}% upper':>12}"]
    for k, v in s.items():
        if k == COMBINATIONS[0]:
            lines.append("-- identifiable combinations")
        lines.append(f"{k:<14}{v['mean']:>12.5g}{v['sd']:>12.4g}{v['lower']:>12.5g}{v['upper']:>12.5g}")
    if result.fixed:
        lines.append("fixed: " + ", ".join(f"{k}={v:g}" for k, v in result.fixed.items()))
    lines.append(_prior_line(result))
    lines += format_at_bounds(result.at_bounds if result.at_bounds is not None else at_bounds(result))
    return "\n".join(lines)


# ----------------------------------------------------------------------------- fit quality
def _spec(result) -> SpecimenResult:
    """The stored result of a :class:`FitResult` or a :class:`SpecimenResult` itself."""
    return result.result if isinstance(result, FitResult) else result


def _prior_of(r: SpecimenResult) -> dict[str, dict[str, Any]]:
    return r.prior_dict()


def _map_row(r: SpecimenResult) -> tuple[np.ndarray, float, str, int | None]:
    """(free-parameter vector in ``r.names`` order, its log-likelihood, source, sample index).

    The highest-likelihood point among the posterior samples and the CMA-ES optima (whose
    objective is −log-likelihood).  The prior is uniform in the sampler's coordinates, so this
    is the posterior mode there (for an all-uniform prior: the MAP in natural units).
    """
    ll = np.asarray(r.log_likelihood, float)
    j = int(np.nanargmax(np.where(np.isfinite(ll), ll, -np.inf))) if ll.size and np.isfinite(ll).any() else 0
    best = (np.asarray(r.samples[j], float), float(ll[j]) if ll.size else -np.inf, "sample", j)
    for o in r.optima or []:
        p = o.get("params", {})
        f = float(o.get("objective", np.nan))
        if all(n in p for n in r.names) and np.isfinite(f) and -f > best[1]:
            best = (np.array([float(p[n]) for n in r.names]), -f, "optimum", None)
    return best


def map_estimate(result) -> dict[str, float]:
    """The best fit as a usable parameter set ``{name: value}`` (natural units).

    The highest-likelihood point among the posterior samples and the CMA-ES optima, with the
    fixed parameters added: model parameters (model order of the result) then noise parameters.
    Unlike the posterior means, this vector lies on the posterior ridge.

    Parameters
    ----------
    result : FitResult or SpecimenResult

    Returns
    -------
    dict
    """
    r = _spec(result)
    row, _, _, _ = _map_row(r)
    out = {k: float(v) for k, v in r.fixed.items()}
    out.update({n: float(v) for n, v in zip(r.names, row)})
    return out


def _edge_coords(x: np.ndarray, lo: float, hi: float, form: str) -> tuple[np.ndarray, float, float]:
    """Values and box in the coordinates where the prior is flat (log for loguniform)."""
    if form == "loguniform":
        with np.errstate(divide="ignore", invalid="ignore"):
            return np.log(x), float(np.log(lo)), float(np.log(hi))
    return x, lo, hi


def at_bounds(result, *, tol: float = EDGE_TOL, mass: float = EDGE_MASS, noise: bool = False) -> list[dict[str, Any]]:
    """Parameters whose best fit or posterior mass sits on a box edge.

    An edge is reported when the MAP (:func:`map_estimate`) lies within ``tol`` of the box width
    of it (log width for loguniform parameters), or when more than ``mass`` of the posterior
    samples do.

    Parameters
    ----------
    result : FitResult or SpecimenResult
    tol : float
        Distance to the edge, as a fraction of the (log) box width.
    mass : float
        Posterior fraction near one edge above which it is reported.
    noise : bool
        Check the noise parameters too.  Off by default: their box runs from a numerical floor
        (1e-4) to half the peak stress, so a well-determined sigma of a clean curve lies
        "within 2 % of the width" of the floor without anything being cut off.

    Returns
    -------
    list of dict
        One per (parameter, edge): ``parameter``, ``side`` ("lower"/"upper"), ``edge`` (the
        edge value, natural units), ``fraction`` (posterior mass within ``tol`` of it) and
        ``map_at_edge`` (bool).  Empty when nothing is at an edge.
    """
    r = _spec(result)
    row, _, _, _ = _map_row(r)
    skip = () if noise else set(_noise_names(r))
    return edges(r.names, _prior_of(r), row, r.samples, tol=tol, mass=mass, skip=skip)


def edges(names: Sequence[str], prior: Mapping[str, Mapping[str, Any]], best, samples, *,
          tol: float = EDGE_TOL, mass: float = EDGE_MASS, skip: Sequence[str] = ()) -> list[dict[str, Any]]:
    """The rule of :func:`at_bounds` for any fit: a best point, samples and per-parameter boxes.

    Parameters
    ----------
    names : sequence of str
        Columns of ``best`` and ``samples``.
    prior : {name: {"lo", "hi", "form"}}
        Boxes (and forms) of the parameters to check; names not listed are skipped.
    best : array (d,)
        The best fit (natural units).
    samples : array (n, d) or None
        Posterior samples (natural units); ``None`` checks the best fit only.
    """
    best = np.asarray(best, float)
    samples = np.empty((0, len(names))) if samples is None else np.asarray(samples, float)
    out = []
    for i, n in enumerate(names):
        if n not in prior or n in skip:
            continue
        p = prior[n]
        x, a, b = _edge_coords(samples[:, i], float(p["lo"]), float(p["hi"]), p["form"])
        xm, _, _ = _edge_coords(best[i:i + 1], float(p["lo"]), float(p["hi"]), p["form"])
        w = tol * (b - a)
        for side, near, near_map, edge in (("lower", x <= a + w, xm[0] <= a + w, p["lo"]),
                                           ("upper", x >= b - w, xm[0] >= b - w, p["hi"])):
            frac = float(np.mean(near)) if x.size else 0.0
            if frac > mass or bool(near_map):
                out.append({"parameter": n, "side": side, "edge": float(edge), "fraction": frac,
                            "map_at_edge": bool(near_map)})
    return out


def format_at_bounds(items: Sequence[Mapping[str, Any]]) -> list[str]:
    """One warning line per :func:`at_bounds` entry."""
    return [f"warning: {a['parameter']} at its {a['side']} bound {a['edge']:g}: "
            f"{100 * a['fraction']:.0f}% of the posterior within {100 * EDGE_TOL:g}% of the box width"
            + ("; the best fit is there too" if a.get("map_at_edge") else "")
            + " -- widen the prior (--prior / --bounds) if the physics allows" for a in items]


def _noise_names(r: SpecimenResult, likelihood=None) -> list[str]:
    if likelihood is not None:
        return list(likelihood.noise_names)
    try:
        cand = get_noise(str(r.config.get("noise", "iid"))).names
    except HbmError:
        cand = ()
    return [n for n in r.names if n in cand]


def _map_prediction(r: SpecimenResult, likelihood, row, source, j) -> np.ndarray | None:
    """Noise-free model stress at the MAP: from the likelihood, else the stored sample prediction."""
    if likelihood is not None:
        return np.asarray(likelihood.predict(likelihood.from_natural(np.asarray(row, float))[None])[0], float)
    if r.predictive_model is None:
        return None
    if source != "sample":  # no model at hand: the best *sample* stands in for the optimum
        ll = np.asarray(r.log_likelihood, float)
        j = int(np.nanargmax(np.where(np.isfinite(ll), ll, -np.inf)))
    return np.asarray(r.predictive_model[j], float)


def map_prediction(result, likelihood=None) -> np.ndarray | None:
    """Noise-free model stress (p,) at the MAP (:func:`map_estimate`).

    Evaluated with ``likelihood`` (a :class:`FitResult` brings its own); from a stored result
    alone, the best posterior sample's stored prediction (None without one).
    """
    r = _spec(result)
    if likelihood is None and isinstance(result, FitResult):
        likelihood = result.likelihood
    row, _, source, j = _map_row(r)
    return _map_prediction(r, likelihood, row, source, j)


def fit_quality(result, data=None, *, likelihood=None, prob: float = 0.9) -> dict[str, Any]:
    """How well the fit reproduces the data -- the numbers to read before any parameter.

    Parameters
    ----------
    result : FitResult or SpecimenResult
        A :class:`FitResult` brings its likelihood (the MAP curve is then evaluated exactly);
        from a stored :class:`SpecimenResult` the best posterior sample's stored prediction is
        used when the best optimum cannot be evaluated.
    data : xarray.Dataset, optional
        Observed curve (variable ``stress``); default the data stored in the result.
    likelihood : Likelihood, optional
        Overrides the FitResult's.
    prob : float
        Central mass of the predictive band and of the combinations' intervals (0.9).

    Returns
    -------
    dict
        ``rmse`` (MPa, MAP curve vs data), ``rmse_rel`` (fraction of the peak |stress|; every
        share in hbm's JSON is a fraction), ``coverage90`` (fraction of observed points inside the
        central 90 % band of the noisy posterior predictive; None without a stored predictive),
        ``coverage`` and ``coverage_prob`` (the same at ``prob``), ``n_points``,
        ``noise`` ({name: {"map", "median", "lower", "upper"}}), ``map`` ({name: value}, a usable
        parameter set), ``map_source`` ("sample" or "optimum"), ``map_log_likelihood``,
        ``combinations`` ({name: {"median", "lower", "upper"}}), ``log_evidence``,
        ``log_evidence_se``, ``at_bounds`` (:func:`at_bounds`), ``prior``.
    """
    r = _spec(result)
    if likelihood is None and isinstance(result, FitResult):
        likelihood = result.likelihood
    raw = data["stress"].values if data is not None else r.stress
    obs = np.asarray(raw if raw is not None else [], float).ravel()
    if obs.size == 0:
        raise HbmError(f"fit_quality: specimen {r.specimen_id}: no observed stress (pass data=)")
    _, ll_map, source, _ = _map_row(r)
    pred = map_prediction(r, likelihood)
    if pred is not None and pred.shape != obs.shape:
        raise HbmError(f"fit_quality: specimen {r.specimen_id}: data have {obs.size} points, "
                       f"the fit {pred.size}")
    rmse = float(np.sqrt(np.mean((pred - obs) ** 2))) if pred is not None else float("nan")
    peak = float(np.max(np.abs(obs)))
    cov, cov90 = None, None
    if r.predictive is not None and np.shape(r.predictive)[-1] == obs.size:
        def inside(p):
            lo, hi = np.quantile(np.asarray(r.predictive, float), [(1 - p) / 2, (1 + p) / 2], axis=0)
            return float(np.mean((obs >= lo) & (obs <= hi)))
        cov, cov90 = inside(prob), inside(0.9)
    s = summarize(r, prob=prob)
    mp = map_estimate(r)
    noise = {n: {"map": mp[n], "median": s[n]["median"], "lower": s[n]["lower"], "upper": s[n]["upper"]}
             for n in _noise_names(r, likelihood)}
    combos = {k: {"median": v["median"], "lower": v["lower"], "upper": v["upper"]}
              for k, v in s.items() if k in COMBINATIONS}
    return {"specimen_id": r.specimen_id, "n_points": int(obs.size), "rmse": rmse,
            "rmse_rel": rmse / peak if peak > 0 else float("nan"), "coverage90": cov90,
            "coverage": cov, "coverage_prob": float(prob),
            "noise": noise, "map": mp, "map_source": source, "map_log_likelihood": float(ll_map),
            "combinations": combos, "log_evidence": float(r.log_evidence),
            "log_evidence_se": float(r.log_evidence_se),
            "at_bounds": r.at_bounds if r.at_bounds is not None else at_bounds(r), "prior": _prior_of(r),
            "prior_dominated": _uninformed_combinations(data["strain"].values if data is not None else r.strain)}


def _uninformed_combinations(strain) -> dict[str, str]:
    """Combinations the data cannot inform, with why: the fibre term c·P1·⟨ε − EOPT⟩₊ is
    identically zero for ε ≤ 0, so on compression data VOLF·P1 is the prior."""
    eps = np.asarray(strain if strain is not None else [], float)
    if eps.size and float(np.max(eps)) <= 0.0:
        return {"VOLF*P1": "the fibre term is identically zero for ε ≤ 0 (compression data)"}
    return {}


def tier_line(r: SpecimenResult) -> str:
    """One line naming the likelihood tier that produced a result (and the quadrature's error)."""
    c = r.config
    line = "likelihood: " + str(c.get("likelihood_note") or c.get("likelihood_tier", "full"))
    col = c.get("collapsed") or {}
    if "quadrature_error" in col:
        line += f"; quadrature error of log L ≤ {col['quadrature_error']:.1e} nats"
    if col.get("route"):
        line += f"; route: {col['route']}"
    imp = col.get("importance")
    if imp:
        line += (f"; evidence by importance sampling (ESS {100 * imp['ess_fraction']:.0f}%, k̂ {imp['khat']:.2f})"
                 if imp["accepted"] else f"; importance finish refused ({imp['reason']}), TMCMC evidence kept")
    return line


def _prior_line(r: SpecimenResult) -> str:
    items = [f"{n} {'log' if p['form'] == 'loguniform' else ''}U[{p['lo']:g}, {p['hi']:g}]"
             for n, p in _prior_of(r).items()]
    return "prior: " + ", ".join(items)


def quality_lines(q: Mapping[str, Any]) -> list[str]:
    """The :func:`fit_quality` numbers as text lines (fit quality first, then the best fit)."""
    cov = "n/a" if q["coverage90"] is None else f"{100 * q['coverage90']:.0f}% of {q['n_points']} points"
    lines = [f"fit quality: RMSE {q['rmse']:.4g} MPa ({100 * q['rmse_rel']:.2f}% of peak |stress|), "
             f"90% predictive coverage {cov}",
             f"log-evidence {q['log_evidence']:.3f} ± {q['log_evidence_se']:.3f}"]
    if q["noise"]:
        lines.append("noise: " + ", ".join(f"{n} {v['median']:.4g} [{v['lower']:.4g}, {v['upper']:.4g}]"
                                           for n, v in q["noise"].items()))
    src = "CMA-ES optima" if q["map_source"] == "optimum" else "posterior samples"
    lines.append(f"best fit (MAP, best of the {src}, log-likelihood {q['map_log_likelihood']:.3f}): "
                 + ", ".join(f"{k}={v:.5g}" for k, v in q["map"].items()))
    prior_dom = q.get("prior_dominated", {})
    ident = {k: v for k, v in q["combinations"].items() if k not in prior_dom}
    if ident:
        lines.append("identified combinations (median [90% interval]): "
                     + ", ".join(f"{k} {v['median']:.4g} [{v['lower']:.4g}, {v['upper']:.4g}]"
                                 for k, v in ident.items()))
    for k, why in prior_dom.items():
        if k in q["combinations"]:
            v = q["combinations"][k]
            lines.append(f"prior-dominated, not identified: {k} {v['median']:.4g} [{v['lower']:.4g}, "
                         f"{v['upper']:.4g}] ({why})")
    lines += format_at_bounds(q["at_bounds"])
    return lines


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
        if r.config.get("input"):
            head.append(input_line(r.config["input"]))
        raw = summarize(r, prob=prob)
        pc = int(round(prob * 100))
        rows = [RIDGE_NOTE, f"{'parameter':<14}{'mean':>12}{'sd':>12}{f'{pc}% lower':>12}{f'{pc}% upper':>12}"]
        rows += [f"{k:<14}{v['mean']:>12.5g}{v['sd']:>12.4g}{v['lower']:>12.5g}{v['upper']:>12.5g}"
                 for k, v in raw.items() if k not in COMBINATIONS]
        if r.fixed:
            rows.append("fixed: " + ", ".join(f"{k}={v:g}" for k, v in r.fixed.items()))
        rows.append(_prior_line(r))
        return "\n".join(head + quality_lines(self.quality(prob=prob)) + [tier_line(r)] + rows)

    def to_json(self, prob: float = 0.9) -> dict[str, Any]:
        """One JSON-able dict: :func:`fit_quality` plus identification of the run.

        Keys include ``rmse``, ``rmse_rel`` (fraction of peak |stress|), ``coverage90``,
        ``log_evidence``, ``log_evidence_se``, ``map`` (name -> value), ``combinations``,
        ``at_bounds`` (list of {parameter, side, edge, fraction, map_at_edge}), ``noise``,
        ``prior``, ``names``, ``n_samples``, ``summary`` (raw-parameter statistics) and ``path``.
        """
        q = self.quality(prob=prob)
        r = self.result
        q.update({"names": list(r.names), "n_samples": r.n_samples, "fixed": dict(r.fixed),
                  "summary": {k: v for k, v in summarize(r, prob=prob).items() if k not in COMBINATIONS},
                  "input": r.config.get("input", ""),
                  "likelihood_tier": r.config.get("likelihood_tier", "full"),
                  "likelihood_note": r.config.get("likelihood_note", ""),
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
                      f"{per_row * evaluations / 60:.0f} min (~{evaluations:.2g} evaluations); neighbouring points "
                      "of a dense record are rarely independent: thin the curve or use the ar1 noise, and "
                      "--max-evaluations caps the cost", HbmWarning, stacklevel=2)


def _specimen_id(data) -> str:
    return str(getattr(data, "attrs", {}).get("id", "specimen"))


def fit_specimen(data, *, model=None, samples: int = 2000, kernel: str = "rw", noise: str = "iid",
                 fix: Mapping[str, float] | None = None, bounds: Mapping[str, tuple[float, float]] | None = None,
                 seed: int | np.random.SeedSequence = 0, restarts: int = 4, sweep: str | tuple | None = None,
                 sobol_n: int | None = None, checkpoint_dir: str | os.PathLike | None = None,
                 out: str | os.PathLike | None = None, progress: bool = True,
                 tmcmc_options: Mapping[str, Any] | None = None,
                 optimize_options: Mapping[str, Any] | None = None,
                 sigma_bounds: tuple[float, float] | None = None,
                 config_extra: Mapping[str, Any] | None = None,
                 on_phase: Callable[[str], None] | None = None,
                 prior: Prior | str | os.PathLike | Mapping | None = None,
                 max_evaluations: int | None = None, likelihood: str = "auto") -> FitResult:
    """CMA-ES optima, TMCMC posterior, posterior predictive and (optionally) Sobol for one specimen.

    Parameters
    ----------
    data : xarray.Dataset
        A specimen (:func:`hbm.data.load_specimen`); ``attrs["id"]`` names it.
    model : Model, optional
        Default :func:`hbm.spyrou_model`.
    samples : int
        TMCMC population size N (= posterior draws stored).
    kernel : {"rw", "manifold"}
        TMCMC move kernel; "manifold" uses the likelihood's gradient and Fisher information.
    noise : {"iid", "weighted", "proportional", "ar1"}
        Noise model (:func:`hbm.likelihood.make_likelihood`).
    fix, bounds : dict, optional
        Parameters held fixed / narrowed prior boxes (inside the prior's box; to widen the
        thesis box pass ``prior=resolve_prior(model, file, bounds)``).
    seed : int or SeedSequence
        Root seed; the four phases get spawned children (module docstring).
    restarts : int
        CMA-ES restarts (0 skips the optimisation).
    sweep : "PARAM:WIDTH" or (name, width), optional
        Thesis §3.1 bound sweep tracing a manifold (e.g. "VOLF:0.05").
    sobol_n : int or None
        Sobol base sample size (power of 2); None or 0 skips Sobol.
    checkpoint_dir : path, optional
        TMCMC checkpoint ``<dir>/<id>.npz``: an interrupted fit resumes from its last stage.
        Removed once the result file is written.  It is resumed whatever made it: pass a folder
        keyed by the fit's content (:func:`hbm.identity.checkpoint_dir` of :func:`hbm.identity.fit_key`,
        as ``hbm fit`` and ``hbm run`` do) so that one of other data or settings is never resumed.
    out : path, optional
        Write the result netCDF here (atomically; ``complete`` flag last).
    progress : bool
        tqdm bar per TMCMC stage.
    tmcmc_options : dict, optional
        Extra keyword arguments for :func:`hbm.samplers.tmcmc` (n_steps, max_stages, ...).
    optimize_options : dict, optional
        Extra keyword arguments for :func:`hbm.optimization.optimize`; default
        ``{"maxfevals": 5000}`` per CMA-ES run (the optima only seed figures and the manifold;
        an unlimited budget costs minutes per specimen for no visible gain).
    sigma_bounds : (lo, hi), optional
        Box of the first noise parameter (the workflow uses one box for all specimens so the
        hierarchical layer sees a common stage-1 prior).
    config_extra : dict, optional
        Extra JSON-able entries for the stored ``config`` attribute (e.g. a settings hash).
    on_phase : callable, optional
        Called with the phase name when a phase starts (progress reporting).
    prior : Prior, TOML path or mapping, optional
        User prior (:mod:`hbm.prior`); default the thesis box, uniform (bitwise the outputs of a
        fit without this argument).  Loguniform parameters are sampled in log coordinates; the
        stored posterior, optima, predictive and Sobol box are in natural units.
    max_evaluations : int, optional
        Cap on TMCMC log-likelihood evaluations (:func:`hbm.samplers.tmcmc`); None = no cap.
    likelihood : {"auto", "collapsed", "full"}
        Likelihood tier (:func:`hbm.collapse.choose_tier`).  "auto" (default): where the model's
        stress is linear in its amplitudes and the noise keeps their integral Gaussian, TMCMC
        samples only the nonlinear and noise parameters on the likelihood with the amplitudes
        integrated out exactly (:func:`hbm.collapse.fit_collapsed`: a 500-particle TMCMC run
        and an importance-sampling finish, or N = ``samples`` with at most 10 MH steps per
        stage when the finish is refused or ``tmcmc_options`` are given), and the amplitudes
        and original parameters are drawn given each posterior sample; the
        stored posterior holds every free parameter as with the full likelihood.  "full":
        today's sampler over all parameters.  The tier and why are stored in
        ``config["likelihood_tier"]`` and ``config["likelihood_note"]``; evaluation counts
        count basis evaluations as model evaluations.

    Returns
    -------
    FitResult
        ``result.prior`` and ``result.at_bounds`` (box-edge warnings, :func:`at_bounds`) are
        stored in the file too.
    """
    t_start = time.perf_counter()
    model = spyrou_model() if model is None else model
    if kernel not in ("rw", "manifold"):
        raise HbmError(f"kernel must be 'rw' or 'manifold', got {kernel!r}")
    if int(samples) < 4:
        raise HbmError(f"samples must be >= 4, got {samples}")
    seed = check_seed(seed)  # the rules of the command line's --seed and --bounds
    check_physical_bounds(bounds, PHYSICAL_RANGE)
    sid = _specimen_id(data)
    prior = load_prior(prior)
    lik = make_likelihood(model, data, noise=noise, fix=fix, bounds=bounds, sigma_bounds=sigma_bounds, prior=prior)
    check_data_size(sid, lik, samples, max_evaluations)
    collapsed, tier_note = choose_tier(lik, likelihood, kernel=kernel)  # before any long computation
    s_opt, s_tm, s_pred, s_sob = seeds.child_ints(seed, len(seeds.PHASES))  # the phase streams of hbm.seeds
    sweep_t = parse_sweep(sweep)
    if sweep_t is not None and sweep_t[0] in lik.names and lik.forms[lik.index(sweep_t[0])] == "loguniform":
        # the sweep's windows are cut in the optimiser's (log) coordinates; a width in natural
        # units would be misread there
        raise PriorError(f"sweep: {sweep_t[0]} has a loguniform prior; sweep a uniform parameter")
    timings: dict[str, float] = {}
    phase = on_phase or (lambda name: None)

    optima = None
    if restarts and int(restarts) > 0:
        phase("cmaes")
        t = time.perf_counter()
        oopts = {"maxfevals": 5000, **dict(optimize_options or {})}
        optima = run_optima(lik, restarts=int(restarts), seed=s_opt, sweep=sweep_t, **oopts)
        timings["cmaes"] = time.perf_counter() - t

    phase("tmcmc")
    t = time.perf_counter()
    ckpt = None
    if checkpoint_dir is not None:
        ckpt = Path(checkpoint_dir) / f"{sid}.npz"
        ckpt.parent.mkdir(parents=True, exist_ok=True)
    opts = dict(tmcmc_options or {})
    if max_evaluations is not None:
        opts["max_evaluations"] = int(max_evaluations)
    if kernel == "manifold":
        opts.setdefault("gradient_fim", lik.gradient_fim)
    collapsed_info = None
    if collapsed is not None:  # sample φ only; the amplitudes are integrated, then drawn given φ
        cf = fit_collapsed(collapsed, int(samples), seed=s_tm, checkpoint=ckpt, progress=progress, **opts)
        y, log_lik, n_evaluations = cf.samples, cf.log_likelihood, cf.n_evaluations
        # FitResult.tmcmc: the φ run's stages and evidence, with the completed full rows as samples
        tr = dataclasses.replace(cf.tmcmc, samples=y, log_likelihood=log_lik)
        log_z, log_z_se, collapsed_info = cf.log_evidence, cf.log_evidence_se, cf.info
    else:
        tr = _tmcmc(lik, lik.bounds, int(samples), seed=s_tm, kernel=kernel, checkpoint=ckpt,
                    progress=progress, **opts)
        y, log_lik, n_evaluations = tr.samples, tr.log_likelihood, tr.n_evaluations
        log_z, log_z_se = tr.log_evidence, tr.log_evidence_se
    timings["tmcmc"] = time.perf_counter() - t

    phase("predictive")
    t = time.perf_counter()
    y = np.asarray(y, float)  # sampler (working) coordinates
    theta = lik.to_natural(y)  # what the user sees: natural units
    m = lik.predict(y)
    pll = pointwise_log_likelihood(lik, y, m)
    pred_model, pred = posterior_predictive(lik, y, s_pred, m)
    timings["predictive"] = time.perf_counter() - t

    sob = None
    if sobol_n:
        phase("sobol")
        t = time.perf_counter()
        sbounds = bounds
        if prior is not None:  # the Sobol input box is the prior's natural box
            sbounds = {n: tuple(map(float, lik.natural_bounds[j])) for j, n in enumerate(lik.model_names)}
        sob = run_sobol(model, data, n=int(sobol_n), seed=s_sob, fix=fix, bounds=sbounds)
        timings["sobol"] = time.perf_counter() - t

    strain = np.asarray(data["strain"].values, float)
    config = {"samples": int(samples), "kernel": kernel, "noise": noise, "fix": dict(fix or {}) or None,
              "bounds": {k: list(map(float, v)) for k, v in (bounds or {}).items()} or None,
              "restarts": int(restarts or 0), "sweep": list(sweep_t) if sweep_t else None,
              "sobol_n": int(sobol_n or 0), "optimize_options": dict(optimize_options or {}) or None,
              "sigma_bounds": list(map(float, sigma_bounds)) if sigma_bounds is not None else None,
              "tmcmc_options": {k: v for k, v in opts.items() if k != "gradient_fim"} or None,
              "seeds": {"cmaes": s_opt, "tmcmc": s_tm, "predictive": s_pred, "sobol": s_sob},
              "n_evaluations": int(n_evaluations), "n_stages": len(tr.stages),
              "likelihood_tier": "full" if collapsed is None else "collapsed", "likelihood_note": tier_note,
              "source_file": str(data.attrs.get("source_file", ""))}
    converted = input_summary(data)
    if converted:  # the numbers rest on these conversions: keep them with the result
        config["input"] = converted
    if prior is not None:
        config["prior"] = prior.to_dict()
    if collapsed_info is not None:
        config["collapsed"] = collapsed_info
    config.update(dict(config_extra or {}))
    if isinstance(seed, np.random.SeedSequence):
        root_seed = int(seed.entropy)
        config["seed_spawn_key"] = list(map(int, seed.spawn_key))
    else:
        root_seed = int(seed)
    res = SpecimenResult(
        specimen_id=sid, names=list(lik.names), samples=theta, log_likelihood=np.asarray(log_lik, float),
        log_evidence=float(log_z), log_evidence_se=float(log_z_se),
        bounds=np.asarray(lik.natural_bounds, float), stages=list(tr.stages), strain=strain,
        stress=np.asarray(data["stress"].values, float),
        time=np.asarray(data["time"].values, float) if "time" in data else None,
        test=np.asarray(data["test"].values) if "test" in data else None,
        pointwise_log_likelihood=pll, predictive=pred, predictive_model=pred_model, optima=optima, sobol=sob,
        model=model.name, effects=list(model.effect_names), config=config, seed=root_seed,
        fixed=dict(lik.fixed), version=__version__,
        prior={n: lik.prior[n].to_dict() for n in lik.names},
        parameter_info={q.name: (q.unit, q.meaning) for q in getattr(model, "parameters", ())})
    res.at_bounds = at_bounds(res)
    path = None
    if out is not None:
        t = time.perf_counter()
        res.timings = dict(timings)
        path = write_specimen_result(res, out)
        timings["write"] = time.perf_counter() - t
        if ckpt is not None and ckpt.exists():
            ckpt.unlink()  # the result file supersedes the checkpoint
            try:
                ckpt.parent.rmdir()  # only if empty
            except OSError:
                pass
    timings["total"] = time.perf_counter() - t_start
    res.timings = dict(timings)
    return FitResult(result=res, path=path, likelihood=lik, tmcmc=tr, timings=timings)
