"""Specimen stress–strain curves: CSV (+ metadata) <-> xarray.Dataset, validation, synthetic data.

CSV format
----------
::

    # id: calvo2010_rat1                  <- optional metadata, ``# key: value``, only at the top
    # source: synthetic stand-in for ...
    strain,stress,time,test               <- header: a deformation and a stress column, any order
    0.0,0.0012,0.0,1
    0.01,0.0031,45.45,1
    ...

Columns (header names are case-insensitive; exactly one deformation and one stress column;
headers as labs write them, ``Strain (%)``, ``Nominal stress [kPa]``, ``Time (s)``, are read as the
names below, see :func:`_canonical_header`; a header without ',' makes tab or ';' the separator and
then decimal commas are read):

* deformation — ``strain``: engineering strain ε = ΔL/L0 (dimensionless); or
  ``strain_percent``: 100·ε; or ``stretch`` λ = L/L0 (ε = λ − 1); or ``sarcomere_length_um``, the sarcomere length SL in µm
  (ε = SL/SL0 − 1 with the reference SL0 from ``# reference_sarcomere_length_um: 2.0`` or the
  ``sl0=`` argument).  The resulting strain must lie within [−0.5, 2] and must not consist of
  whole numbers only (that is what decimal commas or percent leave behind).
* stress — ``stress`` in MPa unless declared otherwise: ``# units_stress: MPa|kPa|Pa`` or a unit
  suffix on the column (``stress_kPa``, ``stress_Pa``, ``stress_MPa``); Cauchy (true) stress
  unless ``# stress_measure: nominal`` or the column is ``nominal_stress*`` (``cauchy_stress*``
  declares Cauchy).  Nominal stress P (force / undeformed area) becomes Cauchy stress
  σ = λ·P = (1 + ε)·P (incompressible uniaxial tension).  The loaded dataset always holds
  Cauchy stress in MPa.  The unit is judged from the physics (:mod:`hbm.plausibility`): a curve
  whose stress per unit strain (toe or peak) is stiffer than passive muscle with NO declared unit
  is refused with the declaration that fixes it; with a declared unit (or outside the range on
  the soft side) it loads with a warning.  A cell like ``01`` (leading zero) is refused: it is the
  tail of a decimal comma.
* ``time`` (optional) — seconds.
* ``test`` (optional) — a protocol segment (a ramp, a hold, an unloading ...): integer ids, or
  labels as labs write them (``load``, ``unload``, ``hold``, ``ramp_0.01``: a letter, then
  letters, digits, spaces or ``_ . + - / ( ) %``, at most 64 characters), not both.  Labels are
  numbered 0, 1, 2 ... in order of first appearance and kept in the ``test_labels`` attribute
  (JSON list).  The rows of one test must be contiguous.

Rules for ``time`` (DESIGN.md §2).  Inside a test, time is non-decreasing.  At the first row
of a new test, time either *continues* (≥ the previous row's time): the new test is the next
segment of the same loading history (load → unload → reload, ramp → relaxation hold), and
history-dependent effects see what came before; or it *restarts at exactly 0*: the new test
starts from rest, a new loading history.  Any other drop in time is an error.  Without a
``test`` column, time must be non-decreasing over the whole file (one history).  Without a
``time`` column, every test is its own history (see :class:`hbm.Loading`).

Metadata lines must come before the header and look like ``# key: value`` (key: letters,
digits, ``_ . -`` and spaces, which become ``_``; each key once).  Blank lines are ignored.
``id`` names the specimen (default: the file stem); ``provenance`` is ``synthetic`` or
``measured``; ``group`` (optional, non-empty) names the specimen's group (species, muscle,
protocol ...): specimens with groups get a population → group → specimen layer
(:func:`specimen_groups`, ``hbm run --group-by KEY`` groups by any other key).  Every row has as many cells as the header; only regular files are read.

Conversions are recorded in the attributes, so that :func:`save_specimen` writes a file that
loads back to the same numbers: ``units_stress`` (then ``MPa``) and ``units_stress_original``,
``stress_measure`` (then ``cauchy``) and ``stress_measure_original``, ``deformation_input``,
``reference_sarcomere_length_um``, ``test_labels``.  A file that carries one of these records
itself keeps it when no conversion happens, and must agree with it when one does.

Every problem raises :class:`hbm.errors.DataError` with a one-line message naming the file,
the line (and column) and what was expected.
"""

from __future__ import annotations

import csv
import io
import json
import math
import os
import re
import stat
import warnings
from dataclasses import dataclass
from numbers import Real
from pathlib import Path
from typing import Any, Mapping, Sequence

import numpy as np
import xarray as xr

from ._version import __version__
from .errors import DataError, HbmError, HbmWarning
from .model.core import Loading, Model
from .noise import make_noise
from .plausibility import describe, implausible, suggest_unit
from .utils import atomic_path, as_generator

__all__ = [
    "STRAIN_RANGE", "MIN_POINTS", "STRESS_UNITS", "DEFORMATIONS",
    "load_specimen", "load_specimens", "save_specimen", "specimen_loading", "provenance",
    "input_summary", "input_line", "synthetic_specimen", "GROUP_KEY", "specimen_groups", "Segment", "ramp", "hold", "cycle", "protocol",
]

#: allowed engineering strain (catches percent-vs-fraction mix-ups)
STRAIN_RANGE = (-0.5, 2.0)
#: minimum number of data points in a specimen
MIN_POINTS = 5
#: stress units of ``# units_stress:`` and of column suffixes -> values per MPa
STRESS_UNITS = {"MPa": 1.0, "kPa": 1e3, "Pa": 1e6}
#: metadata key of a specimen's group (``# group: NAME``)
GROUP_KEY = "group"
#: deformation columns; a file has exactly one
DEFORMATIONS = ("strain", "strain_percent", "stretch", "sarcomere_length_um")

