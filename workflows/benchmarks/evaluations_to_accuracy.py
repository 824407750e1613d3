#!/usr/bin/env python
"""Evaluations (and time) to accuracy on the muscle benchmark posterior (issue 16).

For each hbm setting and seed: likelihood evaluations (rows passed to the log-likelihood), CPU
(process) time, |log Ẑ − gold|, the worst posterior-mean error in gold sd (same seven
combinations as ``muscle_posterior.py``) and whether the run reached the accuracy target
|log Ẑ error| ≤ 0.3 and worst mean error ≤ 0.3 gold sd.  An *expensive-likelihood* column adds a
virtual clock of 1 ms per evaluated row to the measured CPU time (the cost is simulated by
counting, not by sleeping: the same model, with every batched call costing n_rows·1 ms).

The table (medians over seeds) goes to ``results/benchmarks/evaluations_to_accuracy.md`` and every
run to the ``.json`` next to it.  Peers (PyMC SMC, pocoMC, nautilus, dynesty) belong in the separate
benchmark environment (``/work/bench-venv``, subprocess only); rows measured by
``muscle_posterior.py --peers`` are quoted from ``muscle_posterior.json`` when present.

Usage (pin one core)::

    HBM_BENCH_DIR=/work/shared/bench OMP_NUM_THREADS=1 taskset -c 0 \\
        python workflows/benchmarks/evaluations_to_accuracy.py [--seeds 5] [--frugal-seeds 10]
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
for p in (str(ROOT), str(Path(__file__).resolve().parent)):
    if p not in sys.path:
        sys.path.insert(0, p)

import muscle_posterior as mp  # noqa: E402
from hbm.samplers import tmcmc  # noqa: E402
from hbm.utils import atomic_write_text  # noqa: E402

MS_PER_ROW = 1e-3
TARGET_LOGZ, TARGET_MEAN = 0.3, 0.3
# name -> (tmcmc keyword arguments, default number of seeds option)
SETTINGS = {
    "default (N=2000, RW)": ({}, "seeds"),
    "recycle only (N=1000, RW, max 30 steps)": ({"n_samples": 1000, "recycle": True, "n_islands": 8,
                                                  "max_steps": 30}, "seeds"),
    "frugal preset": ({"preset": "frugal"}, "frugal_seeds"),
    "frugal, budget 120k": ({"preset": "frugal", "max_evaluations": 120_000}, "seeds"),
}


def run(lik, gold, name, kw, seed) -> dict:
    rows = [0]

    def counted(x):
        rows[0] += len(x)
        return lik(x)

    c = time.process_time()
    r = tmcmc(counted, lik.bounds, seed=seed, progress=False, **kw)
    cpu = time.process_time() - c
    means = mp.summarise(lik.names, r.samples)
    errs = [abs(means[k] - gold["posterior_mean_and_sd"][g][0]) / gold["posterior_mean_and_sd"][g][1]
            for k, g in mp.GOLD_KEYS.items()]
    err = abs(r.log_evidence - gold["log_evidence"])
    assert rows[0] == r.n_evaluations
    return {"setting": name, "seed": seed, "evaluations": rows[0], "cpu": cpu,
            "virtual_1ms": cpu + MS_PER_ROW * rows[0], "log_evidence": r.log_evidence,
            "log_evidence_se": r.log_evidence_se, "abs_error": err, "max_mean_err_sd": max(errs),
            "covered_2se": bool(err <= 2 * r.log_evidence_se), "budget_exhausted": r.budget_exhausted,
            "reached": bool(err <= TARGET_LOGZ and max(errs) <= TARGET_MEAN), "stages": r.n_stages}


def table(rows) -> str:
    out = ["| setting | seeds | evaluations (median) | CPU s | time with 1 ms/row (virtual) s | \\|log Ẑ error\\| "
           "(median) | SE covers (2 SE) | worst mean err (gold sd, median) | runs reaching target |",
           "|---|---|---|---|---|---|---|---|---|"]
    by: dict = {}
    for r in rows:
        by.setdefault(r["setting"], []).append(r)
    for name, rs in by.items():
        med = lambda k: statistics.median(r[k] for r in rs)  # noqa: E731
        out.append(f"| {name} | {len(rs)} | {med('evaluations'):.3g} | {med('cpu'):.2f} | {med('virtual_1ms'):.1f} | "
                   f"{med('abs_error'):.2f} | {sum(r['covered_2se'] for r in rs)}/{len(rs)} | "
                   f"{med('max_mean_err_sd'):.2f} | {sum(r['reached'] for r in rs)}/{len(rs)} |")
    return "\n".join(out)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--seeds", type=int, default=5)
    ap.add_argument("--frugal-seeds", type=int, default=10)
    ap.add_argument("--settings", default=None, help=f"comma-separated subset of {list(SETTINGS)}")
    ap.add_argument("--out", default=str(ROOT / "results" / "benchmarks"))
    args = ap.parse_args(argv)
    names = list(SETTINGS) if args.settings is None else [s.strip() for s in args.settings.split(",")]
    lik, gold, kind = mp.make_problem()
    rows = []
    for name in names:
        kw, which = SETTINGS[name]
        for seed in range(getattr(args, which)):
            r = run(lik, gold, name, kw, seed)
            rows.append(r)
            print(f"{name} seed {seed}: {r['evaluations']} evals, {r['cpu']:.2f} s CPU, error "
                  f"{r['abs_error']:.2f} (SE {r['log_evidence_se']:.2f}), worst mean {r['max_mean_err_sd']:.2f} sd",
                  file=sys.stderr, flush=True)
    peers = []
    pj = Path(args.out) / "muscle_posterior.json"
    if pj.exists():
        for r in json.loads(pj.read_text()):
            if str(r.get("config", "")).startswith("PyMC"):
                peers.append({"setting": r["config"] + " (from muscle_posterior.json)", "seed": r["seed"],
                              "evaluations": r["evaluations"], "cpu": r["cpu"],
                              "virtual_1ms": r["cpu"] + MS_PER_ROW * r["evaluations"],
                              "log_evidence": r["log_evidence"], "log_evidence_se": float("nan"),
                              "abs_error": r["abs_error"], "max_mean_err_sd": r["max_mean_err_sd"],
                              "covered_2se": False, "budget_exhausted": False,
                              "reached": bool(r["abs_error"] <= TARGET_LOGZ and r["max_mean_err_sd"] <= TARGET_MEAN)})
    stamp = time.strftime("%Y-%m-%d %H:%M", time.gmtime())
    md = ["# Evaluations to accuracy on the muscle benchmark posterior (issue 16)", "",
          f"Likelihood: {kind}; gold log Z = {gold['log_evidence']}. Measured {stamp} UTC on a shared 2-core "
          "machine (CPU = process time). Target: |log Ẑ error| ≤ 0.3 and worst posterior-mean error ≤ 0.3 gold sd. "
          "'time with 1 ms/row' = CPU + 1 ms × evaluations, a virtual clock (the expensive likelihood is "
          "simulated by counting rows, not by sleeping).", "", table(rows + peers), "",
          "Peers: pocoMC, nautilus and dynesty were NOT run in this round (time cap of the session); the PyMC "
          "rows are quoted from muscle_posterior.json (measured earlier, same machine, CPU time of sample_smc)."]
    text = "\n".join(md) + "\n"
    print(text)
    atomic_write_text(Path(args.out) / "evaluations_to_accuracy.md", text)
    atomic_write_text(Path(args.out) / "evaluations_to_accuracy.json", json.dumps(rows + peers, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
