#!/usr/bin/env python
"""The population layer on synthetic populations of 6, 24 and 96 specimens (issue 37).

``make``: populations like the shipped six — 50 points up to a largest strain of 0.40–0.45, iid noise of
1 % of the largest stress — whose specimens are drawn from a known population of the layer's own model
(``--pool combinations``): log G, log c·P1, log (1−c)·T1 and THETA normal (THETA truncated to its box),
T2 and EOPT logit-normal on their boxes (``TRUTH``), VOLF, P1, T1, GF, GM from the box prior given the
combinations (:func:`hbm.identifiability.combinations.sample_conditional`).  The specimens of a smaller
population are the first ones of the larger (one stream per specimen), written with
:func:`hbm.data.synthetic_specimen` into ``--data/pop<N>/``.

``run``: ``hbm run`` on each population (``--workers``, default all cores; ``--no-figures`` by default:
96 specimens' corner plots are not what is measured), then from its files: the wall time of the run and
of each phase (``run.json``), the layer's model evaluations and CPU seconds (master plus the shards'
workers, ``hierarchical.nc`` attribute ``layer``), R-hat and bulk ESS of every hyper-parameter computed by
ArviZ from ``hierarchical.nc``, and the coverage of the generating population: each true hyper-parameter
against the 5–95 % interval of its hyper-posterior.  A run whose specimens are complete refits nothing
(the layer reruns when its file is removed: ``--layer-only``).

``dask``: the layer of one population (specimens complete) with ``--workers 1`` and ``--workers 2``,
interleaved ``--repeats`` times: the draws must be bitwise the same, the wall times are compared.

``layer``: the layer alone on ``pop<size>`` (``run_population`` with the run's settings): the stage-1 results of
``--from-run`` where complete, TMCMC fits without CMA-ES and Sobol otherwise (cached in ``<runs>/stage1``); with
``--workers 1,2`` each in turn on an embedded dask cluster, the draws compared bitwise.

Writes ``results/benchmarks/population_scaling.json`` (``run``/``dask``/``layer`` sections); the findings are in
``results/benchmarks/population_layer.md``.

    OMP_NUM_THREADS=1 python workflows/benchmarks/population_scaling.py make
    OMP_NUM_THREADS=1 python workflows/benchmarks/population_scaling.py run --sizes 6,24,96
    OMP_NUM_THREADS=1 python workflows/benchmarks/population_scaling.py dask --size 96
    OMP_NUM_THREADS=1 python workflows/benchmarks/population_scaling.py layer --size 26 --workers 1,2 --from-run RUN
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[2]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from hbm import io  # noqa: E402
from hbm.data import save_specimen, synthetic_specimen  # noqa: E402
from hbm.data.plausibility import implausible  # noqa: E402
from hbm.identifiability.combinations import (COMBINATION_PARAMS, log_density, sample_conditional, support_hull,  # noqa: E402
                                              to_features)
from hbm.model import spyrou_model  # noqa: E402
from hbm.model.core import Loading  # noqa: E402
from hbm.population import COMBINATION_COLUMNS  # noqa: E402
from hbm.runtime.files import atomic_write_text  # noqa: E402

#: the generating population: (mu, sd) in the layer's coordinates (log for the combinations, logit on the
#: box for T2 and EOPT, identity for THETA)
TRUTH = {"log_G": (np.log(0.02), 0.4), "log_VOLF*P1": (np.log(0.05), 0.5), "log_(1-VOLF)*T1": (np.log(0.3), 0.5),
         "T2": (np.log(12.0 / 188.0), 0.5), "THETA": (58.5, 0.8), "EOPT": (np.log(0.8 / 0.2), 0.5)}
ENTROPY = 37_2026
N_POINTS, NOISE_REL = 50, 0.01
OUT = ROOT / "results" / "benchmarks"
#: default folder of the populations and runs (the system's temporary folder)
SCRATCH = Path(tempfile.gettempdir()) / "hbm_population_scaling"


def _logistic(z, lo, hi):
    return lo + (hi - lo) / (1.0 + np.exp(-z))


def specimen(k: int, model):
    """Specimen k of the population (its own stream: the same in every population that has it)."""
    rng = np.random.default_rng(np.random.SeedSequence(ENTROPY, spawn_key=(k,)))
    names, box = list(model.parameter_names), model.bounds
    cb = np.array([box[names.index(p)] for p in COMBINATION_PARAMS])
    hull = np.log(support_hull(box, names))
    while True:  # the population truncated to the box and to the support of the combinations
        phi = np.array([rng.normal(*TRUTH[c]) for c in COMBINATION_COLUMNS])
        theta_deg = rng.normal(*TRUTH["THETA"])
        if (np.all((phi >= hull[:, 0]) & (phi <= hull[:, 1])) and 55.0 <= theta_deg <= 60.0
                and np.isfinite(log_density(phi[None], cb)[0])):
            break
    th = dict(zip(COMBINATION_PARAMS, sample_conditional(phi[None], cb, rng)[0]))
    th.update(T2=_logistic(rng.normal(*TRUTH["T2"]), *box[names.index("T2")]), THETA=theta_deg,
              EOPT=_logistic(rng.normal(*TRUTH["EOPT"]), *box[names.index("EOPT")]))
    eps_max = round(float(rng.uniform(0.40, 0.45)), 3)
    strain = np.round(np.linspace(0.0, eps_max, N_POINTS), 6)
    sid = f"syn{k:03d}"
    ds = synthetic_specimen(model, th, Loading(strain), NOISE_REL, int(rng.integers(2**31)), relative=True,
                            attrs={"id": sid, "provenance": "synthetic",
                                   "source": "workflows/benchmarks/population_scaling.py (a known population)",
                                   "parameters": json.dumps({k: float(v) for k, v in th.items()})})
    ds["stress"].values[:] = np.round(ds["stress"].values, 7)
    if implausible(ds["strain"].values, ds["stress"].values) is not None:
        # a stiff draw of the population (the loader would take the stress for kPa): its unit is declared
        ds.attrs["units_stress"] = "MPa"
    return sid, ds


def make(a) -> int:
    model = spyrou_model()
    for n in map(int, a.sizes.split(",")):
        folder = Path(a.data) / f"pop{n}"
        folder.mkdir(parents=True, exist_ok=True)
        for k in range(n):
            sid, ds = specimen(k, model)
            save_specimen(ds, folder / f"{sid}.csv")
        print(f"{folder}: {n} specimens")
    return 0


def _hbm(args: list[str], env_extra: dict | None = None) -> tuple[float, float, str]:
    """Run ``python -m hbm ARGS``; (wall s, CPU s of it and its descendants, stderr tail)."""
    import resource

    env = {**os.environ, "PYTHONPATH": str(ROOT), "OMP_NUM_THREADS": "1", **(env_extra or {})}
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    t = time.perf_counter()
    out = subprocess.run([sys.executable, "-m", "hbm", *args], capture_output=True, text=True, env=env)
    wall = time.perf_counter() - t
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    if out.returncode != 0:
        raise SystemExit(f"hbm {' '.join(args)} failed:\n{out.stderr[-3000:]}")
    return wall, (after.ru_utime + after.ru_stime) - (before.ru_utime + before.ru_stime), out.stderr[-2000:]


def drawn(ids, model, data: Path) -> dict:
    """The drawn specimens' own population in the layer's coordinates: column -> (sample mean, sample sd) of
    the specimens ``ids`` from their true parameters (the ``# parameters:`` line of ``data/<id>.csv``)."""
    names, box = list(model.parameter_names), model.bounds
    pars = []
    for sid in ids:
        with open(data / f"{sid}.csv") as f:
            pars.append(json.loads(next(ln for ln in f if ln.startswith("# parameters:")).split(":", 1)[1]))
    th = np.array([[q[p] for p in names] for q in pars])
    cols = dict(zip(COMBINATION_COLUMNS, np.log(to_features(names, th)).T))
    for p in ("T2", "EOPT"):
        lo, hi = box[names.index(p)]
        x = th[:, names.index(p)]
        cols[p] = np.log((x - lo) / (hi - x))
    cols["THETA"] = th[:, names.index("THETA")]
    return {c: (float(v.mean()), float(v.std(ddof=1))) for c, v in cols.items()}


def layer_record(out: Path, data: Path, run_json: bool = True) -> dict:
    """What the stored files say about the layer: evaluations, CPU, ArviZ R-hat/ESS, and the coverage of the
    generating population (``TRUTH``) and of the drawn specimens' own mean and sd (:func:`drawn`) by the 5-95 %
    intervals of the hyper-posterior."""
    import arviz as az

    hf = io.read_hierarchical(out / "hierarchical.nc")
    run = json.loads((out / "run.json").read_text()) if run_json else {"timings": {}}
    post = az.from_netcdf(out / "hierarchical.nc").posterior
    rh, es = az.rhat(post), az.ess(post, method="bulk")  # unrounded (az.summary rounds to 2 decimals)
    diag = {"r_hat": {v: float(rh[v]) for v in rh.data_vars}, "ess_bulk": {v: float(es[v]) for v in es.data_vars}}
    lay = hf.attrs.get("layer", {})
    cover = {}
    sample = drawn(hf.specimen_ids, spyrou_model(), data)
    for p in hf.attrs.get("pooled", []):
        for kind, j in (("mu", 0), ("sd", 1)):
            name = f"{kind}_{p}"
            if p in TRUTH and name in hf.hyper_names:
                lo, hi = np.quantile(hf.hyper(name), [0.05, 0.95])
                cover[name] = {"truth": float(TRUTH[p][j]), "q05": float(lo), "q95": float(hi),
                               "inside": bool(lo <= TRUTH[p][j] <= hi), "drawn": sample[p][j],
                               "drawn_inside": bool(lo <= sample[p][j] <= hi)}
    t = run["timings"]
    return {"specimens": len(hf.specimen_ids), "evaluations": int(hf.evaluations or 0),
            "layer_cpu_s": float(lay.get("cpu_s", float("nan"))), "layer_wall_s": float(lay.get("wall_s", float("nan"))),
            "chains": lay.get("chains"), "draws_per_chain": int(hf.hyper_samples.shape[0] // max(hf.chains, 1)),
            "rhat_max": max(diag["r_hat"].values()), "ess_bulk_min": min(diag["ess_bulk"].values()),
            "rhat": diag["r_hat"], "ess_bulk": diag["ess_bulk"],
            "rhat_specimen_max": lay.get("rhat_specimen_max"), "warnings": hf.attrs.get("warnings", []),
            "coverage": cover, "timings": {k: v for k, v in t.items() if k != "task_times"},
            "dask": lay.get("dask")}


def run(a) -> int:
    rows = {}
    for n in map(int, a.sizes.split(",")):
        data, out = Path(a.data) / f"pop{n}", Path(a.out_runs) / f"pop{n}"
        if a.layer_only and (out / "hierarchical.nc").exists():
            (out / "hierarchical.nc").unlink()
        args = ["run", "--data", str(data), "--out", str(out), "--no-progress", *(["--no-figures"] if not a.figures else [])]
        if a.workers is not None:
            args += ["--workers", str(a.workers)]
        wall, cpu, _ = _hbm(args)
        rec = layer_record(out, data)
        rec.update(run_wall_s=wall, run_cpu_s=cpu, load=os.getloadavg())
        rows[str(n)] = rec
        _save("run", rows, merge=True)
        print(f"{n} specimens: run {wall:.0f} s wall, layer {rec['layer_cpu_s']:.1f} CPU s "
              f"({rec['layer_cpu_s'] / n:.2f} per specimen), {rec['evaluations']:,} evaluations, max R-hat "
              f"{rec['rhat_max']:.3f}, min ESS {rec['ess_bulk_min']:.0f}, covered "
              f"{sum(c['inside'] for c in rec['coverage'].values())}/{len(rec['coverage'])}", flush=True)
    return 0


def dask(a) -> int:
    out = Path(a.out_runs) / f"pop{a.size}"
    data = Path(a.data) / f"pop{a.size}"
    rows = []
    for rep in range(a.repeats):
        for w in (1, 2):
            (out / "hierarchical.nc").unlink(missing_ok=True)
            wall, cpu, _ = _hbm(["run", "--data", str(data), "--out", str(out), "--no-progress", "--no-figures",
                                 "--workers", str(w)])
            hf = io.read_hierarchical(out / "hierarchical.nc")
            shutil.copy(out / "hierarchical.nc", out / f"hierarchical_w{w}.nc")
            t = json.loads((out / "run.json").read_text())["timings"]
            rows.append({"repeat": rep, "workers": w, "run_wall_s": wall, "layer_wall_s": t.get("hierarchical"),
                         "dask": hf.attrs.get("layer", {}).get("dask"), "load": os.getloadavg()})
            print(rows[-1], flush=True)
        a1, a2 = (io.read_hierarchical(out / f"hierarchical_w{w}.nc") for w in (1, 2))
        same = (np.array_equal(a1.hyper_samples, a2.hyper_samples) and np.array_equal(a1.updated, a2.updated)
                and np.array_equal(a1.new_specimen, a2.new_specimen))
        rows[-1]["bitwise_same_as_workers_1"] = bool(same)
        print("bitwise identical:", same, flush=True)
    _save("dask", {"size": a.size, "rows": rows})
    return 0


def _stage1(sid: str, ds, model, sigma_box, cache: Path, from_run: Path | None):
    """Specimen ``sid``'s stage-1 result: the run's own when ``from_run``/specimens has it, else a TMCMC
    fit as the run makes it without CMA-ES and Sobol (they do not enter the layer), cached in ``cache``."""
    from hbm.fit import fit_specimen

    for path in ([from_run / "specimens" / f"{sid}.nc"] if from_run else []) + [cache / f"{sid}.nc"]:
        if io.is_complete(path):
            return io.read_specimen_result(path)
    k = int(sid[3:])
    fit_specimen(ds, model=model, samples=2000, seed=np.random.SeedSequence(ENTROPY, spawn_key=(10_000, k)),
                 restarts=0, sobol_n=None, sweep=None, sigma_bounds=sigma_box, progress=False, out=cache / f"{sid}.nc")
    return io.read_specimen_result(cache / f"{sid}.nc")


_LAYER = r"""
import json, sys, time
import numpy as np
sys.path.insert(0, sys.argv[1])
from pathlib import Path
from hbm.workflow.run import RunSettings
from hbm.population import run_population
from hbm.runtime.parallel import dask_client
sys.path.insert(0, str(Path(sys.argv[1]) / "workflows" / "benchmarks"))
import population_scaling as ps
n, workers, out = int(sys.argv[2]), int(sys.argv[3]), Path(sys.argv[4])
data, cache, from_run = Path(sys.argv[5]), Path(sys.argv[6]), Path(sys.argv[7]) if sys.argv[7] else None
from hbm.data import load_specimens
from hbm.model import spyrou_model
from hbm.workflow.run import _common_sigma_box
model = spyrou_model()
datasets = load_specimens(str(data))
box = _common_sigma_box(datasets)
cache.mkdir(parents=True, exist_ok=True)
results = {sid: ps._stage1(sid, datasets[sid], model, box, cache, from_run) for sid in sorted(datasets)}
extra = json.loads(sys.argv[8]) if len(sys.argv) > 8 else {}
cfg = RunSettings(data=str(data), out=str(out), progress=False, **extra).population_settings()
with dask_client(workers) as client:
    t, c = time.perf_counter(), time.process_time()
    hf, path = run_population(results, datasets, model, config=cfg, out=out, client=client)
    wall = time.perf_counter() - t
print(json.dumps({"layer_call_wall_s": wall}))
"""


def layer(a) -> int:
    """The layer alone on ``pop<size>`` with ``--workers`` (a list: each in turn; bitwise compared)."""
    data = Path(a.data) / f"pop{a.size}"
    cache = Path(a.out_runs) / "stage1"
    from_run = Path(a.from_run) if a.from_run else None
    rows, files = [], {}
    settings = {} if a.sd_range is None else {"hier_sd_range": [float(v) for v in a.sd_range.split(",")]}
    for w in map(int, str(a.workers or "2").split(",")):
        out = Path(a.out_runs) / f"layer{a.size}{a.tag}_w{w}"
        out.mkdir(parents=True, exist_ok=True)
        (out / "hierarchical.nc").unlink(missing_ok=True)
        env = {**os.environ, "PYTHONPATH": str(ROOT), "OMP_NUM_THREADS": "1"}
        t = time.perf_counter()
        p = subprocess.run([sys.executable, "-c", _LAYER, str(ROOT), str(a.size), str(w), str(out), str(data),
                            str(cache), str(from_run or ""), json.dumps(settings)], capture_output=True, text=True,
                           env=env, cwd=str(ROOT))
        if p.returncode != 0:
            raise SystemExit(f"layer failed:\n{p.stderr[-3000:]}")
        rec = layer_record(out, data, run_json=False)
        rec.update(workers=w, settings=settings, process_wall_s=time.perf_counter() - t, load=os.getloadavg(),
                   **json.loads(p.stdout.strip().splitlines()[-1]))
        files[w] = io.read_hierarchical(out / "hierarchical.nc")
        rows.append(rec)
        print(f"{a.size} specimens, {w} worker(s): layer {rec['layer_cpu_s']:.1f} CPU s ({rec['layer_cpu_s'] / a.size:.2f} "
              f"per specimen), {rec['layer_wall_s']:.0f} s wall, dask {rec['dask']}, {rec['evaluations']:,} evaluations, "
              f"max R-hat {rec['rhat_max']:.4f}, min ESS {rec['ess_bulk_min']:.0f}, covered "
              f"{sum(c['inside'] for c in rec['coverage'].values())}/{len(rec['coverage'])}", flush=True)
    if len(files) > 1:
        first = files[min(files)]
        for w, f in files.items():
            same = (np.array_equal(first.hyper_samples, f.hyper_samples) and np.array_equal(first.updated, f.updated)
                    and np.array_equal(first.new_specimen, f.new_specimen))
            for r in rows:
                if r["workers"] == w:
                    r[f"bitwise_same_as_workers_{min(files)}"] = bool(same)
            print(f"workers {w}: bitwise identical to workers {min(files)}: {same}", flush=True)
    _save("layer", {f"{a.size}{a.tag}": rows}, merge=True)
    return 0


def _save(key: str, value, merge: bool = False) -> None:
    path = OUT / "population_scaling.json"
    rec = json.loads(path.read_text()) if path.exists() else {}
    rec[key] = {**rec.get(key, {}), **value} if merge else value
    atomic_write_text(path, json.dumps(rec, indent=1, default=float))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = ap.add_subparsers(dest="cmd", required=True)
    for name in ("make", "run", "dask", "layer"):
        p = sub.add_parser(name)
        p.add_argument("--data", default=os.environ.get("HBM_POPULATION_DATA", str(SCRATCH / "data")),
                       help="the synthetic populations (default $HBM_POPULATION_DATA or <tmp>/hbm_population_scaling/data)")
        p.add_argument("--out-runs", default=os.environ.get("HBM_POPULATION_RUNS", str(SCRATCH / "runs")),
                       help="the runs (default $HBM_POPULATION_RUNS or <tmp>/hbm_population_scaling/runs)")
        p.add_argument("--sizes", default="6,24,96")
        p.add_argument("--workers", default=None, help="worker count (layer: a list, e.g. 1,2, each in turn)")
        p.add_argument("--from-run", default=None, help="layer: use the stage-1 results of this run folder where complete")
        p.add_argument("--figures", action="store_true")
        p.add_argument("--layer-only", action="store_true")
        p.add_argument("--size", type=int, default=96)
        p.add_argument("--repeats", type=int, default=2)
        p.add_argument("--sd-range", default=None, help="layer: the hyperprior's sd range as LO,HI (fractions of "
                       "mu's range; default the run's)")
        p.add_argument("--tag", default="", help="layer: suffix of the output folder and of the record's key")
    a = ap.parse_args(argv)
    return {"make": make, "run": run, "dask": dask, "layer": layer}[a.cmd](a)


if __name__ == "__main__":
    sys.exit(main())
