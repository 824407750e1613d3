#!/usr/bin/env python
"""The population layer on the six shipped specimens: this checkout against another (issue 37).

``layer``: the layer alone, as ``hbm run`` calls it (``run_population`` with the run's settings), on the
stage-1 results of one ``hbm run`` of the shipped six (``--specimens``, the ``specimens/`` folder of a run),
for each checkout in turn (``--before`` and this one, interleaved ``--repeats`` times, each in a fresh
process with ``PYTHONPATH`` at that checkout): wall and CPU seconds (process time of the process and its
children), the layer's model evaluations (the exact fallback's before issue 37, the root attribute
``evaluations`` of ``hierarchical.nc`` after), and max R-hat and min bulk ESS of the hyper-parameters
computed by ArviZ from the written ``hierarchical.nc`` (NaN for one stored chain).

``run``: ``hbm run`` end to end on ``data/specimens`` for each checkout in turn (fresh output folders),
with ``--geometry`` when given: wall seconds and the phases of ``run.json``.

Writes ``results/benchmarks/population_six.json`` (sections ``layer`` and ``run``), and prints a table.

    OMP_NUM_THREADS=1 python workflows/benchmarks/population_six.py layer --before ../before \\
        --specimens hbm-results/specimens --repeats 2
    OMP_NUM_THREADS=1 python workflows/benchmarks/population_six.py run --before ../before
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
OUT = ROOT / "results" / "benchmarks" / "population_six.json"

#: the layer in a fresh process: reads the stage-1 results, runs it as ``hbm run`` does, prints a JSON line
_LAYER = r"""
import json, sys, time
from pathlib import Path
try:
    from hbm.workflow.run import RunConfig, _common_sigma_box
except ImportError:  # a checkout from before issue 34's layout
    from hbm.workflow import RunConfig, _common_sigma_box
from hbm import io
from hbm.data import load_specimens
from hbm.model import spyrou_model
from hbm.population import run_population
spec, data, out = Path(sys.argv[1]), sys.argv[2], sys.argv[3]
datasets = load_specimens(data)
results = {s: io.read_specimen_result(spec / f"{s}.nc") for s in sorted(datasets)}
run_cfg = RunConfig(data=data, out=out, progress=False)
# population_settings since issue 34's settings records (population_config before)
cfg = getattr(run_cfg, "population_settings", None) or run_cfg.population_config
cfg = cfg()
t, c = time.perf_counter(), time.process_time()
hf, path = run_population(results, datasets, spyrou_model(), config=cfg, out=out)
wall, cpu = time.perf_counter() - t, time.process_time() - c
ev = getattr(hf, "evaluations", None)
if ev is None:
    ev = sum((hf.attrs.get("exact") or {}).get("evaluations", {}).values())
