"""``hbm diagnose`` of a specimen tested in several loading modes: its options and its path (issue 35, item 6).

The along-fibre diagnosis (:func:`hbm.detective.diagnose`) writes no file; this one writes each fit's result
(``joint_<reading>.nc``, ``without_<mode>.nc``: :mod:`hbm.io.modes`) and ``diagnosis.json`` /
``diagnosis.txt`` into one folder.  A folder that holds another diagnosis (other data, model or settings) or
a file of those names that is no diagnosis is refused unless ``--force``; the same diagnosis is replaced.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import sys
from pathlib import Path

from .. import plots  # hbm.plots.fit (matplotlib) loads when a figure is drawn
from ..detective.modes import diagnose_modes
from ..errors import OutputError
from ..io.identity import changed, content_key, data_key, model_key, settings_key
from ..runtime.files import atomic_write_text, file_lock, prepare_output_dir
from ..settings import DEFAULT_OUT
from ._common import _jsonable, print_json

#: the summary files beside the fits' results
SUMMARY = ("diagnosis.json", "diagnosis.txt")

__all__ = ["add_modes_diagnose_arguments", "run_modes_diagnosis", "SUMMARY"]


def add_modes_diagnose_arguments(p: argparse.ArgumentParser) -> None:
    """--out and --force of a diagnosis across loading modes (an along-fibre diagnosis writes no file)."""
    p.add_argument("--out", metavar="DIR", default=None,
                   help="tests in several loading modes: folder of the result files (each fit's netCDF, "
                        "diagnosis.json, diagnosis.txt; default hbm-results/diagnoses/<id>); a folder holding "
                        "another diagnosis is refused unless --force")
    p.add_argument("--force", action="store_true", help="replace another diagnosis in --out")


def _check_folder(folder: Path, parts: dict[str, str], force: bool) -> None:
    """Refuse to overwrite another diagnosis (or foreign files of our names) silently."""
    own = folder / SUMMARY[0]
    if own.exists():
        try:
            stored = json.loads(own.read_text()).get("identity")
        except (OSError, ValueError, AttributeError):
            stored = None
        diff = changed(stored if isinstance(stored, dict) else None, parts)
        if diff and not force:
            raise OutputError(f"--out {folder} holds a diagnosis with other {', '.join(diff)}; pass --force to "
                              "replace it, or choose another --out")
        return
    foreign = [p.name for p in folder.glob("*") if p.name in SUMMARY or p.suffix == ".nc"]
    if foreign and not force:
        raise OutputError(f"--out {folder} holds {', '.join(sorted(foreign))} but no diagnosis.json; pass --force "
                          "to replace them, or choose another --out")


def run_modes_diagnosis(args: argparse.Namespace, data, samples: int, model) -> int:
    """Diagnose the tests in their modes (:func:`hbm.detective.modes.diagnose_modes`) with ``model`` (the one
    ``--model``/``--form`` built, :func:`hbm.cli.diagnose._prepare`), write the results, print the report (or one
    JSON object)."""
    folder = Path(args.out) if args.out else Path(DEFAULT_OUT) / "diagnoses" / data.id
    settings = {"samples": samples, "seed": args.seed, "fix": dict(args.fix),
                "max_evaluations": args.max_evaluations, "command": "diagnose"}
    parts = {"data": data_key(data), "model": model_key(model), "settings": settings_key(settings)}
    folder = prepare_output_dir(folder, "--out")
    log = (lambda s: print(f"diagnose: {s}", file=sys.stderr, flush=True)) if args.progress else None
    with contextlib.ExitStack() as held:
        held.enter_context(file_lock(folder / SUMMARY[0], "--out"))
        _check_folder(folder, parts, args.force)
        diag = diagnose_modes(data, model=model, samples=samples, seed=args.seed, fix=dict(args.fix) or None,
                              max_evaluations=args.max_evaluations, max_time=args.max_time,
                              progress=args.progress, out=folder, log=log)
        if args.plot:
            plots.fit.modes_plot(diag.fits[diag.reading], path=args.plot)
        diag.paths.update({"summary": folder / SUMMARY[0], "report": folder / SUMMARY[1]})
        body = {**diag.to_dict(), "identity": parts, "key": content_key(parts)}
        atomic_write_text(folder / SUMMARY[1], diag.summary() + "\n")
        atomic_write_text(folder / SUMMARY[0], json.dumps(_jsonable(body), indent=1, allow_nan=False) + "\n")
    if args.json:
        print_json(body)
    else:
        print(diag.summary())
        if args.plot:
            print(f"figure: {args.plot} (the joint fit, {diag.reading} reading)")
    return 0

