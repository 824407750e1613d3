"""A loaded record made ready for a fit: artefact rows named (or dropped on request), a dense record
reduced.  What ``hbm fit``, ``diagnose`` and ``extend`` (and their Python functions) do first.

A record without artefacts and with at most :data:`~hbm.data.reduction.DENSE_POINTS` rows is
returned as it is (the same object): every result on such a file is what it was before.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field

from ..errors import SettingError
from .artefacts import Artefact, data_lines, describe_artefacts, drop_rows, screen_artefacts
from .reduction import DENSE_POINTS, is_reduced, reduce_record

__all__ = ["REDUCE_CHOICES", "ARTEFACT_CHOICES", "Prepared", "prepare_record", "screen_dataset", "dropped_summary"]

#: ``reduce=`` / ``--reduce``: "auto" reduces a record above DENSE_POINTS rows, "off" never
REDUCE_CHOICES = ("auto", "off")
#: ``artefacts=`` / ``--drop-artefacts``: "flag" names the rows (diagnose: a data_problem verdict), "drop" drops them
ARTEFACT_CHOICES = ("flag", "drop")


@dataclass
class Prepared:
    """The record to fit and what was done to it."""

    data: object                                   # the dataset to fit
    artefacts: list[Artefact] = field(default_factory=list)   # rows flagged and kept ("flag")
    dropped: list[Artefact] = field(default_factory=list)     # rows flagged and dropped ("drop")
    lines: list[int] | None = None                 # the file's line of every raw row, where known
    reduced: bool = False

    def artefact_text(self) -> str:
        """The flagged rows in words, naming the file's lines where known."""
        return describe_artefacts(self.artefacts, self.lines)


def screen_dataset(ds) -> tuple[list[Artefact], list[int] | None]:
    """:func:`hbm.data.artefacts.screen_artefacts` of a loaded dataset, with its file's line numbers
    (None when the file is unknown or its rows do not match)."""
    names = getattr(ds, "data_vars", ds)
    found = screen_artefacts(ds["strain"].values, ds["stress"].values,
                             ds["time"].values if "time" in names else None,
                             ds["test"].values if "test" in names else None)
    lines = data_lines(ds.attrs.get("source_file")) if found and ds.attrs.get("source_file") else None
    if lines is not None and (len(lines) != ds.sizes["point"] or "dropped_rows" in ds.attrs):
        lines = None    # rows dropped before: the file's lines no longer match
    return found, lines


def prepare_record(ds, *, reduce: str = "auto", artefacts: str = "flag") -> Prepared:
    """Screen ``ds`` for artefact rows, drop them when ``artefacts="drop"``, and reduce a dense
    record when ``reduce="auto"`` (:mod:`hbm.data.reduction`).

    Parameters
    ----------
    ds : xarray.Dataset
        A loaded specimen (a reduced one is returned as it is).
    reduce : {"auto", "off"}
    artefacts : {"flag", "drop"}

    Returns
    -------
    Prepared
    """
    if reduce not in REDUCE_CHOICES:
        raise SettingError(f"reduce: expected one of {', '.join(REDUCE_CHOICES)}, got {reduce!r}")
    if artefacts not in ARTEFACT_CHOICES:
        raise SettingError(f"artefacts: expected one of {', '.join(ARTEFACT_CHOICES)}, got {artefacts!r}")
    if not hasattr(ds, "data_vars") or is_reduced(ds):
        return Prepared(ds)
    found, lines = screen_dataset(ds)
    out = Prepared(ds, lines=lines)
    if found and artefacts == "drop":
        out.data, out.dropped = drop_rows(ds, found, lines), found
    elif found:
        out.artefacts = found
    if reduce == "auto" and out.data.sizes["point"] > DENSE_POINTS:
        out.data, out.reduced = reduce_record(out.data), True
    return out


def dropped_summary(attrs) -> str:
    """``"1 artefact row dropped (line 10: pre-test reading)"`` from ``dropped_rows`` ("" if none)."""
    text = attrs.get("dropped_rows") if hasattr(attrs, "get") else None
    if not text:
        return ""
    try:
        items = json.loads(text)
    except (TypeError, ValueError):
        return ""
    parts, rows = [], 0
    for a in items:
        where = a.get("lines") or [r + 1 for r in a.get("rows", [])]
        word = "line" if a.get("lines") else "row"
        parts.append(f"{word}{'s' if len(where) > 1 else ''} {', '.join(map(str, where))}: {a.get('kind', '?')}")
        rows += len(where)
    return f"{rows} artefact row{'s' if rows != 1 else ''} dropped ({'; '.join(parts)})"