_COLUMNS = ("strain", "stress", "time", "test")
_UNITS = {"strain": "-", "stress": "MPa", "time": "s", "test": "-"}
_LONG = {"strain": "engineering strain", "stress": "Cauchy stress along the fibers",
         "time": "time", "test": "protocol segment (test) id"}
_META_RE = re.compile(r"^#\s*([A-Za-z_][A-Za-z0-9_.\- ]*?)\s*:\s?(.*)$")
_KEY_RE = re.compile(r"^[A-Za-z_][A-Za-z0-9_.\-]*$")
_UNIT_NAMES = {u.lower(): u for u in STRESS_UNITS}
_MEASURES = ("cauchy", "nominal")
_STRESS_COL_RE = re.compile(r"^(?:(nominal|cauchy)_)?stress(?:_(mpa|kpa|pa))?$")
_LABEL_RE = re.compile(r"^[A-Za-z][A-Za-z0-9_.+\-/()% ]{0,63}$")
_LEADING_ZERO_RE = re.compile(r"^[+-]?0[0-9]+$")
_DECIMAL_COMMA_RE = re.compile(r"^(\s*[+-]?[0-9]+),([0-9]+(?:[eE][+-]?[0-9]+)?\s*)$")
_INT64 = 2 ** 63
_EXPECTED_COLUMNS = ("strain|strain_percent|stretch|sarcomere_length_um, stress (or stress_MPa|stress_kPa|stress_Pa, "
                     "nominal_stress[_unit], cauchy_stress[_unit]), time, test")
_SEPARATOR_HINT = " (cells are separated by ',', numbers use '.')"
# headers as labs write them: "Strain (%)", "Nominal stress [kPa]", "Time (s)" -> the canonical names
_UNIT_SUFFIX_RE = re.compile(r"^(?P<word>[^()\[\]]*?)\s*(?:\((?P<u1>[^()]*)\)|\[(?P<u2>[^\[\]]*)\])$")
_STRAIN_WORDS = ("strain", "engineering strain", "nominal strain")
_STRESS_WORDS = {"stress": "", "cauchy stress": "cauchy_", "true stress": "cauchy_", "nominal stress": "nominal_",
                 "engineering stress": "nominal_"}
_STRESS_UNIT_ALIASES = {"mpa": "mpa", "n/mm2": "mpa", "n/mm^2": "mpa", "n/mm\u00b2": "mpa", "kpa": "kpa",
                        "mn/mm2": "kpa", "mn/mm^2": "kpa", "mn/mm\u00b2": "kpa", "pa": "pa", "n/m2": "pa",
                        "n/m^2": "pa", "n/m\u00b2": "pa"}
_NO_UNIT = ("", "-", "1", "mm/mm", "m/m")
_MICRO = ("um", "\u00b5m", "\u03bcm", "micrometre", "micrometres", "micrometer", "micrometers", "micron", "microns")
_LABEL_RULE = "a letter, then letters, digits, spaces or _ . + - / ( ) %, at most 64 characters"


# ---------------------------------------------------------------------------------------
# reading
# ---------------------------------------------------------------------------------------
def _show(text: str, limit: int = 40) -> str:
    """``repr`` of a cell, shortened so that a 100 kB cell still gives a one-line message."""
    return repr(text) if len(text) <= limit else repr(text[:limit]) + f"... ({len(text)} characters)"


def _number(cell: str, where: str, *, integer: bool = False) -> float | int:
    text = cell.strip()
    try:
        value = int(text) if integer else float(text)
    except ValueError:
        if integer:
            f = float(text) if _is_float(text) else math.nan
            if math.isfinite(f) and f == int(f):  # accept "3.0" as an integer test id, not "3.5"
                return _test_id(int(f), text, where)
            raise DataError(f"{where}: expected an integer test id, got {_show(text)}") from None
        raise DataError(f"{where}: expected a number, got {_show(text)}") from None
    if integer:
        return _test_id(value, text, where)
    if not math.isfinite(value):
        raise DataError(f"{where}: expected a finite number, got {_show(text)}")
    if _LEADING_ZERO_RE.match(text):
        # "0,01" split at the decimal comma leaves "01": no writer of numbers pads with zeros
        raise DataError(f"{where}: expected a number with '.' as decimal separator, got {_show(text)} "
                        "(a leading zero: the tail of a decimal comma like 0,01?)")
    return value


def _test_id(value: int, text: str, where: str) -> int:
    # ids are stored as int64: a larger one would overflow (a traceback, not a message)
    if not -_INT64 <= value < _INT64:
        raise DataError(f"{where}: test id {_show(text)} out of range, expected an integer id "
                        f"within +-2**63 or a label")
    return value


def _is_float(text: str) -> bool:
    try:
        float(text)
    except ValueError:
        return False
    return True


def _read_text(path: Path) -> str:
    """The file's text (UTF-8, optional BOM, universal newlines); only regular files are opened."""
    name = str(path)
    try:
        # stat before opening: opening a FIFO blocks until a writer appears, a device may act
        mode = path.stat().st_mode
        if stat.S_ISDIR(mode):
            raise DataError(f"{name}: is a directory, expected a CSV file")
        if not stat.S_ISREG(mode):
            raise DataError(f"{name}: not a regular file (a FIFO, socket or device), expected a CSV file")
        # O_NONBLOCK: should the path be swapped for a FIFO after the stat, open still returns
        fd = os.open(path, os.O_RDONLY | getattr(os, "O_NONBLOCK", 0))
        with open(fd, "rb") as fh:
            if not stat.S_ISREG(os.fstat(fh.fileno()).st_mode):
                raise DataError(f"{name}: not a regular file, expected a CSV file")
            raw = fh.read()
    except FileNotFoundError:
        raise DataError(f"{name}: file not found") from None
    except IsADirectoryError:
        raise DataError(f"{name}: is a directory, expected a CSV file") from None
    except OSError as exc:
        raise DataError(f"{name}: cannot read ({exc.strerror or exc})") from None
    try:
        text = raw.decode("utf-8-sig")
    except UnicodeDecodeError as exc:
        raise DataError(f"{name}: not a UTF-8 text file ({exc.reason} at byte {exc.start})") from None
    return text.replace("\r\n", "\n").replace("\r", "\n")


