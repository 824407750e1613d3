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
from .specimen import Specimen, as_specimen

__all__ = ["REDUCE_CHOICES", "ARTEFACT_CHOICES", "Prepared", "prepare_record", "screen_dataset", "dropped_summary"]

#: ``reduce=`` / ``--reduce``: "auto" reduces a record above DENSE_POINTS rows, "off" never
REDUCE_CHOICES = ("auto", "off")
#: ``artefacts=`` / ``--drop-artefacts``: "flag" names the rows (diagnose: a data_problem verdict), "drop" drops them
ARTEFACT_CHOICES = ("flag", "drop")


@dataclass
class Prepared:
    """The record to fit and what was done to it."""

    data: Specimen                                 # the record to fit
    artefacts: list[Artefact] = field(default_factory=list)   # rows flagged and kept ("flag")
    dropped: list[Artefact] = field(default_factory=list)     # rows flagged and dropped ("drop")
    lines: list[int] | None = None                 # the file's line of every raw row, where known
    reduced: bool = False

    def artefact_text(self) -> str:
        """The flagged rows in words, naming the file's lines where known."""
        return describe_artefacts(self.artefacts, self.lines)


def screen_dataset(spec: Specimen) -> tuple[list[Artefact], list[int] | None]:
    """:func:`hbm.data.artefacts.screen_artefacts` of a loaded specimen, with its file's line numbers
    (None when the file is unknown or its rows do not match)."""
    found = screen_artefacts(spec.strain, spec.stress, spec.time, spec.test)
    lines = data_lines(spec.source_file) if found and spec.source_file else None
    if lines is not None and (len(lines) != spec.n_points or "dropped_rows" in spec.attrs):
        lines = None    # rows dropped before: the file's lines no longer match
    return found, lines


def prepare_record(data, *, reduce: str = "auto", artefacts: str = "flag") -> Prepared:
    """Screen a specimen for artefact rows, drop them when ``artefacts="drop"``, and reduce a dense
    record when ``reduce="auto"`` (:mod:`hbm.data.reduction`).

    Parameters
    ----------
    data : Specimen
        A loaded specimen (a Dataset is converted once).  A reduced one is returned as it is; one
        whose artefact rows were dropped already is not screened again.
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
    spec = as_specimen(data)
    if is_reduced(spec) or not spec.has_stress:
        return Prepared(spec)
    out = Prepared(spec)
    if "dropped_rows" not in spec.attrs:   # (a record prepared before, e.g. by the command line: as it is)
        found, lines = screen_dataset(spec)
        out.lines = lines
        if found and artefacts == "drop":
            out.data, out.dropped = drop_rows(spec, found, lines), found
        elif found:
            out.artefacts = found
    if reduce == "auto" and out.data.n_points > DENSE_POINTS:
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
