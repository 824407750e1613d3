"""Organ-scale prediction from fitted specimens (``hbm predict organ``; issue 7, thesis §3.3.2).

Pushes each specimen's parameter uncertainty through the slender-body fusiform-muscle model of
:mod:`hbm.organ`:

* ``"posterior"``: the specimen's TMCMC posterior (a seeded subsample of ``samples`` draws);
* ``"updated"``: its updated individual posterior from the hierarchical layer (when
  ``hierarchical.nc`` exists);
* ``"optima"``: its near-optimal CMA-ES parameter sets (restarts and VOLF-sweep optima within
  ``near`` of the best −log-likelihood), which lie on the non-identifiable VOLF–T1 manifold and
  must give one organ curve (thesis Fig. 3.65);
* ``population``: a new, unseen specimen (the hierarchical predictive).

Every source of one specimen shares one force grid: 0 up to ``extrapolate`` × F_t, where F_t is
the force at which the median posterior draw's thinnest section reaches the largest strain
tested on the specimen (:func:`hbm.organ.force_levels` with ``where="max"``).  Extrapolating in
force rather than in strain keeps the tested range readable for exponentially stiffening
tissue (1.5 × the tested strain can need 1000 × the force).  Stored per force level: the
5/50/95 % quantiles of the elongation and of the largest fiber strain, the share of draws whose organ strains exceed
the tested strain (extrapolation, thesis Fig. 3.64) and the share of unreachable draws.  Curves
go to ``organ.nc`` (:func:`hbm.io.write_organ`), figures to ``figures/`` (:mod:`hbm.plots.organ`).

This module also renders the report section (:func:`organ_section`) and the ``run_workflow``
hook of ``hbm run --geometry`` (:func:`organ_report_hook`).
"""

from __future__ import annotations

import math
import os
import time
import warnings
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Mapping, Sequence

import numpy as np
import xarray as xr

from .. import io
from ..runtime import seeds
from ..effects import REGISTRY, make_effect
from ..errors import HbmError, HbmWarning
from ..model import BASE_EFFECTS, spyrou_model
from ..model.core import Model
from ..model.spec import spec_of


def _fraction(model) -> str:
    """The fraction of the model's manifold (VOLF for the Spyrou base): the optima are ordered by it."""
    man = spec_of(model).manifold
    return man.x if man is not None else ""
from ..organ import (
    FusiformGeometry, OrganResponse, extrapolation_mask, force_levels, load_geometry, nominal_stress,
    organ_response, theta_from_samples)

__all__ = ["OrganPrediction", "predict_organ", "predict_organ_results", "model_for_results", "summary_rows",
           "optima_spread", "optima_agreement", "optima_difference", "force_at_tested_strain",
           "format_summary", "organ_section", "organ_report_hook", "PROBS"]

#: quantiles stored for every band (90 % interval and median)
PROBS = (0.05, 0.5, 0.95)


@dataclass
class OrganPrediction:
    """What :func:`predict_organ` produced.

    Attributes
    ----------
    organ : hbm.io.OrganFile
        The curves (also written to ``path``).
    geometry : FusiformGeometry
    path : Path or None
        ``organ.nc``.
    figures : list of Path
    rows : list of dict
        Summary table (:func:`summary_rows`).
    timings : dict
        Seconds: ``total``, ``solver`` (sum of :func:`hbm.organ.organ_response` wall times) and
        per specimen ``<id>/<source>``.
    notes : list of str
        What was skipped and why.
    """

    organ: io.OrganFile
    geometry: FusiformGeometry
    path: Path | None = None
    figures: list[Path] = field(default_factory=list)
    rows: list[dict] = field(default_factory=list)
    timings: dict = field(default_factory=dict)
    notes: list[str] = field(default_factory=list)


