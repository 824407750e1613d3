"""CPU time of one joint-likelihood call across loading modes, before/after the compiled diagonal path.

Problem (issue 35, item 2; brief of the ``fast3d`` branch): the porcine compression data along and across the
fibres (``../shared/realdata/wang2023_porcine_compression_rates_{along,across}.csv``, the across file as
``uniaxial_c``; folder ``HBM_REALDATA``, default ``../shared/realdata`` next to the repository), 300 points,
fitted jointly with ``--form energy``: what does one likelihood call of a 200-particle population cost?

Variants, each in its own worker process, timed interleaved (every variant sees the same machine load):

* ``before``: the code of ``--baseline-ref`` (default ``c4a247a``, main before the compiled path), extracted
  with ``git archive`` into a temporary folder and put first on the worker's ``PYTHONPATH``;
* ``isotropic``: this tree, compiled path, each lateral root started at the isotropic λ^-1/2 as before
  (the numpy solver's iterates);
* ``after``: this tree as shipped (the compiled root warm-started along each particle's strain path).

Per variant and collagen reading: CPU seconds (``time.process_time`` of the worker) per likelihood call,
median over ``--repeat`` rounds × ``--seeds`` populations (each a uniform draw from the likelihood's prior
box, ``numpy.random.default_rng(seed)``); the energy evaluations per (particle · point) of the
``uniaxial_c`` tests (elements passed to the numpy solver's evaluations; the compiled solver's count);
the agreement of every variant with ``before``: the largest relative difference of the predicted series
(stresses; relative to each value) and of the log-likelihood; and the largest traction-free residual
|τ_ff − τ_nn| / |σ_cc| at the lateral roots each variant returns, evaluated by the numpy energy (the
solvers stop at 1e-12 of the load, or when the Newton step is below 4ε·(1 + |u|)).  Wall seconds are recorded
too; on a shared machine they are not comparable (CPU is).

usage::

    OMP_NUM_THREADS=1 python workflows/benchmarks/modes_throughput.py [--seeds 10] [--repeat 3]
        [--baseline-ref c4a247a] [--out results/benchmarks]
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1].parent
DATA = Path(os.environ.get("HBM_REALDATA", ROOT.parent / "shared" / "realdata"))
FILES = ("wang2023_porcine_compression_rates_along.csv", "wang2023_porcine_compression_rates_across.csv:uniaxial_c")
VARIANTS = ("before", "isotropic", "after")
READINGS = ("cone", "gst")
PARTICLES = 200


# -- the worker (one variant, one reading) ----------------------------------------------------------------
def worker(variant: str, reading: str, seeds: list[int]) -> None:
    """Serve ``run SEED`` (one timed call) and ``dump PATH`` on stdin; reply one JSON line each."""
    import functools

    from hbm.cli._common import load_specimens_arg
    from hbm.likelihood.modes import make_modes_likelihood
    from hbm.model import spyrou_model
    from hbm.model.loadcases import uniaxial_c as uc

    count = {"elements": 0}
    if hasattr(uc, "_lateral_root_compiled"):
        solver = functools.partial(uc._lateral_root_compiled, warm=variant == "after")

        def counted(*a, **k):
            u, sigma, evaluations = solver(*a, **k)
            count["elements"] += int(evaluations.sum())
            return u, sigma, evaluations
        uc._lateral_root_compiled = counted
    else:
        evaluate = uc._evaluate

        def counted(energy, p, u, ec, tangent):
            count["elements"] += int(np.size(u))
            return evaluate(energy, p, u, ec, tangent)
        uc._evaluate = counted
    spec = load_specimens_arg([str(DATA / f) for f in FILES])      # FILE:MODE as on the command line
    lik = make_modes_likelihood(spyrou_model(form="energy"), spec, collagen3d=reading)
    n_c = sum(np.size(spec.strain[t.rows]) for t in spec.tests if lik.cases[t.id].name == "uniaxial_c")
    lo, hi = lik.bounds.T
    pops = {s: lo + (hi - lo) * np.random.default_rng(s).random((PARTICLES, lik.d)) for s in seeds}
    for th in pops.values():
        lik(th)                                  # compile / warm caches
    print(json.dumps({"ready": True, "n_points": int(lik.n_points), "n_uniaxial_c": int(n_c)}), flush=True)
    for line in sys.stdin:
        cmd, arg = line.split()
        if cmd == "run":
            th = pops[int(arg)]
            count["elements"] = 0
            w0, c0 = time.perf_counter(), time.process_time()
            lik(th)
            c1, w1 = time.process_time(), time.perf_counter()
            print(json.dumps({"cpu": c1 - c0, "wall": w1 - w0, "elements": count["elements"]}), flush=True)
        elif cmd == "dump":
            out = {}
            for s, th in pops.items():
                out[f"loglik_{s}"] = lik(th)
                for i, m in enumerate(lik.predict_series(th)):
                    out[f"series_{s}_{i}"] = m
                out[f"residual_{s}"] = np.array([root_residual(lik, th)])
            np.savez(arg, **out)
            print(json.dumps({"dumped": arg}), flush=True)


def root_residual(lik, th) -> float:
    """Largest |τ_ff − τ_nn| / |σ_cc| at the uniaxial_c roots the variant returns, by the numpy energy (the
    traction-free condition the solver stops on at 1e-12; σ_cc = 0 at zero strain is left out)."""
    p = lik.model._params(lik.model_theta(th))
    principal = getattr(lik.energy, "principal_numpy", lik.energy.principal)
    worst = 0.0
    for t in lik.data.tests:
        if lik.cases[t.id].name != "uniaxial_c":
            continue
        strain = lik.data.strain[t.rows]
        with np.errstate(all="ignore"):
            got = lik.cases[t.id].solve(lik.energy, p, strain)
            u, ec = np.log1p(got["strain_f"]), np.log1p(strain)
            tau, _ = principal(p, (u, ec + 0 * u, -u - ec))
            rel = np.abs(tau[0] - tau[2]) / np.abs(tau[1] - 0.5 * (tau[0] + tau[2]))
        worst = max(worst, float(np.nanmax(np.where(strain != 0, rel, 0.0))))
    return worst


# -- the parent ----------------------------------------------------------------------------------------------
class Worker:
    def __init__(self, variant: str, reading: str, pythonpath: Path, seeds: list[int]) -> None:
        env = dict(os.environ, PYTHONPATH=str(pythonpath), OMP_NUM_THREADS="1", OPENBLAS_NUM_THREADS="1",
                   MKL_NUM_THREADS="1")
        self.proc = subprocess.Popen([sys.executable, str(Path(__file__).resolve()), "--worker", variant, reading,
                                      "--seeds", str(len(seeds))], env=env, stdin=subprocess.PIPE,
                                     stdout=subprocess.PIPE, text=True, cwd=str(ROOT))
        self.info = self.ask(None)

    def ask(self, line: str | None) -> dict:
        if line is not None:
            self.proc.stdin.write(line + "\n")
            self.proc.stdin.flush()
        reply = self.proc.stdout.readline()
        if not reply:
            raise RuntimeError("worker ended early (see its stderr above)")
        return json.loads(reply)

    def close(self) -> None:
        self.proc.stdin.close()
        self.proc.wait()


def baseline_tree(ref: str, dest: Path) -> str:
    """``hbm/`` of ``ref`` extracted into ``dest`` (no checkout, the repository is untouched); its full hash."""
    full = subprocess.run(["git", "rev-parse", ref], cwd=ROOT, capture_output=True, text=True,
                          check=True).stdout.strip()
    archive = subprocess.run(["git", "archive", full, "hbm"], cwd=ROOT, capture_output=True, check=True).stdout
    subprocess.run(["tar", "-x", "-C", str(dest)], input=archive, check=True)
    return full


def agreement(a: dict, b: dict) -> dict:
    """Largest relative difference of the series (per value, where the reference is not 0) and the loglik."""
    series = loglik = 0.0
    for k in b:
        x, y = a[k], b[k]
        ok = np.isfinite(y) & (y != 0)
        d = float(np.max(np.abs(x - y)[ok] / np.abs(y)[ok])) if ok.any() else 0.0
        if k.startswith("residual"):
            continue
        if k.startswith("loglik"):
            loglik = max(loglik, d)
        else:
            series = max(series, d)
    return {"series_rel": series, "loglik_rel": loglik}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--seeds", type=int, default=10)
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--baseline-ref", default="c4a247a")
    ap.add_argument("--out", type=Path, default=ROOT / "results" / "benchmarks")
    ap.add_argument("--worker", nargs=2, metavar=("VARIANT", "READING"), help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    seeds = list(range(args.seeds))
    if args.worker:
        worker(*args.worker, seeds)
        return 0
    head = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=ROOT, capture_output=True,
                          text=True).stdout.strip()
    with tempfile.TemporaryDirectory() as tmp:
        base = baseline_tree(args.baseline_ref, Path(tmp))
        t0 = time.time()
        workers = {(v, r): Worker(v, r, Path(tmp) if v == "before" else ROOT, seeds)
                   for r in READINGS for v in VARIANTS}
        runs = {k: [] for k in workers}
        for rep in range(args.repeat):                    # interleaved: every variant sees the same load
            for s in seeds:
                for k, w in workers.items():
                    runs[k].append(w.ask(f"run {s}"))
            print(f"round {rep + 1}/{args.repeat} done ({time.time() - t0:.0f} s)", file=sys.stderr)
        dumps = {}
        for k, w in workers.items():
            path = Path(tmp) / f"{k[0]}_{k[1]}.npz"
            w.ask(f"dump {path}")
            with np.load(path) as z:
                dumps[k] = {n: z[n] for n in z.files}
            info = w.info
            w.close()
    rows = []
    for r in READINGS:
        before = float(np.median([x["cpu"] for x in runs[("before", r)]]))
        for v in VARIANTS:
            xs = runs[(v, r)]
            cpu = float(np.median([x["cpu"] for x in xs]))
            rows.append({"reading": r, "variant": v, "cpu_s_median": cpu,
                         "cpu_s_quartiles": [float(q) for q in np.quantile([x["cpu"] for x in xs], [0.25, 0.75])],
                         "wall_s_median": float(np.median([x["wall"] for x in xs])), "speedup_cpu": before / cpu,
                         "evals_per_particle_point_uniaxial_c": float(np.median([x["elements"] for x in xs]))
                         / (PARTICLES * info["n_uniaxial_c"]),
                         "root_residual_rel": max(float(x[0]) for k, x in dumps[(v, r)].items()
                                                  if k.startswith("residual")),
                         **agreement(dumps[(v, r)], dumps[("before", r)])})
    meta = {"head": head, "baseline": base, "particles": PARTICLES, "seeds": args.seeds, "repeat": args.repeat,
            "n_points": info["n_points"], "n_uniaxial_c": info["n_uniaxial_c"], "python": sys.version.split()[0],
            "load_1min_at_end": os.getloadavg()[0], "cpus": os.cpu_count()}
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "modes_throughput.json").write_text(json.dumps({"meta": meta, "rows": rows}, indent=1) + "\n")
    lines = [f"# Joint likelihood across modes: CPU per call of {PARTICLES} particles (porcine along + across)",
             "",
             f"`workflows/benchmarks/modes_throughput.py`, HEAD {head} vs `before` = {base[:10]}; "
             f"{meta['n_points']} points ({meta['n_uniaxial_c']} uniaxial_c); {args.seeds} populations × "
             f"{args.repeat} rounds, interleaved, one worker process per variant; load average at the end "
             f"{meta['load_1min_at_end']:.1f} on {meta['cpus']} CPUs (wall times under that load).",
             "",
             "| reading | variant | CPU s / call (median) | IQR | speed-up (CPU) | wall s (median) | "
             "energy evals / (particle·point), uniaxial_c | max rel. diff. series vs before | "
             "max rel. diff. loglik | max \\|τ_ff − τ_nn\\| / \\|σ_cc\\| at the roots |",
             "|---|---|---|---|---|---|---|---|---|---|"]
    for x in rows:
        q = x["cpu_s_quartiles"]
        lines.append(f"| {x['reading']} | {x['variant']} | {x['cpu_s_median']:.4f} | {q[0]:.4f}–{q[1]:.4f} | "
                     f"{x['speedup_cpu']:.1f}× | {x['wall_s_median']:.4f} | "
                     f"{x['evals_per_particle_point_uniaxial_c']:.2f} | {x['series_rel']:.1e} | "
                     f"{x['loglik_rel']:.1e} | {x['root_residual_rel']:.1e} |")
    lines += ["",
              "`before` and `isotropic` run the same Newton iterates (isotropic start), so they differ by round-off; "
              "both stop at |τ_ff − τ_nn| ≤ 1e-12·|σ_cc| or when the Newton step is below 4ε·(1 + |u|), which at "
              "small strains (|u| ≪ 1) stops first and leaves the residual in the last column.  `after` starts from "
              "the previous point's root and returns the Newton step past the stop (the exact root to round-off), "
              "so its difference from `before` is `before`'s own stopping error.  Energy evaluations are counted "
              "over all uniaxial_c points; the compiled solver solves each distinct strain of a test once."]
    text = "\n".join(lines) + "\n"
    (args.out / "modes_throughput.md").write_text(text)
    print(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
