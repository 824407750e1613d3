"""ONE validation rule per kind of setting, shared by the command line and the Python API.

Each rule returns the value (converted) or raises :class:`hbm.errors.SettingError` with a
message that names the setting (``name``: ``"--seed"`` on the command line, ``"seed"`` in
Python) and what was expected.  The CLI's ``type=`` functions (:mod:`hbm.cli._common`) and the
public functions (:func:`hbm.fit.fit_specimen`, :func:`hbm.fit.optimization.optimize`,
:func:`hbm.spyrou_model`, :func:`hbm.runtime.parallel.dask_client`) call the same rule, so a value the
command refuses is refused by the API too.
"""

from __future__ import annotations

import math
import os
from numbers import Integral, Real
from typing import Any, Mapping

from ..errors import SettingError

__all__ = ["SEED_LIMIT", "MAX_WORKERS_PER_CORE", "check_seed", "check_int", "check_positive", "check_workers",
           "usable_cores", "check_physical_bounds"]

#: seeds are non-negative integers below 2**32 (numpy's legacy seeding inside cma and SALib)
SEED_LIMIT = 2 ** 32
#: worker processes of the embedded cluster per core: beyond that they only compete for the cores
#: (and each holds a copy of the model and its data)
MAX_WORKERS_PER_CORE = 4


def _integer(value: Any, name: str, expected: str) -> int:
    if isinstance(value, bool) or not isinstance(value, Integral):
        if isinstance(value, Real) and float(value).is_integer():
            return int(value)
        raise SettingError(f"{name}: expected {expected}, got {value!r}")
    return int(value)


def check_seed(value: Any, name: str = "seed") -> int:
    """A seed: an integer from 0 to 2**32 - 1 (a numpy SeedSequence passes unchanged)."""
    if type(value).__name__ == "SeedSequence":
        return value
    expected = f"a seed: an integer from 0 to {SEED_LIMIT - 1}"
    v = _integer(value, name, expected)
    if not 0 <= v < SEED_LIMIT:
        raise SettingError(f"{name}: expected {expected}, got {value!r}")
    return v


def check_int(value: Any, name: str, minimum: int) -> int:
    """A count: an integer >= ``minimum``."""
    expected = f"an integer >= {minimum}"
    v = _integer(value, name, expected)
    if v < minimum:
        raise SettingError(f"{name}: expected {expected}, got {value!r}")
    return v


def check_positive(value: Any, name: str) -> float:
    """A finite number > 0."""
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise SettingError(f"{name}: expected a finite number > 0, got {value!r}") from None
    if not (math.isfinite(v) and v > 0):
        raise SettingError(f"{name}: expected a finite number > 0, got {value!r}")
    return v


def usable_cores() -> int:
    """Cores this process may run on (its CPU affinity where the OS tells it, else the count)."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:      # (not on macOS / Windows)
        return os.cpu_count() or 1


def check_workers(value: Any, name: str = "workers") -> int:
    """Worker processes of an embedded cluster: 0 (no dask) up to MAX_WORKERS_PER_CORE per core."""
    v = check_int(value, name, 0)
    cores = os.cpu_count() or 1
    cap = MAX_WORKERS_PER_CORE * cores
    if v > cap:
        raise SettingError(f"{name}: {v} worker processes on {cores} core(s); expected at most {cap} "
                           f"({MAX_WORKERS_PER_CORE} per core: more only compete for the cores and memory); for a "
                           "larger cluster connect to its scheduler (--scheduler / DASK_SCHEDULER_ADDRESS)")
    return v


def check_physical_bounds(bounds: Mapping[str, Any] | None, ranges: Mapping[str, tuple[float, float]],
                          name: str = "bounds") -> None:
    """A prior box ``{parameter: (lo, hi)}`` inside what the physics allows (``ranges``, e.g.
    :data:`hbm.model.spyrou.PHYSICAL_RANGE`)."""
    for p, box in (bounds or {}).items():
        if p not in ranges:
            continue
        lo, hi = (float(b) for b in box)
        a, b = ranges[p]
        if not (a <= lo and hi <= b):
            allowed = f"[{a:g}, {b:g}]" if math.isfinite(b) else f">= {a:g}"
            raise SettingError(f"{name} {p}={lo:g}:{hi:g}: outside what {p} can physically be ({allowed}); "
                               f"expected a box inside it")
