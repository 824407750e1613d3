"""Results <-> netCDF.  The only module of hbm that knows netCDF group and variable names.

Per-specimen file ``<out>/specimens/<id>.nc`` (ArviZ ``InferenceData`` layout, one netCDF4
file with groups, written with :class:`xarray.DataTree`):

``posterior``             (chain, draw): one variable per free parameter, noise parameters
                          (``sigma`` ...) included.  TMCMC's final population is resampled to
                          equal weights, so it is stored as ONE chain of ``n`` draws.
``sample_stats``          (chain, stage): one float64 variable per field of the sampler's
                          :class:`~hbm.samplers.tmcmc.StageInfo` (``beta``,
                          ``log_evidence_increment``, ``acceptance_rate``, ``cov_weights``,
                          ``ess``, ``evaluations``, ``n_steps``, ``proposal_scale``, ...;
                          NaN where a stage did not report it, ``capped`` as 0/1); (chain,):
                          ``log_marginal_likelihood`` and ``log_marginal_likelihood_se``;
                          (chain, draw): ``log_likelihood_sum`` (total log-likelihood per draw).
                          The stage axis never shares the ``draw`` dimension.
``log_likelihood``        (chain, draw, point): pointwise log-likelihood ``stress``.
``posterior_predictive``  (chain, draw, point): ``stress`` (noisy replicate) and
                          ``stress_model`` (noise-free model prediction).
``observed_data``         (point): ``stress`` with coordinates ``strain`` (and ``time``, ``test``).
``constant_data``         (parameter): prior box ``prior_lower``, ``prior_upper``.
``optima``                (optimum): CMA-ES optima, one variable per parameter + ``objective``
                          (+ ``window_lower``/``window_upper`` of a bound sweep, ``kind``).
``sobol``                 (parameter[, point]): ``S1``, ``ST``, ``S1_conf``, ``ST_conf``,
                          ``relevance`` (+ per-point ``S1_point``/``ST_point``).

Root attributes: ``specimen_id``, ``model``, ``effects`` (JSON list), ``config`` (JSON),
``seed`` (int), ``hbm_version``, ``timings`` (JSON), ``prior`` (JSON ``{name: {"lo", "hi",
"form"}}``: the prior each free parameter was sampled under, natural units), ``at_bounds`` (JSON
list of ``{"parameter", "side", "edge", "fraction", "map_at_edge"}``, see
:func:`hbm.fit.at_bounds`), ``complete`` (int, set to 1 last, after every group is on disk).  netCDF attributes cannot hold bool/None/dict, hence ints and JSON.

Hierarchical file ``<out>/hierarchical.nc``: ``posterior`` (chain, draw) with ``mu_<P>`` and
``sd_<P>`` (hyper-parameters), ``updated`` (chain, draw, specimen) one variable per parameter
(the updated individual posteriors), ``sample_stats`` (chain, stage) + hyper-evidence,
``new_specimen`` (chain, draw) the predictive of a new specimen, ``diagnostics`` (specimen):
importance ESS; root attrs as above.  A grouped layer (population → group → specimen) adds
``sd_between_<P>``, ``sd_within_<P>`` to ``posterior`` (``sd_<P>`` is then their root sum of squares)
and a ``groups`` group: (chain, draw, group) ``mean_<P>`` (group means, transformed units) and
``new_specimen_<P>`` (a new specimen of each group), (specimen) ``specimen_group``; attrs ``key``
(the metadata key grouped by) and ``extra`` (JSON).

``<out>/manifolds.nc``: group per specimen-independent table (specimen, grid) of spline
manifolds and identified combinations (see :func:`write_population_summary`).
"""

from __future__ import annotations

import json
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Mapping, Sequence

import numpy as np
import xarray as xr

from . import conventions
from ._version import __version__
from .errors import HbmError, OutputError
from .samplers.types import StageInfo
from .utils import atomic_path, write_error

__all__ = ["SpecimenResult", "HierarchicalFile", "write_specimen_result", "read_specimen_result",
           "is_complete", "read_attrs", "write_hierarchical", "read_hierarchical", "write_population_summary",
           "read_population_summary", "to_inference_data", "specimen_path", "json_default"]

# netCDF group names (kept here and nowhere else)
G_POSTERIOR = "posterior"
G_STATS = "sample_stats"
G_LOGLIK = "log_likelihood"
G_PRED = "posterior_predictive"
G_OBS = "observed_data"
G_CONST = "constant_data"
G_OPTIMA = "optima"
G_SOBOL = "sobol"
G_UPDATED = "updated"
G_NEW = "new_specimen"
G_DIAG = "diagnostics"
G_MANIFOLD = "manifolds"
G_COMBOS = "combinations"
G_GROUPS = "groups"
G_PRIOR = "prior"

#: per-stage variables of ``sample_stats``: the sampler's stage record is the schema
STAGE_KEYS = StageInfo._fields


def json_default(obj: Any) -> Any:
    """``json.dumps`` fallback for numpy scalars/arrays and paths."""
    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    if isinstance(obj, (Path, os.PathLike)):
        return str(obj)
    return repr(obj)


def _dumps(obj: Any) -> str:
    return json.dumps(obj, default=json_default, sort_keys=True)


def specimen_path(out: str | os.PathLike, specimen_id: str) -> Path:
    """``<out>/specimens/<id>.nc``."""
    return Path(out) / "specimens" / f"{specimen_id}.nc"


