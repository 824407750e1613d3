"""Dense records at the cost of their information (issue 36): the detective on an 8000-reading record,
reduced and at full resolution, interleaved with the code before the change; and the reduced record's
posterior against the full record's over seeds.

Records: a ramp to ε = 0.3 at 1 %/s (2000 readings) and a 120 s hold (6000 readings) -- a 50 Hz machine
export -- from the base model with two relaxation times in parallel (``viscoelastic`` with ``terms=2``:
g 0.2 at τ 2 s, g 0.25 at τ 32 s) or one (g 0.3 at τ 6.3 s), iid noise of 1 % of the peak per reading.

``diagnose`` runs as ``hbm diagnose FILE --json`` in a fresh process per run; CPU is the process's and
its workers' (``RUSAGE_CHILDREN``), wall is the command's.  Runs alternate between the trees (the order
flips every seed) so both see the same machine load.

Run from the repository root (``--before``: a checkout of the code to compare with, e.g. a worktree of
the commit before the change; ``HBM_BEFORE`` is read when the option is not given)::

    PYTHONPATH=. python workflows/benchmarks/dense_records.py --seeds 1 2 3 --before ../before --full 1 \\
        --out results/benchmarks/dense_records.md
    PYTHONPATH=. python workflows/benchmarks/dense_records.py --posterior 10 --out results/benchmarks/dense_posterior.md
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[2]
THETA = dict(VOLF=0.8, EOPT=0.05, P1=0.15, T1=0.5, T2=12.0, THETA=57.0, GF=0.02, GM=0.01)


def record(n: int, seed: int, terms: int, rel: float = 0.01):
    """The synthetic machine record (module docstring)."""
    from hbm.data import hold, protocol, ramp, synthetic_specimen
    from hbm.effects import make_effect
    from hbm.model.spyrou import spyrou_model
    model = spyrou_model() + make_effect("viscoelastic", terms=terms)
    th = dict(THETA, **({"G1": 0.2, "LOGTAU1": 0.3, "G2": 0.25, "LOGTAU2": 1.5} if terms == 2 else
                        {"G1": 0.3, "LOGTAU1": 0.8}))
    prot = protocol([ramp(0.3, 0.01, n // 4), hold(120.0, n - n // 4)])
    return synthetic_specimen(model, th, prot, rel, seed=seed, relative=True)


def diagnose(tree: Path, path: Path, extra: list[str], max_time: float) -> dict:
    """One ``hbm diagnose --json`` with the package at ``tree``: verdict, named effects, CPU and wall."""
    env = dict(os.environ, PYTHONPATH=str(tree), OMP_NUM_THREADS="1")
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    t0 = time.perf_counter()
    # (run in the tree: ``python -m`` puts the working folder first on the path, before PYTHONPATH)
    proc = subprocess.run([sys.executable, "-m", "hbm", "diagnose", str(path), "--json", "--no-progress",
                           "--max-time", str(max_time), *extra], capture_output=True, text=True, env=env, cwd=tree)
    wall = time.perf_counter() - t0
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    cpu = (after.ru_utime + after.ru_stime) - (before.ru_utime + before.ru_stime)
    try:
        out = json.loads(proc.stdout)
    except ValueError:
        return {"error": proc.stderr.strip().splitlines()[-1:] or ["no output"], "cpu": cpu, "wall": wall}
    return {"verdict": out["verdict"], "selected": out["selected"], "message": out["message"][:400],
            "stopped": bool(out.get("stopped")), "input": out.get("input", ""), "cpu": round(cpu, 1),
            "wall": round(wall, 1)}


def posterior(seeds: int) -> list[dict]:
    """The reduced against the full record's posterior (optimum and curvature), per seed."""
    sys.path.insert(0, str(ROOT / "tests"))
    from test_dense_records import THETA as T, _laplace, _record   # the test's own record and Laplace fit
    from hbm.data.reduction import reduce_record
    from hbm.likelihood import make_likelihood
    rows = []
    for seed in range(seeds):
        model, ds = _record(3000, seed=seed)
        fix = {n: v for n, v in T.items() if n not in ("T1", "GM", "G1", "LOGTAU1")}
        full, red = make_likelihood(model, ds, fix=fix), make_likelihood(model, reduce_record(ds), fix=fix)
        x0 = np.array([T.get(n, float(ds.attrs["noise_sd"])) for n in full.names])
        t = time.process_time()
        xf, sf = _laplace(full, x0)
        t_full = time.process_time() - t
        t = time.process_time()
        xr, sr = _laplace(red, x0)
        t_red = time.process_time() - t
        k = full.n_model
        rows.append({"seed": seed, "points": [ds.n_points, int(red.n_points)],
                     "shift_sd": dict(zip(full.names[:k], np.round((xr - xf)[:k] / sf[:k], 3).tolist())),
                     "sd_ratio": dict(zip(full.names[:k], np.round(sr[:k] / sf[:k], 3).tolist())),
                     "sigma_ratio": round(float(xr[k] / xf[k]), 3), "cpu": [round(t_full, 1), round(t_red, 1)]})
        print(rows[-1], flush=True)
    return rows


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, nargs="*", default=[1])
    ap.add_argument("--before", default=os.environ.get("HBM_BEFORE"), help="checkout of the code to compare with")
    ap.add_argument("--full", type=int, nargs="*", default=[], help="seeds also diagnosed at full resolution")
    ap.add_argument("--only-full", action="store_true", help="only the full-resolution runs (a separate job)")
    ap.add_argument("--max-time", type=float, default=300.0, help="--max-time of this code's runs")
    ap.add_argument("--before-max-time", type=float, default=300.0,
                    help="--max-time of the --before runs (default: its command's default)")
    ap.add_argument("--full-max-time", type=float, default=36000.0)
    ap.add_argument("--posterior", type=int, default=0, help="seeds of the posterior comparison (0: skip)")
    ap.add_argument("--out", default=None)
    ap.add_argument("--resume", action="store_true", help="keep the runs already in the --out JSON, run the rest")
    args = ap.parse_args(argv)
    out: dict = {"runs": [], "posterior": []}
    if args.resume and args.out and Path(args.out).with_suffix(".json").exists():
        out = json.loads(Path(args.out).with_suffix(".json").read_text())
    done = {(r["seed"], r["relaxation_times"], r["code"]) for r in out["runs"]}
    if args.posterior:
        out["posterior"] = posterior(args.posterior)
    work = Path(tempfile.mkdtemp(prefix="hbm-dense-"))
    from hbm.data import save_specimen
    for k, seed in enumerate(args.seeds):
        for terms in (2, 1):
            path = save_specimen(record(8000, seed, terms), work / f"dense_{terms}_{seed}.csv")
            trees = [("after", ROOT, [])] + ([("before", Path(args.before), [])] if args.before and terms == 2 else [])
            if k % 2:
                trees.reverse()
            if args.only_full:
                trees = []
            if seed in args.full and terms == 2:
                trees.append(("after, full resolution", ROOT, ["--reduce", "off"]))
            for label, tree, extra in trees:
                if (seed, terms, label) in done:
                    continue
                mt = args.full_max_time if extra else args.before_max_time if label == "before" else args.max_time
                r = {"seed": seed, "relaxation_times": terms, "code": label, **diagnose(tree, path, extra, mt)}
                out["runs"].append(r)
                print(json.dumps(r), flush=True)
                if args.out:
                    Path(args.out).with_suffix(".json").write_text(json.dumps(out, indent=1))
    if args.out:
        Path(args.out).write_text(report(out, args))
    return 0