# ----------------------------------------------------------------------------- helpers
def model_for_results(results: Mapping[str, io.SpecimenResult], model: Model | None = None) -> Model:
    """The constitutive model the specimens were fitted with.

    Rebuilt as the Spyrou base model plus the library effects recorded in the result files
    (``effects`` attribute).  Pass ``model`` for user effects (``file.py:Class``) or a
    non-default ``iso_factor``, which the files do not record.

    Raises
    ------
    HbmError
        Specimens fitted with different effects, or an effect not in :data:`hbm.effects.REGISTRY`.
    """
    if model is not None:
        return model
    sets = {sid: tuple(r.effects) for sid, r in results.items()}
    if len(set(sets.values())) > 1:
        raise HbmError("specimens were fitted with different models: "
                       + "; ".join(f"{k}: {', '.join(v)}" for k, v in sorted(sets.items())))
    extra = [e for e in next(iter(sets.values()), ()) if e not in BASE_EFFECTS]
    if not extra:
        return spyrou_model()
    unknown = [e for e in extra if e not in REGISTRY]
    if unknown:
        raise HbmError(f"the specimens were fitted with effect(s) {', '.join(unknown)} that are not in the "
                       f"effect library; use the Python API predict_organ(..., model=your_model)")
    return spyrou_model().with_effects(*[make_effect(e) for e in extra])


def _quantiles(x: np.ndarray, unreachable: np.ndarray, probs: Sequence[float] = PROBS) -> np.ndarray:
    """Quantiles over draws (axis 0) counting unreachable draws as +inf (they lie beyond every
    reachable value); a quantile that falls among them is NaN."""
    xi = np.where(unreachable, np.inf, x)
    with np.errstate(invalid="ignore"), warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        q = np.quantile(xi, np.asarray(probs, float), axis=0)
    return np.where(np.isfinite(q), q, np.nan)


def force_at_tested_strain(model: Model, theta: np.ndarray, geometry: FusiformGeometry, tested: float) -> np.ndarray:
    """Force at which the most strained (smallest) section reaches the tested strain, per draw.

    For a monotone nominal stress P the organ leaves the tested range exactly at
    F = P(1 + ε_tested) · min A0 (no root find needed).
    """
    a_min = float(geometry.area(geometry.nodes).min())
    return nominal_stress(model, theta, np.array([1.0 + tested]))[:, 0] * a_min


def _nice_floor(x: float) -> float:
    """Largest 1/2/2.5/5 × 10^k not above x (a readable reference force)."""
    if not (np.isfinite(x) and x > 0):
        return float("nan")
    k = math.floor(math.log10(x))
    for m in (5.0, 2.5, 2.0, 1.0):
        if m * 10 ** k <= x * (1 + 1e-12):
            return m * 10 ** k
    return 10.0 ** k  # pragma: no cover


def _band_dataset(resp: OrganResponse, tested, f_ext: np.ndarray, ref: OrganResponse, source: str,
                  attrs: Mapping[str, Any]) -> xr.Dataset:
    """Quantile bands of one population of draws on the common force grid (``ref``: the same
    draws solved at the reference force alone, so the table needs no interpolation)."""
    unr = resp.unreachable
    ext = extrapolation_mask(resp, tested)
    ref_force = float(ref.forces[0])
    e_ref = np.where(ref.unreachable[:, 0], np.inf, ref.elongation[:, 0])
    ds = xr.Dataset(
        {
            "elongation": (("quantile", "force"), _quantiles(resp.elongation, unr), {"units": "mm"}),
            "max_strain": (("quantile", "force"), _quantiles(resp.max_strain, unr), {"units": "-"}),
            "mid_strain": (("quantile", "force"), _quantiles(resp.mid_strain, unr), {"units": "-"}),
            "extrapolated_share": (("force",), ext.mean(axis=0)),
            "unreachable_share": (("force",), unr.mean(axis=0)),
            "tendon_elongation": (("force",), resp.tendon_elongation, {"units": "mm"}),
            "tested_range_force": (("quantile",), _quantiles(f_ext, np.zeros(f_ext.shape, bool)), {"units": "N"}),
            "elongation_at_ref": (("quantile",), _quantiles(e_ref[:, None], np.zeros((e_ref.size, 1), bool))[:, 0],
                                  {"units": "mm"}),
            "extrapolated_at_ref": ((), float(np.mean(f_ext < ref_force)) if np.isfinite(ref_force) else np.nan),
        },
        coords={"quantile": list(PROBS), "force": ("force", resp.forces, {"units": "N"})},
        attrs={"source": source, "n_draws": int(resp.n_samples), "non_monotone": int(resp.non_monotone.sum()),
               "ref_force": float(ref_force), "wall_time": float(resp.wall_time),
               "tested_max_strain": float(np.max(tested)), **attrs},
    )
    return ds