@dataclass
class SpecimenResult:
    """Everything stored for one specimen (what the readers return, what the writer takes).

    Attributes
    ----------
    specimen_id : str
    names : list of str
        Free parameter names, columns of ``samples`` (model parameters then noise parameters).
    samples : ndarray (n, d)
        Equal-weight posterior population.
    log_likelihood : ndarray (n,)
        Total log-likelihood of each sample.
    log_evidence, log_evidence_se : float
    bounds : ndarray (d, 2)
        Prior box of the free parameters.
    stages : list of StageInfo (or mappings with a subset of its fields)
        Per TMCMC stage, as returned by the sampler; read back as :class:`StageInfo`.
    strain, stress : ndarray (p,)
        Observed data; ``time``/``test`` optional.
    pointwise_log_likelihood, predictive, predictive_model : ndarray (n, p) or None
        Pointwise log-likelihood, noisy posterior-predictive replicate, noise-free prediction.
    optima : list of dict or None
        ``{"params": {name: value}, "objective": f, ...}`` as from :mod:`hbm.optimization`.
    sobol : dict or None
        ``{"S1": {name: v}, "ST": ..., "S1_conf": ..., "ST_conf": ..., "relevance": {name: str}}``
        and optionally ``"S1_point"``/``"ST_point"`` as ``{name: array (p,)}`` and ``"qoi"``.
    model, effects, config, seed, timings, complete, version : metadata
    fixed : dict
        Parameters held fixed (name -> value), recorded so model thetas can be rebuilt.
    prior : dict or None
        ``{name: {"lo", "hi", "form"}}`` per free parameter (natural units); None means uniform
        on ``bounds`` (files written before priors were stored read back that way).
    at_bounds : list of dict or None
        Box-edge warnings (:func:`hbm.fit.at_bounds`); None when not computed.
    """

    specimen_id: str
    names: list[str]
    samples: np.ndarray
    log_likelihood: np.ndarray
    log_evidence: float
    log_evidence_se: float
    bounds: np.ndarray
    stages: list[StageInfo | Mapping[str, Any]] = field(default_factory=list)
    strain: np.ndarray | None = None
    stress: np.ndarray | None = None
    time: np.ndarray | None = None
    test: np.ndarray | None = None
    pointwise_log_likelihood: np.ndarray | None = None
    predictive: np.ndarray | None = None
    predictive_model: np.ndarray | None = None
    optima: list[dict] | None = None
    sobol: dict | None = None
    model: str = "spyrou"
    effects: list[str] = field(default_factory=list)
    config: dict = field(default_factory=dict)
    seed: int = 0
    timings: dict = field(default_factory=dict)
    fixed: dict = field(default_factory=dict)
    complete: bool = True
    version: str = __version__
    prior: dict | None = None
    at_bounds: list[dict] | None = None
    parameter_info: dict = field(default_factory=dict)

    def prior_dict(self) -> dict[str, dict[str, Any]]:
        """``{name: {"lo", "hi", "form"}}`` per free parameter (uniform on ``bounds`` when not recorded)."""
        if self.prior:
            return {n: dict(self.prior[n]) for n in self.names if n in self.prior}
        b = np.asarray(self.bounds, float)
        return {n: {"lo": float(b[i, 0]), "hi": float(b[i, 1]), "form": "uniform"} for i, n in enumerate(self.names)}

    @property
    def n_samples(self) -> int:
        return int(self.samples.shape[0])

    def column(self, name: str) -> np.ndarray:
        """Samples of parameter ``name`` (n,)."""
        try:
            return self.samples[:, self.names.index(name)]
        except ValueError:
            if name in self.fixed:
                return np.full(self.n_samples, float(self.fixed[name]))
            raise KeyError(f"parameter {name!r} not in {self.names}") from None

    def as_dict(self) -> dict[str, np.ndarray]:
        """name -> samples, fixed parameters included as constant columns."""
        out = {n: self.samples[:, i] for i, n in enumerate(self.names)}
        for k, v in self.fixed.items():
            out.setdefault(k, np.full(self.n_samples, float(v)))
        return out


# ----------------------------------------------------------------------------- stage records
def _stage_row(s: StageInfo | Mapping[str, Any]) -> Mapping[str, Any]:
    return s._asdict() if isinstance(s, StageInfo) else s


def _add_stage_stats(stats: dict[str, Any], coords: dict[str, Any],
                     stages: Sequence[StageInfo | Mapping[str, Any]]) -> None:
    """One (chain, stage) float64 variable per :class:`StageInfo` field into ``stats``.

    A field no stage reports (a mapping from a foreign sampler) is left out; a field some
    stages lack is NaN there.  Booleans become 0/1.
    """
    if not stages:
        return
    rows = [_stage_row(s) for s in stages]
    coords["stage"] = np.arange(len(rows))
    for key in STAGE_KEYS:
        vals = [row.get(key) for row in rows]
        if all(v is None for v in vals):
            continue
        arr = np.array([np.nan if v is None else float(np.mean(v)) for v in vals], dtype=float)
        stats[key] = (("chain", "stage"), arr[None, :])


def _read_stage_stats(stats: xr.Dataset) -> list[StageInfo]:
    """The per-stage variables of a ``sample_stats`` group back as :class:`StageInfo` records."""
    if "stage" not in stats.dims:
        return []
    cols = {k: stats[k].values[0] for k in STAGE_KEYS if k in stats}
    return [StageInfo.from_record({k: v[i] for k, v in cols.items()}) for i in range(stats.sizes["stage"])]