print(json.dumps({"wall_s": wall, "cpu_s": cpu, "evaluations": int(ev), "path": str(path)}))
"""


def _diag(path: str) -> dict:
    import arviz as az
    import numpy as np

    post = az.from_netcdf(path).posterior
    rh, es = az.rhat(post), az.ess(post, method="bulk")  # unrounded (az.summary rounds to 2 decimals)
    r = np.array([float(rh[v]) for v in rh.data_vars])
    return {"chains": int(post.sizes["chain"]), "draws": int(post.sizes["draw"]),
            "rhat_max": float(np.nanmax(r)) if np.isfinite(r).any() else float("nan"),
            "ess_bulk_min": float(min(float(es[v]) for v in es.data_vars))}


def _checkouts(a) -> list:
    """(label, code) pairs in the order they run: the other checkout first unless ``--before none``."""
    after = [("after", ROOT)]
    return after if a.before == "none" else [("before", Path(a.before).resolve())] + after


def _child_cpu() -> float:
    r = resource.getrusage(resource.RUSAGE_CHILDREN)
    return r.ru_utime + r.ru_stime


def layer(a) -> int:
    rows = []
    for rep in range(a.repeats):
        for label, code in _checkouts(a):
            with tempfile.TemporaryDirectory() as tmp:
                env = {**os.environ, "PYTHONPATH": str(code), "OMP_NUM_THREADS": "1"}
                c0 = _child_cpu()
                p = subprocess.run([sys.executable, "-c", _LAYER, str(Path(a.specimens).resolve()),
                                    str(ROOT / "data" / "specimens"), tmp], capture_output=True, text=True, env=env,
                                   cwd=str(code))  # python -c puts the cwd first on sys.path
                if p.returncode != 0:
                    raise SystemExit(f"{label} failed:\n{p.stderr[-3000:]}")
                rec = json.loads(p.stdout.strip().splitlines()[-1])
                rec.update(label=label, repeat=rep, process_cpu_s=_child_cpu() - c0, load=os.getloadavg(),
                           **_diag(rec.pop("path")))
            rows.append(rec)
            print(json.dumps(rec), flush=True)
    _save(a.record or "layer", rows)
    return 0


def run(a) -> int:
    rows = []
    for rep in range(a.repeats):
        for label, code in _checkouts(a):
            with tempfile.TemporaryDirectory() as tmp:
                env = {**os.environ, "PYTHONPATH": str(code), "OMP_NUM_THREADS": "1"}
                args = [sys.executable, "-m", "hbm", "run", "--out", tmp, "--no-progress",
                        "--data", str(ROOT / "data" / "specimens")]
                if a.geometry:
                    args += ["--geometry", str(ROOT / a.geometry)]
                t, c0 = time.perf_counter(), _child_cpu()
                p = subprocess.run(args, capture_output=True, text=True, env=env, cwd=str(code))
                wall = time.perf_counter() - t
                if p.returncode != 0:
                    raise SystemExit(f"{label} failed:\n{p.stderr[-3000:]}")
                timings = json.loads((Path(tmp) / "run.json").read_text())["timings"]
                # CPU of hbm run and every process it waited for (the embedded cluster's workers included)
                rec = {"label": label, "repeat": rep, "wall_s": wall, "process_cpu_s": _child_cpu() - c0,
                       "load": os.getloadavg(), **{k: v for k, v in timings.items() if k != "task_times"},
                       **_diag(str(Path(tmp) / "hierarchical.nc"))}
                if a.keep:  # the stage-1 results, for the ``layer`` subcommand, and the layer's file
                    shutil.copytree(Path(tmp) / "specimens", Path(a.keep) / f"{label}{rep}", dirs_exist_ok=True)
                    shutil.copy2(Path(tmp) / "hierarchical.nc", Path(a.keep) / f"{label}{rep}.hierarchical.nc")
            rows.append(rec)
            print(json.dumps(rec), flush=True)
    _save(a.record or "run", rows)
    return 0


def _save(key: str, rows) -> None:
    rec = json.loads(OUT.read_text()) if OUT.exists() else {}
    rec[key] = rows
    OUT.write_text(json.dumps(rec, indent=1))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = ap.add_subparsers(dest="cmd", required=True)
    for name in ("layer", "run"):
        p = sub.add_parser(name)
        p.add_argument("--before", default=os.environ.get("HBM_BEFORE", str(ROOT.parent / "before")),
                       help="checkout to compare with (default $HBM_BEFORE or ../before; 'none': this checkout only)")
        p.add_argument("--specimens", default="hbm-results/specimens", help="stage-1 results of the six (layer)")
        p.add_argument("--repeats", type=int, default=2)
        p.add_argument("--record", default=None, help="key of the record in population_six.json (default the "
                       "subcommand's name: it replaces that record)")
        p.add_argument("--geometry", default=None, help="e.g. data/geometry/fusiform.toml (run)")
        p.add_argument("--keep", default=None, help="copy each run's specimens/ to KEEP/<label><repeat> and its "
                       "hierarchical.nc to KEEP/<label><repeat>.hierarchical.nc (run)")
    a = ap.parse_args(argv)
    return {"layer": layer, "run": run}[a.cmd](a)


if __name__ == "__main__":
    sys.exit(main())
