"""Shared helpers of the ``hbm`` subcommands: option parsing, specimen loading, JSON output.

Every parsing error is an :class:`hbm.errors.HbmError` with a one-line message naming the
option and what was expected (the ``hbm`` entry point turns it into exit status 2).
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path
from typing import Any, Iterable, Sequence

import numpy as np

from ..errors import HbmError

SPECIMEN_FOLDER = Path("data") / "specimens"


def _float(text: str, option: str, item: str, expected: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise HbmError(f"{option} {item!r}: expected {expected}, {text!r} is not a number") from None
    if not math.isfinite(value):
        raise HbmError(f"{option} {item!r}: expected {expected} with a finite number")
    return value


def parse_fix(items: Iterable[str] | None, option: str = "--fix") -> dict[str, float]:
    """``["EOPT=0.192", ...]`` -> ``{"EOPT": 0.192}``."""
    out: dict[str, float] = {}
    for item in items or ():
        name, sep, value = item.partition("=")
        name = name.strip()
        if not sep or not name:
            raise HbmError(f"{option} {item!r}: expected NAME=VALUE, e.g. EOPT=0.192")
        out[name] = _float(value.strip(), option, item, "NAME=VALUE")
    return out


def parse_bounds(items: Iterable[str] | None, option: str = "--bounds") -> dict[str, tuple[float, float]]:
    """``["VOLF=0.5:0.75", ...]`` -> ``{"VOLF": (0.5, 0.75)}``."""
    out: dict[str, tuple[float, float]] = {}
    for item in items or ():
        name, sep, rng = item.partition("=")
        name = name.strip()
        lo, sep2, hi = rng.partition(":")
        if not sep or not name or not sep2:
            raise HbmError(f"{option} {item!r}: expected NAME=LO:HI, e.g. VOLF=0.5:0.75")
        a = _float(lo.strip(), option, item, "NAME=LO:HI")
        b = _float(hi.strip(), option, item, "NAME=LO:HI")
        if not a < b:
            raise HbmError(f"{option} {item!r}: expected NAME=LO:HI with LO < HI")
        out[name] = (a, b)
    return out


def parse_range(text: str | None, option: str) -> tuple[float, float] | None:
    """``"LO:HI"`` -> (lo, hi)."""
    if text is None:
        return None
    lo, sep, hi = text.partition(":")
    if not sep:
        raise HbmError(f"{option} {text!r}: expected LO:HI")
    a, b = _float(lo, option, text, "LO:HI"), _float(hi, option, text, "LO:HI")
    if not a < b:
        raise HbmError(f"{option} {text!r}: expected LO:HI with LO < HI")
    return a, b


def parse_sweep(text: str | None, option: str = "--sweep") -> tuple[str, float] | None:
    """``"VOLF:0.01"`` -> ("VOLF", 0.01)."""
    if text is None:
        return None
    name, sep, width = text.partition(":")
    if not sep or not name.strip():
        raise HbmError(f"{option} {text!r}: expected NAME:WIDTH, e.g. VOLF:0.01")
    w = _float(width, option, text, "NAME:WIDTH")
    if w <= 0:
        raise HbmError(f"{option} {text!r}: expected NAME:WIDTH with WIDTH > 0")
    return name.strip(), w


def check_names(model, names: Iterable[str], option: str) -> None:
    """Raise a one-line error if some names are not parameters of ``model``."""
    bad = [n for n in names if n not in model.parameter_names]
    if bad:
        raise HbmError(f"{option}: unknown parameter(s) {', '.join(bad)}; expected one of "
                       f"{', '.join(model.parameter_names)}")


def load_specimen_arg(spec: str):
    """A SPECIMEN argument -> Dataset: a CSV path, or an id of ``data/specimens/<id>.csv``."""
    from ..data import load_specimen

    path = Path(spec)
    if path.exists():
        return load_specimen(path)
    if path.suffix.lower() == ".csv" or len(path.parts) > 1:
        raise HbmError(f"specimen {spec!r}: no such file (expected a CSV path or a specimen id)")
    candidate = SPECIMEN_FOLDER / f"{spec}.csv"
    if candidate.exists():
        return load_specimen(candidate)
    raise HbmError(f"specimen {spec!r}: no such file, and no {candidate} (expected a CSV path or a "
                   "specimen id)")


def add_model_arguments(parser: argparse.ArgumentParser) -> None:
    """--effect / --iso-factor / --fix / --bounds, shared by commands that build a model."""
    parser.add_argument("--effect", action="append", default=[], metavar="ID",
                        help="add an effect to the base model (library id or file.py:Class); repeatable")
    parser.add_argument("--iso-factor", type=float, default=1.0, metavar="K",
                        help="k_iso of the neo-Hookean term: 1 (default) or 2/3 (thesis literal)")
    parser.add_argument("--fix", action="append", default=[], metavar="NAME=VALUE",
                        help="hold a parameter fixed, e.g. --fix EOPT=0.192; repeatable")
    parser.add_argument("--bounds", action="append", default=[], metavar="NAME=LO:HI",
                        help="narrow a parameter's box, e.g. --bounds VOLF=0.5:0.75; repeatable")


def build_model(args: argparse.Namespace):
    """Base Spyrou model plus ``--effect`` effects; checks --fix/--bounds names."""
    from ..model import spyrou_model

    model = spyrou_model(iso_factor=float(getattr(args, "iso_factor", 1.0)))
    effects = list(getattr(args, "effect", []) or [])
    if effects:
        from ..effects import resolve_effect

        model = model.with_effects(*[resolve_effect(e) for e in effects])
    fix = parse_fix(getattr(args, "fix", None))
    bounds = parse_bounds(getattr(args, "bounds", None))
    check_names(model, fix, "--fix")
    check_names(model, bounds, "--bounds")
    box = model.bounds
    for k, (lo, hi) in bounds.items():
        a, b = box[model.index(k)]
        if lo < a or hi > b:
            raise HbmError(f"--bounds {k}={lo:g}:{hi:g}: expected a sub-range of the prior box [{a:g}, {b:g}]")
    for k, v in fix.items():
        a, b = bounds.get(k, box[model.index(k)])
        if not a <= v <= b:
            raise HbmError(f"--fix {k}={v:g}: expected a value inside the box [{a:g}, {b:g}]")
    return model, fix, bounds


def _jsonable(obj: Any) -> Any:
    """Convert numpy scalars/arrays and non-finite floats (-> null) for strict JSON."""
    if isinstance(obj, dict):
        return {str(k): _jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_jsonable(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return _jsonable(obj.tolist())
    if isinstance(obj, (np.bool_, bool)):
        return bool(obj)
    if isinstance(obj, (np.integer, int)):
        return int(obj)
    if isinstance(obj, (np.floating, float)):
        v = float(obj)
        return v if math.isfinite(v) else None
    return obj


def print_json(obj: Any, file=None) -> None:
    """Print exactly one strict JSON object (NaN/inf -> null) on stdout."""
    print(json.dumps(_jsonable(obj), indent=2, allow_nan=False), file=file or sys.stdout)


def format_table(header: Sequence[str], rows: Sequence[Sequence[str]]) -> str:
    """Plain left/right aligned text table (first column left-aligned)."""
    widths = [max(len(str(x)) for x in col) for col in zip(header, *rows)]
    def line(r):
        return "  ".join(str(x).ljust(w) if i == 0 else str(x).rjust(w) for i, (x, w) in enumerate(zip(r, widths)))
    return "\n".join([line(header), "  ".join("-" * w for w in widths)] + [line(r) for r in rows])