# ----------------------------------------------------------------------------- writing
def _specimen_tree(r: SpecimenResult) -> xr.DataTree:
    n, d = r.samples.shape
    if len(r.names) != d:
        raise HbmError(f"specimen {r.specimen_id}: {d} sample columns but {len(r.names)} names")
    draws = {"chain": [0], "draw": np.arange(n)}
    info = r.parameter_info
    post = xr.Dataset({nm: (("chain", "draw"), r.samples[None, :, i]) for i, nm in enumerate(r.names)},
                      coords=draws)
    groups: dict[str, xr.Dataset] = {G_POSTERIOR: conventions.annotate(post, "parameters", info)}
    pd = r.prior_dict()
    if len(pd) == d:  # ArviZ's prior group: draws from the prior box, as many as the posterior's
        pdraws = conventions.prior_draws(r.names, pd, n, r.seed, r.config.get("seed_spawn_key", ()))
        groups[G_PRIOR] = conventions.annotate(xr.Dataset(
            {nm: (("chain", "draw"), pdraws[None, :, i]) for i, nm in enumerate(r.names)}, coords=draws),
            "parameters", info)

    ll_sum = np.asarray(r.log_likelihood, float)
    stats = {"log_marginal_likelihood": (("chain",), [float(r.log_evidence)]),
             "log_marginal_likelihood_se": (("chain",), [float(r.log_evidence_se)]),
             "log_likelihood_sum": (("chain", "draw"), ll_sum[None, :]),
             # ArviZ's lp: log posterior density up to the evidence (log likelihood + log prior)
             "lp": (("chain", "draw"), (ll_sum + conventions.log_prior(r.samples, r.names, pd))[None, :])}
    coords = dict(draws)
    _add_stage_stats(stats, coords, r.stages)
    groups[G_STATS] = conventions.annotate(xr.Dataset(stats, coords=coords), "stats")

    if r.stress is not None:
        p = len(r.stress)
        pc: dict[str, Any] = {"point": np.arange(p)}
        if r.strain is not None:
            pc["strain"] = ("point", np.asarray(r.strain, float))
        if r.time is not None:
            pc["time"] = ("point", np.asarray(r.time, float))
        if r.test is not None:
            pc["test"] = ("point", np.asarray(r.test).astype(np.int64))
        groups[G_OBS] = conventions.annotate(
            xr.Dataset({"stress": ("point", np.asarray(r.stress, float))}, coords=pc), "observed")
        dcp = {**draws, **pc}
        if r.pointwise_log_likelihood is not None:
            groups[G_LOGLIK] = conventions.annotate(xr.Dataset(
                {"stress": (("chain", "draw", "point"), r.pointwise_log_likelihood[None])}, coords=dcp),
                "log_likelihood")
        pred = {}
        if r.predictive is not None:
            pred["stress"] = (("chain", "draw", "point"), r.predictive[None])
        if r.predictive_model is not None:
            pred["stress_model"] = (("chain", "draw", "point"), r.predictive_model[None])
        if pred:
            groups[G_PRED] = conventions.annotate(xr.Dataset(pred, coords=dcp), "predictive")

    b = np.asarray(r.bounds, float)
    groups[G_CONST] = conventions.annotate(
        xr.Dataset({"prior_lower": ("parameter", b[:, 0]), "prior_upper": ("parameter", b[:, 1])},
                   coords={"parameter": list(r.names)}), "constant", info)

    if r.optima:
        pnames = list(r.optima[0]["params"])
        ov: dict[str, Any] = {nm: ("optimum", [float(o["params"].get(nm, np.nan)) for o in r.optima])
                              for nm in pnames}
        ov["objective"] = ("optimum", [float(o.get("objective", np.nan)) for o in r.optima])
        for key in ("window_lower", "window_upper"):
            if any(key in o for o in r.optima):
                ov[key] = ("optimum", [float(o.get(key, np.nan)) for o in r.optima])
        ov["kind"] = ("optimum", np.array([str(o.get("kind", "restart")) for o in r.optima], dtype=object))
        groups[G_OPTIMA] = xr.Dataset(ov, coords={"optimum": np.arange(len(r.optima))})

    if r.sobol:
        s = r.sobol
        spn = list(s["S1"])
        sv: dict[str, Any] = {}
        for key in ("S1", "ST", "S1_conf", "ST_conf"):
            if key in s:
                sv[key] = ("parameter", [float(s[key][nm]) for nm in spn])
        if "relevance" in s:
            sv["relevance"] = ("parameter", np.array([str(s["relevance"][nm]) for nm in spn], dtype=object))
        sc: dict[str, Any] = {"parameter": spn}
        for key in ("S1_point", "ST_point"):
            if s.get(key) is not None:
                sv[key] = (("parameter", "point"), np.array([np.asarray(s[key][nm], float) for nm in spn]))
        sattrs = {k: (v if isinstance(v, (int, float, str)) else _dumps(v))
                  for k, v in s.items() if k not in ("S1", "ST", "S1_conf", "ST_conf", "relevance",
                                                     "S1_point", "ST_point")}
        groups[G_SOBOL] = xr.Dataset(sv, coords=sc, attrs=sattrs)

    root = xr.Dataset(attrs={
        "specimen_id": str(r.specimen_id),
        "model": str(r.model),
        "effects": _dumps(list(r.effects)),
        "config": _dumps(r.config),
        "fixed": _dumps(r.fixed),
        "seed": int(r.seed),
        "hbm_version": str(r.version),
        "timings": _dumps(r.timings),
        "prior": _dumps(r.prior_dict()),
        "at_bounds": _dumps(r.at_bounds if r.at_bounds is not None else []),
        "inference_library": "hbm",
        "likelihood_tier": str(r.config.get("likelihood_tier", "full")),
        "complete": 0,
    })
    return xr.DataTree.from_dict({"/": root, **groups})


