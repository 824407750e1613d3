"""``hbm data``: specimen data utilities (``hbm data check PATH...``)."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

from ..data import input_summary, load_specimen, provenance
from ..errors import DataError, HbmError, SettingError
from ._common import add_data_arguments

CHECK_DESCRIPTION = """\
Validate specimen CSV files and print a summary table.

PATH may be a CSV file or a folder (all *.csv in it, not recursive).  Every file is checked;
each bad file is reported on one line (file, line, column, what was expected) and the exit
status is 2 if any file failed, 0 otherwise.

CSV format: optional '# key: value' metadata lines, then a header with strain,stress
(engineering strain, Cauchy stress in MPa) and optional time (s) and test (integer or label)
columns.  Other inputs are converted and the conversion is shown (column "input" and a line per
converted specimen): '# units_stress: kPa' (or Pa, or a column stress_kPa ...), nominal stress
('# stress_measure: nominal' or a column nominal_stress...), stretch or sarcomere_length_um
(with '# reference_sarcomere_length_um: 2.0') instead of strain.  A Cauchy stress above 5 MPa
is refused as a unit mix-up.
"""


def register(subparsers) -> None:
    """Add ``data`` (with its ``check`` sub-subcommand) to the ``hbm`` parser."""
    parser = subparsers.add_parser("data", help="specimen data utilities (check CSV files)",
                                   description="Specimen data utilities.",
                                   formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = parser.add_subparsers(dest="data_command", metavar="ACTION")
    check = sub.add_parser("check", help="validate specimen CSV files and print a summary",
                           description=CHECK_DESCRIPTION,
                           formatter_class=argparse.RawDescriptionHelpFormatter)
    check.add_argument("paths", nargs="+", metavar="PATH", help="CSV file or folder of CSV files")
    add_data_arguments(check)
    check.set_defaults(func=run_check)
    parser.set_defaults(func=_no_action)


def _no_action(args: argparse.Namespace) -> int:
    raise SettingError("data: expected an action, e.g. 'hbm data check PATH...' (see hbm data --help)")


def _files(paths: list[str], errors: list[str]) -> list[Path]:
    files: list[Path] = []
    for p in map(Path, paths):
        if p.is_dir():
            found = sorted(p.glob("*.csv"))
            if not found:
                errors.append(f"{p}: no *.csv files, expected at least one specimen file")
            files.extend(found)
        elif p.exists():
            files.append(p)
        else:
            errors.append(f"{p}: no such file or folder")
    return files


def _input(ds) -> str:
    """Short form of what the loader converted: original unit, measure, deformation, labels."""
    a = ds.attrs
    parts = [a.get("units_stress_original", ""), a.get("stress_measure_original", "")]
    deformation = a.get("deformation_input", "")
    if deformation == "sarcomere_length_um":
        deformation = f"SL/{a.get('reference_sarcomere_length_um', '?')}um"
    parts += [deformation, "labels" if a.get("test_labels") else ""]
    return ",".join(p for p in parts if p) or "-"


def _row(spec) -> list[str]:
    strain, stress = spec.strain, spec.stress
    source = str(spec.attrs.get("citation") or spec.attrs.get("source") or "")
    if len(source) > 48:
        source = source[:45] + "..."
    return [spec.id, str(strain.size), f"{strain.min():.3g}..{strain.max():.3g}",
            f"{stress[np.argmax(np.abs(stress))]:.4g}", str(len(spec.tests)), "yes" if spec.time is not None else "-",
            _input(spec), provenance(spec), source]


def run_check(args: argparse.Namespace) -> int:
    """Check every file, print the table of good ones and one line per bad one."""
    errors: list[str] = []
    rows: list[list[str]] = []
    notes: list[str] = []
    ids: dict[str, str] = {}
    for f in _files(args.paths, errors):
        try:
            ds = load_specimen(f, sl0=args.sl0)
        except HbmError as exc:
            errors.append(str(exc))
            continue
        sid = ds.id
        if sid in ids:
            errors.append(str(DataError(f"{f}: duplicate specimen id {sid!r} (also in {ids[sid]}), "
                                        "expected unique ids")))
            continue
        ids[sid] = str(f)
        rows.append(_row(ds))
        if input_summary(ds):
            notes.append(f"{sid}: {input_summary(ds)}")
    if rows:
        head = ["id", "points", "strain", "peak stress [MPa]", "tests", "time", "input", "provenance", "source"]
        widths = [max(len(r[i]) for r in rows + [head]) for i in range(len(head))]
        line = lambda r: "  ".join(c.ljust(w) for c, w in zip(r, widths)).rstrip()  # noqa: E731
        print(line(head))
        print("  ".join("-" * w for w in widths))
        for r in rows:
            print(line(r))
        if notes:
            print("converted on loading (dataset: engineering strain, Cauchy stress in MPa):")
            for n in notes:
                print(f"  {n}")
        print(f"{len(rows)} specimen(s) OK" + (f", {len(errors)} failed" if errors else ""))
    for e in errors:
        print(f"hbm: error: {e}", file=sys.stderr)
    return 2 if errors else 0