def _optima_dataset(resp: OrganResponse, tested: float, f_ext: np.ndarray, optima: Sequence[dict],
                    best: float, near: float) -> xr.Dataset:
    """Every near-optimal CMA-ES set's own curve (no bands: a handful of curves)."""
    pnames = list(optima[0]["params"])
    obj = np.array([float(o.get("objective", np.nan)) for o in optima])
    return xr.Dataset(
        {
            "elongation": (("optimum", "force"), resp.elongation, {"units": "mm"}),
            "max_strain": (("optimum", "force"), resp.max_strain, {"units": "-"}),
            "extrapolated": (("optimum", "force"), extrapolation_mask(resp, tested).astype(np.int8)),
            "unreachable": (("optimum", "force"), resp.unreachable.astype(np.int8)),
            "tested_range_force": (("optimum",), f_ext, {"units": "N"}),
            "parameters": (("optimum", "parameter"),
                           np.array([[float(o["params"].get(n, np.nan)) for n in pnames] for o in optima])),
            "objective": (("optimum",), obj),
            "delta_objective": (("optimum",), obj - best),
            "kind": (("optimum",), np.array([str(o.get("kind", "restart")) for o in optima], dtype=object)),
        },
        coords={"optimum": np.arange(len(optima)), "parameter": pnames,
                "force": ("force", resp.forces, {"units": "N"})},
        attrs={"source": "optima", "near": float(near), "best_objective": float(best),
               "tested_max_strain": float(tested), "wall_time": float(resp.wall_time)},
    )


def _grid(model: Model, theta: np.ndarray, geometry: FusiformGeometry, tested: float, extrapolate: float,
          n: int) -> np.ndarray:
    """0 .. extrapolate × (median force at which the thinnest section reaches the tested strain)."""
    return force_levels(model, theta, geometry, tested, factor=1.0, where="max", n_forces=n) * extrapolate


def optima_difference(optima: xr.Dataset) -> tuple[np.ndarray, np.ndarray]:
    """Signed elongation differences of the near-optimal sets from the best set, and the
    forces where some set extrapolates.

    d_i(F) = (δ_i(F) − δ_best(F)) / max(δ_best(F), δ_best(F_t)), F_t the largest force at which no
    set is extrapolated: relative to the curve itself, but at small forces relative to the
    tested-range elongation (a 0.01 mm difference at F ≈ 0 is not a different curve).

    Returns
    -------
    diff : ndarray (optimum, force)
    extrapolated : ndarray (force,) bool
    """
    e = optima["elongation"].values
    ib = int(np.nanargmin(optima["delta_objective"].values))
    ext = optima["extrapolated"].values.astype(bool).any(axis=0)
    inside = np.flatnonzero(~ext)
    floor = e[ib, inside[-1]] if inside.size else 0.0
    with np.errstate(invalid="ignore", divide="ignore"):
        diff = (e - e[ib]) / np.maximum(e[ib], floor)
    return diff, ext


def optima_spread(optima: xr.Dataset) -> tuple[float, float]:
    """Largest |difference| of the near-optimal sets from the best one (:func:`optima_difference`).

    Returns ``(within, beyond)``: over forces where no set is extrapolated, and over the forces
    beyond.  NaN where there are none.
    """
    diff, ext = optima_difference(optima)
    rel = np.abs(diff)

    def mx(cols):
        v = rel[:, cols]
        return float(np.nanmax(v)) if np.isfinite(v).any() else float("nan")

    return mx(~ext), mx(ext)