def _mark_complete(path: Path) -> None:
    """Set the root attribute ``complete = 1`` -- the very last write into the file.

    Only on a file that exists and was written: netCDF's append mode would create an empty
    file (which would then count as a complete result) if another process had removed it.
    """
    import netCDF4  # local: only needed here

    if not path.is_file() or path.stat().st_size == 0:
        raise OutputError(f"cannot mark {path} complete: the file vanished while it was written (removed by "
                          "another process?); nothing was stored")
    with netCDF4.Dataset(path, "r+") as nc:
        nc.setncattr("complete", np.int32(1))


def _write_tree(tree, path: str | os.PathLike, complete: bool | None) -> Path:
    """Write a DataTree atomically; with ``complete`` set the flag is the last write before the rename.

    ``complete=None``: files without a completeness flag.  A failed write (full disk,
    permission) raises :class:`hbm.errors.OutputError` naming ``path``; no temporary file stays.
    """
    path = Path(path)
    with atomic_path(path) as tmp:
        try:
            tree.to_netcdf(tmp, engine="netcdf4")
            if complete:
                _mark_complete(tmp)
        except RuntimeError as exc:  # netCDF4/HDF5 report a failed write (full disk, I/O) this way
            raise write_error(path, exc) from exc
    return path


def write_specimen_result(result: SpecimenResult, path: str | os.PathLike) -> Path:
    """Write ``result`` to ``path`` atomically (temp file, ``complete`` flag last, rename).

    Returns
    -------
    Path
    """
    path = Path(path)
    tree = _specimen_tree(result)
    return _write_tree(tree, path, result.complete)


# ----------------------------------------------------------------------------- reading
def is_complete(path: str | os.PathLike) -> bool:
    """True if ``path`` is a readable hbm result whose ``complete`` flag is 1."""
    path = Path(path)
    if not path.is_file():
        return False
    try:
        import netCDF4

        with netCDF4.Dataset(path, "r") as nc:
            return int(getattr(nc, "complete", 0)) == 1
    except Exception:  # unreadable / truncated file counts as incomplete
        return False


def read_attrs(path: str | os.PathLike) -> dict:
    """Root attributes of a result file (JSON ones decoded); {} if unreadable."""
    try:
        import netCDF4

        with netCDF4.Dataset(path, "r") as nc:
            attrs = {k: nc.getncattr(k) for k in nc.ncattrs()}
    except Exception:
        return {}
    for k in ("config", "effects", "timings", "fixed", "extra", "prior", "at_bounds"):
        if isinstance(attrs.get(k), str):
            try:
                attrs[k] = json.loads(attrs[k])
            except ValueError:
                pass
    return attrs


def _open_tree(path: str | os.PathLike) -> xr.DataTree:
    path = Path(path)
    if not path.is_file():
        raise HbmError(f"{path}: no such result file")
    try:
        tree = xr.open_datatree(path, engine="netcdf4")
        tree = tree.load()
        tree.close()
    except Exception as exc:
        raise HbmError(f"{path}: cannot read netCDF result ({type(exc).__name__}: {exc})") from None
    return tree


def _ds(tree: xr.DataTree, group: str) -> xr.Dataset | None:
    return tree[group].to_dataset() if group in tree.children else None


