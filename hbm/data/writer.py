"""Write a specimen back to the CSV format it was read from."""

from __future__ import annotations


import io
import json


from pathlib import Path
from typing import Any

import numpy as np


from ..errors import HbmError


from ..runtime.files import atomic_path
from .columns import _KEY_RE
from .specimen import as_specimen


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


def save_specimen(specimen, path: str | Path) -> Path:
    """Write a specimen to CSV atomically; :func:`load_specimen` reads it back exactly.

    Attributes become ``# key: value`` metadata lines (except ``source_file``); floats are
    written with ``repr`` (shortest string that round-trips).

    Parameters
    ----------
    specimen : Specimen or xarray.Dataset
        With ``strain`` and ``stress`` (columns: strain, the measured series, time, test).
    path : str or Path
        Destination (parent folders are created).

    Returns
    -------
    Path
    """
    path = Path(path)
    spec = as_specimen(specimen)
    if not spec.has_stress:
        raise HbmError("save_specimen: the specimen has no 'stress' series")
    arrays = {"strain": spec.strain, **{k: s.values for k, s in spec.observed.items()}}
    arrays.update({k: a for k, a in (("time", spec.time), ("test", spec.test)) if a is not None})
    cols = list(arrays)
    n = spec.n_points
    buf = io.StringIO()
    for key, value in spec.attrs.items():
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


