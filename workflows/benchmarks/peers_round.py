#!/usr/bin/env python
"""hbm against the evidence peers on the muscle benchmark, in one round (issue 27's last done-when item).

One process runs everything, one run at a time (the machine is shared): hbm's settings in-process —
the collapsed tier (TMCMC over φ = VOLF, EOPT, T2, THETA, sigma with the three amplitudes integrated
out, and the N = 500 pilot + importance-sampling finish, exactly as ``collapsed_posterior.py``) and the
full-space default TMCMC as the baseline — and the peers as subprocesses of the separate benchmark
environment (``$HBM_PEER_PYTHON``, else ``../venv-bench/bin/python`` next to the repository): pocoMC, nautilus and dynesty
through ``evidence_peers.py`` and PyMC SMC through ``pymc_peer.py``.  The peers see the full
9-parameter problem: they cannot use hbm's collapse, which is what the comparison measures.

Before any peer runs, both peer likelihoods are checked against hbm's (numpy model at 16 prior draws,
the PyMC model's ``datalogp`` at 7 parameter sets); a disagreement stops the round.

Runs are interleaved seed by seed (every setting of seed s before seed s + 1, each setting up to its
own number of seeds) and appended to a JSON-lines log as they finish, so a round stopped early keeps
what it measured.  ``report`` turns the log into a dated section at the top of
``results/benchmarks/peers.md`` and a round in ``results/benchmarks/peers.json``.

CPU: hbm's = process time of the fitting call (this process); a peer's = process time of its sampling
call as the peer script reports it (all threads of the child), and ``cpu_process`` = the child's whole
CPU from ``getrusage(RUSAGE_CHILDREN)``: imports, model building and, for PyMC, pytensor's C
compilation, which runs in g++ grandchildren that the in-call process time does not see.  The first
PyMC run of a round uses an empty pytensor cache, so its cold compilation is counted once there.  A run that hits the wall cap is killed and reported with what it
had spent (not reached).

Usage::

    HBM_BENCH_DIR=../shared/bench nice -n 10 python workflows/benchmarks/peers_round.py run \\
        --log /tmp/peers/round.jsonl --hbm-seeds 10 --pymc-seeds 10 --pocomc-seeds 3 \\
        --nautilus-seeds 3 --dynesty-seeds 3 --cap 600
    python workflows/benchmarks/peers_round.py report --log /tmp/peers/round.jsonl
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
HERE = Path(__file__).resolve().parent
for p in (str(ROOT), str(HERE)):
    if p not in sys.path:
        sys.path.insert(0, p)

import collapsed_posterior as cp  # noqa: E402
import evaluations_to_accuracy as eta  # noqa: E402
import muscle_posterior as mp  # noqa: E402
from hbm.likelihood.collapsed import CollapsedLikelihood  # noqa: E402
from hbm.runtime.files import atomic_write_text  # noqa: E402

MS_PER_ROW = eta.MS_PER_ROW
REACH_SHARE = eta.REACH_SHARE  # as the earlier peer tables: a time to accuracy when the median run reaches the target
HBM = {"hbm collapsed + IS finish (N=500, ≤5 steps, 10k draws)": "collapsed N=500, ≤5 steps + IS (10k draws)",
       "hbm collapsed TMCMC (N=1000, ≤10 steps)": "collapsed TMCMC (N=1000, ≤10 steps)",
       "hbm full default (N=2000), baseline": cp.BASELINE}
# peer -> (script, arguments after "run --bench DIR"): each peer's documented defaults
PEERS = {"PyMC SMC (IMH, draws=2000)": ("pymc_peer.py", ["--n", "2000"]),
         "pocoMC (n_effective=512, n_active=256, n_total=4096)": ("evidence_peers.py", ["--peer", "pocomc",
                                                                                       "--size", "512"]),
         "nautilus (n_live=2000, n_eff=10000, discard_exploration)": ("evidence_peers.py", ["--peer", "nautilus",
                                                                                           "--size", "2000"]),
         "dynesty (nlive=500, bound multi, sample unif, dlogz 0.1)": ("evidence_peers.py", ["--peer", "dynesty",
                                                                                           "--size", "500"])}
SEED_OPTION = {"PyMC SMC (IMH, draws=2000)": "pymc_seeds", "pocoMC (n_effective=512, n_active=256, n_total=4096)":
               "pocomc_seeds", "nautilus (n_live=2000, n_eff=10000, discard_exploration)": "nautilus_seeds",
               "dynesty (nlive=500, bound multi, sample unif, dlogz 0.1)": "dynesty_seeds"}


def peer_python() -> Path:
    return Path(os.environ.get("HBM_PEER_PYTHON", ROOT.parent / "venv-bench" / "bin" / "python"))


def _children_cpu() -> float:
    ru = resource.getrusage(resource.RUSAGE_CHILDREN)
    return ru.ru_utime + ru.ru_stime


def run_peer(py: Path, name: str, seed: int, cap: float, tmp: Path, env: dict) -> dict:
    """One peer run in the bench environment, killed after ``cap`` s of wall time."""
    script, args = PEERS[name]
    prog = tmp / f"progress-{seed}.json"
    prog.unlink(missing_ok=True)
    extra = ["--progress-file", str(prog)] if script == "evidence_peers.py" else []
    if "nautilus" in args:  # its own timeout a little inside the cap, so a stopped run still reports
        extra += ["--timeout", str(max(cap - 60.0, 0.8 * cap))]
    cmd = [str(py), str(HERE / script), "run", "--bench", str(mp.BENCH), *args, "--seed", str(seed), *extra]
    c0, w0 = _children_cpu(), time.perf_counter()
    try:
        p = subprocess.run(cmd, capture_output=True, text=True, timeout=cap, env=env)
    except subprocess.TimeoutExpired:
        spent = json.loads(prog.read_text()) if prog.exists() else {"evaluations": 0, "cpu": float("nan")}
        return {"setting": name, "seed": seed, "status": "capped", "wall_total": time.perf_counter() - w0,
                "cpu_process": _children_cpu() - c0, "evaluations": spent["evaluations"], "cpu": spent["cpu"]}
    out = {"wall_total": time.perf_counter() - w0, "cpu_process": _children_cpu() - c0}
    lines = p.stdout.strip().splitlines()
    if p.returncode != 0 or not lines:
        tail = (p.stderr.strip().splitlines() or ["no output"])[-1][:300]
        return {"setting": name, "seed": seed, "status": f"failed (exit {p.returncode}): {tail}", **out,
                "evaluations": 0, "cpu": float("nan")}
    r = json.loads(lines[-1])
    status = "completed" if r.get("completed", True) else "stopped at its own timeout"
    return {"setting": name, "seed": seed, "status": status, "raw": r, **out,
            "version": r.get("version", r.get("pymc", "?")), "evaluations": int(r["evaluations"]),
            "cpu": float(r["cpu"]), "wall": float(r["wall"]), "log_evidence": float(r["log_evidence"]),
            "log_evidence_se": float(r.get("log_evidence_se", float("nan"))),
            "max_mean_err_sd": float(r["max_mean_err_sd"])}


def finish_row(r: dict, gold: dict) -> dict:
    """Add |Δlog Ẑ|, SE coverage, the target test and the 1 ms virtual clock to a run record."""
    if "log_evidence" in r:
        err = abs(r["log_evidence"] - gold["log_evidence"])
        se = r.get("log_evidence_se", float("nan"))
        r["abs_error"] = err
        r["covered_2se"] = bool(se == se and err <= 2 * se)
        r["reached"] = bool(r.get("status", "completed") == "completed" and err <= cp.TARGET_LOGZ
                            and r["max_mean_err_sd"] <= cp.TARGET_MEAN)
    else:
        r["reached"] = False
    r["virtual_1ms"] = r["cpu"] + MS_PER_ROW * r["evaluations"]
    return r


def check_likelihoods(lik, gold, py: Path) -> list[str]:
    """Both peer likelihoods against hbm's; raises SystemExit when one disagrees."""
    os.environ.setdefault("HBM_PYMC_PYTHON", str(py))
    d_np = eta.check_peer_likelihood(py, lik, gold)
    with tempfile.TemporaryDirectory() as t:
        d_pm, msg = mp.check_peer_model(py, lik, Path(t))
    notes = [f"likelihood check: evidence_peers.py (numpy) vs hbm at 16 prior draws: max |Δ log L| / "
             f"max(1, |log L|) = {d_np:.1e}", f"likelihood check: PyMC {msg}"]
    if not (d_np <= 1e-8 and d_pm <= mp.PEER_TOL):
        raise SystemExit("peers_round: error: a peer likelihood disagrees with hbm's: " + "; ".join(notes))
    return notes