def read_specimen_result(path: str | os.PathLike) -> SpecimenResult:
    """Read a per-specimen file written by :func:`write_specimen_result`.

    Raises
    ------
    HbmError
        If the file is missing or not an hbm specimen result.
    """
    tree = _open_tree(path)
    attrs = dict(tree.attrs)
    post = _ds(tree, G_POSTERIOR)
    if post is None:
        raise HbmError(f"{path}: no '{G_POSTERIOR}' group; not an hbm specimen result")
    names = [str(v) for v in post.data_vars]
    samples = np.stack([post[nm].values.reshape(-1) for nm in names], axis=1)
    stats = _ds(tree, G_STATS)
    stages: list[StageInfo] = []
    loglik = np.full(samples.shape[0], np.nan)
    lz, lz_se = np.nan, np.nan
    if stats is not None:
        stages = _read_stage_stats(stats)
        if "log_likelihood_sum" in stats:
            loglik = stats["log_likelihood_sum"].values.reshape(-1)
        lz = float(stats["log_marginal_likelihood"].values[0])
        if "log_marginal_likelihood_se" in stats:
            lz_se = float(stats["log_marginal_likelihood_se"].values[0])
    const = _ds(tree, G_CONST)
    if const is not None:
        bounds = np.stack([const["prior_lower"].sel(parameter=names).values,
                           const["prior_upper"].sel(parameter=names).values], axis=1)
    else:
        bounds = np.stack([samples.min(0), samples.max(0)], axis=1)
    res = SpecimenResult(
        specimen_id=str(attrs.get("specimen_id", Path(path).stem)), names=names, samples=samples,
        log_likelihood=loglik, log_evidence=lz, log_evidence_se=lz_se, bounds=bounds, stages=stages,
        model=str(attrs.get("model", "")), effects=json.loads(attrs.get("effects", "[]")),
        config=json.loads(attrs.get("config", "{}")), seed=int(attrs.get("seed", 0)),
        timings=json.loads(attrs.get("timings", "{}")), fixed=json.loads(attrs.get("fixed", "{}")),
        complete=int(attrs.get("complete", 0)) == 1, version=str(attrs.get("hbm_version", "")),
        prior=json.loads(attrs["prior"]) if "prior" in attrs else None,
        at_bounds=json.loads(attrs["at_bounds"]) if "at_bounds" in attrs else None)
    obs = _ds(tree, G_OBS)
    if obs is not None:
        res.stress = obs["stress"].values
        for key in ("strain", "time", "test"):
            if key in obs.coords:
                setattr(res, key, obs.coords[key].values)
    ll = _ds(tree, G_LOGLIK)
    if ll is not None:
        res.pointwise_log_likelihood = ll["stress"].values[0]
    pred = _ds(tree, G_PRED)
    if pred is not None:
        if "stress" in pred:
            res.predictive = pred["stress"].values[0]
        if "stress_model" in pred:
            res.predictive_model = pred["stress_model"].values[0]
    opt = _ds(tree, G_OPTIMA)
    if opt is not None:
        extra = {"objective", "window_lower", "window_upper", "kind"}
        pn = [str(v) for v in opt.data_vars if v not in extra]
        res.optima = []
        for i in range(opt.sizes["optimum"]):
            o: dict[str, Any] = {"params": {nm: float(opt[nm].values[i]) for nm in pn},
                                 "objective": float(opt["objective"].values[i])}
            for key in ("window_lower", "window_upper"):
                if key in opt and np.isfinite(opt[key].values[i]):
                    o[key] = float(opt[key].values[i])
            if "kind" in opt:
                o["kind"] = str(opt["kind"].values[i])
            res.optima.append(o)
    sob = _ds(tree, G_SOBOL)
    if sob is not None:
        spn = [str(x) for x in sob.coords["parameter"].values]
        s: dict[str, Any] = {}
        for key in ("S1", "ST", "S1_conf", "ST_conf"):
            if key in sob:
                s[key] = dict(zip(spn, map(float, sob[key].values)))
        if "relevance" in sob:
            s["relevance"] = dict(zip(spn, map(str, sob["relevance"].values)))
        for key in ("S1_point", "ST_point"):
            if key in sob:
                s[key] = {nm: sob[key].values[i] for i, nm in enumerate(spn)}
        s.update(sob.attrs)
        res.sobol = s
    return res


def to_inference_data(path: str | os.PathLike):
    """Open a result file as ``arviz.InferenceData`` (ArviZ is an optional dependency)."""
    try:
        import arviz as az
    except ImportError:  # pragma: no cover
        raise HbmError("arviz is not installed (pip install arviz)") from None
    return az.from_netcdf(str(path))


# ----------------------------------------------------------------------------- hierarchical
@dataclass
class HierarchicalFile:
    """Contents of ``hierarchical.nc``.

    Attributes
    ----------
    param_names : list of str
        Stage-1 columns (columns of ``updated``).
    hyper_names : list of str
    hyper_samples : ndarray (n, k)
    specimen_ids : list of str
    updated : ndarray (n, S, d) or None
        Updated individual posteriors (shrunk toward the population), columns ``param_names``.
    new_specimen : ndarray (n, k) or None
        Pooled parameters (``pooled_names``) of a new, unseen specimen drawn from the
        hyper-posterior predictive.
    pooled_names : list of str
        Parameters with a population distribution (hyper-parameters ``mu_P``, ``sd_P``).
    log_evidence, log_evidence_se : float
        Hyper-evidence log p(all data | hyperprior family).
    stages : list of StageInfo (or mappings with a subset of its fields)
        Per stage of the hyper-level TMCMC; read back as :class:`StageInfo`.
    ess : ndarray (S,) or None
        Minimum per-specimen importance ESS over the hyper-posterior population.
    attrs : dict
        Extra metadata (JSON-able), e.g. transform, hyperprior, warnings.
    groups : dict or None
        The group level of a grouped layer: ``key`` (metadata key), ``names`` (groups),
        ``specimen_group`` ({specimen: group}), ``pooled`` (parameters), ``means`` and
        ``predictive`` (n, G, len(pooled)) and any JSON-able extras; None without groups.
    reuse : dict specimen -> dict
        Per-specimen reuse diagnostics of the stage-1 samples
        (:func:`hbm.samplers.hierarchical.reuse_diagnostics`): the numbers of :data:`REUSE_VARS`
        are stored as variables ``reuse_<name>`` over ``specimen`` in the diagnostics group,
        the flag as ``reuse_unreliable`` (0/1), the reasons in the attributes.
    """

    param_names: list[str]
    hyper_names: list[str]
    hyper_samples: np.ndarray
    specimen_ids: list[str]
    updated: np.ndarray | None = None
    new_specimen: np.ndarray | None = None
    log_evidence: float = float("nan")
    log_evidence_se: float = float("nan")
    stages: list[StageInfo | Mapping[str, Any]] = field(default_factory=list)
    ess: np.ndarray | None = None
    attrs: dict = field(default_factory=dict)
    complete: bool = True
    pooled_names: list[str] = field(default_factory=list)
    groups: dict | None = None
    reuse: dict = field(default_factory=dict)

    def hyper(self, name: str) -> np.ndarray:
        return self.hyper_samples[:, self.hyper_names.index(name)]


