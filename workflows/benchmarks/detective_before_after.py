"""Default diagnoses by two checkouts of hbm, interleaved case by case (issue 28's wall-time table).

Every validation case (``workflows/detective_validation.py``: ``run_case``, its seeds) and every given
specimen file is diagnosed by the ``--before`` checkout and then by the ``--after`` checkout, each in a
fresh process, one at a time, so both see the same machine load.  Rows go to ``--json``; a table to stdout.

Run from the repository root, with the old code in a worktree::

    git worktree add --detach /tmp/before <commit>
    python workflows/benchmarks/detective_before_after.py --before /tmp/before --after . \\
        --groups clean unknown library two --json /tmp/ba.json \\
        --file "data/measured/smith2011_gracilis_bundles.csv --sl0 2.0"
"""

from __future__ import annotations

import argparse
import json
import os
import shlex
import statistics
import subprocess
import sys
import time
from pathlib import Path

# the cases are the measured checkout's (--after) definitions; hbm is the checkout run's own
_CASE = r'''
import json, sys
sys.path.insert(0, {cases!r} + "/workflows")
import {module} as V
from hbm.detective import diagnose
seed, c = [(17 + k, c) for k, c in enumerate(V.cases({groups!r}))][{i}]
print("ROW" + json.dumps(V.run_case(c, seed, diagnose), default=str))
'''


def _run(tree: str, argv: list[str]) -> subprocess.CompletedProcess:
    # no calibration cache: every run pays for its calibration (a rerun of the benchmark would hit it)
    return subprocess.run([sys.executable, *argv], capture_output=True, text=True, cwd=tree,
                          env={**os.environ, "PYTHONPATH": str(Path(tree).resolve()), "HBM_CACHE_DIR": "off"})


def case_row(tree: str, groups: list[str], i: int, module: str = "detective_validation",
             cases: str | None = None) -> dict | None:
    src = str(Path(cases or tree).resolve())
    out = _run(tree, ["-c", _CASE.format(cases=src, module=module, groups=groups, i=i)])
    line = [ln for ln in out.stdout.splitlines() if ln.startswith("ROW")]
    return json.loads(line[0][3:]) if line else None


def file_row(tree: str, spec: str) -> dict:
    """``hbm diagnose FILE [options] --json`` by the checkout ``tree``; wall time of the command."""
    argv = shlex.split(spec)
    argv[0] = str(Path(argv[0]).resolve())
    t0 = time.perf_counter()
    out = _run(tree, ["-m", "hbm", "diagnose", *argv, "--json", "--no-progress"])
    wall = time.perf_counter() - t0
    try:
        d = json.loads(out.stdout)
    except json.JSONDecodeError:
        return {"case": Path(argv[0]).stem, "verdict": f"error: {out.stderr.strip()[-200:]}", "seconds": wall}
    return {"case": Path(argv[0]).stem, "verdict": d["verdict"], "selected": d.get("selected") or [],
            "seconds": round(wall, 1), "diagnosis_seconds": round(d["timings"]["total"], 1),
            "cpu_seconds": round(d["timings"]["cpu"], 1), "stopped": bool(d.get("stopped"))}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--before", required=True, help="checkout of the baseline")
    ap.add_argument("--after", required=True, help="checkout of the code measured")
    ap.add_argument("--groups", nargs="*", default=[], help="validation groups (e.g. clean unknown library two)")
    ap.add_argument("--file", action="append", default=[], help="'FILE [diagnose options]' (repeatable)")
    ap.add_argument("--run-groups", nargs="*", default=None,
                    help="run only these groups, in this order (seeds as in the enumeration of --groups)")
    ap.add_argument("--module", default="detective_validation",
                    help="the cases' module in the --after checkout's workflows/ (e.g. calibration_validation)")
    ap.add_argument("--own-cases", action="store_true",
                    help="each checkout generates the cases with its own workflows/ module (for a baseline that "
                         "cannot import the --after module's helpers; check first that both generate the same data)")
    ap.add_argument("--json", required=True)
    args = ap.parse_args(argv)
    sys.path.insert(0, str(Path(args.after).resolve() / "workflows"))
    V = __import__(args.module)
    rows: dict[str, list] = {"before": [], "after": []}
    every = V.cases(args.groups) if args.groups else []
    order = args.run_groups if args.run_groups is not None else sorted({c["group"] for c in every},
                                                                       key=[c["group"] for c in every].index)
    todo = [("case", i) for g in order for i, c in enumerate(every) if c["group"] == g] + \
        [("file", f) for f in args.file]
    for kind, what in todo:
        for lab in ("before", "after"):
            tree = getattr(args, lab)
            cases = tree if args.own_cases else args.after
            r = case_row(tree, args.groups, what, args.module, cases) if kind == "case" else file_row(tree, what)
            if r is None:
                print(f"{lab} {what}: failed", flush=True)
                continue
            rows[lab].append(r)
            print(f"{r['case']:<32} {lab:<7} {r['verdict']:<13} {r['seconds']} s", flush=True)
        Path(args.json).write_text(json.dumps(rows, indent=1, default=str))
    for lab in ("before", "after"):
        w = [r["seconds"] for r in rows[lab]]
        if w:
            print(f"{lab}: wall median {statistics.median(w):.1f} s, max {max(w):.1f} s over {len(w)}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
