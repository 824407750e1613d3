"""Load specimen CSV files (one or a folder) into checked :class:`~hbm.data.specimen.Specimen` objects."""

from __future__ import annotations

import csv

import json


import re


from pathlib import Path
from typing import Sequence

import numpy as np


from ..errors import DataError, HbmError
from ..model.loadcases import DEFAULT_LOAD_CASE, get_load_case


from .columns import (
    GROUP_KEY, MIN_POINTS, STRESS_UNITS, _Columns, _DECIMAL_COMMA_RE, _MEASURES, _META_RE,
    _SEPARATOR_HINT, _UNIT_NAMES, _check_plausible, _check_sign, _check_sl0, _columns, _declared,
    _is_float, _number, _read_text, _record, _reference_sl, _same_labels, _show, _strain, _test_column)
from .machine import convert_machine, machine_column
from .modes import MODE_COLUMNS, read_mode_columns
from .specimen import Series, Specimen, Test


def load_specimen(path: str | Path, *, sl0: float | None = None, mode: str | None = None) -> Specimen:
    """Read and validate one specimen CSV, converting units, stress measure and deformation.

    Parameters
    ----------
    path : str or Path
        CSV file in the format described in the module docstring (README "Data format").
    sl0 : float, optional
        Reference sarcomere length in µm for a ``sarcomere_length_um`` column
        (strain = SL/SL0 − 1), for files without ``# reference_sarcomere_length_um``.  If the
        file declares one too, both must be equal.  Ignored for other deformation columns.
    mode : str, optional
        The loading mode of every test of a file without a ``mode`` column (a name or alias of
        :data:`hbm.model.loadcases.LOAD_CASES`; labs often share one file per direction).  It acts as if the
        column were there, so nominal stress converts along that mode's axes.  ``uniaxial_f`` (the default)
        loads the file exactly as without it.  A file with its own ``mode`` column refuses it.

    Returns
    -------
    Specimen
        ``strain``, the series ``stress`` (Cauchy, MPa) and, when present, ``time`` (s) and
        ``test`` (int); ``attrs``: the metadata (strings), ``id`` (metadata ``id`` or the file
        stem), ``source_file`` and the record of every conversion (``units_stress_original``,
        ``stress_measure_original``, ``deformation_input``, ``reference_sarcomere_length_um``,
        ``test_labels``).  ``.to_dataset()`` is the xarray view.

    Raises
    ------
    DataError
        One-line message naming the file, line (and column) and the expectation.
    """
    path = Path(path)
    name = str(path)
    sl0 = _check_sl0(sl0)
    text = _read_text(path)
    if not text.strip():
        raise DataError(f"{name}: empty file, expected '# key: value' metadata lines and a "
                        "header with strain,stress")

    attrs: dict[str, str] = {}
    meta_line: dict[str, int] = {}
    header: list[str] | None = None
    header_lineno = 0
    cols: _Columns | None = None
    rows: list[tuple[int, list[str]]] = []
    delimiter = ","
    for lineno, line in enumerate(text.split("\n"), start=1):
        if not line.strip():
            continue
        if line.lstrip().startswith("#"):
            if header is not None:
                raise DataError(f"{name}: line {lineno}: expected a data row, got a '#' line after "
                                f"the header (metadata '# key: value' lines go before the header)")
            m = _META_RE.match(line.strip())
            if not m:
                raise DataError(f"{name}: line {lineno}: unknown metadata format {_show(line.strip())}, "
                                "expected '# key: value'")
            key, value = re.sub(r"\s+", "_", m.group(1)), m.group(2).strip()
            if key in attrs:
                raise DataError(f"{name}: line {lineno}: metadata key {key!r} repeated "
                                f"(first on line {meta_line[key]})")
            if key == GROUP_KEY and not value:  # a group must have a name the report can use
                raise DataError(f"{name}: line {lineno}: metadata {GROUP_KEY} is empty, expected a group name "
                                "(e.g. a species, muscle or protocol)")
            attrs[key], meta_line[key] = value, lineno
            continue
        if header is None:  # the header fixes the separator: ',' or, in a header without one, tab or ';'
            delimiter = "," if "," in line else "\t" if "\t" in line else ";" if ";" in line else ","
        try:
            cells = next(csv.reader([line], delimiter=delimiter))
        except csv.Error as exc:  # e.g. a cell over the csv module's 128 KiB field limit
            raise DataError(f"{name}: line {lineno}: unreadable CSV row ({exc}), expected "
                            "comma-separated numbers") from None
        if delimiter != ",":  # spreadsheets that separate by tab/';' write decimal commas: 0,01 -> 0.01
            cells = [_DECIMAL_COMMA_RE.sub(r"\1.\2", c) for c in cells]
        if header is None:
            if all(_is_float(c) for c in cells):
                raise DataError(f"{name}: line {lineno}: expected a header with strain,stress before the data, "
                                f"got a numeric row {_show(line.strip())}")
            cols = _columns(name, cells, lineno, line)
            header, header_lineno = [c.strip().lower() for c in cells], lineno
            continue
        if [c.strip().lower() for c in cells] == header:
            raise DataError(f"{name}: line {lineno}: duplicate header (first on line {header_lineno}), "
                            "expected a data row")
        if len(cells) != len(header):
            hint = _SEPARATOR_HINT if any(c in line for c in ";\t") else ""
            raise DataError(f"{name}: line {lineno}: ragged row with {len(cells)} cells, expected "
                            f"{len(header)} like the header on line {header_lineno}{hint}")
        rows.append((lineno, cells))

    if header is None or cols is None:
        raise DataError(f"{name}: no header line, expected a header with strain,stress after the metadata")
    unit = _declared(name, attrs, meta_line, "units_stress", _UNIT_NAMES, cols.unit, cols.names["stress"])
    measure = _declared(name, attrs, meta_line, "stress_measure", {m: m for m in _MEASURES}, cols.measure,
                        cols.names["stress"])
    ref = _reference_sl(name, attrs, meta_line, sl0)
    if cols.deformation == "sarcomere_length_um" and ref is None:
        raise DataError(f"{name}: line {header_lineno}, column {cols.names['deformation']!r}: a sarcomere "
                        "length needs the reference SL0 (strain = SL/SL0 - 1); add "
                        "'# reference_sarcomere_length_um: <SL0 in um, e.g. 2.0>' or pass sl0 (--sl0)")
    if len(rows) < MIN_POINTS:
        raise DataError(f"{name}: {len(rows)} data rows, expected at least {MIN_POINTS} points")

    linenos = [ln for ln, _ in rows]
    raw: dict[str, np.ndarray] = {}
    labels = None
    by_test = [role for role in cols.index if role in MODE_COLUMNS]  # tests as data (hbm.data.modes)
    given = _given_mode(name, mode, cols)
    if given is not None:
        by_test.append("mode")
    for role, j in sorted(cols.index.items(), key=lambda kv: kv[1]):
        column = cols.names[role]
        if role in by_test:
            continue
        if role == "stress" and by_test:  # an empty cell is a value not measured
            raw[role] = np.asarray([_number(cells[j], f"{name}: line {lineno}, column {column!r}")
                                    if cells[j].strip() else np.nan for lineno, cells in rows], dtype=float)
            continue
        if role == "test":
            raw[role], labels = _test_column(name, [cells[j] for _, cells in rows], linenos, column)
            continue
        raw[role] = np.asarray([_number(cells[j], f"{name}: line {lineno}, column {column!r}")
                                for lineno, cells in rows], dtype=float)

    deformation = cols.deformation
    if cols.force is not None or machine_column(deformation) is not None:
        # a machine export: force -> nominal stress (MPa), displacement -> strain (hbm.data.machine)
        for key, value in convert_machine(name, attrs, meta_line, cols.names, cols.index, cols.force, deformation,
                                          raw, header_lineno).items():
            _record(name, attrs, meta_line, key, value)
    data: dict[str, np.ndarray] = {"strain": _strain(name, raw["deformation"], deformation, ref,
                                                     cols.names["deformation"], linenos)}
    for role in ("time", "test"):
        if role in raw:
            data[role] = raw[role]
    if by_test:
        _check_tests_and_time(name, data.get("time"), data.get("test"), linenos, labels)
        return _load_modes(name, path, cols, rows, linenos, raw, data, labels, unit, measure, attrs, meta_line,
                           header_lineno, ref, given)
    stress = raw["stress"]
    if unit not in (None, "MPa"):
        stress = stress / STRESS_UNITS[unit]
    if measure == "nominal":
        stress = (1.0 + data["strain"]) * stress  # incompressible uniaxial: sigma = lambda * P
    data["stress"] = stress
    _check_tests_and_time(name, data.get("time"), data.get("test"), linenos, labels)
    _check_plausible(name, raw["stress"], data["strain"], stress, unit, measure == "nominal", cols, linenos)
    _check_sign(name, data["strain"], stress, cols, linenos)

    _record_conversions(name, path, cols, attrs, meta_line, unit, measure, ref, labels)
    return Specimen(str(attrs["id"]), data["strain"], data.get("time"), data.get("test"),
                    {"stress": Series.known("stress", data["stress"])}, attrs)


