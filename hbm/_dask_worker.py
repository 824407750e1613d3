"""Imported by every worker process of hbm's embedded dask cluster (``preload``).

When a run is interrupted, the workers are torn down while a client object inside them may
still be alive; its ``__del__`` then reports "IOLoop is closed" on the shared stderr after the
main process has said ``hbm: interrupted``.  Those reports of dask's own objects are dropped;
every other unraisable exception is still printed.  dask's own loggers in the workers report
only CRITICAL: a failing task reaches the main process as the task's exception (and the run's
one-line error), while teardown races ("ConnectionPool is closed", semaphore releases after an
interrupt) would otherwise print tracebacks after it.
"""

from __future__ import annotations

import logging
import sys

_previous = sys.unraisablehook


def _hook(unraisable) -> None:
    obj = getattr(unraisable, "object", None)
    module = getattr(obj, "__module__", None) or type(obj).__module__
    if str(module).split(".")[0] in ("distributed", "tornado"):
        return
    _previous(unraisable)


sys.unraisablehook = _hook

for _name in ("distributed", "tornado", "asyncio"):
    logging.getLogger(_name).setLevel(logging.CRITICAL)
