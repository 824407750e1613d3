"""The exceptions of hbm: every bad input raises an :class:`HbmError` subclass.

The ``hbm`` command turns each of them into one line ``hbm: error: <message>`` and exit status 2;
from Python, catch :class:`HbmError` (or a subclass) around any hbm call.  Messages are one line
and name the file or option and what was expected.

Hierarchy::

    HbmError                      any bad input, option, file or setting
    ├── DataError (ValueError)    a malformed specimen file or dataset
    ├── SettingError (ValueError) a bad option/setting value (names the option)
    │   └── TooLargeError         a size whose memory cannot exist on this machine
    └── OutputError (OSError)     an output/checkpoint path that cannot be created, written or
        │                         replaced, or a full disk (names the file)
        └── OutputLockedError     the output folder is in use by another ``hbm run``

This module imports nothing heavy: ``hbm/__init__.py`` calls :func:`exit_on_interrupt` before it
imports numpy, scipy and xarray.
"""

from __future__ import annotations

import os
import signal
import sys
import threading
from typing import Callable

__all__ = ["HbmError", "DataError", "SettingError", "TooLargeError", "OutputError", "OutputLockedError",
           "HbmWarning", "exit_on_interrupt"]


class HbmError(Exception):
    """A user-facing error: bad input, bad option, missing file.  Message is one line."""


class DataError(HbmError, ValueError):
    """A specimen file or dataset is malformed (message names the file, line/column, expectation)."""


class SettingError(HbmError, ValueError):
    """A setting (command-line option or keyword argument) has a value hbm cannot use."""


class TooLargeError(SettingError):
    """A requested size needs more memory than this machine has available."""


class OutputError(HbmError, OSError):
    """An output or checkpoint file cannot be created, written or replaced (message names it)."""


class OutputLockedError(OutputError):
    """The output folder is locked by another running ``hbm run``."""


class HbmWarning(UserWarning):
    """A result rests on an assumption the user did not choose (a prior edge, few points, a
    departure from the thesis box); the ``hbm`` command prints it as one ``hbm: warning:`` line."""


def _running_as_command() -> bool:
    """True in the process of the ``hbm`` command (console script or ``python -m hbm``)."""
    argv0 = os.path.basename(sys.argv[0]) if sys.argv else ""
    if os.path.splitext(argv0)[0] in ("hbm", "hbm-script"):
        command = True
    else:  # ``python [options] -m hbm ...``: while the package imports, sys.argv[0] is "-m"
        orig = list(getattr(sys, "orig_argv", []))
        command = "-mhbm" in orig or any(a == "-m" and b == "hbm" for a, b in zip(orig, orig[1:]))
    if not command:
        return False
    import multiprocessing  # cheap; only on this path

    # dask worker processes inherit the command's sys.argv but are not the command
    return multiprocessing.parent_process() is None


def exit_on_interrupt() -> Callable[[], None]:
    """While the ``hbm`` command is still importing, Ctrl-C ends it as ``hbm: interrupted``.

    Installs a SIGINT handler that prints that line and raises ``SystemExit(130)`` (no traceback)
    -- only in the process of the ``hbm`` command, from its main thread, when SIGINT has Python's
    default handler.  Returns the function that puts the previous handler back.  Anywhere else
    (``import hbm`` in a script or notebook) nothing changes and KeyboardInterrupt propagates.
    """
    if (threading.current_thread() is not threading.main_thread()
            or signal.getsignal(signal.SIGINT) is not signal.default_int_handler or not _running_as_command()):
        return lambda: None

    def interrupted(signum, frame):
        sys.stderr.write("hbm: interrupted\n")
        sys.stderr.flush()
        raise SystemExit(130)

    previous = signal.signal(signal.SIGINT, interrupted)
    return lambda: signal.signal(signal.SIGINT, previous)