def _record_conversions(name, path, cols, attrs, meta_line, unit, measure, ref, labels) -> None:
    # the dataset holds Cauchy stress in MPa and strain: record what the file held
    if unit is not None:
        attrs["units_stress"] = "MPa"  # the declaration now describes the dataset
        if unit != "MPa":
            _record(name, attrs, meta_line, "units_stress_original", unit)
    if measure is not None:
        attrs["stress_measure"] = "cauchy"
        if measure == "nominal":
            _record(name, attrs, meta_line, "stress_measure_original", "nominal")
    if cols.deformation != "strain":
        _record(name, attrs, meta_line, "deformation_input", cols.deformation)
    if cols.deformation == "sarcomere_length_um":
        attrs["reference_sarcomere_length_um"] = repr(ref)
    if labels is not None:
        _record(name, attrs, meta_line, "test_labels", json.dumps(labels), same=_same_labels)
    attrs.setdefault("id", path.stem)
    attrs["source_file"] = str(path)


def _given_mode(name: str, mode: str | None, cols) -> str | None:
    """The canonical mode given for a file without a ``mode`` column (None: none given, or uniaxial_f,
    which is the file as it is)."""
    if mode is None:
        return None
    try:
        case = get_load_case(mode)
    except HbmError as exc:
        raise DataError(f"{name}: {exc}") from None
    if "mode" in cols.index:
        raise DataError(f"{name}: the file names its tests' modes in its column {cols.names['mode']!r}; a mode "
                        f"given for the whole file ({mode!r}) would contradict it: drop one of them")
    return None if case.name == DEFAULT_LOAD_CASE else case.name


