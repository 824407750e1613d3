"""One specimen's result (ArviZ-compatible groups): the SpecimenResult record, its per-stage sampler statistics, writing and reading."""

from __future__ import annotations

import json
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Mapping, Sequence

import numpy as np
import xarray as xr

from .conventions import annotate, log_prior, prior_draws, udunits
from .._version import __version__
from ..data.specimen import Series, Specimen
from ..errors import HbmError
from ..samplers.chains import POOLED, Chains
from ..samplers.types import StageInfo
from ..settings.fit import FitRecord

from .common import (
    G_CONST, G_LOGLIK, G_OBS, G_OPTIMA, G_POSTERIOR, G_PRED, G_PRIOR, G_SOBOL, G_STATS, STAGE_KEYS, _ds, _dumps,
    _open_tree, _write_tree)


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
        Equal-weight posterior population; chain-major when ``chains`` has several chains (rows
        of chain c are ``c·n/C … (c+1)·n/C − 1``; the per-row arrays below follow the same order).
    log_likelihood : ndarray (n,)
        Total log-likelihood of each sample.
    log_evidence, log_evidence_se : float
    bounds : ndarray (d, 2)
        Prior box of the free parameters.
    stages : list of StageInfo (or mappings with a subset of its fields)
        Per TMCMC stage, as returned by the sampler; read back as :class:`StageInfo`.
    data : Specimen or None
        The observed specimen (control path and measured series; read back from ``observed_data``
        with the result's id and without the file's metadata).
    pointwise_log_likelihood, predictive, predictive_model : ndarray (n, p) or None
        Pointwise log-likelihood, noisy posterior-predictive replicate, noise-free prediction.
    optima : list of dict or None
        ``{"params": {name: value}, "objective": f, ...}`` as from :mod:`hbm.fit.optimization`.
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
    chains : Chains
        How the rows split into independent chains (:mod:`hbm.samplers.chains`); stored as the
        ``chain`` dimension of every (chain, draw) group and the posterior's ``chains*`` attributes.
    """

    specimen_id: str
    names: list[str]
    samples: np.ndarray
    log_likelihood: np.ndarray
    log_evidence: float
    log_evidence_se: float
    bounds: np.ndarray
    stages: list[StageInfo | Mapping[str, Any]] = field(default_factory=list)
    data: Specimen | None = None
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
    chains: Chains = POOLED
    #: the registered base model (:mod:`hbm.model.spec`) when it is not the default (Spyrou) base; stored as the
    #: root attribute ``base_model`` only then, so files of the default base stay as they were
    base_model: str | None = None

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
                     stages: Sequence[StageInfo | Mapping[str, Any]], n_chains: int = 1) -> None:
    """One (chain, stage) float64 variable per :class:`StageInfo` field into ``stats``.

    A field no stage reports (a mapping from a foreign sampler) is left out; a field some
    stages lack is NaN there.  Booleans become 0/1.  The stages are the whole population's (the
    chains share them), so every chain holds the same row.
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
        stats[key] = (("chain", "stage"), np.repeat(arr[None, :], n_chains, axis=0))


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
    chains = r.chains
    if n % chains.n_chains:  # rows subset after sampling: they no longer form the chains
        chains = Chains(1, "pooled", f"{n} rows do not split into the sampler's {chains.n_chains} chains: one chain")
    nc = chains.n_chains

    def cd(a) -> np.ndarray:  # rows (n, ...) -> (chain, draw, ...), chain-major
        a = np.asarray(a)
        return a.reshape(nc, n // nc, *a.shape[1:])

    draws = {"chain": np.arange(nc), "draw": np.arange(n // nc)}
    info = r.parameter_info
    stored = FitRecord.from_attrs(r.config)
    post = xr.Dataset({nm: (("chain", "draw"), cd(r.samples[:, i])) for i, nm in enumerate(r.names)},
                      coords=draws)
    post = annotate(post, "parameters", info)
    post.attrs.update(chains.to_attrs())
    groups: dict[str, xr.Dataset] = {G_POSTERIOR: post}
    pd = r.prior_dict()
    if len(pd) == d:  # ArviZ's prior group: draws from the prior box, as many as the posterior's
        pdraws = prior_draws(r.names, pd, n, r.seed, stored.seed_spawn_key or ())
        groups[G_PRIOR] = annotate(xr.Dataset(
            {nm: (("chain", "draw"), cd(pdraws[:, i])) for i, nm in enumerate(r.names)}, coords=draws),
            "parameters", info)

    ll_sum = np.asarray(r.log_likelihood, float)
    # the evidence is the whole population's (pooled over the chains): the same value for every chain
    stats = {"log_marginal_likelihood": (("chain",), [float(r.log_evidence)] * nc),
             "log_marginal_likelihood_se": (("chain",), [float(r.log_evidence_se)] * nc),
             "log_likelihood_sum": (("chain", "draw"), cd(ll_sum)),
             # ArviZ's lp: log posterior density up to the evidence (log likelihood + log prior)
             "lp": (("chain", "draw"), cd(ll_sum + log_prior(r.samples, r.names, pd)))}
    coords = dict(draws)
    _add_stage_stats(stats, coords, r.stages, nc)
    groups[G_STATS] = annotate(xr.Dataset(stats, coords=coords), "stats")

    if r.data is not None and r.data.observed:
        spec = r.data
        pc: dict[str, Any] = {"point": np.arange(spec.n_points), "strain": ("point", spec.strain)}
        if spec.time is not None:
            pc["time"] = ("point", spec.time)
        if spec.test is not None:
            pc["test"] = ("point", spec.test)
        # one observed variable per measured series, with its unit (annotate names the known ones)
        groups[G_OBS] = annotate(xr.Dataset(
            {k: ("point", s.values, {"long_name": s.long_name, "units": udunits(s.unit)})
             for k, s in spec.observed.items()}, coords=pc), "observed")
        dcp = {**draws, **pc}
        if r.pointwise_log_likelihood is not None:
            groups[G_LOGLIK] = annotate(xr.Dataset(
                {"stress": (("chain", "draw", "point"), cd(r.pointwise_log_likelihood))}, coords=dcp),
                "log_likelihood")
        pred = {}
        if r.predictive is not None:
            pred["stress"] = (("chain", "draw", "point"), cd(r.predictive))
        if r.predictive_model is not None:
            pred["stress_model"] = (("chain", "draw", "point"), cd(r.predictive_model))
        if pred:
            groups[G_PRED] = annotate(xr.Dataset(pred, coords=dcp), "predictive")

    b = np.asarray(r.bounds, float)
    groups[G_CONST] = annotate(
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
        "likelihood_tier": str(stored.tier_used),
        **({"base_model": str(r.base_model)} if r.base_model else {}),
        "complete": 0,
    })
    return xr.DataTree.from_dict({"/": root, **groups})


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


def _rows(var: xr.DataArray) -> np.ndarray:
    """A (chain, draw, point) variable as rows (chain·draw, point), chain-major like ``samples``."""
    v = var.values
    return v.reshape(-1, v.shape[-1])


def _observed_specimen(sid: str, obs: xr.Dataset) -> Specimen:
    """The specimen of a result's ``observed_data`` group: its coordinates and one series per variable."""
    coord = {k: obs.coords[k].values for k in ("time", "test") if k in obs.coords}
    series = {str(k): Series(str(k), v.values, str(v.attrs.get("units", "")), str(v.attrs.get("long_name", "")))
              for k, v in obs.data_vars.items()}
    return Specimen(sid, obs.coords["strain"].values, coord.get("time"), coord.get("test"), series)


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
        at_bounds=json.loads(attrs["at_bounds"]) if "at_bounds" in attrs else None,
        chains=Chains.from_attrs(dict(post.attrs), int(post.sizes.get("chain", 1))),
        base_model=str(attrs["base_model"]) if "base_model" in attrs else None)
    obs = _ds(tree, G_OBS)
    if obs is not None and "strain" in obs.coords:
        res.data = _observed_specimen(res.specimen_id, obs)
    ll = _ds(tree, G_LOGLIK)
    if ll is not None:
        res.pointwise_log_likelihood = _rows(ll["stress"])
    pred = _ds(tree, G_PRED)
    if pred is not None:
        if "stress" in pred:
            res.predictive = _rows(pred["stress"])
        if "stress_model" in pred:
            res.predictive_model = _rows(pred["stress_model"])
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
