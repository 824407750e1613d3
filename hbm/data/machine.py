"""What a testing machine writes: force and displacement columns, the specimen's geometry in the header.

A machine export holds time, load and crosshead position (``Time (s)``, ``Load (N)``, ``Position (mm)``);
the specimen's size is in the header.  The loader converts them to engineering strain and nominal
stress, then to Cauchy stress as for any nominal-stress file, recording every step:

=========================================  ===========================================================
in the file                                meaning
=========================================  ===========================================================
``force_N``, ``Force (N)``, ``Load (kN)``  the force on the specimen; units N, mN, kN
``displacement_mm``, ``Extension (mm)``,   the change of the specimen's length from its gauge length;
``Position (mm)``, ``Displacement (µm)``   units mm, µm
``# area_mm2: A``                          cross-section in mm² (or ``# diameter_mm: D`` of a cylinder,
                                           or ``# width_mm: W`` and ``# thickness_mm: T``)
``# gauge_length_mm: L0``                  the length the displacement is relative to (compression:
                                           the specimen's height)
``# loading: tension|compression``         ``compression``: the columns hold magnitudes (a machine
                                           that reports compression positive); they are negated
=========================================  ===========================================================

Conversion: ε = s·d/L0 and P = s·F/A (MPa = N/mm²) with s = −1 for ``# loading: compression`` and
+1 otherwise; then σ = (1 + ε)·P (incompressible uniaxial, as every nominal stress).  The steps are
kept in the dataset's attributes (``stress_input``, ``deformation_input``, ``cross_section_mm2``,
``conversion_steps``), so the numbers can be redone by hand.
"""

from __future__ import annotations

import json
import math
import re
from typing import Mapping, Sequence

import numpy as np

from ..errors import DataError

__all__ = ["FORCE_UNITS", "LENGTH_UNITS", "GEOMETRY_KEYS", "machine_column", "machine_header", "convert_machine",
           "machine_summary"]

#: force units -> newtons per unit
FORCE_UNITS = {"N": 1.0, "mN": 1e-3, "kN": 1e3}
#: displacement units -> millimetres per unit
LENGTH_UNITS = {"mm": 1.0, "um": 1e-3}
#: header keys the conversion reads
GEOMETRY_KEYS = ("area_mm2", "diameter_mm", "width_mm", "thickness_mm", "gauge_length_mm", "loading")

_FORCE_WORDS = ("force", "load")
_LENGTH_WORDS = ("displacement", "extension", "position", "elongation")
_FORCE_ALIASES = {"n": "N", "newton": "N", "newtons": "N", "mn": "mN", "kn": "kN"}
_LENGTH_ALIASES = {"mm": "mm", "um": "um", "\u00b5m": "um", "\u03bcm": "um", "micrometre": "um",
                   "micrometres": "um", "micrometer": "um", "micrometers": "um", "micron": "um", "microns": "um"}
_CANONICAL_RE = re.compile(r"^(force|displacement)_(n|mn|kn|mm|um)$")
_LOADINGS = ("tension", "compression")


def _show(text: str, limit: int = 40) -> str:
    return repr(text) if len(text) <= limit else repr(text[:limit]) + f"... ({len(text)} characters)"


def machine_column(col: str) -> tuple[str, str] | None:
    """``("force", "N")`` / ``("displacement", "mm")`` for a canonical column name (``force_n``,
    ``displacement_um``: lower case), else None."""
    m = _CANONICAL_RE.match(col)
    if m is None:
        return None
    kind, unit = m.groups()
    if kind == "force" and unit in ("n", "mn", "kn"):
        return kind, _FORCE_ALIASES[unit]
    if kind == "displacement" and unit in ("mm", "um"):
        return kind, unit
    return None


#: machine quantities: header words, unit spellings -> unit, and what the conversion needs
_QUANTITIES = (
    ("force", _FORCE_WORDS, _FORCE_ALIASES,
     "stress = force / cross-sectional area when the header names its unit (N, mN or kN, e.g. 'Load (N)') and the "
     "file gives the cross-section ('# area_mm2:', '# diameter_mm:', or '# width_mm:' and '# thickness_mm:'); or "
     "give a stress column in MPa, kPa or Pa"),
    ("displacement", _LENGTH_WORDS, _LENGTH_ALIASES,
     "strain = displacement / gauge length when the header names its unit (mm or um, e.g. 'Extension (mm)') and "
     "the file gives '# gauge_length_mm:'"),
)