def write_hierarchical(h: HierarchicalFile, path: str | os.PathLike) -> Path:
    """Write the hierarchical layer's results atomically."""
    path = Path(path)
    n = h.hyper_samples.shape[0]
    draws = {"chain": [0], "draw": np.arange(n)}
    transforms = dict(h.attrs.get("transforms") or {})
    post = xr.Dataset({nm: (("chain", "draw"), h.hyper_samples[None, :, i], conventions.hyper_attrs(nm, transforms))
                       for i, nm in enumerate(h.hyper_names)}, coords=draws)
    groups: dict[str, xr.Dataset] = {G_POSTERIOR: conventions.annotate(post, "other")}
    stats: dict[str, Any] = {"log_marginal_likelihood": (("chain",), [float(h.log_evidence)]),
                             "log_marginal_likelihood_se": (("chain",), [float(h.log_evidence_se)])}
    coords: dict[str, Any] = {"chain": [0]}
    _add_stage_stats(stats, coords, h.stages)
    groups[G_STATS] = xr.Dataset(stats, coords=coords)
    if h.updated is not None:
        m = h.updated.shape[0]
        groups[G_UPDATED] = xr.Dataset(
            {nm: (("chain", "draw", "specimen"), h.updated[None, :, :, i]) for i, nm in enumerate(h.param_names)},
            coords={"chain": [0], "draw": np.arange(m), "specimen": list(h.specimen_ids)})
    if h.new_specimen is not None:
        m = h.new_specimen.shape[0]
        groups[G_NEW] = conventions.annotate(xr.Dataset({nm: (("chain", "draw"), h.new_specimen[None, :, i])
                                                         for i, nm in enumerate(h.pooled_names or h.param_names)},
                                                        coords={"chain": [0], "draw": np.arange(m)}), "parameters")
    diag_vars = _reuse_vars(h)
    if h.ess is not None:
        diag_vars["importance_ess"] = ("specimen", np.asarray(h.ess, float))
    if diag_vars:
        groups[G_DIAG] = xr.Dataset(diag_vars, coords={"specimen": list(h.specimen_ids)},
                                    attrs={"reuse_reasons": _dumps({k: list(v.get("reasons") or [])
                                                                    for k, v in h.reuse.items()})})
    if h.groups is not None:
        groups[G_GROUPS] = _groups_dataset(h.groups, h.specimen_ids)
    root = xr.Dataset(attrs={"param_names": _dumps(list(h.param_names)),
                             "pooled_names": _dumps(list(h.pooled_names or h.param_names)),
                             "specimen_ids": _dumps(list(h.specimen_ids)),
                             "extra": _dumps(h.attrs), "hbm_version": __version__, "complete": 0})
    tree = xr.DataTree.from_dict({"/": root, **groups})
    return _write_tree(tree, path, h.complete)


def read_hierarchical(path: str | os.PathLike) -> HierarchicalFile:
    """Read ``hierarchical.nc``."""
    tree = _open_tree(path)
    post = _ds(tree, G_POSTERIOR)
    if post is None:
        raise HbmError(f"{path}: no '{G_POSTERIOR}' group; not an hbm hierarchical result")
    hn = [str(v) for v in post.data_vars]
    params = json.loads(tree.attrs.get("param_names", "[]"))
    ids = json.loads(tree.attrs.get("specimen_ids", "[]"))
    h = HierarchicalFile(param_names=params, hyper_names=hn,
                         hyper_samples=np.stack([post[v].values.reshape(-1) for v in hn], axis=1),
                         specimen_ids=ids, attrs=json.loads(tree.attrs.get("extra", "{}")),
                         complete=int(tree.attrs.get("complete", 0)) == 1,
                         pooled_names=json.loads(tree.attrs.get("pooled_names", "[]")) or list(params))
    stats = _ds(tree, G_STATS)
    if stats is not None:
        h.log_evidence = float(stats["log_marginal_likelihood"].values[0])
        h.log_evidence_se = float(stats["log_marginal_likelihood_se"].values[0])
        h.stages = _read_stage_stats(stats)
    up = _ds(tree, G_UPDATED)
    if up is not None:
        h.updated = np.stack([up[nm].values[0] for nm in params], axis=-1)
    new = _ds(tree, G_NEW)
    if new is not None:
        h.new_specimen = np.stack([new[nm].values[0] for nm in h.pooled_names], axis=-1)
    diag = _ds(tree, G_DIAG)
    if diag is not None:
        if "importance_ess" in diag:
            h.ess = diag["importance_ess"].values
        h.reuse = _read_reuse(diag, ids)
    grp = _ds(tree, G_GROUPS)
    if grp is not None:
        h.groups = _read_groups(grp)
    return h


_GROUP_ARRAYS = {"means": "mean", "predictive": "new_specimen"}


def _groups_dataset(g: Mapping[str, Any], specimen_ids: Sequence[str]) -> xr.Dataset:
    """The ``groups`` group of hierarchical.nc from :attr:`HierarchicalFile.groups`."""
    names, pooled = list(g["names"]), list(g["pooled"])
    data: dict[str, Any] = {}
    for key, prefix in _GROUP_ARRAYS.items():
        a = np.asarray(g[key], float)  # (n, G, d)
        data.update({f"{prefix}_{p}": (("chain", "draw", "group"), a[None, :, :, k]) for k, p in enumerate(pooled)})
    sg = dict(g["specimen_group"])
    data["specimen_group"] = ("specimen", [str(sg[s]) for s in specimen_ids])
    extra = {k: v for k, v in g.items() if k not in (*_GROUP_ARRAYS, "names", "pooled", "specimen_group", "key")}
    n = np.asarray(g["means"]).shape[0]
    return xr.Dataset(data, coords={"chain": [0], "draw": np.arange(n), "group": names, "specimen": list(specimen_ids)},
                      attrs={"key": str(g.get("key", "group")), "pooled": _dumps(pooled), "extra": _dumps(extra)})


