"""Verification report of ``hbm export``: every format x summary for a set of result files, and the energy cards in
every loading mode hbm predicts.

Usage (results from ``hbm run``/``hbm fit``; writes the Markdown report to stdout and the cards to OUT)::

    python workflows/export_verification.py OUT RESULT.nc [RESULT.nc ...] > results/export/verification.md

For each file: the cards of every format for median, p05 and p95 (population for hierarchical.nc); the energy
cards (febio-energy, abaqus-uanisohyper) only for energy-form results (thesis-form ones are refused, and the
refusal is listed).  Tables: the worst along-fibre difference per result and card, the energy cards' deviation
from hbm's cone in every loading mode (median / population summary) with its N-family share, every check per
summary, and the Drucker stability fractions (energy form).
"""

from __future__ import annotations

import sys
import time
from pathlib import Path

from hbm.errors import HbmError
from hbm.export import FORMATS, export
from hbm.model.loadcases import LOAD_CASES

CARDS = ("febio-uniaxial", "febio-energy", "abaqus-marlow", "abaqus-uanisohyper")
ENERGY_CARDS = ("febio-energy", "abaqus-uanisohyper")

PREAMBLE = """\
# hbm export: verification of every card (issue 29; every loading mode: issue 35)

Inputs (quick fits, not the shipped production run; regenerate with the commands below, OUT any folder):

```bash
hbm run --quick --workers 0 --no-figures --form energy --out OUT/run_energy     # six specimens, energy form
hbm run --quick --workers 0 --no-figures --out OUT/run_thesis                   # six specimens, thesis form
hbm fit data/measured/smith2011_gracilis_{fibres,bundles}.csv --sl0 2.0 --form {energy,thesis} \\
    --samples 500 --restarts 0 --out OUT/measured_{form}_{curve}.nc
python workflows/export_verification.py OUT/cards OUT/run_*/specimens/*.nc OUT/run_*/hierarchical.nc \\
    OUT/measured_*.nc > results/export/verification.md
```

**Along the fibres** (every card): max relative difference (|Δσ| / max(|σ_hbm|, 1e-3·max|σ_hbm|)) between the
card's law, re-implemented from its documentation and solved for homogeneous incompressible uniaxial tension in 3-D
(lateral stretch by root finding), and hbm's curve over the tested strain range; worst over the summaries (median,
p05, p95; population for hierarchical.nc).  Exact cards: tolerance 5e-3; `febio-energy` is approximate (the range
of its stated bounds over the summaries; in brackets the worst on 1.5x the tested range).  `abaqus-uanisohyper`:
the subroutine compiled with gfortran and called through its Abaqus interface.  `febio-uniaxial` and
`abaqus-marlow` represent along-fibre uniaxial tension only (not 3-D materials; they say so).  `febio-optimize`,
`csv`, `json` are not laws (no check).  Thesis-form results are refused for the energy cards, with the reason.
No febio4 executable: no FEBio run.

**Every loading mode** (the energy cards, `hbm.export.modes`): the card solved from its own law in each of the ten
modes of `hbm.model.loadcases` (traction-free faces by root finding, independently of hbm's energy code), against
hbm's prediction with the collagen's **cone** reading (the exact azimuthal average), the reading both cards
implement.  Controls: the tested along-fibre strain range applied as each mode's strain (or shear γ; biaxial
equibiaxial).  Deviation: |Δ| relative to the mode's largest stress at that point (lateral strains: to the
applied strain), floored at 1e-3 of its max over the range.  In brackets the share of it that is the N equally
spaced collagen families instead of the exact average (hbm's own segment law on the card's N azimuths); the rest
of a febio-energy deviation is its exp-linear fibre law, fitted on the segment stretches all modes reach.  Each
card also agrees with hbm's evaluation of its own laws to <= 1e-6 in every mode (else nothing is written).
"""


def _label(f: Path) -> str:
    """run/specimen, run/population, or the file's stem (a single fit)."""
    if f.name == "hierarchical.nc":
        return f.parent.name + "/population"
    return f.parent.parent.name + "/" + f.stem if f.parent.name == "specimens" else f.stem


