"""The result file of a fit across loading modes (:func:`hbm.fit.modes.fit_modes`): ArviZ groups with one
variable per measured observable.

Each observable measured in any test (``stress``, ``stress_2``, ``strain_f`` ...) is one variable of
``observed_data`` on its own dimension ``<observable>_point`` (the values of every test that measured it,
test by test), with coordinates ``<observable>_test``, ``_mode``, ``_strain`` (the control) and ``_row`` of each value; the
``log_likelihood`` and ``posterior_predictive`` groups hold the same variables over (chain, draw,
``<observable>_point``), so ``arviz.loo(idata, var_name="strain_f")`` is the per-observable LOO.  The
posterior is one pooled chain (TMCMC's final population).  Root attributes: log-evidence, the collagen
reading, the tier and why, the settings, and ``identifiability``: what the tests identify as JSON
(:meth:`hbm.identifiability.modes.ModesIdentifiability.to_dict`, linearised at the highest-likelihood
draw; absent when it was not computed).
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any, Mapping

import numpy as np
import xarray as xr

from .common import G_LOGLIK, G_OBS, G_POSTERIOR, G_PRED, G_STATS, _dumps, _open_tree, _write_tree

__all__ = ["write_modes_result", "read_modes_observed"]


def _by_observable(series, arrays=None) -> dict[str, dict[str, Any]]:
    """Observable -> its series' values concatenated test by test (and their test, mode, strain, row)."""
    out: dict[str, dict[str, list]] = {}
    for k, s in enumerate(series):
        e = out.setdefault(s.observable, {"values": [], "test": [], "mode": [], "row": [], "arrays": []})
        e["values"].append(s.observed)
        e["test"].append(np.full(s.rows.size, s.test.id))
        e["mode"].append(np.full(s.rows.size, s.test.load_case, dtype=object))
        e["row"].append(s.rows)
        if arrays is not None:
            e["arrays"].append(arrays[k])
    return {k: {n: (np.concatenate(v, axis=-1) if v else None) for n, v in e.items()} for k, e in out.items()}


def write_modes_result(fit, path: str | os.PathLike, config: Mapping[str, Any]) -> Path:
    """Write a :class:`~hbm.fit.modes.ModesFit` as netCDF (module docstring), atomically, flagged complete.

    Returns
    -------
    Path
    """
    lik = fit.likelihood
    spec = lik.data
    n = fit.samples.shape[0]
    draws = {"chain": [0], "draw": np.arange(n)}
    post = xr.Dataset({nm: (("chain", "draw"), fit.samples[None, :, j]) for j, nm in enumerate(lik.names)},
                      coords=draws)
    stats = xr.Dataset({"log_likelihood_sum": (("chain", "draw"), fit.log_likelihood[None]),
                        "log_marginal_likelihood": (("chain",), [fit.log_evidence]),
                        "log_marginal_likelihood_se": (("chain",), [fit.log_evidence_se])}, coords=draws)
    obs, ll, pp = {}, {}, {}
    for name, e in _by_observable(lik.series).items():
        dim = f"{name}_point"
        unit = "MPa" if name.startswith("stress") else "1"
        # coordinates named per observable: each observable has its own dimension
        coords = {f"{name}_test": (dim, e["test"]), f"{name}_mode": (dim, e["mode"].astype(str)),
                  f"{name}_strain": (dim, spec.strain[e["row"]]), f"{name}_row": (dim, e["row"])}
        obs[name] = xr.DataArray(e["values"], dims=(dim,), coords=coords,
                                 attrs={"units": unit, "long_name": f"measured {name}"})
    for group, arrays in ((ll, fit.pointwise), (pp, fit.replicates)):
        for name, e in _by_observable(lik.series, arrays).items():
            group[name] = (("chain", "draw", f"{name}_point"), e["arrays"][None])
    attrs = {"specimen_id": spec.id, "log_evidence": fit.log_evidence, "log_evidence_se": fit.log_evidence_se,
             "collagen3d": lik.energy.collagen3d, "energy": lik.energy.label, "n_evaluations": fit.n_evaluations,
             "noise_kinds": _dumps(list(lik.kinds)), "config": _dumps(dict(config)),
             "load_cases": _dumps([t.load_case for t in spec.tests])}
    ident = getattr(fit, "identifiability", None)
    if ident is not None:
        attrs["identifiability"] = _dumps(ident.to_dict())
    tree = xr.DataTree.from_dict({
        "/": xr.Dataset(attrs=attrs),
        G_POSTERIOR: post, G_STATS: stats, G_OBS: xr.Dataset(obs),
        G_LOGLIK: xr.Dataset(ll, coords=draws), G_PRED: xr.Dataset(pp, coords=draws)})
    return _write_tree(tree, path, complete=True)


def read_modes_observed(path: str | os.PathLike) -> dict[str, xr.Dataset]:
    """The groups of a modes result as plain Datasets (``{group: Dataset}``, the root as ``"/"``)."""
    tree = _open_tree(path)
    out = {"/": tree.to_dataset().load()}
    for g in (G_POSTERIOR, G_STATS, G_OBS, G_LOGLIK, G_PRED):
        out[g] = tree[g].to_dataset().load()
    tree.close()
    return out