def cmd_run(a) -> int:
    lik, gold, _ = mp.make_problem()
    cl = CollapsedLikelihood(lik)
    py = peer_python()
    if not py.exists():
        raise SystemExit(f"peers_round: error: bench environment python {py} is missing (see README.md)")
    log = Path(a.log)
    log.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix="hbm-peers-round-"))
    # a fresh pytensor cache: the first PyMC run pays (and reports) the cold compilation
    env = {**os.environ, "OMP_NUM_THREADS": "1", "OPENBLAS_NUM_THREADS": "1", "MKL_NUM_THREADS": "1",
           "PYTENSOR_FLAGS": f"compiledir={tmp / 'pytensor'}"}

    def emit(r: dict) -> None:
        r = finish_row(r, gold)
        r["finished"] = time.strftime("%Y-%m-%d %H:%M:%S UTC", time.gmtime())
        r["load1"] = os.getloadavg()[0]
        with log.open("a") as f:
            f.write(json.dumps(r, default=float) + "\n")
        print(f"{r['finished']} {r['setting']} seed {r['seed']}: {r.get('status', 'completed')}, "
              f"{r['evaluations']} evals, CPU {r['cpu']:.1f} s, virtual {r['virtual_1ms']:.1f} s"
              + (f", |Δlog Z| {r['abs_error']:.3f}, worst {r['max_mean_err_sd']:.2f} sd, reached {r['reached']}"
                 if "abs_error" in r else ""), flush=True)

    if not a.skip_check:
        for n in check_likelihoods(lik, gold, py):
            print(n, flush=True)
            with log.open("a") as f:
                f.write(json.dumps({"note": n}) + "\n")
    seeds = {name: a.hbm_seeds for name in HBM} | {name: getattr(a, SEED_OPTION[name]) for name in PEERS}
    only = set(a.only or seeds)
    for seed in range(a.first_seed, a.first_seed + max(seeds.values())):
        for name in list(HBM) + list(PEERS):
            if name not in only or seed - a.first_seed >= seeds[name]:
                continue
            if name in HBM:
                inner = HBM[name]
                r = cp.run_full(lik, gold, seed) if inner == cp.BASELINE else cp.run_collapsed(lik, cl, gold, inner, seed)
                r = {k: v for k, v in r.items() if k not in ("abs_error", "covered_2se", "reached")}
                r.update(setting=name, status="completed", version="hbm (this branch)")
            else:
                r = run_peer(py, name, seed, a.cap, tmp, env)
            emit(r)
    return 0


