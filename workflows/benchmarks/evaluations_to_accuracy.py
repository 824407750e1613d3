#!/usr/bin/env python
"""Evaluations (and time) to accuracy on the muscle benchmark posterior (issue 16), hbm and peers.

For each setting and seed: likelihood evaluations (rows passed to the log-likelihood), CPU
(process) time, |log Ẑ − gold|, the worst posterior-mean error in gold sd (same seven
combinations as ``muscle_posterior.py``) and whether the run reached the accuracy target
|log Ẑ error| ≤ 0.3 and worst mean error ≤ 0.3 gold sd.  An *expensive-likelihood* column adds a
virtual clock of 1 ms per evaluated row to the measured CPU time (the cost is simulated by
counting, not by sleeping: the same model, with every batched call costing n_rows·1 ms).  A
setting's *time to accuracy* is its median virtual time when ≥ 90 % of its runs reach the
target, else "not reached".

Peers (``--peers``) run in the same invocation, one subprocess per run, in the separate benchmark
environment (``$HBM_PEER_PYTHON``, else the nearest ``bench-venv/bin/python`` above this
repository): pocoMC, nautilus and dynesty through ``evidence_peers.py`` and PyMC SMC through
``pymc_peer.py`` (neither imports hbm; their likelihoods are checked against hbm's first).

The table (medians over seeds) goes to ``results/benchmarks/evaluations_to_accuracy.md`` and every
run to the ``.json`` next to it.

Usage (pin one core)::

    HBM_BENCH_DIR=/work/shared/bench OMP_NUM_THREADS=1 taskset -c 0 \\
        python workflows/benchmarks/evaluations_to_accuracy.py [--seeds 5] [--preset-seeds 10] [--peers]
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[2]
HERE = Path(__file__).resolve().parent
for p in (str(ROOT), str(HERE)):
    if p not in sys.path:
        sys.path.insert(0, p)

import muscle_posterior as mp  # noqa: E402
from hbm.samplers import tmcmc  # noqa: E402
from hbm.utils import atomic_write_text  # noqa: E402

MS_PER_ROW = 1e-3
TARGET_LOGZ, TARGET_MEAN = 0.3, 0.3
REACH_SHARE = 0.9  # share of runs that must reach the target for a "time to accuracy"
# name -> (tmcmc keyword arguments, which seed-count option)
SETTINGS = {
    "default (N=2000, RW)": ({}, "seeds"),
    "frugal preset (N=1000, mixture moves, ≤30 steps)": ({"preset": "frugal"}, "seeds"),
    "frugal, budget 120k": ({"preset": "frugal", "max_evaluations": 120_000}, "seeds"),
}
# name -> (script, arguments after "run --bench DIR", timeout s); peers' own accuracy knobs at
# their defaults (pocoMC n_effective 512, nautilus n_live 2000, dynesty nlive 500) and one larger
PEERS = {
    "pocoMC n_effective=512": ("evidence_peers.py", ["--peer", "pocomc", "--size", "512"], 900),
    "pocoMC n_effective=2048": ("evidence_peers.py", ["--peer", "pocomc", "--size", "2048"], 900),
    "nautilus n_live=2000 (stopped at 240 s)": ("evidence_peers.py", ["--peer", "nautilus", "--size", "2000",
                                                                      "--timeout", "240"], 600),
    "dynesty nlive=500": ("evidence_peers.py", ["--peer", "dynesty", "--size", "500"], 900),
    "PyMC SMC IMH N=2000": ("pymc_peer.py", ["--n", "2000"], 900),
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
    assert rows[0] == r.n_evaluations
    return _row(name, seed, rows[0], cpu, r.log_evidence, r.log_evidence_se, max(errs), gold,
                budget_exhausted=r.budget_exhausted, stages=r.n_stages)


def _row(name, seed, evaluations, cpu, log_z, se, worst, gold, **extra) -> dict:
    err = abs(log_z - gold["log_evidence"])
    return {"setting": name, "seed": seed, "evaluations": int(evaluations), "cpu": cpu,
            "virtual_1ms": cpu + MS_PER_ROW * evaluations, "log_evidence": log_z, "log_evidence_se": se,
            "abs_error": err, "max_mean_err_sd": worst,
            "covered_2se": bool(np.isfinite(se) and err <= 2 * se),
            "reached": bool(err <= TARGET_LOGZ and worst <= TARGET_MEAN), **extra}


# ------------------------------------------------------------------------------- peers
def peer_python() -> Path:
    """$HBM_PEER_PYTHON, else the nearest ``bench-venv/bin/python`` in a parent folder."""
    env = os.environ.get("HBM_PEER_PYTHON")
    if env:
        return Path(env)
    for parent in ROOT.parents:
        cand = parent / "bench-venv" / "bin" / "python"
        if cand.exists():
            return cand
    return ROOT.parent / "bench-venv" / "bin" / "python"


def _peer_call(py: Path, script: str, args: list[str], timeout: float) -> dict:
    env = {**os.environ, "OMP_NUM_THREADS": "1", "OPENBLAS_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}
    p = subprocess.run([str(py), str(HERE / script), *args], capture_output=True, text=True, timeout=timeout, env=env)
    lines = p.stdout.strip().splitlines()
    if p.returncode != 0 or not lines:
        tail = p.stderr.strip().splitlines()[-1:] or ["no output"]
        raise RuntimeError(f"{script} {args[0]} failed (exit {p.returncode}): {tail[0][:300]}")
    return json.loads(lines[-1])


def check_peer_likelihood(py: Path, lik, gold) -> float:
    """Largest |Δ log-likelihood| between evidence_peers.py's numpy model and hbm at 16 prior draws."""
    rng = np.random.default_rng(0)
    b = np.asarray(lik.bounds, float)
    theta = b[:, 0] + rng.random((16, len(b))) * (b[:, 1] - b[:, 0])
    with tempfile.TemporaryDirectory() as tmp:
        f = Path(tmp) / "theta.json"
        f.write_text(json.dumps([dict(zip(lik.names, map(float, row))) for row in theta]))
        out = _peer_call(py, "evidence_peers.py", ["check", "--bench", str(mp.BENCH), "--theta", str(f)], 120)
    return float(np.max(np.abs(np.asarray(out["log_likelihood"]) - lik(theta))))