def machine_header(word: str, unit: str | None, text: str, where: str) -> str | None:
    """The canonical name of a machine header (``Load (N)`` -> ``force_n``, ``Position (mm)`` ->
    ``displacement_mm``), None for other words; a force or length without a unit hbm converts is
    a DataError naming what is accepted.  ``word``/``unit``: the header's quantity and unit, lower case."""
    for kind, words, aliases, needs in _QUANTITIES:
        if word in words:
            if unit in aliases:
                return f"{kind}_{aliases[unit].lower()}"
            got = "no unit" if unit is None else f"unit {_show(unit)}"
            raise DataError(f"{where}: column {_show(text)} is a {kind} ({got}); hbm converts it to {needs}")
    return None


def _positive(name: str, attrs: Mapping[str, str], meta_line: Mapping[str, int], key: str) -> float:
    try:
        value = float(attrs[key])
    except ValueError:
        value = math.nan
    if not (math.isfinite(value) and value > 0):
        raise DataError(f"{name}: line {meta_line[key]}: metadata {key} is {_show(attrs[key])}, expected a positive "
                        "number in millimetres")
    return value


def _cross_section(name: str, attrs, meta_line, column: str, where: str) -> tuple[float, str]:
    """Area in mm² and how it was obtained, from exactly one of the three ways of giving it."""
    ways = [k for k in ("area_mm2", "diameter_mm") if k in attrs]
    rect = [k for k in ("width_mm", "thickness_mm") if k in attrs]
    if rect:
        ways.append("width_mm + thickness_mm")
    if not ways:
        raise DataError(f"{where}: {_show(column)} is a force: its cross-sectional area is missing, add "
                        "'# area_mm2: <mm2>' (or '# diameter_mm: <mm>' of a cylinder, or '# width_mm:' and "
                        "'# thickness_mm:')")
    if len(ways) > 1:
        lines = ", ".join(str(n) for n in sorted(meta_line[k] for k in ("area_mm2", "diameter_mm", "width_mm",
                                                                          "thickness_mm") if k in attrs))
        raise DataError(f"{name}: lines {lines}: the cross-section is given {len(ways)} ways ({', '.join(ways)}), "
                        "expected one of '# area_mm2:', '# diameter_mm:', or '# width_mm:' and '# thickness_mm:'")
    if rect:
        missing = [k for k in ("width_mm", "thickness_mm") if k not in attrs]
        if missing:
            raise DataError(f"{name}: line {meta_line[rect[0]]}: '# {rect[0]}:' without '# {missing[0]}:', expected "
                            "both (area = width x thickness)")
        w, t = (_positive(name, attrs, meta_line, k) for k in ("width_mm", "thickness_mm"))
        return w * t, f"width_mm {attrs['width_mm'].strip()} x thickness_mm {attrs['thickness_mm'].strip()}"
    if ways[0] == "area_mm2":
        return _positive(name, attrs, meta_line, "area_mm2"), "area_mm2"
    d = _positive(name, attrs, meta_line, "diameter_mm")
    return math.pi * d * d / 4.0, f"pi/4 x diameter_mm {attrs['diameter_mm'].strip()}^2"


def _sign(name: str, attrs, meta_line, columns: Sequence[tuple[str, np.ndarray]]) -> float:
    """-1 when ``# loading: compression`` (magnitudes: negated), else +1; a compression file whose
    columns peak at a negative value (already signed) is refused."""
    if "loading" not in attrs:
        return 1.0
    value = attrs["loading"].strip().lower()
    if value not in _LOADINGS:
        raise DataError(f"{name}: line {meta_line['loading']}: metadata loading is {_show(attrs['loading'])}, "
                        f"expected {' or '.join(_LOADINGS)}")
    if value == "tension":
        return 1.0
    for column, raw in columns:
        i = int(np.argmax(np.abs(raw)))
        if raw[i] < 0:
            raise DataError(f"{name}: line {meta_line['loading']}: '# loading: compression' reads the machine's "
                            f"columns as magnitudes (compression positive), but column {_show(column)} peaks at "
                            f"{raw[i]:g}; drop the key for a signed file (tension positive)")
    return -1.0