def optima_agreement(optima: xr.Dataset, tol: float = 0.01) -> int:
    """Number of near-optimal sets within ``tol`` of the best set's curve (:func:`optima_difference`)
    at every force of the tested range, the best set included."""
    diff, ext = optima_difference(optima)
    v = np.abs(diff[:, ~ext])
    v = np.where(np.isfinite(v), v, 0.0)
    return int(np.sum(v.max(axis=1, initial=0.0) <= tol))


def _subsample(n: int, m: int, rng: np.random.Generator) -> np.ndarray:
    return np.arange(n) if m >= n else np.sort(rng.choice(n, m, replace=False))


# ----------------------------------------------------------------------------- the prediction
def predict_organ(results: str | os.PathLike, geometry: FusiformGeometry | str | os.PathLike, *,
                  out: str | os.PathLike | None = None, **kwargs) -> OrganPrediction:
    """Organ force–elongation curves for every specimen of an ``hbm run`` output folder.

    Parameters
    ----------
    results : path
        Output folder of ``hbm run``: ``specimens/<id>.nc`` (complete files only) and, if
        present, ``hierarchical.nc``.
    geometry : FusiformGeometry or path of a TOML file (:func:`hbm.organ.load_geometry`)
    out : path, optional
        Output folder (default ``<results>/organ``): ``organ.nc`` and ``figures/``.
    **kwargs
        See :func:`predict_organ_results`.

    Raises
    ------
    HbmError
        Missing folder, no complete specimen results, bad geometry.
    """
    results = Path(results)
    if not results.is_dir():
        raise HbmError(f"RESULTS {str(results)!r}: no such folder (expected the output folder of 'hbm run')")
    files = sorted((results / "specimens").glob("*.nc"))
    done = [p for p in files if io.is_complete(p)]
    if not done:
        raise HbmError(f"RESULTS {str(results)!r}: no complete specimen results in {results / 'specimens'} "
                       f"(expected <id>.nc files written by 'hbm run' or 'hbm fit')")
    specimens = {}
    for p in done:
        r = io.read_specimen_result(p)
        specimens[r.specimen_id] = r
    hpath = results / "hierarchical.nc"
    hier = io.read_hierarchical(hpath) if io.is_complete(hpath) else None
    if hier is None and hpath.exists():  # never drop the updated and population rows silently
        warnings.warn(f"{hpath} is incomplete or unreadable (truncated?): predictions without the hierarchical "
                      "layer (no updated-individual or population rows); rerun 'hbm run' to rebuild it",
                      HbmWarning, stacklevel=2)
    pred = predict_organ_results(specimens, geometry, hierarchical=hier,
                                 out=Path(out) if out is not None else results / "organ", **kwargs)
    skipped = [p.stem for p in files if p not in done]
    if skipped:
        pred.notes.append(f"incomplete result files skipped: {', '.join(skipped)}")
    return pred