@dataclass(frozen=True)
class _Columns:
    """What the header says: column index and header text per role, units in the names."""

    index: dict[str, int]  # role ("deformation", "stress", "time", "test") -> column index
    names: dict[str, str]  # role -> header cell as written
    deformation: str  # one of DEFORMATIONS
    unit: str | None  # stress unit carried by the column name
    measure: str | None  # stress measure carried by the column name


def _canonical_header(text: str, where: str) -> str | None:
    """The canonical column name of a header written as labs write it, or None.

    ``Strain (%)`` -> ``strain_percent``, ``Strain [-]`` / ``Engineering strain`` -> ``strain``,
    ``Stretch ratio`` -> ``stretch``, ``Sarcomere length (µm)`` -> ``sarcomere_length_um``,
    ``Nominal stress (kPa)`` / ``Engineering stress [N/mm2]`` -> ``nominal_stress_kpa`` /
    ``nominal_stress_mpa``, ``True stress (MPa)`` -> ``cauchy_stress_mpa``, ``Time (s)`` -> ``time``.
    A known quantity with a unit hbm does not convert is a DataError naming what is accepted.
    """
    m = _UNIT_SUFFIX_RE.match(text.strip().lower())
    word, unit = (m.group("word"), (m.group("u1") if m.group("u1") is not None else m.group("u2")).strip()) \
        if m else (text.strip().lower(), None)
    word = re.sub(r"[\s_]+", " ", word).strip()
    if word in ("force", "load"):
        raise DataError(f"{where}: column {_show(text)} is a force; hbm needs stress = force / cross-sectional "
                        "area (a stress column in MPa, kPa or Pa)")
    if word in _STRAIN_WORDS:
        if unit == "%":
            return "strain_percent"
        if unit is None or unit in _NO_UNIT:
            return "strain"
        raise DataError(f"{where}: strain unit {_show(unit)} of column {_show(text)}: expected a fraction "
                        "('-', 'mm/mm') or '%'")
    if word in ("stretch", "stretch ratio"):
        if unit is None or unit in _NO_UNIT:
            return "stretch"
        raise DataError(f"{where}: stretch L/L0 has no unit, got {_show(unit)} in column {_show(text)}")
    if word == "sarcomere length":
        if unit in _MICRO:
            return "sarcomere_length_um"
        raise DataError(f"{where}: column {_show(text)}: a sarcomere length needs its unit, micrometres "
                        "('Sarcomere length (um)' or sarcomere_length_um)")
    if word in _STRESS_WORDS:
        if unit is None:
            return _STRESS_WORDS[word] + "stress"
        if unit in _STRESS_UNIT_ALIASES:
            return f"{_STRESS_WORDS[word]}stress_{_STRESS_UNIT_ALIASES[unit]}"
        raise DataError(f"{where}: stress unit {_show(unit)} of column {_show(text)}: expected MPa (N/mm2), "
                        "kPa (mN/mm2) or Pa (N/m2)")
    if word == "time" and unit is not None:
        if unit in ("s", "sec", "second", "seconds"):
            return "time"
        raise DataError(f"{where}: time unit {_show(unit)} of column {_show(text)}: expected seconds "
                        "(convert the column to s)")
    return None


def _columns(name: str, cells: list[str], lineno: int, line: str) -> _Columns:
    index: dict[str, int] = {}
    names: dict[str, str] = {}
    seen: dict[str, int] = {}
    deformation, unit, measure = "strain", None, None
    for j, cell in enumerate(cells):
        text = cell.strip()
        col = text.lower()
        where = f"{name}: line {lineno}, column {j + 1}"
        if col not in DEFORMATIONS and col not in ("time", "test") and not _STRESS_COL_RE.match(col):
            col = _canonical_header(text, where) or col
        if col in seen:
            raise DataError(f"{where}: duplicate column name {col!r} (also column {seen[col] + 1})")
        seen[col] = j
        m = _STRESS_COL_RE.match(col)
        if col in DEFORMATIONS:
            role = "deformation"
        elif m:
            role = "stress"
        elif col in ("time", "test"):
            role = col
        else:
            hint = _SEPARATOR_HINT if any(c in text for c in ";\t") else ""
            raise DataError(f"{where}: unknown column {_show(text)}, expected one of "
                            f"{_EXPECTED_COLUMNS}{hint}")
        if role in index:
            raise DataError(f"{where}: second {role} column {_show(text)} (column {index[role] + 1} is "
                            f"{names[role]!r}), expected exactly one {role} column")
        index[role], names[role] = j, text
        if role == "deformation":
            deformation = col
        elif role == "stress":
            measure, unit = m.group(1), _UNIT_NAMES.get(m.group(2) or "")
    for role, need in (("deformation", "strain"), ("stress", "stress")):
        if role not in index:
            raise DataError(f"{name}: line {lineno}: header has no {need!r} column, expected columns "
                            f"strain,stress[,time][,test] (see {_EXPECTED_COLUMNS}), got {_show(line.strip())}")
    return _Columns(index, names, deformation, unit, measure)