def run_peers(lik, gold, names, seeds, n_jobs: int = 2) -> tuple[list[dict], list[str]]:
    py = peer_python()
    if not py.exists():
        return [], [f"peers skipped: bench environment python {py} is missing"]
    diff = check_peer_likelihood(py, lik, gold)
    notes = [f"peer likelihood (numpy, evidence_peers.py) vs hbm at 16 prior draws: max |Δ log L| = {diff:.1e}"]
    if not diff <= 1e-8:
        return [], notes + ["peers not run: their likelihood disagrees with hbm's"]
    if any(PEERS[name][0] == "pymc_peer.py" for name in names):
        # warm-up: the first sample_smc compiles the logp functions (in child processes that
        # process_time does not see); pytensor caches them, so the timed runs measure sampling
        try:
            _peer_call(py, "pymc_peer.py", ["run", "--bench", str(mp.BENCH), "--n", "100", "--seed", "999"], 600)
        except Exception as e:  # noqa: BLE001
            notes.append(f"PyMC warm-up failed: {e}")
    jobs = [(name, seed) for name in names for seed in seeds]

    def one(job):
        name, seed = job
        script, args, timeout = PEERS[name]
        try:
            return _peer_call(py, script, ["run", "--bench", str(mp.BENCH), *args, "--seed", str(seed)], timeout)
        except subprocess.TimeoutExpired:
            return RuntimeError(f"did not finish within {timeout} s wall time (stopped)")
        except Exception as e:  # noqa: BLE001 - a failing peer is reported, not fatal
            return e

    rows = []
    # peers are separate processes: run `n_jobs` at once so a round fits its time slot (CPU time
    # is process time, so the overlap does not change the measured numbers)
    with ThreadPoolExecutor(max_workers=n_jobs) as pool:
        for (name, seed), r in zip(jobs, pool.map(one, jobs)):
            if isinstance(r, Exception):
                notes.append(f"{name} seed {seed}: {str(r)[:300]}")
                continue
            label = f"{name} ({r.get('peer', 'pymc')} {r.get('version', r.get('pymc', '?'))})"
            row = _row(label, seed, r["evaluations"], r["cpu"], r["log_evidence"],
                       r.get("log_evidence_se", float("nan")), r["max_mean_err_sd"], gold, wall=r["wall"])
            rows.append(row)
            _say(row)
    return rows, notes