def predict_organ_results(specimens: Mapping[str, io.SpecimenResult], geometry: FusiformGeometry | str | os.PathLike,
                          *, hierarchical: io.HierarchicalFile | None = None, out: str | os.PathLike | None = None,
                          model: Model | None = None, samples: int = 2000, forces: int = 200, seed: int = 0,
                          extrapolate: float = 2.0, ref_force: float | None = None, near: float = 3.0,
                          figures: bool = True, optima_specimen: str | None = None) -> OrganPrediction:
    """Organ curves from in-memory specimen results (the engine behind :func:`predict_organ`).

    Parameters
    ----------
    specimens : {id: SpecimenResult}
    geometry : FusiformGeometry or TOML path
    hierarchical : HierarchicalFile, optional
        Adds the ``"updated"`` source per specimen and the population predictive.
    out : path, optional
        Folder for ``organ.nc`` and ``figures/``; None keeps everything in memory.
    model : Model, optional
        Default: rebuilt from the result files (:func:`model_for_results`).
    samples : int
        Posterior (and updated-individual) draws per specimen: a seeded subsample without
        replacement; all draws when the files hold fewer.
    forces : int
        Force levels of the common grid per specimen.
    seed : int
        Root seed of the subsampling (streams ``organ_*`` of :mod:`hbm.runtime.seeds`).
    extrapolate : float
        The force grid ends at ``extrapolate`` × the force at which the median posterior draw's
        thinnest section reaches the largest tested strain (>= 1; 1 = no extrapolation).
    ref_force : float, optional
        Force (N) of the summary table's "elongation at F_ref"; default: a round number ≤ 0.8 ×
        the smallest (over specimens) median force at which the organ leaves the tested range,
        so that the comparison across specimens is mostly interpolation.
    near : float
        CMA-ES optima with −log-likelihood within ``near`` of the specimen's best are
        "near-optimal" (3 ≈ the 95 % likelihood-ratio region for 2 parameters).
    figures : bool
        Draw the figures (needs ``out``).
    optima_specimen : str, optional
        Specimen of the highlighted CMA-ES figure (default: the one with most near-optimal sets).

    Returns
    -------
    OrganPrediction
    """
    t_all = time.perf_counter()
    if not specimens:
        raise HbmError("no specimen results to predict from")
    if isinstance(geometry, (str, os.PathLike)):
        geometry = load_geometry(geometry)
    if int(samples) < 2:
        raise HbmError(f"samples must be >= 2, got {samples}")
    if int(forces) < 2:
        raise HbmError(f"forces must be >= 2, got {forces}")
    if not (np.isfinite(extrapolate) and extrapolate >= 1):
        raise HbmError(f"extrapolate must be a number >= 1 (a force multiple), got {extrapolate!r}")
    if ref_force is not None and not (np.isfinite(ref_force) and ref_force > 0):
        raise HbmError(f"ref_force must be a force > 0 N, got {ref_force!r}")
    if optima_specimen is not None and optima_specimen not in specimens:
        raise HbmError(f"optima specimen {optima_specimen!r} is not among the results ({', '.join(sorted(specimens))})")
    model = model_for_results(specimens, model)
    ids = sorted(specimens)
    notes: list[str] = []
    timings: dict[str, float] = {}

    # pass 1: draws, tested strains and the force where each draw's organ leaves the tested range
    prep: dict[str, dict] = {}
    for k, sid in enumerate(ids):
        r = specimens[sid]
        if r.data is None:
            raise HbmError(f"specimen {sid}: the result holds no observed strains (needed for the extrapolation check)")
        tested = float(np.max(r.data.strain))
        if not tested > 0:
            raise HbmError(f"specimen {sid}: largest tested strain is {tested:g}; expected > 0")
        rng = seeds.rng(int(seed), "organ_posterior", k)
        idx = _subsample(r.n_samples, int(samples), rng)
        theta = theta_from_samples(model, r.names, r.samples[idx], r.fixed)
        d = {"tested": tested, "theta": theta, "f_ext": force_at_tested_strain(model, theta, geometry, tested)}
        if hierarchical is not None and hierarchical.updated is not None and sid in hierarchical.specimen_ids:
            up = hierarchical.updated[:, hierarchical.specimen_ids.index(sid), :]
            iu = _subsample(up.shape[0], int(samples), seeds.rng(int(seed), "organ_updated", k))
            d["theta_up"] = theta_from_samples(model, hierarchical.param_names, up[iu], r.fixed)
        if r.optima:
            best = min(float(o["objective"]) for o in r.optima)
            sel = [o for o in r.optima if float(o["objective"]) <= best + near]
            sel.sort(key=lambda o: float(o["params"].get(_fraction(model), 0.0)))
            d["optima"], d["best"] = sel, best
            d["optima_dropped"] = len(r.optima) - len(sel)
        prep[sid] = d
    if ref_force is None:
        ref_force = _nice_floor(0.8 * min(float(np.median(d["f_ext"])) for d in prep.values()))

    # pass 2: organ responses on one force grid per specimen
    curves: dict[str, dict[str, xr.Dataset]] = {}
    excluded: tuple = ()

    def solve(key: str, th: np.ndarray, grid: np.ndarray, with_ref: bool = True):
        nonlocal excluded
        resp = organ_response(model, th, geometry, grid)
        timings[key] = resp.wall_time
        excluded = resp.excluded_effects
        if not with_ref:
            return resp, None
        ref = organ_response(model, th, geometry, np.array([ref_force]))  # exact, no interpolation
        timings[key] += ref.wall_time
        return resp, ref

    for sid in ids:
        d = prep[sid]
        grid = _grid(model, d["theta"], geometry, d["tested"], extrapolate, int(forces))
        resp, ref = solve(f"{sid}/posterior", d["theta"], grid)
        curves[sid] = {"posterior": _band_dataset(resp, d["tested"], d["f_ext"], ref, "posterior",
                                                  {"specimen": sid})}
        if "theta_up" in d:
            th = d["theta_up"]
            resp, ref = solve(f"{sid}/updated", th, grid)
            curves[sid]["updated"] = _band_dataset(
                resp, d["tested"], force_at_tested_strain(model, th, geometry, d["tested"]), ref, "updated",
                {"specimen": sid})
        if d.get("optima"):
            cols = list(d["optima"][0]["params"])
            th = theta_from_samples(model, cols, np.array([[o["params"][n] for n in cols] for o in d["optima"]]),
                                    specimens[sid].fixed)
            resp, _ = solve(f"{sid}/optima", th, grid, with_ref=False)
            curves[sid]["optima"] = _optima_dataset(resp, d["tested"],
                                                    force_at_tested_strain(model, th, geometry, d["tested"]),
                                                    d["optima"], d["best"], near)
            curves[sid]["optima"].attrs["dropped"] = int(d["optima_dropped"])

    population = None
    if hierarchical is not None and hierarchical.new_specimen is not None:
        fixed = specimens[ids[0]].fixed
        try:
            th = theta_from_samples(model, hierarchical.pooled_names, hierarchical.new_specimen, fixed)
        except HbmError:
            notes.append("population predictive skipped: the hierarchical layer pooled only "
                         f"{', '.join(hierarchical.pooled_names)}, so a new specimen's other parameters are unknown")
        else:
            ip = _subsample(th.shape[0], int(samples), seeds.rng(int(seed), "organ_new_specimen"))
            th = th[ip]
            # a new specimen was never tested: its tested range is the widest of the specimens'
            tested = max(d["tested"] for d in prep.values())
            grid = _grid(model, th, geometry, tested, extrapolate, int(forces))
            resp, ref = solve("population", th, grid)
            population = _band_dataset(resp, tested, force_at_tested_strain(model, th, geometry, tested), ref,
                                       "population", {"specimen": "new specimen"})
    solver = float(sum(timings.values()))
    timings["solver"] = solver

    attrs = {"geometry": geometry.to_dict(), "geometry_description": geometry.describe(), "model": model.name,
             "effects": list(model.effect_names), "excluded_effects": list(excluded),
             "samples": int(samples), "forces": int(forces), "seed": int(seed), "extrapolate": float(extrapolate),
             "ref_force": float(ref_force), "near": float(near), "probs": list(PROBS), "notes": notes}
    organ = io.OrganFile(curves=curves, population=population, attrs=attrs)
    pred = OrganPrediction(organ=organ, geometry=geometry, timings=timings, notes=notes)
    if out is not None:
        out = Path(out)
        if figures:
            t = time.perf_counter()
            from ..plots.organ import organ_figures  # matplotlib: loaded only when figures are drawn

            comparison = {sid: (optima_difference(c["optima"])[0], optima_spread(c["optima"]))
                          for sid, c in organ.curves.items() if "optima" in c and c["optima"].sizes["optimum"] >= 1}
            pred.figures = organ_figures(organ, out / "figures", optima_specimen=optima_specimen,
                                         optima_comparison=comparison)
            timings["figures"] = time.perf_counter() - t
        timings["total"] = time.perf_counter() - t_all
        organ.attrs["timings"] = timings
        pred.path = io.write_organ(organ, out / "organ.nc")
    timings["total"] = time.perf_counter() - t_all
    pred.rows = summary_rows(organ)
    return pred


