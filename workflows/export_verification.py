"""Verification table of ``hbm export``: every format x summary for a set of result files.

Usage (results from ``hbm run``/``hbm fit``; writes Markdown to stdout and the cards to OUT)::

    python workflows/export_verification.py OUT RESULT.nc [RESULT.nc ...]

For each file: the cards of every format for median, p05 and p95 (population for
hierarchical.nc); febio-energy only for energy-form results (thesis-form ones are refused, and
the refusal is listed).  Columns: the max relative difference of the independent uniaxial check
to hbm's curve on the tested range and on 1.5x it, the tolerance/bound, and the Drucker
stability fractions (energy form).
"""

from __future__ import annotations

import sys
import time
from pathlib import Path

from hbm.errors import HbmError
from hbm.export import FORMATS, export

CARDS = ("febio-uniaxial", "febio-energy", "abaqus-marlow", "abaqus-uanisohyper")


def main(argv: list[str]) -> int:
    out = Path(argv[0])
    out.mkdir(parents=True, exist_ok=True)
    print("| result | form | summary | format | tested range | 1.5x range | tolerance / bound | passed | s |")
    print("|---|---|---|---|---|---|---|---|---|")
    stab_rows = []
    for f in map(Path, argv[1:]):
        summaries = ("population",) if f.name == "hierarchical.nc" else ("median", "p05", "p95")
        label = f.parent.parent.name + "/" + f.stem if f.name != "hierarchical.nc" else f.parent.name + "/population"
        for s in summaries:
            for fmt in FORMATS:
                t = time.perf_counter()
                try:
                    rep = export(f, fmt, s, out / f"{label.replace('/', '_')}_{s}_{fmt}.txt")
                except HbmError as exc:
                    if fmt in CARDS:
                        print(f"| {label} | | {s} | {fmt} | refused: {str(exc)[:90]}... | | | | |")
                    continue
                dt = time.perf_counter() - t
                for c in rep.written.checks:
                    print(f"| {label} | {rep.source.form} | {s} | {fmt} | {c.error_tested:.2e} | {c.error_extended:.2e} "
                          f"| {c.bound:.2e} | {'yes' if c.passed else 'NO'} | {dt:.1f} |")
                if fmt == "febio-uniaxial" and rep.stability is not None:
                    fr = rep.stability.unstable_fraction
                    stab_rows.append(f"| {label} | {s} | {'stable' if rep.stability.median_stable else 'UNSTABLE'} | "
                                     + " | ".join(f"{100 * fr[m]:.1f} %" for m in fr) + f" | {rep.stability.n_draws} |")
        sys.stdout.flush()
    print("\nDrucker stability (energy form, 1.5x the tested strain range): the summary's draw and the "
          "fraction of posterior draws unstable somewhere\n")
    print("| result | summary | summary's draw | uniaxial | equibiaxial | planar | draws |")
    print("|---|---|---|---|---|---|---|")
    print("\n".join(stab_rows))
    return 0


if __name__ == "__main__":
    raise SystemExit(main(sys.argv[1:]))