def report(out: dict, args) -> str:
    lines = ["# Dense records: the detective on 8000 readings, reduced and at full resolution", "",
             f"`workflows/benchmarks/dense_records.py` (seeds {args.seeds}, full resolution for {args.full}, "
             f"--max-time {args.max_time:g} s, before: {args.before_max_time:g} s); CPU includes the refit workers; "
             "wall times were taken on a shared, loaded machine.", ""]
    if out["runs"]:
        lines += ["| seed | relaxation times | code | verdict | named | stopped at --max-time | CPU s | wall s |",
                  "|---|---|---|---|---|---|---|---|"]
        lines += [f"| {r['seed']} | {r['relaxation_times']} | {r['code']} | {r.get('verdict', r.get('error'))} | "
                  f"{', '.join(r.get('selected') or [])} | {'yes' if r.get('stopped') else 'no'} | {r['cpu']} | "
                  f"{r['wall']} |" for r in out["runs"]]
    if out["posterior"]:
        p = out["posterior"]
        shifts = np.array([list(r["shift_sd"].values()) for r in p])
        ratios = np.array([list(r["sd_ratio"].values()) for r in p])
        lines += ["", f"Reduced against full record (3000 readings, {len(p)} seeds; optimum shift in posterior sd and "
                  "sd ratio per model parameter):", "",
                  f"- |shift|: mean {np.mean(np.abs(shifts)):.3f}, max {np.max(np.abs(shifts)):.3f}",
                  f"- sd ratio: mean {np.mean(ratios):.3f}, range {np.min(ratios):.3f}-{np.max(ratios):.3f} "
                  "(the same for every parameter within a seed: the noise sd each estimates, from the bin means "
                  "or from every reading)",
                  f"- CPU of the optimum + curvature: full {np.mean([r['cpu'][0] for r in p]):.1f} s, reduced "
                  f"{np.mean([r['cpu'][1] for r in p]):.1f} s"]
    return "\n".join(lines) + "\n"


if __name__ == "__main__":
    raise SystemExit(main())
