"""``hbm data``: specimen data utilities (``hbm data check PATH...``)."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

from ..data import input_summary, load_specimen, provenance
from ..data.artefacts import describe_artefacts
from ..data.prepare import screen_dataset
from ..errors import DataError, HbmError, SettingError
from ._common import add_data_arguments, print_json, split_mode

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
(with '# reference_sarcomere_length_um: 2.0') instead of strain, and a testing machine's force
and displacement ('Load (N)', 'Extension (mm)', 'Position (mm)') with the specimen's geometry
('# diameter_mm:' or '# area_mm2:' or '# width_mm:' + '# thickness_mm:', '# gauge_length_mm:',
'# loading: compression' for machines that report magnitudes).  A curve much stiffer than
passive muscle without a declared unit is refused as a unit mix-up.

Rows that are not the tissue -- pre-test readings, spikes, dropouts, dips during holds,
post-failure tails -- are found by a model-free screen and listed with their lines (hbm fit,
diagnose and extend --drop-artefacts drop them, with a record in the result).

--json prints one object: per specimen the loaded series (engineering strain, Cauchy stress in
MPa, time in s, test), the conversion record and the flagged rows.

Tests as data (README "Loading modes"): a 'mode' column (uniaxial_f, uniaxial_c, planar_*,
biaxial_*, shear_*; constant within a test) and the observables strain_2, stress_2, strain_c,
strain_n, strain_f (empty cell = not measured); the check then lists each specimen's tests by mode.

examples:
  hbm data check data/specimens
  hbm data check raw_machine_export.csv --json
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
    check.add_argument("paths", nargs="+", metavar="PATH",
                       help="CSV file or folder of CSV files; PATH:MODE gives files without a mode column their "
                            "loading mode (e.g. across.csv:uniaxial_c)")
    check.add_argument("--json", action="store_true",
                       help="print one JSON object: per specimen its series, tests by mode, conversion record and "
                            "flagged rows")
    add_data_arguments(check)
    check.set_defaults(func=run_check)
    parser.set_defaults(func=_no_action)


def _no_action(args: argparse.Namespace) -> int:
    raise SettingError("data: expected an action, e.g. 'hbm data check PATH...' (see hbm data --help)")


def _files(paths: list[str], errors: list[str]) -> list[tuple[Path, str | None]]:
    """The CSV files of the PATH arguments, each with the mode given by ``FILE:MODE`` (or None)."""
    files: list[tuple[Path, str | None]] = []
    for text in paths:
        text, mode = split_mode(text)
        p = Path(text)
        if p.is_dir():
            found = sorted(p.glob("*.csv"))
            if not found:
                errors.append(f"{p}: no *.csv files, expected at least one specimen file")
            files.extend((f, mode) for f in found)
        elif p.exists():
            files.append((p, mode))
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
            f"{stress[np.nanargmax(np.abs(stress))]:.4g}" if np.isfinite(stress).any() else "-", str(len(spec.tests)), "yes" if spec.time is not None else "-",
            _input(spec), provenance(spec), source]


def tests_by_mode(spec) -> dict[str, list[dict]]:
    """Mode -> its tests (id, label, points, the observables measured in it with their counts)."""
    out: dict[str, list[dict]] = {}
    for t in spec.tests:
        measured = {k: int(np.isfinite(s.values[t.rows]).sum()) for k, s in spec.observed.items()}
        out.setdefault(t.load_case, []).append(
            {"id": t.id, "label": t.label, "points": t.n_points, "measured": {k: v for k, v in measured.items() if v}})
    return out


def _mode_line(spec) -> str:
    parts = []
    for mode, tests in tests_by_mode(spec).items():
        names = ", ".join(str(t["label"] if t["label"] is not None else t["id"]) for t in tests)
        seen = sorted({k for t in tests for k in t["measured"]})
        parts.append(f"{mode}: {len(tests)} test(s) ({names}; measured {', '.join(seen)})")
    return f"  {spec.id}: " + "; ".join(parts)


#: dataset attributes that record a conversion (hbm.data: loader, machine, prepare)
_RECORDS = ("units_stress", "units_stress_original", "stress_measure", "stress_measure_original", "deformation_input",
            "reference_sarcomere_length_um", "test_labels", "stress_input", "cross_section_mm2", "loading",
            "area_mm2", "diameter_mm", "width_mm", "thickness_mm", "gauge_length_mm")


def _series(spec) -> dict:
    """The loaded series of one specimen, in the specimen's units (the JSON of --json); ``mode``:
    each test's load case (:attr:`hbm.data.Test.load_case`)."""
    out = {"strain": spec.strain.tolist(), **{k: sr.values.tolist() for k, sr in spec.observed.items()}}
    for name in ("time", "test"):
        if getattr(spec, name) is not None:
            out[name] = getattr(spec, name).tolist()
    out["mode"] = {str(t.id): t.load_case for t in spec.tests}
    return out