def main(argv: list[str]) -> int:
    out = Path(argv[0])
    out.mkdir(parents=True, exist_ok=True)
    rows, stab_rows, mode_rows, worst = [], [], [], {}
    for f in map(Path, argv[1:]):
        summaries = ("population",) if f.name == "hierarchical.nc" else ("median", "p05", "p95")
        label = _label(f)
        for s in summaries:
            for fmt in FORMATS:
                t = time.perf_counter()
                try:
                    rep = export(f, fmt, s, out / f"{label.replace('/', '_')}_{s}_{fmt}.txt")
                except HbmError as exc:
                    if fmt in CARDS:
                        rows.append(f"| {label} | | {s} | {fmt} | refused: {str(exc)[:90]}... | | | | |")
                        worst.setdefault((label, ""), {})[fmt] = "refused (thesis form)"
                    continue
                dt = time.perf_counter() - t
                form = rep.source.form
                for c in rep.written.checks:
                    rows.append(f"| {label} | {form} | {s} | {fmt} | {c.error_tested:.2e} | {c.error_extended:.2e} "
                                f"| {c.bound:.2e} | {'yes' if c.passed else 'NO'} | {dt:.1f} |")
                    cell = worst.setdefault((label, form), {}).setdefault(fmt, [])
                    if isinstance(cell, list):
                        cell.append((c.error_tested, c.error_extended, c.bound))
                if rep.written.modes and s in ("median", "population"):
                    n = rep.written.modes[0].families
                    cells = [f"{c.error_tested:.2g} ({c.family_tested:.2g})" + ("" if c.passed else " FAILED")
                             for c in rep.written.modes]
                    mode_rows.append(f"| {label} | {fmt} | {n} | " + " | ".join(cells) + " |")
                if fmt == "febio-uniaxial" and rep.stability is not None and s in ("median", "population"):
                    fr = rep.stability.unstable_fraction
                    stab_rows.append(f"| {label} | {'stable' if rep.stability.median_stable else 'UNSTABLE'} | "
                                     + " | ".join(f"{100 * fr[m]:.1f} %" for m in fr)
                                     + f" | {rep.stability.n_draws} |")
        sys.stderr.write(f"{label}: done\n")
    print(PREAMBLE)
    print("| result | form | " + " | ".join(CARDS) + " |")
    print("|---|---|" + "---|" * len(CARDS))
    for (label, form), cards in worst.items():
        if not form:
            continue
        cells = []
        for fmt in CARDS:
            v = cards.get(fmt) or worst.get((label, ""), {}).get(fmt, "")
            if isinstance(v, list) and fmt == "febio-energy":
                cells.append(f"{min(b for _, _, b in v):.2g}–{max(b for _, _, b in v):.2g} (stated bound, 1.5x: "
                             f"≤ {max(x for _, x, _ in v):.2g})")
            elif isinstance(v, list):
                cells.append(f"{max(t for t, _, _ in v):.1e}")
            else:
                cells.append(v or "refused (thesis form)")
        print(f"| {label} | {form} | " + " | ".join(cells) + " |")
    print("\n## Every loading mode (energy cards, median / population summary)\n")
    print("Max deviation from hbm's cone on the tested range, over the mode's observables (in brackets: the N-family "
          "share); N = the card's collagen families.\n")
    print("| result | card | N | " + " | ".join(LOAD_CASES) + " |")
    print("|---|---|---|" + "---|" * len(LOAD_CASES))
    print("\n".join(mode_rows))
    print("\n## Every check (per summary)\n")
    print("| result | form | summary | format | tested range | 1.5x range | tolerance / bound | passed | wall s |")
    print("|---|---|---|---|---|---|---|---|---|")
    print("\n".join(rows))
    print("\n## Drucker stability (energy form)\n")
    print("Fraction of posterior draws unstable somewhere on 1.5x the tested strain range, per mode (fibre direction "
          "loaded), and the summary's (median / population) draw:\n")
    print("| result | summary's draw | uniaxial | equibiaxial | planar | draws |")
    print("|---|---|---|---|---|---|")
    print("\n".join(stab_rows))
    return 0


if __name__ == "__main__":
    raise SystemExit(main(sys.argv[1:]))
