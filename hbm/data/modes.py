"""Tests as data: the per-test columns of a specimen CSV that say how each test loads the tissue (issue 35).

A file without these columns is today's file (every test ``uniaxial_f``, one stress series) and is read
by the loader's unchanged path.  With them, each row also carries:

* ``mode`` (per test, constant within it): the load case, a name or alias of
  :data:`hbm.model.loadcases.LOAD_CASES` (``uniaxial_f`` when the test's cells are empty);
* ``stress_measure`` (per test, optional): ``nominal`` or ``cauchy`` (empty: the file's
  ``# stress_measure:``, default Cauchy); nominal P becomes Cauchy σ = λ·P with λ the stretch along the
  stress's axis (1 in simple shear and on held faces);
* ``strain_2`` (biaxial modes): the engineering strain along the second axis (empty: equal to ``strain``);
* observed series besides ``stress``: ``stress_2`` (in the file's stress unit) and the lateral engineering
  strains ``strain_c``, ``strain_n``, ``strain_f`` (fractions).

An empty cell means "not measured" (NaN: excluded from the likelihood), also in ``stress``; a test
without any measured value is a protocol to simulate (``hbm simulate``).  A mode that
does not define an observable refuses a value in its column.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from typing import Mapping, Sequence

import numpy as np

from ..errors import DataError, HbmError
from .specimen import Series, Specimen
from ..model.loadcases import ALIASES, DEFAULT_LOAD_CASE, LoadCase, get_load_case

__all__ = ["MODE_COLUMNS", "SERIES_COLUMNS", "mode_column", "ModeColumns", "read_mode_columns", "combine_tests",
           "check_along_fibre"]

#: per-row observed series of the vocabulary -> (unit of the loaded data, long name)
SERIES_COLUMNS: dict[str, tuple[str, str]] = {
    "stress_2": ("MPa", "second Cauchy stress of the test's mode (see its load case)"),
    "strain_f": ("-", "engineering strain along the fibres f (traction-free face)"),
    "strain_c": ("-", "engineering strain along the cross-fibre axis c (traction-free face)"),
    "strain_n": ("-", "engineering strain along the third axis n (traction-free face)"),
}
#: header words of the per-test columns -> canonical name
_TEST_WORDS = {"mode": "mode", "load_case": "mode", "stress_measure": "stress_measure"}
#: every column this module reads
MODE_COLUMNS = ("mode", "stress_measure", "strain_2", *SERIES_COLUMNS)
_MEASURES = ("cauchy", "nominal")


def mode_column(col: str) -> str | None:
    """The canonical name of a header cell this module reads (``mode``, ``strain_2`` ...), or None."""
    col = col.strip().lower()
    if col in _TEST_WORDS:
        return _TEST_WORDS[col]
    return col if col in MODE_COLUMNS else None


@dataclass(frozen=True)
class ModeColumns:
    """What the per-test columns of one file say, after conversion.

    Attributes
    ----------
    load_cases : tuple of str
        The mode of each test, in the order of the tests.
    stress : ndarray (n,)
        The main series, Cauchy, MPa (NaN where not measured).
    series : dict
        Further observed series name -> values (stress_2 in MPa Cauchy, strains as fractions).
    strain_2 : ndarray (n,) or None
        The second control of biaxial tests (``strain`` where the cell is empty; NaN in other modes);
        None when the file has no biaxial test.
    measures : tuple of str
        The stress measure each test was given in.
    """

    load_cases: tuple[str, ...]
    stress: np.ndarray
    series: dict[str, np.ndarray]
    strain_2: np.ndarray | None
    measures: tuple[str, ...]

    def attrs(self) -> dict[str, str]:
        """The records that let a saved file load back to the same specimen."""
        out = {"test_load_cases": json.dumps(list(self.load_cases))}
        if "nominal" in self.measures:
            out["test_stress_measures_original"] = json.dumps(list(self.measures))
        return out


def _mode_name(text: str) -> str:
    return ALIASES.get(text.strip(), text.strip())


def _blocks(test: np.ndarray | None, n: int) -> list[tuple[int, int]]:
    if test is None:
        return [(0, n)]
    cut = np.flatnonzero(test[1:] != test[:-1]) + 1
    return list(zip(np.r_[0, cut].tolist(), np.r_[cut, n].tolist()))


def _per_test(name: str, column: str, cells: Sequence[str], linenos: Sequence[int], a: int, b: int,
              show_test: str, canon=str.lower) -> tuple[str, int] | None:
    """The one value of a per-test column in rows a..b-1 (None when all empty), with its first line."""
    first = None
    for i in range(a, b):
        text = cells[i].strip()
        if first is None:
            first = (text, i)
            continue
        if canon(text) != canon(first[0]):
            raise DataError(f"{name}: line {linenos[i]}, column {column!r}: {column} changes within test "
                            f"{show_test} ({first[0]!r} on line {linenos[first[1]]}, {text!r} here); expected "
                            f"one {column} per test, on all its rows or none (give the rows another test id)")
    return first if first is not None and first[0] else None


def _numbers(name: str, column: str, cells: Sequence[str], linenos: Sequence[int], number) -> np.ndarray:
    out = np.full(len(cells), np.nan)
    for i, c in enumerate(cells):
        if c.strip():
            out[i] = number(c, f"{name}: line {linenos[i]}, column {column!r}")
            if not np.isfinite(out[i]):
                raise DataError(f"{name}: line {linenos[i]}, column {column!r}: expected a finite number or an "
                                f"empty cell (not measured), got {c.strip()!r}")
    return out


def read_mode_columns(name: str, columns: Mapping[str, str], cells: Mapping[str, Sequence[str]],
                      linenos: Sequence[int], strain: np.ndarray, stress_raw: np.ndarray,
                      test: np.ndarray | None, labels: Sequence[str] | None, unit_factor: float,
                      file_measure: str | None, number) -> ModeColumns:
    """Read and check the per-test columns of one file.

    Parameters
    ----------
    name : str
        The file (for messages).
    columns : mapping
        Canonical column name -> header text as written (for messages).
    cells : mapping
        Canonical column name -> its cells (one per data row).
    linenos : sequence of int
        The line of each data row.
    strain : ndarray (n,)
        Engineering strain (γ in shear tests), already converted.
    stress_raw : ndarray (n,)
        The stress column in the file's unit and measure (NaN where empty).
    test : ndarray (n,) or None
        Test ids (contiguous blocks, checked by the loader).
    labels : sequence of str, optional
        The test labels (for messages).
    unit_factor : float
        Values per MPa of the file's stress unit.
    file_measure : {"cauchy", "nominal"} or None
        The file's declared stress measure (None: not declared, Cauchy).
    number : callable
        ``number(cell, where) -> float`` (the loader's number parser).

    Returns
    -------
    ModeColumns

    Raises
    ------
    DataError
        An unknown mode, a mode or measure changing within a test, an observable or control the mode does
        not define, a stretch ≤ 0, a per-test measure contradicting the file's.
    """
    n = len(linenos)
    show = (lambda t: repr(labels[t])) if labels is not None else str  # noqa: E731
    modes, measures = [], []
    values = {c: _numbers(name, columns[c], cells[c], linenos, number) for c in ("strain_2", *SERIES_COLUMNS)
              if c in cells}
    stress = stress_raw / unit_factor
    # a column left empty throughout measures nothing: no series
    series = {c: (values[c] / unit_factor if c == "stress_2" else values[c]) for c in SERIES_COLUMNS
              if c in values and not np.isnan(values[c]).all()}
    strain_2 = None
    for a, b in _blocks(test, n):
        tid = show(int(test[a])) if test is not None else "0"
        found = _per_test(name, columns["mode"], cells["mode"], linenos, a, b, tid, _mode_name) \
            if "mode" in cells else None
        try:
            case: LoadCase = get_load_case(found[0] if found else DEFAULT_LOAD_CASE)
        except HbmError as exc:
            raise DataError(f"{name}: line {linenos[found[1]]}, column {columns['mode']!r}: {exc}") from None
        modes.append(case.name)
        allowed = set(case.observable_names) | set(case.inputs)
        for c, v in values.items():
            bad = np.flatnonzero(~np.isnan(v[a:b]))
            if bad.size and c not in allowed:
                what = "control" if c == "strain_2" else "observable"
                raise DataError(f"{name}: line {linenos[a + bad[0]]}, column {columns[c]!r}: mode {case.name} "
                                f"(test {tid}) defines no {what} {c}; it predicts "
                                f"{', '.join(case.observable_names)} from {', '.join(case.inputs)}; leave the "
                                "cell empty or give the test its mode")
        s = strain[a:b]
        if case.control == "stretch" and np.any(s <= -1.0):
            i = a + int(np.argmin(s))
            raise DataError(f"{name}: line {linenos[i]}: strain {strain[i]:g} in mode {case.name} is a stretch "
                            "<= 0; expected strain > -1")
        if "strain_2" in case.inputs:
            if strain_2 is None:
                strain_2 = np.full(n, np.nan)
            s2 = values["strain_2"][a:b] if "strain_2" in values else np.full(b - a, np.nan)
            s2 = np.where(np.isnan(s2), s, s2)
            if np.any(s2 <= -1.0):
                i = a + int(np.argmin(s2))
                raise DataError(f"{name}: line {linenos[i]}, column {columns.get('strain_2', 'strain_2')!r}: "
                                f"{s2[i - a]:g} is a stretch <= 0; expected strain_2 > -1")
            strain_2[a:b] = s2
        m = _per_test(name, columns["stress_measure"], cells["stress_measure"], linenos, a, b, tid) \
            if "stress_measure" in cells else None
        measure = file_measure or "cauchy"
        if m is not None:
            text = m[0].lower()
            where = f"{name}: line {linenos[m[1]]}, column {columns['stress_measure']!r}"
            if text not in _MEASURES:
                raise DataError(f"{where}: expected one of {', '.join(_MEASURES)} or an empty cell, got {m[0]!r}")
            if file_measure is not None and text != file_measure:
                raise DataError(f"{where}: test {tid} says {text} but the file declares {file_measure} stress; "
                                "expected one declaration (drop one of them)")
            measure = text
        measures.append(measure)
        if measure == "nominal":
            # P = σ/λ along the stress's axis (λ = 1 on held faces and in simple shear)
            s2 = None if strain_2 is None or "strain_2" not in case.inputs else strain_2[a:b]
            stress[a:b] = stress[a:b] * (1.0 + s if case.control == "stretch" else 1.0)
            if "stress_2" in series and "stress_2" in case.observable_names:
                series["stress_2"][a:b] = series["stress_2"][a:b] * case.load_stretch("stress_2", s, s2)
    return ModeColumns(tuple(modes), stress, series, strain_2, tuple(measures))


def check_along_fibre(datasets: Mapping[str, Specimen], folder) -> None:
    """Refuse specimens tested in other loading modes in a run of ``folder`` (``hbm run``: its fits and its
    population layer are along-fibre; a run that would fail at that specimen after fitting the others is
    refused before any fit)."""
    other = sorted(sid for sid, ds in datasets.items() if ds.key_extras())
    if other:
        raise DataError(f"--data {folder}: {', '.join(other)} hold(s) tests in other loading modes than uniaxial_f "
                        "or series besides stress; hbm run fits along-fibre specimens and their population. Fit "
                        "such a specimen with 'hbm fit FILE --form energy' (the joint fit across modes) and move it "
                        "out of the run's folder")


def combine_tests(parts, id: str):  # noqa: A002 - the specimen's field name
    """One specimen from the tests of several (one file per direction, as labs often share them).

    Parameters
    ----------
    parts : sequence of (Specimen, mode)
        Each specimen's tests all take ``mode`` (a name or alias; None: each test keeps its own load case,
        e.g. a file loaded with :func:`hbm.data.load_specimen`'s ``mode``); their test ids are renumbered in order
        (labels ``<specimen id>:<label or id>``), their time columns kept (each test its own history when a
        part has none).  The same result as concatenating the CSV files with a ``mode`` column.
    id : str
        The new specimen's id.

    Returns
    -------
    Specimen

    Raises
    ------
    DataError
        Parts with and without time, a series with different units, an unknown mode.
    """
    strain, time, test, labels, cases, observed, strain_2 = [], [], [], [], [], {}, []
    has_time = {p.time is not None for p, _ in parts}
    if len(has_time) > 1:
        raise DataError(f"{id}: some parts have a time column and some not; expected all or none")
    offset, n = 0, 0
    for spec, mode in parts:
        try:
            case = None if mode is None else get_load_case(mode)
        except HbmError as exc:
            raise DataError(f"{id}: {spec.id}: {exc}") from None
        ids = spec.test if spec.test is not None else np.zeros(spec.n_points, np.int64)
        for t in spec.tests:
            labels.append(f"{spec.id}:{t.label if t.label is not None else t.id}")
            cases.append(t.load_case if case is None else case.name)
        strain_2.append(spec.strain_2 if spec.strain_2 is not None else np.full(spec.n_points, np.nan))
        order = {t.id: k for k, t in enumerate(spec.tests)}
        test.append(np.array([order[int(i)] for i in ids]) + offset)
        offset += len(spec.tests)
        strain.append(spec.strain)
        if spec.time is not None:
            time.append(spec.time)
        for k, s in spec.observed.items():
            if k in observed and observed[k][0] != s.unit:
                raise DataError(f"{id}: series {k} in {s.unit} in {spec.id}, {observed[k][0]} before")
            observed.setdefault(k, (s.unit, s.long_name, {}))[2][n] = s.values
        n += spec.n_points
    series = {}
    for k, (unit, long_name, pieces) in observed.items():
        v = np.full(n, np.nan)
        for start, values in pieces.items():
            v[start: start + values.size] = values
        series[k] = Series(k, v, unit, long_name)
    attrs = {"id": id, "test_labels": json.dumps(labels), "test_load_cases": json.dumps(cases),
             "combined_from": json.dumps([p.id for p, _ in parts])}
    s2 = np.concatenate(strain_2)
    return Specimen(id, np.concatenate(strain), np.concatenate(time) if time else None, np.concatenate(test),
                    series, attrs, strain_2=None if np.isnan(s2).all() else s2)
