"""End-to-end latency of everyday ``hbm`` commands, this checkout against a baseline (issue 38 item 3).

Times, each in a fresh process (``python -m hbm ...`` with ``PYTHONPATH`` set to the checkout, so the
checkout's own code runs), interleaved per repeat so both checkouts see the same machine load:

* ``hbm --version``
* ``hbm data check data/specimens/calvo2010_rat1.csv`` (this checkout's shipped file, for both)
* ``hbm fit <bench>/muscle_benchmark.csv`` at defaults (samples, restarts, tier, figure), from a fresh
  empty folder so the default output ``hbm-results/specimens/muscle_benchmark.nc`` and its figure are new
* ``hbm summary`` of that fit's result (each checkout reads the file its own fit wrote)

After one untimed warm-up round (numba compiles into a fresh checkout's cache once), wall seconds
(median, min and max over ``--repeats``, at least 5) and CPU seconds of the child process
(user + system, ``resource.getrusage``) -- use the CPU column when the machine is shared.  Whether the
machine was quiet is measured, not guessed from the load average (which counts this benchmark's own previous
command): the busy CPU seconds of the whole machine during each run (``/proc/stat``) minus the command's own
CPU seconds are what other processes used; the report says "quiet" only if that stayed below
``--quiet-share`` (default 5 %) of one CPU in every run of 1 s or more (a 0.04 s run sees the 10 ms ticks of
``/proc/stat`` as shares of 25 %; the report gives the wall-time weighted mean over all runs too), otherwise
which wall numbers were taken beside other work.  The 1-minute load average is recorded too.

Run from the repository root, with the baseline in a detached worktree::

    git worktree add --detach /tmp/hbm-baseline <commit>
    OMP_NUM_THREADS=1 python workflows/benchmarks/command_latency.py --baseline /tmp/hbm-baseline

The benchmark folder is ``$HBM_BENCH_DIR`` (default ``../shared/bench`` next to the repository).
Results: ``results/benchmarks/command_latency.{json,md}`` (``--out DIR`` to change), naming both commits.
The interpreter running the script runs the commands: its environment matters (a development install with the
test extras has pint, which xarray imports when it builds an index: ~0.35 s more per netCDF-writing command), so
the report records it.  A user's environment is ``python -m venv V && V/bin/pip install .`` without extras.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
SPECIMEN = ROOT / "data" / "specimens" / "calvo2010_rat1.csv"
BENCH_FILE = "muscle_benchmark.csv"
#: issue 38's targets, seconds of wall time end to end on a quiet 2-core machine
TARGETS = {"version": 0.5, "data check": 1.5, "fit": 6.0}
COMMANDS = ("version", "data check", "fit", "summary")
#: how the table names them
SHOWN = {"version": "hbm --version", "data check": "hbm data check", "fit": "hbm fit", "summary": "hbm summary"}


def commit_of(tree: Path) -> str:
    """Short commit of a checkout, '+dirty' if its tracked files differ from it."""
    def git(*args: str) -> str:
        return subprocess.run(["git", "-C", str(tree), *args], capture_output=True, text=True,
                              check=True).stdout.strip()
    try:
        head = git("rev-parse", "--short", "HEAD")
        return head + ("+dirty" if git("status", "--porcelain", "--untracked-files=no") else "")
    except (OSError, subprocess.CalledProcessError):
        return "unknown (not a git checkout)"


def environment() -> str:
    """The interpreter and which optional packages that change import time it can import."""
    import importlib.util

    extras = [m for m in ("pint", "pint_xarray", "cf_xarray", "felupe", "hypothesis", "pytest")
              if importlib.util.find_spec(m) is not None]
    kind = "a virtual environment" if sys.prefix != sys.base_prefix else "the base interpreter"
    return f"Python {sys.version.split()[0]} in {kind}; test extras importable: {', '.join(extras) or 'none'}"


def argv_of(command: str, bench: Path, work: Path) -> list[str]:
    if command == "version":
        return ["--version"]
    if command == "data check":
        return ["data", "check", str(SPECIMEN)]
    if command == "fit":
        return ["fit", str(bench / BENCH_FILE), "--no-progress"]
    return ["summary", str(work / "hbm-results" / "specimens" / Path(BENCH_FILE).with_suffix(".nc"))]


def machine_busy_seconds() -> float | None:
    """CPU seconds the whole machine has spent busy since boot (``/proc/stat``; None where there is none)."""
    try:
        fields = Path("/proc/stat").read_text().splitlines()[0].split()[1:]
    except OSError:
        return None
    ticks = [int(v) for v in fields]
    idle = ticks[3] + (ticks[4] if len(ticks) > 4 else 0)  # idle + iowait
    # guest time is already counted in user/nice
    return (sum(ticks[:8]) - idle) / os.sysconf("SC_CLK_TCK")


def timed(tree: Path, argv: list[str], cwd: Path) -> dict:
    """One fresh ``python -m hbm ARGV`` of ``tree``: wall and CPU seconds, exit status, the load before, and
    the share of one CPU that other processes used meanwhile."""
    env = {**os.environ, "PYTHONPATH": str(tree), "HBM_DEBUG": ""}
    load = os.getloadavg()[0]
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    busy0 = machine_busy_seconds()
    t0 = time.perf_counter()
    res = subprocess.run([sys.executable, "-m", "hbm", *argv], cwd=cwd, env=env, capture_output=True, text=True)
    wall = time.perf_counter() - t0
    busy1 = machine_busy_seconds()
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    cpu = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
    if res.returncode != 0:
        raise SystemExit(f"{tree}: hbm {' '.join(argv)} failed ({res.returncode}): {res.stderr.strip()[-500:]}")
    others = None if busy0 is None else max(0.0, (busy1 - busy0) - cpu) / wall
    return {"wall": round(wall, 3), "cpu": round(cpu, 3), "load1": round(load, 2),
            "others": None if others is None else round(others, 3)}


def run(trees: dict[str, Path], bench: Path, repeats: int) -> list[dict]:
    """Repeat -1 is an untimed warm-up (numba's on-disk cache of a fresh checkout, the OS file cache)."""
    rows = []
    for rep in range(-1, repeats):
        # alternate which checkout goes first, so neither always runs right after the other's cache warm-up
        order = list(trees) if rep % 2 == 0 else list(reversed(trees))
        works = {name: Path(tempfile.mkdtemp(prefix=f"latency-{name}-")) for name in trees}
        try:
            for command in COMMANDS:
                for name in order:
                    row = timed(trees[name], argv_of(command, bench, works[name]), works[name])
                    if rep < 0:
                        continue
                    rows.append({"tree": name, "command": command, "repeat": rep, **row})
                    print(f"{rep} {command:10s} {name:8s} wall {row['wall']:6.2f} s  cpu {row['cpu']:6.2f} s  "
                          f"load {row['load1']}  others {row['others']}", file=sys.stderr)
        finally:
            for work in works.values():
                shutil.rmtree(work, ignore_errors=True)
    return rows


def summarise(rows: list[dict], trees: list[str]) -> dict:
    out = {}
    for command in COMMANDS:
        for name in trees:
            sel = [r for r in rows if r["command"] == command and r["tree"] == name]
            walls, cpus = [r["wall"] for r in sel], [r["cpu"] for r in sel]
            out[f"{command}|{name}"] = {"wall_median": round(statistics.median(walls), 3), "wall_min": min(walls),
                                        "wall_max": max(walls), "cpu_median": round(statistics.median(cpus), 3),
                                        "n": len(sel)}
    return out


def _quiet_words(meta: dict) -> str:
    load = f"1-minute load average before the runs: median {meta['load_median']}, max {meta['load_max']}"
    if meta.get("others_max") is None:   # records of the load-average era
        return load + " -- " + ("a quiet machine." if meta["quiet"] else
                                f"**not quiet** (above {meta['quiet_load']}): the wall seconds were taken under "
                                "load and are longer than on a quiet machine; compare the CPU seconds, and "
                                "re-measure wall time quietly.")
    share = (f"CPU used by other processes during the runs: {meta['others_mean']:.1%} of one CPU on average "
             f"(weighted by wall time), at most {meta['others_max']:.1%} in a run of 1 s or more")
    return share + " -- " + ("a quiet machine" if meta["quiet"] else
                             f"**not quiet** (above {meta['quiet_share']:.0%}): wall seconds taken beside other work; "
                             "compare the CPU seconds") + f" ({load}, this benchmark's own commands included)."


def markdown(meta: dict, stats: dict) -> str:
    lines = [f"# Command latency (issue 38 item 3): `{meta['this']}` against `{meta['baseline']}`", "",
             f"Measured {meta['date']} with `workflows/benchmarks/command_latency.py`, {meta['repeats']} repeats "
             f"interleaved, each a fresh `python -m hbm` process; OMP_NUM_THREADS={meta['omp']}; "
             f"{meta['cpus']} CPUs.", "", f"Environment: {meta.get('environment', 'not recorded')}.", "",
             _quiet_words(meta), "",
             "| command | baseline wall s (median, min–max) | this wall s (median, min–max) | baseline CPU s | "
             "this CPU s | target (quiet wall) |", "|---|---|---|---|---|---|"]
    for command in COMMANDS:
        b, t = stats[f"{command}|baseline"], stats[f"{command}|this"]
        target = TARGETS.get(command)
        met = target is not None and t["wall_median"] <= target
        # under load a met target is met a fortiori; a missed one is undecided until measured quietly
        verdict = "" if target is None else f"≤ {target} s: " + (
            ("met" if met else "not met") if meta["quiet"] else ("met even under load" if met else "undecided (load)"))
        lines.append(f"| `{SHOWN[command]}` | {b['wall_median']:.2f} ({b['wall_min']:.2f}–{b['wall_max']:.2f}) | "
                     f"{t['wall_median']:.2f} ({t['wall_min']:.2f}–{t['wall_max']:.2f}) | {b['cpu_median']:.2f} | "
                     f"{t['cpu_median']:.2f} | {verdict} |")
    lines += ["", "`hbm fit` is the default fit of `$HBM_BENCH_DIR/muscle_benchmark.csv` (collapsed tier, CMA-ES "
              "restarts, TMCMC, netCDF and figure written); `hbm summary` reads that fit's result.", ""]
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--baseline", required=True, metavar="DIR", help="checkout of the code to compare with")
    ap.add_argument("--repeats", type=int, default=5, help="runs per command and checkout (at least 5)")
    ap.add_argument("--quiet-share", type=float, default=0.05,
                    help="largest share of one CPU other processes may use during a run called quiet")
    ap.add_argument("--out", default=str(ROOT / "results" / "benchmarks"), metavar="DIR")
    ap.add_argument("--table-only", action="store_true",
                    help="rewrite command_latency.md from the command_latency.json in --out (no runs)")
    args = ap.parse_args(argv)
    out = Path(args.out)
    if args.table_only:
        saved = json.loads((out / "command_latency.json").read_text())
        (out / "command_latency.md").write_text(markdown(saved["meta"], saved["summary"]))
        return 0
    if args.repeats < 5:
        ap.error("--repeats: at least 5 (the medians are the result)")
    bench = Path(os.environ.get("HBM_BENCH_DIR", ROOT.parent / "shared" / "bench")).resolve()
    if not (bench / BENCH_FILE).is_file():
        ap.error(f"no {BENCH_FILE} in {bench} (set HBM_BENCH_DIR)")
    trees = {"baseline": Path(args.baseline).resolve(), "this": ROOT}
    rows = run(trees, bench, args.repeats)
    loads = [r["load1"] for r in rows]
    # other processes' share of one CPU, weighted by each run's wall time (a 0.04 s run sees the
    # 10 ms clock ticks of /proc/stat as shares of 25 %), and its largest value over runs of >= 1 s
    timed_rows = [r for r in rows if r.get("others") is not None]
    others = [r["others"] for r in timed_rows if r["wall"] >= 1.0]
    others_mean = (sum(r["others"] * r["wall"] for r in timed_rows) / sum(r["wall"] for r in timed_rows)
                   if timed_rows else None)
    meta = {"this": commit_of(ROOT), "baseline": commit_of(trees["baseline"]), "repeats": args.repeats,
            "date": time.strftime("%Y-%m-%d %H:%M"), "omp": os.environ.get("OMP_NUM_THREADS", "unset"),
            "cpus": os.cpu_count(), "load_median": round(statistics.median(loads), 2), "load_max": max(loads),
            "others_mean": None if others_mean is None else round(others_mean, 4),
            "others_max": max(others) if others else None, "quiet_share": args.quiet_share,
            "quiet": bool(others) and max(others) <= args.quiet_share, "targets": TARGETS,
            "environment": environment()}
    stats = summarise(rows, list(trees))
    out.mkdir(parents=True, exist_ok=True)
    (out / "command_latency.json").write_text(json.dumps({"meta": meta, "summary": stats, "rows": rows}, indent=1)
                                              + "\n")
    text = markdown(meta, stats)
    (out / "command_latency.md").write_text(text)
    print(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
