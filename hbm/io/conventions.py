"""The ecosystem's conventions for result files: CF/UDUNITS ``units`` and ``long_name``, ArviZ group
attributes, the ``prior`` draws and ``lp`` -- computed here, written by :mod:`hbm.io` (which alone
knows the group names; this module only sees datasets and their roles).

Units are UDUNITS strings (``"1"`` for dimensionless, ``"degree"``, ``"MPa"``, ``"s"``), so
``pint_xarray``/``cf_xarray`` can quantify every variable that has one.
"""

from __future__ import annotations

import datetime as _dt
from typing import Any, Mapping

import numpy as np
import xarray as xr

from ..runtime import seeds
from .._version import __version__
from ..model.spec import parameter_info

#: noise parameter -> (unit as written in hbm, meaning); the base models' parameters come from their specs
#: (:func:`hbm.model.spec.parameter_info`), effects' own parameters from the model
PARAMETER_INFO: dict[str, tuple[str, str]] = {
    "sigma": ("MPa", "noise standard deviation"),
    "scale": ("-", "noise scale relative to the thesis weights (sd = scale x max(max|stress|/10, |stress|))"),
    "sigma_rel": ("-", "noise standard deviation per unit model stress"),
    "rho": ("-", "lag-1 autocorrelation of the noise"),
}

#: coordinates and data variables with a fixed meaning (units, long_name)
FIXED: dict[str, tuple[str, str]] = {
    "chain": ("1", "chain index"),
    "draw": ("1", "draw index"),
    "point": ("1", "data point index"),
    "strain": ("1", "engineering strain along the fibres"),
    "time": ("s", "time"),
    "test": ("1", "test (loading history) id"),
    "parameter": ("1", "parameter name"),
    "stage": ("1", "TMCMC stage index"),
    "optimum": ("1", "CMA-ES optimum index"),
    "specimen": ("1", "specimen id"),
    "group": ("1", "group name"),
}

#: (role, variable) -> (units, long_name)
ROLE_VARS: dict[tuple[str, str], tuple[str, str]] = {
    ("observed", "stress"): ("MPa", "measured Cauchy stress along the fibres"),
    ("predictive", "stress"): ("MPa", "posterior-predictive replicate of the stress (model + noise)"),
    ("predictive", "stress_model"): ("MPa", "noise-free model stress of each posterior draw"),
    ("log_likelihood", "stress"): ("1", "pointwise log-likelihood"),
    ("constant", "prior_lower"): (None, "lower edge of the prior box (units per parameter: units_by_parameter)"),
    ("constant", "prior_upper"): (None, "upper edge of the prior box (units per parameter: units_by_parameter)"),
}


def udunits(unit: str) -> str:
    """hbm's unit string as UDUNITS: "-"/"" -> "1", "deg" -> "degree"."""
    return {"-": "1", "": "1", "deg": "degree"}.get(unit, unit)


def parameter_attrs(name: str, info: Mapping[str, tuple[str, str]] | None = None) -> dict[str, str]:
    """``units``/``long_name`` of a parameter (``info`` first, then the registered base models' and
    the noise parameters' of :data:`PARAMETER_INFO`)."""
    unit, meaning = (info or {}).get(name) or parameter_info().get(name) or PARAMETER_INFO.get(name, ("", ""))
    if not unit and not meaning:
        return {"long_name": name}
    return {"units": udunits(unit), "long_name": meaning or name}


def group_attrs() -> dict[str, str]:
    """ArviZ's per-group attributes (as ``arviz.from_dict`` writes them)."""
    return {"created_at": _dt.datetime.now(_dt.timezone.utc).replace(microsecond=0).isoformat(),
            "inference_library": "hbm", "inference_library_version": __version__,
            "creation_library": "hbm", "creation_library_version": __version__}


def annotate(ds: xr.Dataset, role: str, info: Mapping[str, tuple[str, str]] | None = None) -> xr.Dataset:
    """Add units/long_name to every variable and coordinate of ``ds`` and the ArviZ group attributes.

    ``role``: "parameters" (one variable per parameter), "observed", "predictive",
    "log_likelihood", "constant", "stats" or "other".
    """
    for name in ds.coords:
        if name in FIXED:
            u, ln = FIXED[str(name)]
            ds.coords[name].attrs.update({"units": u, "long_name": ln})
    for name in ds.data_vars:
        var = ds[name]
        if role == "parameters":
            var.attrs.update(parameter_attrs(str(name), info))
        elif (role, str(name)) in ROLE_VARS:
            u, ln = ROLE_VARS[(role, str(name))]
            var.attrs["long_name"] = ln
            if u is not None:
                var.attrs["units"] = u
    if role == "constant" and "parameter" in ds.coords:
        ds.attrs["units_by_parameter"] = ", ".join(
            f"{p}: {parameter_attrs(str(p), info).get('units', '?')}" for p in ds.coords["parameter"].values)
    ds.attrs.update(group_attrs())
    return ds


def log_prior(samples: np.ndarray, names, prior: Mapping[str, Mapping[str, Any]]) -> np.ndarray:
    """Log prior density (natural units) of each row of ``samples``: uniform -log(hi - lo),
    loguniform -log(x) - log(log(hi/lo)); -inf outside the box."""
    lp = np.zeros(samples.shape[0])
    for j, n in enumerate(names):
        p = prior.get(n)
        if p is None:
            continue
        lo, hi, x = float(p["lo"]), float(p["hi"]), samples[:, j]
        if p.get("form") == "loguniform":
            d = -np.log(np.where(x > 0, x, np.nan)) - np.log(np.log(hi / lo))
        else:
            d = np.full(x.shape, -np.log(hi - lo))
        lp += np.where((x >= lo) & (x <= hi), np.nan_to_num(d, nan=-np.inf), -np.inf)
    return lp


def prior_draws(names, prior: Mapping[str, Mapping[str, Any]], n: int, seed: int,
                spawn_key=()) -> np.ndarray:
    """``n`` draws (n, d) from the prior, on the ``prior`` stream of the run's seed (hbm.runtime.seeds)."""
    root = np.random.SeedSequence(int(seed), spawn_key=tuple(int(k) for k in spawn_key))
    rng = seeds.rng(root, "prior")
    out = np.empty((n, len(names)))
    for j, nm in enumerate(names):
        p = prior[nm]
        lo, hi = float(p["lo"]), float(p["hi"])
        u = rng.random(n)
        out[:, j] = np.exp(np.log(lo) + u * np.log(hi / lo)) if p.get("form") == "loguniform" else lo + u * (hi - lo)
    return out


_HYPER_PREFIXES = (("sd_between_", "between-group sd"), ("sd_within_", "within-group sd"),
                   ("mu_", "population mean"), ("sd_", "population sd"))


def hyper_attrs(name: str, transforms: Mapping[str, str]) -> dict[str, str]:
    """``transform``, ``units``, ``long_name`` of a hyper-parameter ``mu_P``/``sd_P``/... of hierarchical.nc.

    The population lives on transformed coordinates: logit/log values are dimensionless ("1"),
    identity ones carry the parameter's unit."""
    for prefix, what in _HYPER_PREFIXES:
        if name.startswith(prefix):
            base = name[len(prefix):]
            tr = str(transforms.get(base, "identity"))
            unit = "1" if tr != "identity" else parameter_attrs(base).get("units", "1")
            return {"transform": tr, "units": unit,
                    "long_name": f"{what} of {tr}({base})" if tr != "identity" else f"{what} of {base}"}
    return {"long_name": name}