def _read_groups(ds: xr.Dataset) -> dict:
    """:attr:`HierarchicalFile.groups` back from the ``groups`` group."""
    pooled = json.loads(ds.attrs.get("pooled", "[]"))
    out = {"key": str(ds.attrs.get("key", "group")), "names": [str(v) for v in ds["group"].values],
           "pooled": pooled,
           "specimen_group": dict(zip(map(str, ds["specimen"].values), map(str, ds["specimen_group"].values))),
           **json.loads(ds.attrs.get("extra", "{}"))}
    for key, prefix in _GROUP_ARRAYS.items():
        out[key] = np.stack([ds[f"{prefix}_{p}"].values[0] for p in pooled], axis=-1)
    return out


#: per-specimen reuse diagnostics stored as variables ``reuse_<name>`` of the diagnostics group
REUSE_VARS = ("khat_median", "khat_q90", "khat_frac", "khat_updated", "uncovered", "outside_measured",
              "population_outside", "population_beyond", "ess_q10", "ess_raw_q10")


def _reuse_vars(h: HierarchicalFile) -> dict[str, Any]:
    """The diagnostics-group variables of ``h.reuse`` (empty without diagnostics)."""
    if not h.reuse:
        return {}
    ids = list(h.specimen_ids)
    out = {f"reuse_{k}": ("specimen", np.array([float(h.reuse.get(s, {}).get(k, np.nan)) for s in ids]))
           for k in REUSE_VARS}
    out["reuse_unreliable"] = ("specimen", np.array([int(bool(h.reuse.get(s, {}).get("unreliable"))) for s in ids]))
    return out


def _read_reuse(diag: xr.Dataset, ids: Sequence[str]) -> dict:
    """``HierarchicalFile.reuse`` back from the diagnostics group ({} for files without it)."""
    if "reuse_unreliable" not in diag:
        return {}
    reasons = json.loads(diag.attrs.get("reuse_reasons", "{}"))
    out = {}
    for j, sid in enumerate(ids):
        r = {k: float(diag[f"reuse_{k}"].values[j]) for k in REUSE_VARS if f"reuse_{k}" in diag}
        r["unreliable"] = bool(diag["reuse_unreliable"].values[j])
        r["reasons"] = list(reasons.get(sid, []))
        out[sid] = r
    return out


# ----------------------------------------------------------------------------- population summary
def write_population_summary(path: str | os.PathLike, *, specimen_ids: Sequence[str],
                             manifolds: Mapping[str, Mapping[str, np.ndarray]] | None = None,
                             combinations: Mapping[str, Mapping[str, Sequence[float]]] | None = None,
                             attrs: Mapping[str, Any] | None = None) -> Path:
    """Write cross-specimen tables (``<out>/manifolds.nc``).

    Parameters
    ----------
    specimen_ids : sequence of str
    manifolds : {specimen: {"x": (g,), "y": (g,), "x_name": str, "y_name": str}}, optional
        Spline-evaluated manifold curves (e.g. VOLF -> T1), stored over (specimen, grid); curves
        of different length are NaN-padded.
    combinations : {quantity: {"mean": [...], "lower": [...], "upper": [...]}} per specimen, optional
    """
    groups: dict[str, xr.Dataset] = {}
    ids = list(specimen_ids)
    if manifolds:
        g = max(len(np.asarray(m["x"])) for m in manifolds.values())
        x = np.full((len(ids), g), np.nan)
        y = np.full((len(ids), g), np.nan)
        for i, sid in enumerate(ids):
            if sid in manifolds:
                mx, my = np.asarray(manifolds[sid]["x"], float), np.asarray(manifolds[sid]["y"], float)
                x[i, :mx.size], y[i, :my.size] = mx, my
        first = next(iter(manifolds.values()))
        groups[G_MANIFOLD] = xr.Dataset({"x": (("specimen", "grid"), x), "y": (("specimen", "grid"), y)},
                                        coords={"specimen": ids},
                                        attrs={"x_name": str(first.get("x_name", "VOLF")),
                                               "y_name": str(first.get("y_name", "T1"))})
    if combinations:
        cv = {}
        for q, stats in combinations.items():
            safe = q.replace("*", "_x_").replace("(", "").replace(")", "").replace("-", "m")
            for k, vals in stats.items():
                cv[f"{safe}__{k}"] = ("specimen", np.asarray(vals, float))
        groups[G_COMBOS] = xr.Dataset(cv, coords={"specimen": ids},
                                      attrs={"quantities": _dumps(list(combinations))})
    root = xr.Dataset(attrs={"specimen_ids": _dumps(ids), "extra": _dumps(dict(attrs or {})),
                             "hbm_version": __version__})
    tree = xr.DataTree.from_dict({"/": root, **groups})
    return _write_tree(tree, path, None)


