"""Memory checks: refuse sizes whose memory cannot exist, before any computation."""

from __future__ import annotations

import os
from pathlib import Path

from ..errors import TooLargeError

__all__ = ["available_memory", "require_memory", "format_bytes"]


def _meminfo_available() -> int | None:
    try:
        with open("/proc/meminfo", encoding="ascii") as fh:
            for line in fh:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        pass
    try:
        return os.sysconf("SC_AVPHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")
    except (ValueError, OSError, AttributeError):
        return None


def _cgroup_available() -> int | None:
    """Room left under a cgroup v2 memory limit (containers, SLURM jobs), if there is one."""
    try:
        limit = Path("/sys/fs/cgroup/memory.max").read_text().strip()
        if limit == "max":
            return None
        used = int(Path("/sys/fs/cgroup/memory.current").read_text().strip())
        return max(int(limit) - used, 0)
    except (OSError, ValueError):
        return None


def available_memory() -> int | None:
    """Bytes of memory this process can still get (MemAvailable, capped by a cgroup limit), or None."""
    values = [v for v in (_meminfo_available(), _cgroup_available()) if v is not None]
    return min(values) if values else None


def format_bytes(n: float) -> str:
    """``1536 -> "1.5 KiB"``."""
    for unit in ("B", "KiB", "MiB", "GiB", "TiB", "PiB"):
        if abs(n) < 1024 or unit == "PiB":
            return f"{n:.0f} {unit}" if unit == "B" else f"{n:.1f} {unit}"
        n /= 1024
    return f"{n:.1f} PiB"  # pragma: no cover


def require_memory(nbytes: float, what: str, how: str = "") -> None:
    """Raise :class:`TooLargeError` if ``nbytes`` (a lower bound of what a computation needs)
    exceeds the memory available now.  ``what`` names the setting, ``how`` the estimate."""
    avail = available_memory()
    if avail is not None and nbytes > avail:
        raise TooLargeError(f"{what}: needs at least {format_bytes(nbytes)} of memory"
                            + (f" ({how})" if how else "") + f", {format_bytes(avail)} available")
