"""Ctrl-C policy of the ``hbm`` command's processes, set up first thing when ``hbm`` imports.

Imported by ``hbm/__init__.py`` before numpy, scipy and xarray (this module imports only the
standard library).  In the command's own process, Ctrl-C during the package's imports prints
``hbm: interrupted`` and exits 130; :func:`hbm.cli.main` ends that with ``restore_sigint()`` once it
has imported the invoked command's module, and turns Ctrl-C into that line itself from then on (the
package imports little and the command's module loads inside ``main``: the guard covers them all).  In the dask
worker processes the command spawns, Ctrl-C is ignored: the command shuts them down.  Any other
process that imports hbm (a script, a notebook) is left alone.
"""

from __future__ import annotations

import os
import signal
import sys
import threading
from typing import Callable

__all__ = ["exit_on_interrupt", "restore_sigint"]


def _hbm_command_line() -> bool:
    """True if ``sys.argv`` is the ``hbm`` command's (console script or ``python -m hbm``).

    Spawned child processes (dask workers) get the same ``sys.argv`` from their parent.
    """
    argv0 = sys.argv[0] if sys.argv else ""
    if os.path.splitext(os.path.basename(argv0))[0] in ("hbm", "hbm-script"):
        return True
    if os.path.basename(os.path.dirname(argv0)) == "hbm" and os.path.basename(argv0) == "__main__.py":
        return True  # python -m hbm, after runpy found the module
    # python [options] -m hbm: while the package imports, sys.argv[0] is still "-m"
    orig = list(getattr(sys, "orig_argv", []))
    return "-mhbm" in orig or any(a == "-m" and b == "hbm" for a, b in zip(orig, orig[1:]))


def _spawned_child() -> bool:
    """A process started by multiprocessing's spawn method (how dask starts its workers)."""
    return "--multiprocessing-fork" in list(getattr(sys, "orig_argv", []))


def exit_on_interrupt() -> Callable[[], None]:
    """Ctrl-C handling of the ``hbm`` command's processes while the package imports.

    * The command itself: a SIGINT handler that prints ``hbm: interrupted`` and raises
      ``SystemExit(130)`` (no traceback) while it is still importing; the returned function puts
      the previous handler back (from then on :func:`hbm.cli.main` turns Ctrl-C into that line).
    * A worker process spawned by the command (dask): SIGINT is ignored for good.  A terminal's
      Ctrl-C reaches every process of the foreground group, and a worker's KeyboardInterrupt
      would print tracebacks and hang its task; the command shuts its workers down itself
      (and :func:`_quiet_closed_loop` keeps that shutdown quiet).

    Only from the main thread, when SIGINT has Python's default handler.  Anywhere else
    (``import hbm`` in a script or notebook) nothing changes and KeyboardInterrupt propagates.
    """
    if (threading.current_thread() is not threading.main_thread()
            or signal.getsignal(signal.SIGINT) is not signal.default_int_handler or not _hbm_command_line()):
        return lambda: None
    if _spawned_child():
        signal.signal(signal.SIGINT, signal.SIG_IGN)
        sys.unraisablehook = _quiet_closed_loop
        return lambda: None

    def interrupted(signum, frame):
        sys.stderr.write("hbm: interrupted\n")
        sys.stderr.flush()
        raise SystemExit(130)

    previous = signal.signal(signal.SIGINT, interrupted)
    return lambda: signal.signal(signal.SIGINT, previous)


def _quiet_closed_loop(unraisable) -> None:
    """Unraisable-exception hook of the command's workers: a dask client that a task created
    (xarray asks dask for its scheduler) is finalized after the worker's event loop stopped
    when an interrupted run shuts the worker down mid-task; that one error is not worth a
    traceback.  Everything else goes to Python's default hook."""
    exc = unraisable.exc_value
    if isinstance(exc, RuntimeError) and str(exc) == "IOLoop is closed":
        return
    sys.__unraisablehook__(unraisable)


restore_sigint = exit_on_interrupt()