def convert_machine(name: str, attrs: Mapping[str, str], meta_line: Mapping[str, int], names: Mapping[str, str],
                    index: Mapping[str, int], force: str | None, deformation: str, raw: dict[str, np.ndarray],
                    header_lineno: int) -> dict[str, str]:
    """Convert a force column to nominal stress (MPa) and a displacement column to engineering
    strain, in place in ``raw`` (roles ``stress`` and ``deformation``).

    Parameters
    ----------
    name : str
        The file, for messages.
    attrs, meta_line : mapping
        The header's metadata and the line of each key.
    names, index : mapping
        Role -> header cell as written, and its column (0-based).
    force : str or None
        Unit of the force column (``"N"``, ``"mN"``, ``"kN"``), None for a stress column.
    deformation : str
        The deformation column's canonical name (``displacement_mm`` / ``displacement_um`` or another).
    raw : dict
        Role -> the column's numbers.
    header_lineno : int
        Line of the header (messages).  The strain's range is checked by the loader afterwards.

    Returns
    -------
    dict
        The records to keep in the dataset's attributes: ``stress_input``, ``cross_section_mm2``
        and ``conversion_steps`` (a JSON list of the steps in words).
    """
    length = machine_column(deformation)
    columns = []
    if force is not None:
        columns.append((names["stress"], raw["stress"]))
    if length is not None:
        columns.append((names["deformation"], raw["deformation"]))
    sign = _sign(name, attrs, meta_line, columns)
    flip = " (compression: magnitudes negated)" if sign < 0 else ""
    minus = "-" if sign < 0 else ""
    steps, records = [], {}
    if length is not None:
        column = names["deformation"]
        if "gauge_length_mm" not in attrs:
            raise DataError(f"{name}: line {header_lineno}, column {index['deformation'] + 1}: {_show(column)} is a "
                            "displacement: its gauge length is missing, add '# gauge_length_mm: <mm>' (for "
                            "compression the specimen's height)")
        l0 = _positive(name, attrs, meta_line, "gauge_length_mm")
        unit = length[1]
        raw["deformation"] = sign * raw["deformation"] * LENGTH_UNITS[unit] / l0 + 0.0  # (+ 0.0: no -0.0)
        scale = "" if unit == "mm" else " x 0.001 mm/um"
        steps.append(f"strain = {minus}{column}{scale} / gauge_length_mm {attrs['gauge_length_mm'].strip()}{flip}")
    if force is not None:
        column = names["stress"]
        area, how = _cross_section(name, attrs, meta_line, column,
                                   f"{name}: line {header_lineno}, column {index['stress'] + 1}")
        raw["stress"] = sign * raw["stress"] * FORCE_UNITS[force] / area
        scale = "" if force == "N" else f" x {FORCE_UNITS[force]:g} N/{force}"
        steps.append(f"nominal stress (MPa = N/mm2) = {minus}{column}{scale} / cross_section_mm2 {area!r} ({how})"
                     + flip)
        steps.append("Cauchy stress = (1 + strain) x nominal stress (incompressible uniaxial)")
        records["stress_input"] = f"force_{force}"
        records["cross_section_mm2"] = repr(area)
    records["conversion_steps"] = json.dumps(steps)
    return records


def machine_summary(attrs: Mapping[str, str]) -> str:
    """The conversion of a machine export in a few words ("" for other files), e.g.
    ``"strain from displacement (mm) / 21.0 mm, stress from force (N) / 153.9 mm2; compression"``."""
    parts = []
    dfm = str(attrs.get("deformation_input", ""))
    if dfm.startswith("displacement_") and attrs.get("gauge_length_mm"):
        parts.append(f"strain from displacement ({dfm.split('_')[1]}) / gauge length {attrs['gauge_length_mm']} mm")
    if str(attrs.get("stress_input", "")).startswith("force_") and attrs.get("cross_section_mm2"):
        try:
            area = f"{float(attrs['cross_section_mm2']):.5g}"
        except ValueError:
            area = str(attrs["cross_section_mm2"])
        parts.append(f"stress from force ({attrs['stress_input'].split('_')[1]}) / cross-section {area} mm2")
    if parts and str(attrs.get("loading", "")).strip().lower() == "compression":
        parts.append("compression magnitudes negated")
    return ", ".join(parts)
