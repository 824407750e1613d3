"""Issue 35's synthetic check: a specimen tested along, across and in shear recovers the generating combinations.

For each seed: a specimen with along-fibre tension, cross-fibre tension and shear along the fibres
(``tests/independent3d.py``: an implementation sharing no code with hbm, cone reading, Calvo rat-1-like
parameters, iid noise of 2 % of each test's largest stress) is fitted with :func:`hbm.fit.modes.fit_modes`
(all tests), and its along-fibre test alone with the same likelihood.  Recorded per seed: whether each
generating combination lies inside its central 90 % interval, and the interval widths of (1-VOLF)*T1 and
T2 in both fits (their ratio: how much the other modes shrink them).

usage (from the repository root)::

    OMP_NUM_THREADS=1 python workflows/benchmarks/modes_coverage.py --seeds 20        # ~25 min CPU
    # or split: --first 0 --seeds 10 --out A & --first 10 --seeds 10 --out B, then --merge A/*.json B/*.json
    python workflows/benchmarks/modes_coverage.py --seeds 1 --samples 300 --max-steps 10   # smoke

Writes ``results/benchmarks/modes_coverage.{md,json}`` (``--out DIR`` to change).
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT / "tests"))
import independent3d as ind  # noqa: E402

from hbm.data import load_specimen  # noqa: E402
from hbm.fit.modes import fit_modes  # noqa: E402
from hbm.model.spec import spec_of  # noqa: E402
from hbm.model import spyrou_model  # noqa: E402

MODEL = spyrou_model(form="energy")
SPEC = spec_of(MODEL)
# the rate of the collagen's exponential: the one raw parameter checked besides the combinations
RATE = SPEC.parameters[4].name


def truth() -> dict[str, float]:
    cols = {k: np.array([v]) for k, v in ind.CALVO.items()}
    out = {c.name: float(c.compute(cols)[0]) for c in SPEC.combinations}
    out[RATE] = float(ind.CALVO[RATE])
    return out


def quantities(fit) -> dict[str, np.ndarray]:
    out = dict(fit.combinations())
    out[RATE] = fit.samples[:, fit.names.index(RATE)]
    return out


def run_seed(seed: int, samples: int, max_steps: int, folder: Path, reading: str = "cone") -> dict:
    path = folder / f"s{seed}.csv"
    ind.synthetic_csv(path, seed, reading=reading)
    spec = load_specimen(path)
    row = {"seed": seed}
    true = truth()
    for label, data in (("all", spec), ("along", spec.select(spec.tests[0].rows))):
        t0 = time.process_time()
        fit = fit_modes(data, model=MODEL, collagen3d=reading, samples=samples, seed=1000 + seed, progress=False,
                        tmcmc_options={"max_steps": max_steps})
        q = quantities(fit)
        row[label] = {"cpu_s": time.process_time() - t0, "evaluations": fit.n_evaluations,
                      "stages": len(fit.stages), "log_evidence": fit.log_evidence,
                      "intervals": {k: list(map(float, fit.interval(v))) for k, v in q.items()},
                      "inside": {k: bool(fit.interval(v)[0] <= true[k] <= fit.interval(v)[1]) for k, v in q.items()}}
    return row


def table(rows: list[dict], args, commit: str) -> str:
    true = truth()
    names = list(true)
    n = len(rows)
    lines = [f"# Issue 35 synthetic check ({args.reading}): along + across + shear vs along alone ({n} seeds)", "",
             f"commit {commit}; TMCMC N = {args.samples}, max_steps = {args.max_steps}; generator "
             f"tests/independent3d.py ({args.reading} reading, generator and fit; Calvo rat 1, 2 % noise, 10 points per test); script "
             "workflows/benchmarks/modes_coverage.py.  CPU seconds are process time (the machine was shared).", "",
             "| quantity | truth | inside 90 % (all tests) | inside 90 % (along only) | median width all | "
             "median width along | width ratio along/all (median) |", "|---|---|---|---|---|---|---|"]
    for k in names:
        wa = np.array([r["all"]["intervals"][k][1] - r["all"]["intervals"][k][0] for r in rows])
        wl = np.array([r["along"]["intervals"][k][1] - r["along"]["intervals"][k][0] for r in rows])
        ia = sum(r["all"]["inside"][k] for r in rows)
        il = sum(r["along"]["inside"][k] for r in rows)
        lines.append(f"| {k} | {true[k]:.4g} | {ia}/{n} | {il}/{n} | {np.median(wa):.3g} | {np.median(wl):.3g} | "
                     f"{np.median(wl / wa):.1f} |")
    cpu_a = np.median([r["all"]["cpu_s"] for r in rows])
    cpu_l = np.median([r["along"]["cpu_s"] for r in rows])
    ev_a = np.median([r["all"]["evaluations"] for r in rows])
    lines += ["", f"median per fit: all tests {cpu_a:.1f} s CPU, {ev_a:.0f} evaluations (30 points, 3 tests); "
                  f"along only {cpu_l:.1f} s CPU.",
              "Nominal 90 % coverage over n seeds: the count is Binomial(n, 0.9) (n = 20: 15-20 holds 98 %)."]
    return "\n".join(lines) + "\n"


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--seeds", type=int, default=20)
    ap.add_argument("--samples", type=int, default=600)
    ap.add_argument("--max-steps", type=int, default=40)
    ap.add_argument("--reading", choices=("cone", "gst"), default="cone",
                    help="collagen reading of the generator and the fit (gst: about 13x cheaper per evaluation)")
    ap.add_argument("--first", type=int, default=0, help="first seed (split a run over processes)")
    ap.add_argument("--merge", type=Path, nargs="+", default=None, metavar="JSON",
                    help="only merge the rows of earlier runs' JSON files into one table")
    ap.add_argument("--out", type=Path, default=ROOT / "results" / "benchmarks")
    args = ap.parse_args(argv)
    if args.merge:
        parts = [json.loads(p.read_text()) for p in args.merge]
        args.samples, args.max_steps = parts[0]["samples"], parts[0]["max_steps"]
        args.reading = parts[0].get("reading", "cone")
        rows = sorted((r for p in parts for r in p["rows"]), key=lambda r: r["seed"])
        return _write(args, rows, parts[0]["commit"])
    commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=ROOT, capture_output=True,
                            text=True).stdout.strip()
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for seed in range(args.first, args.first + args.seeds):
            rows.append(run_seed(seed, args.samples, args.max_steps, Path(tmp), args.reading))
            r = rows[-1]
            width = {k: (r["along"]["intervals"][k][1] - r["along"]["intervals"][k][0])
                     / (r["all"]["intervals"][k][1] - r["all"]["intervals"][k][0]) for k in r["all"]["intervals"]}
            print(f"seed {seed}: all {r['all']['cpu_s']:.1f} s inside {sum(r['all']['inside'].values())}/"
                  f"{len(r['all']['inside'])}; along {r['along']['cpu_s']:.1f} s; width ratios along/all "
                  + ", ".join(f"{k} {v:.1f}" for k, v in width.items()), flush=True)
            args.out.mkdir(parents=True, exist_ok=True)  # partial rows after every seed (--merge reads them)
            (args.out / "modes_coverage.partial.json").write_text(json.dumps(
                {"commit": commit, "samples": args.samples, "max_steps": args.max_steps, "reading": args.reading,
                 "rows": rows}, indent=1))
    return _write(args, rows, commit)


def _write(args, rows, commit) -> int:
    text = table(rows, args, commit)
    print(text)
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "modes_coverage.md").write_text(text)
    (args.out / "modes_coverage.json").write_text(json.dumps({"commit": commit, "samples": args.samples,
                                                               "reading": args.reading,
                                                               "max_steps": args.max_steps, "truth": truth(),
                                                               "rows": rows}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
