"""The export formats: name -> module.  Each module has ``DESCRIPTION``, ``SUFFIX`` and
``write(source, path) -> Written`` (the file text is built in memory, checked, then written)."""

from __future__ import annotations

import importlib
from dataclasses import dataclass, field
from types import ModuleType

from ..errors import HbmError

#: format name -> module of hbm.export
FORMATS: dict[str, str] = {
    "febio-uniaxial": "febio_uniaxial",
    "febio-energy": "febio_energy",
    "febio-optimize": "febio_optimize",
    "abaqus-marlow": "abaqus_marlow",
    "abaqus-uanisohyper": "abaqus_uanisohyper",
    "csv": "table_csv",
    "json": "table_json",
}


@dataclass
class Written:
    """What a format wrote: the text, the checks run on it, notes for the user; for a material law its
    scope (a 3-D material or along-fibre only) and, for a 3-D one, its check in every loading mode."""

    text: str
    checks: list = field(default_factory=list)
    notes: list[str] = field(default_factory=list)
    card: dict = field(default_factory=dict)
    modes: list = field(default_factory=list)
    scope: str = ""


def format_module(name: str) -> ModuleType:
    """The module of format ``name``; HbmError naming --to otherwise."""
    if name not in FORMATS:
        raise HbmError(f"--to {name!r}: expected one of {', '.join(FORMATS)}")
    return importlib.import_module(f"{__package__}.{FORMATS[name]}")