def _load_modes(name, path, cols, rows, linenos, raw, data, labels, unit, measure, attrs, meta_line, header_lineno,
                ref, given=None) -> Specimen:
    """The rest of :func:`load_specimen` for a file with per-test columns (:mod:`hbm.data.modes`);
    ``given``: the mode of every test of a file without a mode column."""
    cells = {role: [r[j] for _, r in rows] for role, j in cols.index.items() if role in MODE_COLUMNS}
    if given is not None:
        cells["mode"] = [given] * len(rows)
        cols.names.setdefault("mode", "mode")
    strain = data["strain"]
    got = read_mode_columns(name, cols.names, cells, linenos, strain, raw["stress"], data.get("test"), labels,
                            STRESS_UNITS.get(unit or "MPa", 1.0), measure, _number)
    stress = got.stress
    # the unit judge knows along-fibre tension: it sees the measured along-fibre rows only
    along = np.zeros(len(linenos), bool)
    specimen_tests = _tests_of(data.get("test"), len(linenos), got.load_cases)
    for t in specimen_tests:
        if t.load_case == "uniaxial_f":
            along[t.rows] = True
    along &= np.isfinite(stress)
    if along.sum() >= 2:
        idx = np.flatnonzero(along)
        _check_plausible(name, raw["stress"][idx], strain[idx], stress[idx], unit, measure == "nominal", cols,
                         [linenos[i] for i in idx])
    ok = np.flatnonzero(np.isfinite(stress))
    if ok.size:
        _check_sign(name, strain[ok], stress[ok], cols, [linenos[i] for i in ok])
    _record_conversions(name, path, cols, attrs, meta_line, unit, measure, ref, labels)
    attrs.update(got.attrs())
    observed = {"stress": Series.known("stress", stress)}
    observed.update({k: Series.known(k, v) for k, v in got.series.items()})
    # the tests' modes travel in attrs["test_load_cases"] (saved files load back the same)
    return Specimen(str(attrs["id"]), strain, data.get("time"), data.get("test"), observed, attrs,
                    strain_2=got.strain_2)