def _declared(name: str, attrs: Mapping[str, str], meta_line: Mapping[str, int], key: str,
              allowed: Mapping[str, str], from_column: str | None, column: str) -> str | None:
    """A stress declaration (unit or measure) from metadata and column name; a conflict is an error."""
    if key not in attrs:
        return from_column
    where = f"{name}: line {meta_line[key]}"
    value = allowed.get(attrs[key].strip().lower())
    if value is None:
        raise DataError(f"{where}: metadata {key} is {_show(attrs[key])}, expected one of "
                        f"{', '.join(dict.fromkeys(allowed.values()))}")
    if from_column is not None and from_column != value:
        raise DataError(f"{where}: '# {key}: {attrs[key]}' contradicts column {column!r} ({from_column}), "
                        "expected one declaration (drop the metadata line or rename the column)")
    return value


def _positive_sl(text: Any) -> float | None:
    try:
        value = float(text)
    except (TypeError, ValueError):
        return None
    return value if math.isfinite(value) and value > 0 else None


def _reference_sl(name: str, attrs: Mapping[str, str], meta_line: Mapping[str, int],
                  sl0: float | None) -> float | None:
    """SL0 in µm from ``# reference_sarcomere_length_um`` and/or ``sl0``; they must agree."""
    key = "reference_sarcomere_length_um"
    if key not in attrs:
        return sl0
    where = f"{name}: line {meta_line[key]}"
    value = _positive_sl(attrs[key])
    if value is None:
        raise DataError(f"{where}: metadata {key} is {_show(attrs[key])}, expected a positive sarcomere "
                        "length in micrometres (e.g. 2.0)")
    if sl0 is not None and sl0 != value:
        raise DataError(f"{where}: '# {key}: {attrs[key]}' contradicts sl0={sl0!r}, expected one reference "
                        "sarcomere length (drop the metadata line or the sl0 argument)")
    return value


def _check_sl0(sl0: Any) -> float | None:
    if sl0 is None:
        return None
    value = None if isinstance(sl0, bool) or not isinstance(sl0, (Real, str)) else _positive_sl(sl0)
    if value is None:
        raise DataError(f"sl0: expected a positive reference sarcomere length in micrometres "
                        f"(e.g. 2.0), got {sl0!r}")
    return value


def _record(name: str, attrs: dict[str, str], meta_line: Mapping[str, int], key: str, value: str,
            same=lambda a, b: a.strip().lower() == b.lower()) -> None:
    """Record a conversion in ``attrs[key]``; a record the file carries itself must agree."""
    if key in attrs and not same(attrs[key], value):
        raise DataError(f"{name}: line {meta_line[key]}: metadata {key} is {_show(attrs[key])} but the file "
                        f"says {value!r}; expected the key absent (it records a conversion) or equal")
    attrs[key] = value


def _same_labels(text: str, labels_json: str) -> bool:
    try:
        return json.loads(text) == json.loads(labels_json)
    except ValueError:
        return False


def _test_column(name: str, cells: Sequence[str], linenos: Sequence[int],
                 column: str) -> tuple[np.ndarray, list[str] | None]:
    """Integer test ids, or labels numbered in order of first appearance (then also the labels)."""
    texts = [c.strip() for c in cells]
    labelled = not _is_float(texts[0])
    first = f"line {linenos[0]} has {_show(texts[0])}"
    ids: list[int] = []
    order: dict[str, int] = {}
    for lineno, text in zip(linenos, texts):
        where = f"{name}: line {lineno}, column {column!r}"
        if not labelled:
            if not _is_float(text):
                raise DataError(f"{where}: expected an integer test id like the rows above ({first}), "
                                f"got {_show(text)}")
            ids.append(_number(text, where, integer=True))
        elif _is_float(text):
            raise DataError(f"{where}: expected a test label like the rows above ({first}), got the number "
                            f"{_show(text)}; expected either integer ids or labels throughout")
        elif not _LABEL_RE.match(text):
            raise DataError(f"{where}: expected an integer test id or a test label ({_LABEL_RULE}), "
                            f"got {_show(text)}")
        else:
            ids.append(order.setdefault(text, len(order)))
    return np.asarray(ids, dtype=np.int64), (list(order) if labelled else None)


def _strain(name: str, raw: np.ndarray, deformation: str, sl0: float | None,
            column: str, linenos: Sequence[int]) -> np.ndarray:
    """Engineering strain from the deformation column, range-checked."""
    if deformation == "stretch":
        strain = raw - 1.0
    elif deformation == "strain_percent":
        strain = raw / 100.0
    elif deformation == "sarcomere_length_um":
        strain = raw / sl0 - 1.0
    else:
        strain = raw
    lo, hi = STRAIN_RANGE
    bad = np.flatnonzero(~((strain >= lo) & (strain <= hi)))
    if bad.size:
        i = bad[0]
        where = f"{name}: line {linenos[i]}, column {column!r}"
        if deformation == "stretch":
            raise DataError(f"{where}: expected stretch L/L0 in [{1 + lo}, {1 + hi}] (strain in [{lo}, {hi}]), "
                            f"got {raw[i]!r}")
        if deformation == "strain_percent":
            raise DataError(f"{where}: expected strain in percent within [{100 * lo:g}, {100 * hi:g}], "
                            f"got {raw[i]!r}")
        if deformation == "sarcomere_length_um":
            raise DataError(f"{where}: expected a sarcomere length in micrometres within "
                            f"[{(1 + lo) * sl0:.4g}, {(1 + hi) * sl0:.4g}] (strain SL/SL0 - 1 in [{lo}, {hi}] "
                            f"with SL0 = {sl0!r} um), got {raw[i]!r}")
        raise DataError(f"{where}: expected engineering strain in [{lo}, {hi}] (a fraction, not percent), "
                        f"got {strain[i]!r}")
    if deformation != "strain_percent" and np.all(raw == np.round(raw)):
        # a curve needs varying deformation; whole numbers only = decimal commas split the cells
        raise DataError(f"{name}: lines {linenos[0]}-{linenos[-1]}, column {column!r}: every value is a whole "
                        f"number ({', '.join(map(repr, np.unique(raw)[:4].tolist()))}), expected a varying "
                        "deformation (decimal commas? write 0.01, not 0,01)")
    return strain


