"""Views of fitted results for tables and figures: identified directions, manifolds, variability, population.

Pure functions of :class:`hbm.io.SpecimenResult` and :class:`hbm.io.HierarchicalFile` (no files
written, no plotting): the report (:mod:`hbm.workflow.report`), the figures (:mod:`hbm.plots`) and the
workflow (:mod:`hbm.workflow`) read results through them.
"""

from __future__ import annotations

from typing import Mapping

import numpy as np
from scipy.special import expit
from scipy.stats import chi2

from .. import io
from ..errors import HbmError
from .identify import identifiable_directions, volf_t1_manifold
from ..model.spec import spec_of

__all__ = ["identified_directions", "manifold_spline", "specimen_variability", "quantity_samples", "pooled_view",
           "population_table"]


def identified_directions(result: io.SpecimenResult) -> list[dict]:
    """Combinations of parameters that the specimen's posterior pins down
    (:func:`hbm.identifiability.identify.identifiable_directions`).

    Returns
    -------
    list of dict
        ``{"expression", "ratio" (posterior/prior sd of the rounded combination), "median", "lo", "hi"}``,
        a sparse basis of the identified subspace, best first; empty when the samples are too few.
    """
    try:
        rep = identifiable_directions(result.samples, result.names, bounds=result.bounds, spec=spec_of(result))
    except HbmError:
        return []
    return [{"expression": d["label"], "ratio": float(d["sd_ratio_rounded"]), "median": float(d["median"]),
             "lo": float(d["lo"]), "hi": float(d["hi"])} for d in rep.directions]


def manifold_spline(result: io.SpecimenResult, n_grid: int = 60) -> dict | None:
    """The specimen's fraction–amplitude manifold (the spec's :class:`~hbm.model.spec.Manifold`: VOLF–T1
    for the Spyrou base; :func:`hbm.identifiability.identify.volf_t1_manifold`) on a grid.

    Points: the CMA-ES sweep optima (one per window of the fraction) when there are at least four
    distinct fraction values, otherwise binned medians of the posterior samples.

    Returns
    -------
    dict or None
        ``{"x", "y" (grid), "points_x", "points_y", "x_name", "y_name", "source",
        "combination_rel_spread" (flatness of (1 − x)·y along the curve), "level", "object"}``;
        None when the model has no manifold, x or y is fixed, or the fit is impossible.
    """
    spec_man = spec_of(result).manifold
    if spec_man is None:
        return None
    x, y = spec_man.x, spec_man.y
    pts = [(o["params"][x], o["params"][y]) for o in (result.optima or [])
           if o.get("kind") == "sweep" and x in o["params"] and y in o["params"]]
    try:
        if len({round(p[0], 9) for p in pts}) >= 4:
            px, py = np.array(pts).T
            man = volf_t1_manifold(px, py, source="points")
            src = "CMA-ES sweep optima"
        elif x in result.names and y in result.names:
            man = volf_t1_manifold(result.column(x), result.column(y), source="samples")
            src = "posterior samples (binned medians)"
            px, py = man.knots_volf, np.exp(man.knots_log_t1)
        else:
            return None
    except HbmError:
        return None
    g = man.grid(n_grid)
    return {"x": g, "y": man(g), "points_x": np.asarray(px), "points_y": np.asarray(py), "x_name": x,
            "y_name": y, "source": src, "combination_rel_spread": float(man.flatness), "level":
            np.asarray(man.level, float), "object": man}