# ----------------------------------------------------------------------------- summaries
def summary_rows(organ: io.OrganFile) -> list[dict]:
    """One row per (specimen, source) with a band, plus the population.

    Keys: ``specimen``, ``source``, ``ref_force`` (N), ``elongation_at_ref`` (5/50/95 %, mm),
    ``extrapolated_at_ref`` (share of draws whose organ strains exceed the tested strain at
    F_ref), ``tested_range_force`` (5/50/95 % of the force at which the organ leaves the tested
    strain range, N), ``tested_max_strain``, ``n_draws``, ``unreachable`` (largest share of
    draws needing a stretch beyond the solver's ``max_stretch``).
    """
    rows = []
    items = [(sid, src, ds) for sid in organ.specimen_ids for src, ds in organ.curves[sid].items()
             if src != "optima"]
    if organ.population is not None:
        items.append(("population", "new specimen", organ.population))
    for sid, src, ds in items:
        rows.append({"specimen": sid, "source": src, "ref_force": float(ds.attrs["ref_force"]),
                     "elongation_at_ref": ds["elongation_at_ref"].values.tolist(),
                     "extrapolated_at_ref": float(ds["extrapolated_at_ref"]),
                     "tested_range_force": ds["tested_range_force"].values.tolist(),
                     "tested_max_strain": float(ds.attrs["tested_max_strain"]), "n_draws": int(ds.attrs["n_draws"]),
                     "unreachable": float(ds["unreachable_share"].max())})
    return rows