def _check_plausible(name: str, raw: np.ndarray, strain: np.ndarray, stress: np.ndarray, unit: str | None,
                     nominal: bool, cols: _Columns, linenos: Sequence[int]) -> None:
    """Judge the stress unit from the physics (:mod:`hbm.plausibility`): stress per unit strain in
    the toe and at the peak against passive muscle.  An undeclared unit that makes the curve too
    stiff is refused with the declaration that fixes it; a declared unit is the user's decision:
    outside the range it is a warning (with the same fix), never a refusal."""
    found = implausible(strain, stress)
    if found is None:
        return
    i = found[4]
    where = f"{name}: line {linenos[i]}, column {cols.names['stress']!r}"
    have = unit or "MPa"
    guess = suggest_unit(found, have)
    if guess is None:
        fix = "check the values and their unit"
    elif cols.unit is not None:
        prefix = f"{cols.measure}_" if cols.measure else ""
        fix = f"if the values are in {guess}, rename the column to '{prefix}stress_{guess}'"
    else:
        fix = f"add '# units_stress: {guess}'" if unit is None else f"if the values are in {guess}, write " \
                                                                    f"'# units_stress: {guess}'"
    seen = f"{float(raw[i]):g} {'(no unit declared, read as MPa)' if unit is None else unit}"
    measure = " nominal" if nominal else ""
    text = (f"{where}: stress {seen}{measure} is a Cauchy stress of {abs(float(stress[i])):g} MPa: "
            f"{describe(found)}; {fix}")
    if unit is None and found[1] == "stiff":
        raise DataError(text)
    warnings.warn(text + ("" if unit is None else f" (loaded as declared: {unit})"), HbmWarning, stacklevel=3)


def _check_sign(name: str, strain: np.ndarray, stress: np.ndarray, cols: _Columns,
                linenos: Sequence[int]) -> None:
    """Refuse a curve whose largest stress has the opposite sign of its strain.

    Passive muscle pulls back when stretched and pushes back when compressed: tension positive.
    Noise may flip small stresses near zero strain, never the peak; a flipped peak means a
    compression-positive convention (or a column mix-up), and fitting it would fit nothing.
    """
    i = int(np.argmax(np.abs(stress)))
    if strain[i] * stress[i] >= 0:
        return
    side = "tension (strain > 0)" if strain[i] > 0 else "compression (strain < 0)"
    raise DataError(f"{name}: line {linenos[i]}, column {cols.names['stress']!r}: the largest stress "
                    f"{stress[i]:g} MPa has the opposite sign of its strain {strain[i]:g}, expected tension "
                    f"positive (stress of the sign of the strain in {side}); a compression-positive file: "
                    "flip the sign of the stress column")