def _specimen_json(f: Path, spec, found, lines) -> dict:
    a = spec.attrs
    record = {k: a[k] for k in _RECORDS if k in a}
    if a.get("conversion_steps"):
        record["steps"] = json.loads(a["conversion_steps"])
    if a.get("test_labels"):
        record["test_labels"] = json.loads(a["test_labels"])
    units = {"strain": "1 (engineering strain)", **{k: sr.unit for k, sr in spec.observed.items()},
             "stress": "MPa (Cauchy)", "time": "s"}
    return {"id": spec.id, "file": str(f), "points": spec.n_points, "units": units,
            "series": _series(spec), "tests_by_mode": tests_by_mode(spec),
            "conversion": {"summary": input_summary(spec), **record},
            "artefacts": [x.to_dict(lines) for x in found]}


def run_check(args: argparse.Namespace) -> int:
    """Check every file, print the table of good ones (or the JSON) and one line per bad one."""
    errors: list[str] = []
    rows: list[list[str]] = []
    notes: list[str] = []
    flagged: list[str] = []
    specimens: list[dict] = []
    ids: dict[str, str] = {}
    modes: list[str] = []
    for f, mode in _files(args.paths, errors):
        try:
            ds = load_specimen(f, sl0=args.sl0, mode=mode)
        except HbmError as exc:
            errors.append(str(exc))
            continue
        sid = ds.id
        if sid in ids:
            errors.append(str(DataError(f"{f}: duplicate specimen id {sid!r} (also in {ids[sid]}), "
                                        "expected unique ids")))
            continue
        ids[sid] = str(f)
        found, lines = screen_dataset(ds)
        rows.append(_row(ds))
        if "test_load_cases" in ds.attrs or len(ds.observed) > 1:
            modes.append(_mode_line(ds))
        specimens.append(_specimen_json(f, ds, found, lines) if args.json else {})
        if input_summary(ds):
            notes.append(f"{sid}: {input_summary(ds)}")
        if found:
            flagged.append(f"{sid}: {describe_artefacts(found, lines)}")
    if args.json:
        print_json({"specimens": specimens, "errors": errors})
    elif rows:
        head = ["id", "points", "strain", "peak stress [MPa]", "tests", "time", "input", "provenance", "source"]
        widths = [max(len(r[i]) for r in rows + [head]) for i in range(len(head))]
        line = lambda r: "  ".join(c.ljust(w) for c, w in zip(r, widths)).rstrip()  # noqa: E731
        print(line(head))
        print("  ".join("-" * w for w in widths))
        for r in rows:
            print(line(r))
        if modes:
            print("tests by mode:")
            for m in modes:
                print(m)
        if notes:
            print("converted on loading (dataset: engineering strain, Cauchy stress in MPa):")
            for n in notes:
                print(f"  {n}")
        if flagged:
            print("rows that are not the tissue (artefact screen; hbm fit/diagnose/extend --drop-artefacts drops "
                  "them, recorded in the result):")
            for n in flagged:
                print(f"  {n}")
        ok = len(rows) - len(flagged)
        print(f"{ok} specimen(s) OK" + (f", {len(flagged)} with artefact rows" if flagged else "")
              + (f", {len(errors)} failed" if errors else ""))
    for e in errors:
        print(f"hbm: error: {e}", file=sys.stderr)
    return 2 if errors else 0