def _g(x, digits=3) -> str:
    return "–" if x is None or not np.isfinite(x) else f"{x:.{digits}g}"


def _pct(x) -> str:
    return "–" if x is None or not np.isfinite(x) else f"{100 * x:.2g}%"


def _interval(q) -> str:
    return f"{_g(q[1])} [{_g(q[0])}, {_g(q[2])}]"


def _table_cells(rows: Sequence[dict]) -> tuple[list[str], list[list[str]]]:
    f_ref = rows[0]["ref_force"] if rows else float("nan")
    header = ["specimen", "curves from", f"elongation at F_ref = {_g(f_ref)} N (mm, median [90%])",
              "draws extrapolated at F_ref", "organ leaves tested range at F (N, median [90%])",
              "max tested strain", "draws"]
    body = [[r["specimen"], r["source"], _interval(r["elongation_at_ref"]), f"{r['extrapolated_at_ref']:.0%}",
             _interval(r["tested_range_force"]), _g(r["tested_max_strain"]), str(r["n_draws"])] for r in rows]
    return header, body


def format_summary(rows: Sequence[dict]) -> str:
    """Plain-text table of :func:`summary_rows` for the terminal."""
    header, body = _table_cells(rows)
    widths = [max(len(str(x)) for x in col) for col in zip(header, *body)]

    def line(r):
        return "  ".join(str(x).ljust(w) if i < 2 else str(x).rjust(w) for i, (x, w) in enumerate(zip(r, widths)))

    return "\n".join([line(header), "  ".join("-" * w for w in widths)] + [line(r) for r in body])


def _rel(path: Path, base: Path) -> str:
    try:
        return os.path.relpath(path, base)
    except ValueError:  # pragma: no cover - other drive
        return str(path)


