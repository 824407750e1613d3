"""``hbm export``: from a posterior to a finite-element material card, verified on the way out.

Modules: :mod:`.source` (result file + summary -> parameters/curve), :mod:`.laws` (card
parameters and the documented stress of each card law), one module per format (see
:data:`.registry.FORMATS`), :mod:`.febio_tags` (FEBio names pinned from FEBio's source),
:mod:`.verify` (the independent uniaxial check every export runs) and :mod:`.stability` (Drucker).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

from ..errors import HbmError
from ..runtime.files import atomic_path
from .registry import FORMATS, Written, format_module
from .source import ExportSource, load_source
from .stability import Stability, check as stability_check

__all__ = ["FORMATS", "ExportReport", "export", "load_source"]


@dataclass
class ExportReport:
    """What ``hbm export`` did."""

    path: Path | None
    format: str
    source: ExportSource
    written: Written
    stability: Stability | None = None
    notes: list[str] = field(default_factory=list)

    @property
    def passed(self) -> bool:
        return all(c.passed for c in self.written.checks)

    def to_json(self) -> dict:
        return {"file": str(self.path) if self.path else None, "format": self.format,
                "provenance": self.source.provenance(), "card": self.written.card,
                "verification": [c.as_dict() for c in self.written.checks], "passed": self.passed,
                "stability": self.stability.as_dict() if self.stability else None,
                "notes": self.source.notes + self.written.notes + self.notes}

    def report(self) -> str:
        lines = [f"hbm export {self.source.specimen} ({self.source.form} form, k_iso {self.source.k_iso:.4g}, "
                 f"summary {self.source.summary}) -> {self.format}"]
        lo, hi = self.source.strain_range
        for c in self.written.checks:
            kind = "exact card, tolerance" if c.exact else "approximate card, stated bound"
            lines.append(f"verification ({c.method}): max relative difference to hbm's curve "
                         f"{c.error_tested:.3g} on the tested strain range [{lo:.3g}, {hi:.3g}], "
                         f"{c.error_extended:.3g} on 1.5x it; {kind} {c.bound:.3g}: "
                         f"{'passed' if c.passed else 'FAILED'}")
        if not self.written.checks:
            lines.append("verification: none (not a material law: a parameter table or an optimisation input)")
        if self.stability is not None:
            lines.append(self.stability.line())
        lines.append("febio4 one-element run: skipped (no febio4 executable on PATH)" if self.format.startswith(
            "febio") and not _has_febio() else "")
        lines += self.source.notes + self.written.notes + self.notes
        if self.path:
            lines.append(f"wrote {self.path}")
        return "\n".join(line for line in lines if line)


def _has_febio() -> bool:
    import shutil

    return shutil.which("febio4") is not None


def export(result: str | Path, fmt: str, summary: str = "median", out: str | Path | None = None) -> ExportReport:
    """Export a result file as a material card (verified) and write it to ``out``.

    Parameters
    ----------
    result : path
        A specimen result (``specimens/<id>.nc``) or ``hierarchical.nc`` (``summary="population"``).
    fmt : str
        One of :data:`FORMATS`.
    summary : str
        ``median``, ``p05``, ``p95``, ``population`` or ``draws:N`` (module :mod:`.source`).
    out : path, optional
        File to write; None computes and verifies only.

    Returns
    -------
    ExportReport

    Raises
    ------
    HbmError
        Bad format/summary, unreadable result, a thesis-form result asked for an energy card, or a
        card that fails its verification (nothing is written then).
    """
    mod = format_module(fmt)
    if summary.startswith("draws") and fmt not in ("csv", "json"):
        raise HbmError(f"--summary {summary}: draws are written by --to csv/json only; a card holds one law")
    src = load_source(result, summary)
    written = mod.write(src)
    failed = [c for c in written.checks if not c.passed]
    if failed:
        c = failed[0]
        raise HbmError(f"{fmt}: the card does not reproduce hbm's curve (max relative difference {c.error_tested:.3g} "
                       f"> {c.bound:.3g} on the tested range); nothing written")
    stab = (stability_check(src.draws, src.theta, src.k_iso, src.strain_range, src.spec) if src.form == "energy"
            else None)
    notes = [] if src.form == "energy" else [
        "stability: not checked (the thesis form is not derived from a strain energy)"]
    path = None
    if out is not None:
        path = Path(out)
        with atomic_path(path) as tmp:
            Path(tmp).write_text(written.text, encoding="utf-8")
    return ExportReport(path=path, format=fmt, source=src, written=written, stability=stab, notes=notes)
