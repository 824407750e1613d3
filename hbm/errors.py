"""Exceptions that the CLI turns into a one-line message and exit status 2."""


class HbmError(Exception):
    """A user-facing error: bad input, bad option, missing file.  Message is one line."""


class DataError(HbmError, ValueError):
    """A specimen file or dataset is malformed (message names the file, line/column, expectation)."""
