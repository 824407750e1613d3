"""Progress of long work on stderr: phase lines of a run, and bars that are lines in a log.

:func:`progress_bar` is a tqdm bar on a terminal; where stderr is not a terminal (a log file, a
pipe, a batch job) it is :class:`LineProgress`, which writes one line per step instead of the
carriage-return updates a bar would leave in the log.
"""

from __future__ import annotations

import sys
import time

__all__ = ["log_progress", "progress_bar", "LineProgress"]


def log_progress(msg: str, progress: bool, prefix: str = "hbm run") -> None:
    """Print ``[prefix] msg`` to stderr when ``progress`` (the progress lines of a run)."""
    if progress:
        print(f"[{prefix}] {msg}", file=sys.stderr, flush=True)


class LineProgress:
    """The part of tqdm's interface hbm uses, as one line per :meth:`update`:
    ``[desc] 3/6 specimen (50%, 12.1 s) postfix``.  ``total`` in per mille with ``unit="‰β"``
    (TMCMC's tempering) is shown as a percentage only."""

    def __init__(self, total: int, desc: str = "", unit: str = "it", file=None) -> None:
        self.total, self.desc, self.unit = int(total), desc, unit
        self.file = sys.stderr if file is None else file
        self.n = 0
        self.postfix = self._written = ""
        self._t0 = time.perf_counter()

    def update(self, n: int = 1) -> None:
        """Advance by ``n`` and write the line (a zero step writes one only for a new postfix: a
        TMCMC stage whose tempering moved by less than a per mille is still a step)."""
        if not n and self.postfix == self._written:
            return
        self.n += int(n)
        self._written = self.postfix
        pct = 100.0 * self.n / self.total if self.total else 100.0
        count = "" if self.unit.startswith("‰") else f"{self.n}/{self.total} {self.unit} "
        tail = f" {self.postfix}" if self.postfix else ""
        print(f"[{self.desc}] {count}({pct:.0f}%, {time.perf_counter() - self._t0:.1f} s){tail}",
              file=self.file, flush=True)

    def set_postfix_str(self, s: str = "", refresh: bool = True) -> None:
        """The text the next line ends with."""
        self.postfix = str(s)

    def close(self) -> None:
        """Nothing to clear: the lines stay in the log."""


def progress_bar(total: int, desc: str, unit: str = "it", leave: bool = True, bar_format: str | None = None):
    """A tqdm bar on stderr when it is a terminal, else a :class:`LineProgress` (one line per step)."""
    if not getattr(sys.stderr, "isatty", lambda: False)():
        return LineProgress(total, desc, unit)
    from tqdm.auto import tqdm      # (a terminal only)
    return tqdm(total=total, desc=desc, unit=unit, leave=leave, file=sys.stderr,
                **({"bar_format": bar_format} if bar_format else {}))