def _tests_of(test, n, load_cases) -> list[Test]:
    if test is None:
        return [Test(0, None, 0, n, load_cases[0])]
    cut = np.flatnonzero(test[1:] != test[:-1]) + 1
    return [Test(int(test[a]), None, int(a), int(b), c) for a, b, c in zip(np.r_[0, cut], np.r_[cut, n], load_cases)]


def _check_tests_and_time(name: str, time: np.ndarray | None, test: np.ndarray | None,
                          linenos: Sequence[int], labels: Sequence[str] | None = None) -> None:
    n = len(linenos)
    show = (lambda t: repr(labels[t])) if labels is not None else str  # noqa: E731
    if test is not None:
        seen: dict[int, int] = {}
        for i in range(n):
            t = int(test[i])
            if i and t != test[i - 1] and t in seen:
                raise DataError(f"{name}: line {linenos[i]}, column 'test': test {show(t)} reappears after "
                                f"other tests (first block ends before line {linenos[seen[t]]}), expected "
                                "the rows of each test to be contiguous")
            seen.setdefault(t, i)
    if time is None:
        return
    drops = np.flatnonzero(np.diff(time) < 0) + 1
    for i in drops:
        new_test = test is not None and test[i] != test[i - 1]
        if new_test and time[i] == 0.0:
            continue  # a new test that starts from rest: a new loading history
        where = f"{name}: line {linenos[i]}, column 'time'"
        if new_test:
            raise DataError(f"{where}: time drops from {time[i - 1]!r} to {time[i]!r} at the start of test "
                            f"{show(int(test[i]))}; expected it to continue (>= {time[i - 1]!r}, same loading "
                            "history) or to restart at exactly 0 (new history from rest)")
        raise DataError(f"{where}: decreasing time ({time[i - 1]!r} -> {time[i]!r}); expected non-decreasing "
                        "time within a test (time may restart at 0 only where a new test starts)")


def load_specimens(folder: str | Path, *, sl0: float | None = None) -> dict[str, Specimen]:
    """Load every ``*.csv`` in ``folder`` (not recursive).

    Parameters
    ----------
    folder : str or Path
        Folder of specimen CSV files.
    sl0 : float, optional
        Reference sarcomere length in µm for files with a ``sarcomere_length_um`` column and no
        ``# reference_sarcomere_length_um`` line (see :func:`load_specimen`).

    Returns
    -------
    dict
        ``id -> Specimen`` sorted by id.

    Raises
    ------
    DataError
        If the folder is missing or has no CSV, a file is malformed, or two files share an id.
    """
    folder = Path(folder)
    if not folder.is_dir():
        raise DataError(f"{folder}: not a directory, expected a folder of specimen CSV files")
    files = sorted(folder.glob("*.csv"))
    if not files:
        raise DataError(f"{folder}: no *.csv files, expected at least one specimen file")
    out: dict[str, Specimen] = {}
    for f in files:
        spec = load_specimen(f, sl0=sl0)
        sid = spec.id
        if sid in out:
            raise DataError(f"{f}: duplicate specimen id {sid!r} (also in {out[sid].source_file}), "
                            "expected unique ids (metadata 'id' or file stem)")
        out[sid] = spec
    return dict(sorted(out.items()))