def load_specimen(path: str | Path, *, sl0: float | None = None) -> xr.Dataset:
    """Read and validate one specimen CSV, converting units, stress measure and deformation.

    Parameters
    ----------
    path : str or Path
        CSV file in the format described in the module docstring (README "Data format").
    sl0 : float, optional
        Reference sarcomere length in µm for a ``sarcomere_length_um`` column
        (strain = SL/SL0 − 1), for files without ``# reference_sarcomere_length_um``.  If the
        file declares one too, both must be equal.  Ignored for other deformation columns.

    Returns
    -------
    xarray.Dataset
        Dimension ``point``; variables ``strain``, ``stress`` (Cauchy, MPa) and, when present,
        ``time`` (s) and ``test`` (int).  Attributes: the metadata (strings), ``id``
        (metadata ``id`` or the file stem), ``source_file`` and the record of every conversion
        (``units_stress_original``, ``stress_measure_original``, ``deformation_input``,
        ``reference_sarcomere_length_um``, ``test_labels``).

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
    for role, j in sorted(cols.index.items(), key=lambda kv: kv[1]):
        column = cols.names[role]
        if role == "test":
            raw[role], labels = _test_column(name, [cells[j] for _, cells in rows], linenos, column)
            continue
        raw[role] = np.asarray([_number(cells[j], f"{name}: line {lineno}, column {column!r}")
                                for lineno, cells in rows], dtype=float)

    data: dict[str, np.ndarray] = {"strain": _strain(name, raw["deformation"], cols.deformation, ref,
                                                     cols.names["deformation"], linenos)}
    stress = raw["stress"]
    if unit not in (None, "MPa"):
        stress = stress / STRESS_UNITS[unit]
    if measure == "nominal":
        stress = (1.0 + data["strain"]) * stress  # incompressible uniaxial: sigma = lambda * P
    data["stress"] = stress
    for role in ("time", "test"):
        if role in raw:
            data[role] = raw[role]
    _check_tests_and_time(name, data.get("time"), data.get("test"), linenos, labels)
    _check_plausible(name, raw["stress"], data["strain"], stress, unit, measure == "nominal", cols, linenos)
    _check_sign(name, data["strain"], stress, cols, linenos)

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
    return _dataset(data, attrs)


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


def _dataset(data: Mapping[str, np.ndarray], attrs: Mapping[str, str]) -> xr.Dataset:
    variables = {}
    for col in _COLUMNS:
        if col in data:
            variables[col] = xr.Variable("point", np.asarray(data[col]),
                                         {"units": _UNITS[col], "long_name": _LONG[col]})
    return xr.Dataset(variables, attrs=dict(attrs))


def load_specimens(folder: str | Path, *, sl0: float | None = None) -> dict[str, xr.Dataset]:
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
        ``id -> Dataset`` sorted by id.

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
    out: dict[str, xr.Dataset] = {}
    for f in files:
        ds = load_specimen(f, sl0=sl0)
        sid = ds.attrs["id"]
        if sid in out:
            raise DataError(f"{f}: duplicate specimen id {sid!r} (also in {out[sid].attrs['source_file']}), "
                            "expected unique ids (metadata 'id' or file stem)")
        out[sid] = ds
    return dict(sorted(out.items()))


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


# ---------------------------------------------------------------------------------------
# helpers for consumers
# ---------------------------------------------------------------------------------------
def specimen_loading(ds: xr.Dataset | Loading) -> Loading:
    """The :class:`hbm.Loading` (strain, time, test) of a specimen or protocol Dataset."""
    if isinstance(ds, Loading):
        return ds
    time = np.asarray(ds["time"].values, dtype=float) if "time" in ds else None
    test = np.asarray(ds["test"].values) if "test" in ds else None
    return Loading(np.asarray(ds["strain"].values, dtype=float), time, test)


def provenance(ds: xr.Dataset) -> str:
    """``"synthetic"``, ``"measured"`` or ``"unknown"`` from the ``provenance``/``source`` metadata."""
    prov = str(ds.attrs.get("provenance", "")).strip().lower()
    word = prov.split(maxsplit=1)[0] if prov else ""
    if word in ("synthetic", "measured"):  # "measured (group mean of ...)" -> "measured"
        return word
    if prov:
        return prov
    source = str(ds.attrs.get("source", "")).lower()
    if "synthetic" in source:
        return "synthetic"
    return "measured" if source else "unknown"


def specimen_groups(datasets: Mapping[str, xr.Dataset], key: str | None = None) -> dict[str, str] | None:
    """Each specimen's group from its metadata: ``{id: group name}``, or None for ungrouped data.

    Parameters
    ----------
    datasets : mapping id -> Dataset
        Loaded specimens (:func:`load_specimens`).
    key : str, optional
        Metadata key to group by (``--group-by``: e.g. ``species``, ``muscle``, ``protocol``).
        None: the ``# group:`` lines, if any specimen has one; a single group then means
        ungrouped data (None).

    Raises
    ------
    DataError
        A specimen without the key (or an empty value) when others have it or ``key`` is given,
        or a given ``key`` whose values name a single group.
    """
    explicit = key is not None
    key = GROUP_KEY if key is None else re.sub(r"\s+", "_", str(key).strip())
    if explicit and not _KEY_RE.match(key):
        raise DataError(f"group key {key!r} is not a metadata key (letters, digits, _ . -)")
    values = {sid: str(ds.attrs.get(key, "")).strip() for sid, ds in datasets.items()}
    if not explicit and not any(values.values()):
        return None
    lacking = sorted(sid for sid, v in values.items() if not v)
    if lacking:
        shown = ", ".join(lacking[:5]) + (f" (+{len(lacking) - 5} more)" if len(lacking) > 5 else "")
        raise DataError(f"grouping by {key!r}: specimen{'s' if len(lacking) > 1 else ''} {shown} "
                        f"{'have' if len(lacking) > 1 else 'has'} no '# {key}: NAME' metadata line, expected one in "
                        "every specimen file")
    names = sorted(set(values.values()))
    if len(names) < 2:
        if not explicit:
            return None
        raise DataError(f"grouping by {key!r}: every specimen has {key} {names[0]!r}, expected at least two "
                        "groups (drop --group-by for one population)")
    return dict(sorted(values.items()))


def input_line(summary: str, where: str = "below") -> str:
    """The one line a command prints first about :func:`input_summary` (``""`` when nothing was converted)."""
    return f"input converted: {summary} (stresses {where} are Cauchy, MPa)" if summary else ""


def input_summary(ds: xr.Dataset) -> str:
    """What the loader converted, from the attributes; ``""`` when the file held strain and MPa.

    Examples: ``"stress kPa->MPa, nominal->Cauchy; strain from sarcomere_length_um (SL0 2.0 um)"``,
    ``"tests labelled load, unload, reload"``.
    """
    a = ds.attrs
    parts = []
    stress = []
    if a.get("units_stress_original"):
        stress.append(f"{a['units_stress_original']}->{a.get('units_stress', 'MPa')}")
    if a.get("stress_measure_original"):
        stress.append(f"{a['stress_measure_original']}->Cauchy")
    if stress:
        parts.append("stress " + ", ".join(stress))
    deformation = a.get("deformation_input")
    if deformation:
        ref = a.get("reference_sarcomere_length_um")
        parts.append(f"strain from {deformation}" + (f" (SL0 {ref} um)" if ref and "sarcomere" in deformation
                                                     else ""))
    if a.get("test_labels"):
        try:
            labels = ", ".join(map(str, json.loads(a["test_labels"])))
        except (TypeError, ValueError):
            labels = str(a["test_labels"])
        parts.append(f"tests labelled {labels}")
    return "; ".join(parts)


# ---------------------------------------------------------------------------------------
# protocols
# ---------------------------------------------------------------------------------------
@dataclass(frozen=True)
class Segment:
    """One test of a protocol: a ramp to a target strain or a hold, sampled at ``n`` points.

    Build segments with :func:`ramp`, :func:`hold` and :func:`cycle`, and combine them with
    :func:`protocol`.  A segment starts where the previous segment of its loading history
    ended (or at ``start``/0 when it opens a history).
    """

    kind: str  # "ramp" or "hold"
    n: int
    target: float | None = None  # ramp end strain
    rate: float | None = None  # ramp |dε/dt| in 1/s
    duration: float | None = None  # hold duration in s
    start: float | None = None  # explicit start strain (only when opening a history)
    spacing: str = "linear"  # hold sampling: "linear" or "log"

    def points(self, eps0: float, t0: float, first: bool) -> tuple[np.ndarray, np.ndarray]:
        """Strain and time of the segment's points starting from (eps0, t0).

        When ``first`` the start point itself is included (n points from t0); otherwise the
        start point belongs to the previous segment and the n points follow it.
        """
        k = np.arange(self.n) if first else np.arange(1, self.n + 1)
        m = self.n - 1 if first else self.n
        if self.kind == "ramp":
            span = float(self.target) - eps0
            frac = k / m if m > 0 else np.zeros(1)
            return eps0 + span * frac, t0 + abs(span) / self.rate * frac
        frac = k / m if m > 0 else np.zeros(1)
        if self.spacing == "log":
            # geometric spacing resolves fast relaxation early in a long hold
            d = float(self.duration)
            tau = np.where(frac > 0, d * np.power(1e-3, 1.0 - frac), 0.0)
            times = t0 + tau
        else:
            times = t0 + float(self.duration) * frac
        return np.full(frac.shape, eps0), times


def ramp(to: float, rate: float, n: int, *, start: float | None = None) -> Segment:
    """A constant-rate ramp to strain ``to`` (loading or unloading).

    Parameters
    ----------
    to : float
        End strain.
    rate : float
        Strain rate magnitude |dε/dt| in 1/s (Calvo et al. 2010: 0.022 %/s = 2.2e-4 /s).
    n : int
        Number of points of the segment.  A segment that opens a history includes its start
        point (n ≥ 2); a continuing segment has n new points after the previous segment's end.
    start : float, optional
        Start strain when the segment opens a loading history (default 0, from rest).
    """
    if not (rate > 0 and math.isfinite(rate)):
        raise HbmError(f"ramp: rate must be a positive finite strain rate in 1/s, got {rate!r}")
    if n < 1:
        raise HbmError(f"ramp: n must be >= 1, got {n!r}")
    return Segment("ramp", int(n), target=float(to), rate=float(rate), start=start)


def hold(duration: float, n: int, *, at: float | None = None, spacing: str = "linear") -> Segment:
    """A relaxation hold at constant strain for ``duration`` seconds.

    Parameters
    ----------
    duration : float
        Hold time (s).
    n : int
        Number of points (as for :func:`ramp`).
    at : float, optional
        Strain when the hold opens a history (otherwise the end strain of the previous segment).
    spacing : {"linear", "log"}
        Time sampling inside the hold; "log" spaces points geometrically from 1e-3·duration.
    """
    if not (duration > 0 and math.isfinite(duration)):
        raise HbmError(f"hold: duration must be positive (s), got {duration!r}")
    if spacing not in ("linear", "log"):
        raise HbmError(f"hold: spacing must be 'linear' or 'log', got {spacing!r}")
    if n < 1:
        raise HbmError(f"hold: n must be >= 1, got {n!r}")
    return Segment("hold", int(n), duration=float(duration), start=at, spacing=spacing)


def cycle(eps_max: float, rate: float, n: int, *, eps_min: float = 0.0,
          reload_to: float | None = None) -> list[Segment]:
    """Load–unload–reload: 0 → ``eps_max`` → ``eps_min`` → ``reload_to`` (default ``eps_max``).

    Returns three segments (three tests of one loading history) with ``n`` points each.
    """
    if not eps_max > eps_min:
        raise HbmError(f"cycle: need eps_max > eps_min, got {eps_max!r} <= {eps_min!r}")
    return [ramp(eps_max, rate, n), ramp(eps_min, rate, n),
            ramp(eps_max if reload_to is None else reload_to, rate, n)]


def protocol(*histories: Segment | Sequence[Segment], first_test: int = 1) -> xr.Dataset:
    """Concatenate loading histories into a protocol Dataset (strain, time, test).

    Each positional argument is one loading history that starts from rest at time 0: a
    single :class:`Segment` or a sequence of segments whose time continues (load, unload,
    reload; a ramp followed by a relaxation hold).  Every segment becomes one test, numbered
    consecutively from ``first_test``.

    Examples
    --------
    Ramps at three rates, each from rest::

        protocol(ramp(0.4, 1e-3, 30), ramp(0.4, 1e-2, 30), ramp(0.4, 1e-1, 30))

    A ramp followed by a 600 s relaxation hold (one history, two tests)::

        protocol([ramp(0.3, 1e-2, 25), hold(600.0, 20)])

    Load–unload–reload::

        protocol(cycle(0.4, 1e-2, 20, eps_min=0.1, reload_to=0.45))
    """
    if not histories:
        raise HbmError("protocol: give at least one segment or list of segments")
    strain, time, test = [], [], []
    tid = int(first_test)
    for h in histories:
        segs = [h] if isinstance(h, Segment) else list(h)
        if not segs or not all(isinstance(s, Segment) for s in segs):
            raise HbmError("protocol: each history must be a Segment or a non-empty list of Segments")
        eps, t = None, 0.0
        for j, seg in enumerate(segs):
            first = j == 0
            if first:
                eps = float(seg.start) if seg.start is not None else 0.0
            elif seg.start is not None:
                raise HbmError("protocol: 'start'/'at' is only allowed on the first segment of a history")
            if first and seg.kind == "ramp" and seg.n < 2:
                raise HbmError("protocol: a ramp that opens a history needs n >= 2")
            e, tt = seg.points(eps, t, first)
            strain.append(e)
            time.append(tt)
            test.append(np.full(e.size, tid, dtype=np.int64))
            eps, t = float(e[-1]), float(tt[-1])
            tid += 1
    return _dataset({"strain": np.concatenate(strain), "time": np.concatenate(time),
                     "test": np.concatenate(test)}, {"id": "protocol", "provenance": "synthetic"})


# ---------------------------------------------------------------------------------------
# synthetic specimens
# ---------------------------------------------------------------------------------------
def _seed_text(seed) -> str:
    if isinstance(seed, np.random.SeedSequence):
        return json.dumps({"entropy": int(seed.entropy) if isinstance(seed.entropy, int) else seed.entropy,
                           "spawn_key": list(seed.spawn_key)})
    if isinstance(seed, (int, np.integer)):
        return str(int(seed))
    raise HbmError(f"synthetic_specimen: seed must be an int or numpy SeedSequence, got {type(seed).__name__}")


def _theta_array(model: Model, theta) -> np.ndarray:
    if isinstance(theta, Mapping):
        unknown = set(theta) - set(model.parameter_names)
        if unknown:
            raise HbmError(f"synthetic_specimen: unknown parameters {sorted(unknown)}; the model has "
                           f"{model.parameter_names}")
        try:
            return model.null_theta(dict(theta))
        except ValueError:
            missing = [q for q in model.parameter_names if q not in theta]
            raise HbmError(f"synthetic_specimen: no value for parameters {missing}") from None
    arr = np.asarray(theta, dtype=float)
    if arr.shape != (model.n_params,):
        raise HbmError(f"synthetic_specimen: theta must have shape ({model.n_params},) for "
                       f"{model.parameter_names}, got {arr.shape}")
    return arr


def synthetic_specimen(model: Model, theta, strain_or_protocol, noise_sd: float, seed, *,
                       noise: str = "iid", rho: float = 0.0, relative: bool = False,
                       attrs: Mapping[str, Any] | None = None) -> xr.Dataset:
    """A labelled synthetic specimen: model stress plus Gaussian noise.

    Parameters
    ----------
    model : Model
        Generating model (may include effects, e.g. a hidden effect).
    theta : array (n_params,) or mapping name -> value
        Generating parameters; with a mapping, parameters of added effects that are not given
        take their null values.
    strain_or_protocol : array (n_points,), Loading or Dataset
        A strain array, or a protocol (see :func:`protocol`) with ``time``/``test``.
    noise_sd : float
        Marginal noise standard deviation in MPa, or a fraction of the maximum |stress| of the
        noise-free curve when ``relative=True``.
    seed : int or numpy.random.SeedSequence
        Seed of the numpy Generator (recorded in the attributes).
    noise : {"iid", "ar1"}
        Independent noise, or AR(1) noise with lag-one correlation ``rho`` and marginal sd
        ``noise_sd`` that restarts (stationary) at each loading history.
    rho : float
        AR(1) coefficient in (−1, 1).
    relative : bool
        Interpret ``noise_sd`` relative to the maximum |stress|.
    attrs : mapping, optional
        Extra attributes (e.g. ``id``, ``source``); they override the defaults.

    Returns
    -------
    xarray.Dataset
        Like :func:`load_specimen`, with attributes ``provenance="synthetic"``, ``generator``,
        ``model``, ``parameters`` (JSON), ``noise``, ``noise_sd`` (MPa), ``rho``, ``seed``.
    """
    if noise not in ("iid", "ar1"):
        raise HbmError(f"synthetic_specimen: noise must be 'iid' or 'ar1', got {noise!r}")
    if not (-1.0 < rho < 1.0):
        raise HbmError(f"synthetic_specimen: rho must be in (-1, 1), got {rho!r}")
    if not (noise_sd >= 0 and math.isfinite(noise_sd)):
        raise HbmError(f"synthetic_specimen: noise_sd must be >= 0, got {noise_sd!r}")
    seed_text = _seed_text(seed)
    if isinstance(strain_or_protocol, (xr.Dataset, Loading)):
        loading = specimen_loading(strain_or_protocol)
    else:
        loading = Loading(np.asarray(strain_or_protocol, dtype=float))
    th = _theta_array(model, theta)
    clean = np.asarray(model.stress(loading, th), dtype=float)
    if not np.all(np.isfinite(clean)):
        raise HbmError("synthetic_specimen: the model stress is not finite for these parameters")
    sd = float(noise_sd) * (float(np.max(np.abs(clean))) if relative else 1.0)
    rng = as_generator(seed if not isinstance(seed, (int, np.integer)) else int(seed))
    noise_model = make_noise(noise, history_starts=loading.history_starts)
    q = np.array([[sd, float(rho)]] if noise == "ar1" else [[sd]])
    stress = clean + noise_model.simulate(rng, q)[0]

    data = {"strain": loading.strain.copy(), "stress": stress}
    if loading.time is not None:
        data["time"] = loading.time.copy()
    if loading.test is not None:
        data["test"] = np.asarray(loading.test, dtype=np.int64)
    meta = {
        "id": "synthetic",
        "provenance": "synthetic",
        "source": "synthetic (hbm.synthetic_specimen)",
        "generator": f"hbm.data.synthetic_specimen (hbm {__version__})",
        "model": model.name,
        "effects": ",".join(model.effect_names),
        "parameters": json.dumps({k: float(v) for k, v in zip(model.parameter_names, th)}),
        "noise": noise,
        "noise_sd": repr(sd),
        "noise_relative": repr(float(noise_sd)) if relative else "",
        "rho": repr(float(rho)) if noise == "ar1" else "0.0",
        "seed": seed_text,
    }
    if not relative:
        del meta["noise_relative"]
    for k, v in (attrs or {}).items():
        meta[k] = _attr_text(k, v)
    return _dataset(data, meta)
