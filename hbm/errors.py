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
        └── OutputLockedError     an output folder or file is being written by another hbm process
"""

from __future__ import annotations

__all__ = ["HbmError", "DataError", "SettingError", "TooLargeError", "OutputError", "OutputLockedError",
           "HbmWarning"]


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
    """An output folder or file is locked by another running hbm process (the one writer rule)."""


class HbmWarning(UserWarning):
    """A result rests on an assumption the user did not choose (a prior edge, few points, a
    departure from the thesis box); the ``hbm`` command prints it as one ``hbm: warning:`` line."""
