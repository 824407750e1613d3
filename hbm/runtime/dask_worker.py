"""Preloaded by every worker process of hbm's embedded dask cluster (``preload``), and the
filter the main process installs when an interrupted run tears its cluster down.

When a run is interrupted, the workers are torn down while a client object inside them may
still be alive; its ``__del__`` then reports "IOLoop is closed" on the shared stderr after the
main process has said ``hbm: interrupted``.  Those reports of dask's own objects are dropped;
every other unraisable exception is still printed.  In the workers, dask's own loggers report
only CRITICAL: a failing task reaches the main process as the task's exception (and the run's
one-line error), while teardown races ("ConnectionPool is closed", semaphore releases after an
interrupt) would otherwise print tracebacks after it.
"""

from __future__ import annotations

import logging
import sys

__all__ = ["drop_dask_unraisables", "dask_setup"]


def drop_dask_unraisables() -> None:
    """From now on, drop unraisable exceptions of dask's/tornado's objects (teardown noise)."""
    previous = sys.unraisablehook

    def hook(unraisable) -> None:
        obj = getattr(unraisable, "object", None)
        module = getattr(obj, "__module__", None) or type(obj).__module__
        if str(module).split(".")[0] in ("distributed", "tornado"):
            return
        previous(unraisable)

    sys.unraisablehook = hook


def dask_setup(worker=None) -> None:
    """Called by dask in each worker process after the preload import."""
    drop_dask_unraisables()
    for name in ("distributed", "tornado", "asyncio"):
        logging.getLogger(name).setLevel(logging.CRITICAL)
