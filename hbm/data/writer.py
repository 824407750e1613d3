"""Write a specimen Dataset back to the CSV format it was read from."""

from __future__ import annotations


import io
import json


from pathlib import Path
from typing import Any

import numpy as np
import xarray as xr


from ..errors import HbmError


from ..runtime.files import atomic_path
from .columns import _COLUMNS, _KEY_RE


# ---------------------------------------------------------------------------------------
# writing
# ---------------------------------------------------------------------------------------
def _attr_text(key: str, value: Any) -> str:
    if isinstance(value, str):
        text = value
    elif isinstance(value, (np.ndarray, list, tuple, dict)):
        text = json.dumps(np.asarray(value).tolist() if isinstance(value, np.ndarray) else value)
    else:
        text = str(value.item() if isinstance(value, np.generic) else value)
    if "\n" in text or "\r" in text:
        raise HbmError(f"attribute {key!r}: metadata values must be one line, got {text[:40]!r}...")
    return text


def save_specimen(ds: xr.Dataset, path: str | Path) -> Path:
    """Write a specimen Dataset to CSV atomically; :func:`load_specimen` reads it back exactly.

    Attributes become ``# key: value`` metadata lines (except ``source_file``); floats are
    written with ``repr`` (shortest string that round-trips).

    Parameters
    ----------
    ds : xarray.Dataset
        With ``strain`` and ``stress`` over dim ``point``, optional ``time`` and ``test``.
    path : str or Path
        Destination (parent folders are created).

    Returns
    -------
    Path
    """
    path = Path(path)
    for need in ("strain", "stress"):
        if need not in ds:
            raise HbmError(f"save_specimen: dataset has no {need!r} variable")
    cols = [c for c in _COLUMNS if c in ds]
    arrays = {c: np.asarray(ds[c].values).ravel() for c in cols}
    n = arrays["strain"].size
    for c, a in arrays.items():
        if a.size != n:
            raise HbmError(f"save_specimen: variable {c!r} has {a.size} values, strain has {n}")
    buf = io.StringIO()
    for key, value in ds.attrs.items():
        if key == "source_file":
            continue
        if not _KEY_RE.match(str(key)):
            raise HbmError(f"save_specimen: attribute name {key!r} is not a valid metadata key")
        buf.write(f"# {key}: {_attr_text(key, value)}\n")
    buf.write(",".join(cols) + "\n")
    fmt = {c: (lambda v: str(int(v))) if c == "test" else (lambda v: repr(float(v))) for c in cols}
    for i in range(n):
        buf.write(",".join(fmt[c](arrays[c][i]) for c in cols) + "\n")
    with atomic_path(path) as tmp:
        tmp.write_text(buf.getvalue(), encoding="utf-8")
    return path