def specimen_variability(samples: Mapping[str, np.ndarray], *, log: bool = True) -> dict:
    """Do specimens differ in a quantity beyond their posterior uncertainty?

    Cochran's Q heterogeneity statistic on the posterior means (in log space for positive
    quantities) with the posterior sds as standard errors: Q = Σ (m_i − m̄_w)² / s_i² ~ χ²(S−1)
    under "all specimens share one value".  Also the pairs whose posterior difference excludes
    zero with 95 % probability.

    Returns
    -------
    dict
        ``{"Q", "df", "p_value", "separated_pairs": [(a, b), ...], "n_pairs"}``
    """
    ids = sorted(samples)
    vals = {k: np.asarray(samples[k], float) for k in ids}
    if log and all(np.all(v > 0) for v in vals.values()):
        vals = {k: np.log(v) for k, v in vals.items()}
    m = np.array([v.mean() for v in vals.values()])
    s = np.array([v.std(ddof=1) for v in vals.values()])
    s = np.maximum(s, 1e-12 * (np.abs(m) + 1e-300))
    w = 1 / s ** 2
    mw = float((w * m).sum() / w.sum())
    q = float((w * (m - mw) ** 2).sum())
    df = len(ids) - 1
    pairs = []
    rng = np.random.default_rng(0)  # pairing of draws only; any fixed seed gives the same answer up to MC error
    for i in range(len(ids)):
        for j in range(i + 1, len(ids)):
            a, b = vals[ids[i]], vals[ids[j]]
            n = min(a.size, b.size)
            diff = rng.permutation(a)[:n] - rng.permutation(b)[:n]
            p = float((diff > 0).mean())
            if p > 0.975 or p < 0.025:
                pairs.append((ids[i], ids[j]))
    return {"Q": q, "df": df, "p_value": float(chi2.sf(q, df)) if df > 0 else float("nan"),
            "separated_pairs": pairs, "n_pairs": len(ids) * (len(ids) - 1) // 2}


def quantity_samples(names, theta, spec=None) -> dict[str, np.ndarray]:
    """The spec's identifiable combinations plus its shape parameters (the Spyrou base: G, VOLF*P1,
    (1-VOLF)*T1, T2, THETA, EOPT) from rows of named parameters; default the default base's spec."""
    return spec_of(spec).quantities(list(names), theta)


def pooled_view(h) -> list[dict]:
    """The pooled columns of a hierarchical result in natural units, for tables and figures.

    A column ``log_X`` with the identity transform (``--pool combinations``) is shown as X with
    a log-normal population; log/logit columns are mapped back with g⁻¹.

    Returns
    -------
    list of dict
        Per pooled column with hyperparameters: ``name`` (column), ``display`` (quantity name),
        ``transform`` (of the displayed quantity: log, logit or identity), ``median`` (draws of
        the population median g⁻¹(mu) over the hyper-posterior), ``new`` (a new specimen's draws
        or None), ``sd`` (median population sd in transformed units), ``log_scale`` (bool).
    """
    transforms = dict(h.attrs.get("transforms", {}))
    bounds = dict(h.attrs.get("bounds", {}))
    out = []
    for j, nm in enumerate(h.pooled_names):
        if f"mu_{nm}" not in h.hyper_names:  # derived column of the new specimen (--pool combinations)
            continue
        mu = np.asarray(h.hyper(f"mu_{nm}"), float)
        t = transforms.get(nm, "identity")
        new = None if h.new_specimen is None else np.asarray(h.new_specimen[:, j], float)
        display = nm
        if t == "identity" and nm.startswith("log_"):  # a pooled log-combination
            display, t = nm[4:], "log"
            mu_nat, new = np.exp(mu), (None if new is None else np.exp(new))
        elif t == "log":
            mu_nat = np.exp(mu)
        elif t == "logit":
            lo, hi = bounds.get(nm, (0.0, 1.0))
            mu_nat = lo + (hi - lo) * expit(mu)
        else:
            mu_nat = mu
        out.append({"name": nm, "display": display, "transform": t, "median": mu_nat, "new": new,
                    "sd": float(np.median(h.hyper(f"sd_{nm}"))), "log_scale": t == "log"})
    return out


def population_table(h, *, prob: float = 0.9) -> dict[str, dict[str, float]]:
    """Population estimates in natural units from the hierarchical result, keyed by quantity.

    ``median``: g⁻¹(mu) (the population median for logit/log/identity populations without
    active truncation), with its ``prob`` interval over the hyper-posterior; ``new_*``: the
    predictive distribution of a new specimen's value; ``sd_transformed``: the population sd
    in transformed units (log units for log-normal populations).
    """
    q = [(1 - prob) / 2, 0.5, (1 + prob) / 2]
    out = {}
    for v in pooled_view(h):
        a, b, c = np.quantile(v["median"], q)
        row = {"median": float(b), "median_lower": float(a), "median_upper": float(c),
               "sd_transformed": v["sd"], "transform": v["transform"]}
        if v["new"] is not None:
            na, nb, nc = np.quantile(v["new"], q)
            row.update(new_lower=float(na), new_median=float(nb), new_upper=float(nc))
        out[v["display"]] = row
    return out