# ------------------------------------------------------------------------------- report
def _say(r: dict) -> None:
    print(f"{r['setting']} seed {r['seed']}: {r['evaluations']} evals, {r['cpu']:.2f} s CPU, error "
          f"{r['abs_error']:.2f} (SE {r['log_evidence_se']:.2f}), worst mean {r['max_mean_err_sd']:.2f} sd",
          file=sys.stderr, flush=True)


def table(rows) -> str:
    out = ["| setting | seeds | evaluations (median) | CPU s | time with 1 ms/row (virtual) s | \\|log Ẑ error\\| "
           "(median) | SE covers (2 SE) | worst mean err (gold sd, median) | runs reaching target | "
           "time to accuracy (1 ms/row) |",
           "|---|---|---|---|---|---|---|---|---|---|"]
    by: dict = {}
    for r in rows:
        by.setdefault(r["setting"], []).append(r)
    for name, rs in by.items():
        med = lambda k: statistics.median(r[k] for r in rs)  # noqa: E731
        reached = sum(r["reached"] for r in rs)
        tta = f"{med('virtual_1ms'):.0f} s" if reached >= REACH_SHARE * len(rs) else "not reached"
        out.append(f"| {name} | {len(rs)} | {med('evaluations'):.3g} | {med('cpu'):.2f} | {med('virtual_1ms'):.1f} | "
                   f"{med('abs_error'):.2f} | {sum(r['covered_2se'] for r in rs)}/{len(rs)} | "
                   f"{med('max_mean_err_sd'):.2f} | {reached}/{len(rs)} | {tta} |")
    return "\n".join(out)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--seeds", type=int, default=5, help="seeds of every hbm setting")
    ap.add_argument("--settings", default=None, help=f"comma-separated subset of {list(SETTINGS)}")
    ap.add_argument("--peers", default=None, help=f"comma-separated subset of {list(PEERS)}, or 'all'")
    ap.add_argument("--peer-seeds", type=int, default=2)
    ap.add_argument("--peer-jobs", type=int, default=2, help="peer processes at once")
    ap.add_argument("--out", default=str(ROOT / "results" / "benchmarks"))
    args = ap.parse_args(argv)
    names = list(SETTINGS) if args.settings is None else [s.strip() for s in args.settings.split(",")]
    lik, gold, kind = mp.make_problem()
    rows, notes = [], []
    for name in names:
        kw, _ = SETTINGS[name]
        for seed in range(args.seeds):
            rows.append(run(lik, gold, name, kw, seed))
            _say(rows[-1])
    if args.peers:
        peer_names = list(PEERS) if args.peers == "all" else [s.strip() for s in args.peers.split(",")]
        prow, notes = run_peers(lik, gold, peer_names, list(range(args.peer_seeds)), args.peer_jobs)
        rows += prow
    stamp = time.strftime("%Y-%m-%d %H:%M", time.gmtime())
    load = os.getloadavg()[0]
    md = ["# Evaluations to accuracy on the muscle benchmark posterior (issue 16)", "",
          f"Likelihood: {kind}; gold log Z = {gold['log_evidence']}. Measured {stamp} UTC on a shared 2-core "
          f"machine (1-min load {load:.1f} at the end; CPU = process time, robust to the load). Target: |log Ẑ error| "
          "≤ 0.3 and worst posterior-mean error ≤ 0.3 gold sd. 'time with 1 ms/row' = CPU + 1 ms × evaluations, a "
          "virtual clock (the expensive likelihood is simulated by counting rows, not by sleeping). 'time to "
          f"accuracy' = median virtual time when ≥ {REACH_SHARE:.0%} of the runs reach the target.", "",
          table(rows), ""] + [f"- {n}" for n in notes]
    text = "\n".join(md) + "\n"
    print(text)
    atomic_write_text(Path(args.out) / "evaluations_to_accuracy.md", text)
    atomic_write_text(Path(args.out) / "evaluations_to_accuracy.json", json.dumps(rows, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