# ----------------------------------------------------------------------------------------- report
def _load(log: Path) -> tuple[list[dict], list[str]]:
    rows, notes = [], []
    for line in log.read_text().splitlines():
        d = json.loads(line)
        (notes.append(d["note"]) if "note" in d else rows.append(d))
    return rows, notes


def peer_versions(py: Path) -> dict[str, str]:
    """Versions of the peer packages in the bench environment (a capped run reports none)."""
    code = ("import json, importlib.metadata as m; print(json.dumps({k: m.version(v) for k, v in "
            "{'pymc': 'pymc', 'pocomc': 'pocomc', 'nautilus': 'nautilus-sampler', 'dynesty': 'dynesty'}.items()}))")
    try:
        return json.loads(subprocess.run([str(py), "-c", code], capture_output=True, text=True, timeout=120).stdout)
    except (OSError, ValueError, subprocess.SubprocessError):
        return {}


def table(rows: list[dict]) -> str:
    head = ["setting", "version", "seeds", "completed", "evaluations (median)", "CPU s (median)",
            "child-process CPU s (median)",
            "time with 1 ms/row (virtual, median) s", "\\|log Ẑ error\\| (median / max)", "SE covers (2 SE)",
            "worst mean err (gold sd, median / max)", "runs reaching target", "time to accuracy (1 ms/row)"]
    out = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    by: dict[str, list[dict]] = {}
    for r in rows:
        by.setdefault(r["setting"], []).append(r)
    for name, rs in by.items():
        med = lambda k, rs=rs: statistics.median(r[k] for r in rs)  # noqa: E731
        done = [r for r in rs if "abs_error" in r]
        reached = sum(r["reached"] for r in rs)
        tta = f"**{med('virtual_1ms'):.0f} s**" if reached >= REACH_SHARE * len(rs) else "not reached"
        err = f"{statistics.median(r['abs_error'] for r in done):.2f} / {max(r['abs_error'] for r in done):.2f}" if done else "—"
        worst = (f"{statistics.median(r['max_mean_err_sd'] for r in done):.2f} / "
                 f"{max(r['max_mean_err_sd'] for r in done):.2f}") if done else "—"
        if not done:
            se = "—"
        elif all(r["log_evidence_se"] != r["log_evidence_se"] for r in done):
            se = "n/a (none reported)"
        else:
            se = f"{sum(r.get('covered_2se', False) for r in rs)}/{len(rs)}"
        cpu_process = f"{med('cpu_process'):.1f}" if all("cpu_process" in r for r in rs) else "(in-process)"
        out.append(f"| {name} | {rs[0].get('version', '?')} | {len(rs)} | "
                   f"{sum(r['status'] == 'completed' for r in rs)}/{len(rs)} | {med('evaluations'):.3g} | "
                   f"{med('cpu'):.1f} | {cpu_process} | {med('virtual_1ms'):.1f} | {err} | {se} | {worst} | {reached}/{len(rs)} | {tta} |")
    return "\n".join(out)


