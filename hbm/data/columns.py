"""How a specimen CSV is read: header words and units, columns, numbers, reference length, plausibility of the stress."""

from __future__ import annotations


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


from ..errors import DataError, HbmWarning


from .plausibility import describe, implausible, suggest_unit


STRAIN_RANGE = (-0.5, 2.0)
#: minimum number of data points in a specimen
MIN_POINTS = 5
#: stress units of ``# units_stress:`` and of column suffixes -> values per MPa
STRESS_UNITS = {"MPa": 1.0, "kPa": 1e3, "Pa": 1e6}
#: metadata key of a specimen's group (``# group: NAME``)
GROUP_KEY = "group"
#: deformation columns; a file has exactly one
DEFORMATIONS = ("strain", "strain_percent", "stretch", "sarcomere_length_um")

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
    """Judge the stress unit from the physics (:mod:`hbm.data.plausibility`): stress per unit strain in
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


