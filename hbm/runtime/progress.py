"""Progress lines of long work (a run's phases) on stderr."""

from __future__ import annotations

import sys

__all__ = ["log_progress"]


def log_progress(msg: str, progress: bool, prefix: str = "hbm run") -> None:
    """Print ``[prefix] msg`` to stderr when ``progress`` (the progress lines of a run)."""
    if progress:
        print(f"[{prefix}] {msg}", file=sys.stderr, flush=True)