def cmd_report(a) -> int:
    rows, notes = _load(Path(a.log))
    versions = peer_versions(peer_python())
    for r in rows:
        if r.get("version", "?") == "?":
            r["version"] = next((v for k, v in versions.items() if k in r["setting"].lower()), "?")
    gold = json.loads((mp.BENCH / "muscle_benchmark_gold.json").read_text())
    first, last = min(r["finished"] for r in rows), max(r["finished"] for r in rows)
    lines = [f"## Round {first[:16]} – {last[11:16]} UTC: hbm's collapsed tier and full default against the peers",
             "", f"Benchmark `{mp.BENCH}` (40-point curve, base Spyrou model, 9 parameters, uniform box); gold "
             f"log Z = {gold['log_evidence']}; target |log Ẑ − gold| ≤ {cp.TARGET_LOGZ} and worst posterior-mean "
             f"error of the 7 gold quantities ≤ {cp.TARGET_MEAN} gold sd.  Time with 1 ms/row = CPU + 1 ms × "
             "evaluations (a virtual clock for an expensive model); time to accuracy = its median when ≥ 50 % "
             "of a setting's runs reach the target.  One process at a time under `nice -n 10` on the shared "
             f"2-core machine (1-min load {min(r['load1'] for r in rows):.1f}–{max(r['load1'] for r in rows):.1f} "
             "while it ran); CPU = process time.", "", table(rows), ""]
    lines += [f"- {n}" for n in notes]
    for r in rows:
        if r.get("status", "completed") != "completed":
            lines.append(f"- {r['setting']} seed {r['seed']}: {r['status']} (wall {r.get('wall_total', 0):.0f} s; "
                         f"{r['evaluations']} evaluations, {r['cpu']:.0f} s CPU by then, so its time with 1 ms/row "
                         f"is ≥ {r['virtual_1ms']:.0f} s)")
    section = "\n".join(lines) + "\n\n"
    out = Path(a.out)
    prev = out.read_text() if out.exists() else "# hbm against evidence peers on the muscle benchmark\n"
    title, _, rest = prev.partition("\n")
    atomic_write_text(out, title + "\n\n" + section + (a.append_text or "") + "\n" + rest.lstrip("\n"))
    js = out.with_suffix(".json")
    rounds = json.loads(js.read_text()).get("rounds", []) if js.exists() else []
    rounds.insert(0, {"measured": f"{first} – {last}", "gold": gold["log_evidence"], "notes": notes, "runs": rows})
    atomic_write_text(js, json.dumps({"rounds": rounds}, indent=1, default=float))
    print(section)
    return 0


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = ap.add_subparsers(dest="mode", required=True)
    r = sub.add_parser("run", help="run the round, appending to --log")
    r.add_argument("--log", required=True)
    r.add_argument("--first-seed", type=int, default=0)
    r.add_argument("--hbm-seeds", type=int, default=10)
    for name in SEED_OPTION.values():
        r.add_argument("--" + name.replace("_", "-"), type=int, default=3)
    r.add_argument("--cap", type=float, default=600.0, help="wall-time cap of one peer run, s")
    r.add_argument("--only", action="append", choices=list(HBM) + list(PEERS))
    r.add_argument("--skip-check", action="store_true", help="(continuation of a checked round)")
    q = sub.add_parser("report", help="write the section at the top of --out from --log")
    q.add_argument("--log", required=True)
    q.add_argument("--out", default=str(ROOT / "results" / "benchmarks" / "peers.md"))
    q.add_argument("--append-text", default="", help="text placed under the section's notes (a reading)")
    a = ap.parse_args(argv)
    return cmd_run(a) if a.mode == "run" else cmd_report(a)


if __name__ == "__main__":
    raise SystemExit(main())
