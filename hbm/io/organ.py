"""Organ-scale predictions (hbm predict organ): one group per specimen and source, and the population."""

from __future__ import annotations

import json
import os
from dataclasses import dataclass, field
from pathlib import Path


import xarray as xr


from .._version import __version__
from ..errors import HbmError


from .common import _ds, _dumps, _nc_attrs, _open_tree, _write_tree


# ----------------------------------------------------------------------------- organ prediction
# ``<out>/organ.nc`` (``hbm predict organ``): one group per (specimen, source) of curves,
# ``specimens/<id>/<source>`` with source in ORGAN_SOURCES, and ``population`` for the
# new-specimen predictive of the hierarchical layer.  Each group holds one xarray Dataset built
# by :mod:`hbm.workflow.organ` (dims quantile, force[, optimum, parameter]); root attributes:
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

