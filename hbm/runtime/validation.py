"""Moved: the validation rules live in :mod:`hbm.settings.rules` (ONE rule per kind of setting, shared
by the command line and the Python API).  This module re-exports them for older imports."""

from ..settings.rules import (  # noqa: F401
    MAX_WORKERS_PER_CORE, SEED_LIMIT, check_int, check_physical_bounds, check_positive, check_seed, check_workers,
    usable_cores)

__all__ = ["SEED_LIMIT", "MAX_WORKERS_PER_CORE", "check_seed", "check_int", "check_positive", "check_workers",
           "usable_cores", "check_physical_bounds"]
