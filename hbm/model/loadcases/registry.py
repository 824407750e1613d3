"""The registry of load cases: name or alias -> the one instance of its class."""

from __future__ import annotations

from ...errors import HbmError
from .base import LoadCase

#: mode name -> load case (each mode's module registers itself)
LOAD_CASES: dict[str, LoadCase] = {}
#: alias -> mode name
ALIASES: dict[str, str] = {}
#: the mode of a test that names none: today's along-fibre tension files
DEFAULT_LOAD_CASE = "uniaxial_f"


def register_load_case(cls: type[LoadCase]) -> type[LoadCase]:
    """Class decorator: register one instance of ``cls`` under its ``name`` and ``aliases``."""
    case = cls()
    taken = [n for n in (case.name, *case.aliases) if n in LOAD_CASES or n in ALIASES]
    if not case.name or taken:
        raise ValueError(f"load case {cls.__name__}: name {case.name!r} empty or {taken} already taken")
    if case.control not in ("stretch", "shear") or not case.observables or case.observables[0].name != "stress":
        raise ValueError(f"load case {case.name}: control must be stretch|shear and the first observable 'stress'")
    LOAD_CASES[case.name] = case
    ALIASES.update({a: case.name for a in case.aliases})
    return cls


def is_load_case(text: str) -> bool:
    """True when ``text`` is a registered mode name or alias."""
    key = str(text).strip()
    return ALIASES.get(key, key) in LOAD_CASES


def get_load_case(name_or_alias) -> LoadCase:
    """The load case of a mode name, an alias or a :class:`LoadCase` (returned as is).

    Raises
    ------
    HbmError
        For an unknown name, listing the modes.
    """
    if isinstance(name_or_alias, LoadCase):
        return name_or_alias
    key = str(name_or_alias).strip()
    key = ALIASES.get(key, key)
    if key not in LOAD_CASES:
        raise HbmError(f"unknown mode {name_or_alias!r}; expected one of {', '.join(LOAD_CASES)} "
                       f"(aliases: {', '.join(f'{a}={n}' for a, n in ALIASES.items())})")
    return LOAD_CASES[key]
