"""matplotlib for :mod:`hbm.plots`: the headless backend, ``plt`` and the atomic :func:`save`.

Every module of hbm.plots imports matplotlib through this one, so the backend is chosen before
``pyplot`` loads.
"""

from __future__ import annotations

import os
import shutil
from pathlib import Path

import matplotlib

matplotlib.use("Agg")  # headless: figures are files, never windows
import matplotlib.pyplot as plt  # noqa: E402
from matplotlib.backend_bases import FigureCanvasBase  # noqa: E402

from ..runtime.files import atomic_path  # noqa: E402

__all__ = ["plt", "save", "supported_formats", "RELEVANCE_COLORS"]

#: colours of the thesis's relevance classes (Table 2.1)
RELEVANCE_COLORS = {"very important": "#b2182b", "important": "#ef8a62", "unimportant": "#67a9cf",
                    "irrelevant": "#bababa"}


def supported_formats() -> list[str]:
    """File extensions :func:`save` can write: matplotlib's formats (pgf only with its TeX program)."""
    formats = set(FigureCanvasBase.get_supported_filetypes())
    if shutil.which(str(matplotlib.rcParams["pgf.texsystem"])) is None:
        formats.discard("pgf")
    return sorted(formats)


def save(fig, path: str | os.PathLike, dpi: int = 110, tight: bool = True) -> Path:
    """Save ``fig`` atomically (format from the suffix, PNG by default, mode ``0o666 & ~umask``) and close it."""
    path = Path(path)
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=dpi, bbox_inches="tight" if tight else None, format=path.suffix.lstrip(".") or "png")
    plt.close(fig)
    return path
