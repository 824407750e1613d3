"""What a specimen fit says: posterior summaries, the MAP, box edges, fit quality and its report lines.

Used by :func:`hbm.fit.fit_specimen` (which re-exports these names) and by every command that reads a
result back (:class:`hbm.io.SpecimenResult`).
"""

from __future__ import annotations

from typing import Any, Mapping, Sequence

import numpy as np

from ..data.specimen import as_specimen
from ..errors import HbmError
from ..io import SpecimenResult
from ..settings.fit import FitRecord
from ..model.spec import spec_of
from ..likelihood.noise import get_noise
from ..samplers.hierarchical import rhat_ess

#: a value lies "at" a box edge within this fraction of the box width (log width for loguniform)
EDGE_TOL = 0.02
#: posterior mass near one edge above which the edge is reported
EDGE_MASS = 0.2
#: why the raw-parameter table is not a parameter set (printed right above it)
RIDGE_NOTE = ("raw parameters: posterior means are NOT a parameter set -- along non-identified directions the "
              "posterior is a curved ridge whose means lie off it; use the MAP or the combinations above")


# ----------------------------------------------------------------------------- summaries
def summarize(result: SpecimenResult, *, prob: float = 0.9) -> dict[str, dict[str, float]]:
    """Posterior mean, sd and central ``prob`` interval per free parameter and combination.

    Returns
    -------
    dict
        ``{name: {"mean", "sd", "lower", "upper", "median"}}``; parameters first, then the
        identifiable combinations of the model's spec (when none of their parameters is fixed).
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
    for k, v in combination_samples(result).items():
        out[k] = stats(v)
    return out


def combination_samples(result: SpecimenResult) -> dict[str, np.ndarray]:
    """The identifiable combinations of every posterior sample, by the result's spec (:mod:`hbm.model.spec`);
    empty when one of their parameters was fixed or is absent."""
    return spec_of(result).combination_values(result.as_dict())


def summary_table(result: SpecimenResult, *, prob: float = 0.9) -> str:
    """Plain-text table of :func:`summarize` plus the log-evidence, the prior and box-edge warnings."""
    result = _spec(result)
    s = summarize(result, prob=prob)
    pc = int(round(prob * 100))
    lines = [f"specimen {result.specimen_id}: {result.n_samples} posterior samples, "
             f"log-evidence {result.log_evidence:.3f} ± {result.log_evidence_se:.3f}",
             f"{'quantity':<14}{'mean':>12}{'sd':>12}{f'{pc}% lower':>12}{f'{pc}% upper':>12}"]
    first = next(iter(spec_of(result).combination_names), None)
    for k, v in s.items():
        if k == first:
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
    return result if isinstance(result, SpecimenResult) else result.result


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
        cand = get_noise(FitRecord.from_attrs(r.config).settings.noise).names
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
    if likelihood is None and not isinstance(result, SpecimenResult):  # a FitResult brings its likelihood
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
    data : Specimen or xarray.Dataset, optional
        The observed specimen; default the one stored in the result.
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
    if likelihood is None and not isinstance(result, SpecimenResult):  # a FitResult brings its likelihood
        likelihood = result.likelihood
    spec = as_specimen(data) if data is not None else r.data
    if spec is None or not spec.has_stress:
        raise HbmError(f"fit_quality: specimen {r.specimen_id}: no observed stress (pass data=)")
    obs = spec.stress
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
              for k, v in s.items() if k in spec_of(r).combination_names}
    return {"specimen_id": r.specimen_id, "n_points": int(obs.size), "rmse": rmse,
            "rmse_rel": rmse / peak if peak > 0 else float("nan"), "coverage90": cov90,
            "coverage": cov, "coverage_prob": float(prob),
            "noise": noise, "map": mp, "map_source": source, "map_log_likelihood": float(ll_map),
            "combinations": combos, "log_evidence": float(r.log_evidence),
            "log_evidence_se": float(r.log_evidence_se),
            "at_bounds": r.at_bounds if r.at_bounds is not None else at_bounds(r), "prior": _prior_of(r),
            "prior_dominated": _uninformed_combinations(spec.strain, spec_of(r))}


def _uninformed_combinations(strain, model_spec=None) -> dict[str, str]:
    """Combinations the data cannot inform, with why: a term that vanishes for ε ≤ 0 (the Spyrou fibres,
    c·P1·⟨ε − EOPT⟩₊) leaves its combination at the prior on compression data."""
    eps = np.asarray(strain, float)
    if eps.size and float(np.max(eps)) <= 0.0:
        return {c.name: c.compression_note for c in spec_of(model_spec).combinations if c.compression_note}
    return {}


def tier_line(r: SpecimenResult) -> str:
    """One line naming the likelihood tier that produced a result (and the quadrature's error)."""
    stored = FitRecord.from_attrs(r.config)
    line = "likelihood: " + str(stored.tier_note or stored.tier_used)
    col = stored.collapsed or {}
    if "quadrature_error" in col:
        line += f"; quadrature error of log L ≤ {col['quadrature_error']:.1e} nats"
    if col.get("route"):
        line += f"; route: {col['route']}"
    imp = col.get("importance")
    if imp:
        line += (f"; evidence by importance sampling (ESS {100 * imp['ess_fraction']:.0f}%, k̂ {imp['khat']:.2f})"
                 if imp["accepted"] else f"; importance finish refused ({imp['reason']}), TMCMC evidence kept")
    return line


def chain_rhat(result: SpecimenResult, values: np.ndarray) -> float:
    """Rank-normalised split R-hat of per-row ``values`` over the result's chains (NaN for one chain)."""
    k = int(result.chains.n_chains)
    v = np.asarray(values, float)
    if k < 2 or v.size % k:
        return float("nan")
    return rhat_ess(v.reshape(k, -1))[0]


def chains_line(r: SpecimenResult) -> str:
    """One line: how many chains the posterior has and the largest R-hat, or why there is one chain."""
    c = r.chains
    if c.n_chains < 2:
        return f"chains: one, no R-hat ({c.note})"
    rh = max(chain_rhat(r, r.samples[:, j]) for j in range(r.samples.shape[1]))
    what = {"tmcmc_islands": "TMCMC islands (independent up to the shared beta schedule and proposal)",
            "importance_batches": "batches of the importance draws (independent given the shared proposal)"
            }.get(c.method, c.method)
    verdict = "they agree" if rh <= 1.01 else "above 1.01: the chains disagree, the posterior is not well mixed"
    return f"chains: {c.n_chains} {what}; largest R-hat {rh:.3f} over the parameters ({verdict})"


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
