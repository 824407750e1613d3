"""What every hbm netCDF file shares: the group names (kept here and nowhere else in hbm), JSON attributes, atomic writes with a completion flag, reading attributes and groups."""

from __future__ import annotations

import json
import os

from pathlib import Path
from typing import Any, Mapping

import numpy as np
import xarray as xr


from ..errors import HbmError, OutputError
from ..samplers.types import StageInfo
from ..runtime.files import atomic_path, write_error


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