def read_population_summary(path: str | os.PathLike) -> dict:
    """Read ``manifolds.nc`` back into ``{"manifolds": {...}, "specimen_ids": [...]}``."""
    tree = _open_tree(path)
    out: dict[str, Any] = {"specimen_ids": json.loads(tree.attrs.get("specimen_ids", "[]")), "manifolds": {}}
    man = _ds(tree, G_MANIFOLD)
    if man is not None:
        for i, sid in enumerate(out["specimen_ids"]):
            x, y = man["x"].values[i], man["y"].values[i]
            ok = np.isfinite(x) & np.isfinite(y)
            out["manifolds"][sid] = {"x": x[ok], "y": y[ok], "x_name": man.attrs.get("x_name"),
                                     "y_name": man.attrs.get("y_name")}
    return out


# ----------------------------------------------------------------------------- organ prediction
# ``<out>/organ.nc`` (``hbm predict organ``): one group per (specimen, source) of curves,
# ``specimens/<id>/<source>`` with source in ORGAN_SOURCES, and ``population`` for the
# new-specimen predictive of the hierarchical layer.  Each group holds one xarray Dataset built
# by :mod:`hbm.organ_report` (dims quantile, force[, optimum, parameter]); root attributes:
# ``specimen_ids`` (JSON), ``extra`` (JSON: geometry, settings, timings), ``hbm_version``,
# ``complete`` (set to 1 last).
G_ORGAN_SPECIMENS = "specimens"
G_ORGAN_POPULATION = "population"
ORGAN_SOURCES = ("posterior", "updated", "optima")


@dataclass
class OrganFile:
    """Contents of ``organ.nc``.

    Attributes
    ----------
    curves : dict
        ``{specimen_id: {source: xarray.Dataset}}``, source in :data:`ORGAN_SOURCES`
        (``"posterior"``: the specimen's TMCMC posterior, ``"updated"``: its updated individual
        posterior of the hierarchical layer, ``"optima"``: its CMA-ES optima).
    population : xarray.Dataset or None
        Curves of a new, unseen specimen (hierarchical predictive).
    attrs : dict
        JSON-able metadata (geometry, settings, timings, reference force ...).
    complete : bool
    """

    curves: dict[str, dict[str, xr.Dataset]]
    population: xr.Dataset | None = None
    attrs: dict = field(default_factory=dict)
    complete: bool = True

    @property
    def specimen_ids(self) -> list[str]:
        return sorted(self.curves)


def _nc_attrs(attrs: Mapping[str, Any]) -> dict[str, Any]:
    """netCDF-storable attributes: numbers and strings stay, bool -> int, the rest -> JSON."""
    out: dict[str, Any] = {}
    for k, v in attrs.items():
        if isinstance(v, (bool, np.bool_)):
            out[k] = int(v)
        elif isinstance(v, (str, int, float, np.integer, np.floating)):
            out[k] = v
        else:
            out[k] = _dumps(v)
    return out


def write_organ(organ: OrganFile, path: str | os.PathLike) -> Path:
    """Write organ-prediction curves atomically (temp file, ``complete`` flag last, rename).

    Raises
    ------
    HbmError
        For an unknown source name or a specimen id that cannot be a netCDF group name.
    """
    path = Path(path)
    groups: dict[str, xr.Dataset] = {}
    for sid, by_source in organ.curves.items():
        if not sid or "/" in sid:
            raise HbmError(f"organ curves: specimen id {sid!r} cannot be stored as a netCDF group")
        for source, ds in by_source.items():
            if source not in ORGAN_SOURCES:
                raise HbmError(f"organ curves of {sid}: unknown source {source!r}; expected one of {ORGAN_SOURCES}")
            groups[f"{G_ORGAN_SPECIMENS}/{sid}/{source}"] = ds.assign_attrs(_nc_attrs(ds.attrs))
    if organ.population is not None:
        groups[G_ORGAN_POPULATION] = organ.population.assign_attrs(_nc_attrs(organ.population.attrs))
    root = xr.Dataset(attrs={"specimen_ids": _dumps(sorted(organ.curves)), "extra": _dumps(organ.attrs),
                             "hbm_version": __version__, "complete": 0})
    tree = xr.DataTree.from_dict({"/": root, **groups})
    return _write_tree(tree, path, organ.complete)


def read_organ(path: str | os.PathLike) -> OrganFile:
    """Read ``organ.nc`` written by :func:`write_organ`.

    Raises
    ------
    HbmError
        If the file is missing or not an hbm organ prediction.
    """
    tree = _open_tree(path)
    if "specimen_ids" not in tree.attrs:
        raise HbmError(f"{path}: not an hbm organ prediction (no 'specimen_ids' attribute)")
    ids = json.loads(tree.attrs["specimen_ids"])
    curves: dict[str, dict[str, xr.Dataset]] = {}
    spec = tree[G_ORGAN_SPECIMENS] if G_ORGAN_SPECIMENS in tree.children else None
    for sid in ids:
        if spec is None or sid not in spec.children:
            raise HbmError(f"{path}: specimen {sid!r} listed but its group is missing")
        curves[sid] = {src: spec[sid][src].to_dataset() for src in ORGAN_SOURCES if src in spec[sid].children}
    return OrganFile(curves=curves, population=_ds(tree, G_ORGAN_POPULATION),
                     attrs=json.loads(tree.attrs.get("extra", "{}")),
                     complete=int(tree.attrs.get("complete", 0)) == 1)


__all__ += ["OrganFile", "write_organ", "read_organ", "ORGAN_SOURCES"]