def organ_section(pred: OrganPrediction, *, base: str | os.PathLike | None = None) -> str:
    """Markdown report section: geometry, assumptions, summary table, figure links, timing.

    Parameters
    ----------
    pred : OrganPrediction
    base : path, optional
        Folder of the report (figure links are relative to it).
    """
    base = Path(base) if base is not None else (pred.path.parent if pred.path else Path("."))
    g = pred.geometry
    a = pred.organ.attrs
    header, body = _table_cells(pred.rows)
    lines = ["| " + " | ".join(header) + " |", "|" + "|".join("---" for _ in header) + "|"]
    lines += ["| " + " | ".join(r) + " |" for r in body]
    parts = ["## Organ-scale prediction (fusiform muscle)",
             f"Geometry: {g.describe()}" + (f" Source: {g.source}." if g.source else ""),
             "Slender-body model (`hbm.organ`): every belly section carries the same axial force with the "
             "uniaxial stress of the fitted tissue law over its current area A0/λ; elongation = ∫(λ−1)dz + "
             "tendons. Assumes slow radius variation, fibers along the axis, incompressible, passive and "
             "quasi-static tissue (elastic stage of the model only"
             + (f"; not used: {', '.join(a.get('excluded_effects', []))}" if a.get("excluded_effects") else "")
             + "). Bands: pointwise 5–95 % over the draws at each force (one force grid per specimen). "
             "**Extrapolation:** where the organ's largest fiber strain (at the thinnest section) exceeds the "
             "largest strain tested on the specimen, the curve is an extrapolation of the material law "
             "(dashed/hatched in the figures).",
             "\n".join(lines)]
    opt = {sid: c["optima"] for sid, c in pred.organ.curves.items() if "optima" in c}
    if opt:
        spreads = []
        for sid, ds in sorted(opt.items()):
            n_opt = ds.sizes["optimum"]
            if n_opt >= 2:
                within, beyond = optima_spread(ds)
                x = _fraction(None)
                vol = ds["parameters"].sel(parameter=x).values if x in ds["parameter"] else None
                spreads.append(f"| {sid} | {n_opt} | "
                               + (f"{vol.min():.2f}–{vol.max():.2f}" if vol is not None else "–")
                               + f" | {optima_agreement(ds)} of {n_opt} | {_pct(within)} | {_pct(beyond)} |")
        if spreads:
            parts.append(f"Near-optimal CMA-ES sets (−log L within {a.get('near', 3):g} of the best; restarts and "
                         "VOLF-sweep optima) pushed through the organ model (thesis Fig. 3.65): how many sets give "
                         "the best set's curve to 1 % throughout the tested range, and the largest difference of "
                         "any set's elongation from the best set's (relative to the best set's elongation, at "
                         "least its value at the end of the tested range), where every set is within its tested "
                         "strain range and beyond it. Sets off the best set's manifold (other local optima) "
                         "differ most, often at small forces; see the optima figure.\n\n"
                         "| specimen | sets | VOLF range | sets agreeing to 1 % | largest difference, tested range | "
                         "largest difference, extrapolated |\n|---|---|---|---|---|---|\n"
                         + "\n".join(spreads))
    if pred.notes:
        parts.append("Notes: " + "; ".join(pred.notes) + ".")
    if pred.figures:
        parts.append("\n".join(f"![{Path(f).stem}]({_rel(Path(f), base)})" for f in pred.figures))
    t = pred.timings
    parts.append(f"Computation: {_g(t.get('solver'))} s in the organ solver, {_g(t.get('total'))} s in total "
                 f"(up to {a.get('samples')} draws per source (column 'draws') × {a.get('forces')} force levels × "
                 f"{g.n_sections} sections)." + (f" Curves: `{_rel(pred.path, base)}`." if pred.path else ""))
    return "\n\n".join(parts)


def organ_report_hook(geometry: FusiformGeometry | str | os.PathLike, *, out: str | os.PathLike | None = None,
                      **kwargs) -> Callable[[Any], str]:
    """A ``run_workflow(extra_sections=[...])`` hook running the organ prediction on the run's results.

    The hook reads the in-memory results of the run, writes ``<run out>/organ/organ.nc`` (or
    ``out``) and figures, stores the prediction on ``hook.prediction``, adds
    ``timings["organ"]`` to the run and returns :func:`organ_section`.

    Parameters
    ----------
    geometry : FusiformGeometry or TOML path
    out : path, optional
    **kwargs
        Passed to :func:`predict_organ_results` (model, samples, forces, seed, figures, ...).
    """
    if isinstance(geometry, (str, os.PathLike)):
        geometry = load_geometry(geometry)

    def organ_prediction(wres) -> str:
        if not wres.results:
            return ""
        t = time.perf_counter()
        pred = predict_organ_results(wres.results, geometry, hierarchical=wres.hierarchical,
                                     out=Path(out) if out is not None else Path(wres.out) / "organ", **kwargs)
        organ_prediction.prediction = pred
        wres.timings["organ"] = time.perf_counter() - t
        return organ_section(pred, base=wres.out)

    organ_prediction.prediction = None
    return organ_prediction
