"""Lazy public names of a package (PEP 562): a package's ``__init__`` lists which of its modules
defines each name, and a name's module is imported the first time the name is used.

Why: ``import hbm`` is the first thing every ``hbm`` command does; when the packages' ``__init__``
files imported all their modules, ``hbm --version`` loaded the samplers, the detective, cma,
matplotlib, scipy.stats and xarray.  With this, each command imports what it uses.

Usage in a package's ``__init__.py``::

    from ..runtime.lazy import attach
    __getattr__, __dir__ = attach(__name__, {".specimen": ["SpecimenResult", "write_specimen_result"]})

``from package import name`` and ``package.name`` work as before; ``__all__`` stays a plain list
in the ``__init__`` (tests iterate it).  This module imports only the standard library.
"""

from __future__ import annotations

import importlib
import sys
from typing import Any, Callable, Iterable, Mapping


def attach(package: str, exports: Mapping[str, Iterable[str]], submodules: Iterable[str] = (),
           fallback: Callable[[str], Any] | None = None) -> tuple[Callable[[str], Any], Callable[[], list[str]]]:
    """PEP 562 ``__getattr__`` and ``__dir__`` of ``package`` that import on first use.

    Parameters
    ----------
    package : str
        The package's ``__name__``.
    exports : mapping of str to iterable of str
        Module (relative to the package, e.g. ``".specimen"``) -> the public names it defines.
    submodules : iterable of str, optional
        Sub-modules that load on attribute access too (``package.io`` after ``import package``).
    fallback : callable, optional
        Called with a name found in neither (for names computed on access); it raises
        ``AttributeError`` itself for unknown names.

    Returns
    -------
    (__getattr__, __dir__) : tuple of callables
        Assign them to the package's ``__getattr__`` and ``__dir__``.
    """
    where = {name: module for module, names in exports.items() for name in names}
    subs = frozenset(submodules)
    clash = subs & where.keys()
    if clash:  # a name must mean one thing: the module or an attribute of another module
        raise ValueError(f"{package}: {sorted(clash)} named both as sub-modules and as exported names")

    def __getattr__(name: str) -> Any:
        if name in where:
            value = getattr(importlib.import_module(where[name], package), name)
        elif name in subs:
            value = importlib.import_module(f".{name}", package)
        elif fallback is not None:
            return fallback(name)
        else:
            raise AttributeError(f"module {package!r} has no attribute {name!r}")
        setattr(sys.modules[package], name, value)  # later look-ups are plain attribute reads
        return value

    def __dir__() -> list[str]:
        return sorted(set(vars(sys.modules[package])) | where.keys() | subs)

    return __getattr__, __dir__
