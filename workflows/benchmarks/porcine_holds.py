"""The porcine compression data along and across the fibres *with* their 300 s relaxation holds (issue 35).

``../shared/realdata/wang2023_porcine_compression_rates_{along,across}.csv`` (folder: ``HBM_REALDATA``,
default ``../shared/realdata`` next to the repository): group-mean unconfined compression to -30 % at 0.5, 1
and 5 %/s, each ramp followed by a 300 s hold (one loading history per ramp + hold; the time restarts at
each ramp).  ``porcine_modes.py`` fitted the ramps only, because no effect existed outside along-fibre
tension; here both directions, ramps *and* holds, are fitted jointly (along = ``uniaxial_f``, across =
``uniaxial_c``, :func:`hbm.data.modes.combine_tests`), energy form, cone reading:

* ``elastic``: the base model;
* ``qlv``: + ``viscoelastic`` (one Prony term, G1 and LOGTAU1 inferred), acting on each test's stress
  history in its mode (:mod:`hbm.model.modes_effects`);
* ``qlv2``: + ``viscoelastic_2`` (a second relaxation time), unless ``--no-qlv2``.

Per fit: CPU (process) time, likelihood evaluations, log-evidence, and per test (ramp / hold of each rate
and direction) the rmse of the posterior-mean prediction relative to the largest |stress| of that test
and cov90 (share of points inside the 90 % posterior-predictive band).  Seeds come from ``--seeds``
(each the root of :mod:`hbm.runtime.seeds`).  The machine is shared: keep ``--samples`` modest.

usage::

    OMP_NUM_THREADS=1 nice python workflows/benchmarks/porcine_holds.py --samples 300 --seeds 0
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

from hbm.data import load_specimen, save_specimen
from hbm.data.modes import combine_tests
from hbm.effects import make_effect
from hbm.fit.modes import fit_modes
from hbm.model import spyrou_model

ROOT = Path(__file__).resolve().parents[2]
DATA = Path(os.environ.get("HBM_REALDATA", ROOT.parent / "shared" / "realdata"))
BASE = spyrou_model(form="energy")
MODELS = {"elastic": BASE,
          "qlv": BASE + make_effect("viscoelastic"),
          "qlv2": BASE + make_effect("viscoelastic") + make_effect("viscoelastic_2")}


def specimen():
    """Along + across, ramps and holds, one specimen (tests: along ramp/hold per rate, then across)."""
    along = load_specimen(DATA / "wang2023_porcine_compression_rates_along.csv")
    across = load_specimen(DATA / "wang2023_porcine_compression_rates_across.csv")
    return combine_tests([(along, "uniaxial_f"), (across, "uniaxial_c")], "wang2023_porcine_holds")


def short(label: str) -> str:
    """``wang2023_porcine_compression_rates_along:3`` -> ``along 1%/s ramp`` (odd id ramp, even hold)."""
    name, k = label.rsplit(":", 1)
    k = int(k)
    rate = {1: "0.5", 2: "0.5", 3: "1", 4: "1", 5: "5", 6: "5"}.get(k, "?")
    return f"{name.rsplit('_', 1)[-1]} {rate}%/s {'ramp' if k % 2 else 'hold'}"


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--samples", type=int, default=300)
    ap.add_argument("--max-steps", type=int, default=10)
    ap.add_argument("--seeds", type=str, default="0")
    ap.add_argument("--no-qlv2", action="store_true", help="skip the two-relaxation-time fit")
    ap.add_argument("--out", type=Path, default=ROOT / "results" / "benchmarks")
    ap.add_argument("--render", type=Path, default=None, metavar="FILE.json",
                    help="only write the Markdown of a (partial) run's JSON next to it")
    args = ap.parse_args(argv)
    if args.render is not None:
        text = render(json.loads(args.render.read_text()))
        args.render.with_suffix(".md").write_text(text)
        print(text)
        return 0
    seeds = [int(s) for s in args.seeds.split(",")]
    commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=ROOT, capture_output=True,
                            text=True).stdout.strip()
    spec = specimen()
    args.out.mkdir(parents=True, exist_ok=True)
    save_specimen(spec, args.out / "porcine_holds.csv")
    names = [n for n in MODELS if not (args.no_qlv2 and n == "qlv2")]
    print(f"{len(names)} models x {len(seeds)} seed(s), TMCMC N = {args.samples}, max_steps = {args.max_steps}; "
          f"{spec.n_points} points in {len(spec.tests)} tests; expect ~2-10 min CPU per fit", flush=True)
    res = {"commit": commit, "samples": args.samples, "max_steps": args.max_steps, "seeds": seeds, "fits": []}
    for seed in seeds:
        for name in names:
            t0 = time.process_time()
            f = fit_modes(spec, model=MODELS[name], collagen3d="cone", samples=args.samples, seed=seed,
                          progress=False, tmcmc_options={"max_steps": args.max_steps})
            cpu = time.process_time() - t0
            q = f.quality()
            for r in q:
                r["short"] = short(r["label"])
            post = {n: list(map(float, np.quantile(f.samples[:, j], [0.05, 0.5, 0.95])))
                    for j, n in enumerate(f.names)}
            res["fits"].append({"model": name, "seed": seed, "cpu_s": cpu, "evaluations": f.n_evaluations,
                                "stages": len(f.stages), "log_evidence": f.log_evidence,
                                "log_evidence_se": f.log_evidence_se, "quality": q, "posterior_q05_50_95": post})
            print(f"{name} seed {seed}: {cpu:.0f} s CPU, {f.n_evaluations} evaluations, "
                  f"log Z {f.log_evidence:.1f} +- {f.log_evidence_se:.1f}", flush=True)
            (args.out / "porcine_holds.json").write_text(json.dumps(res, indent=1, default=str))
    text = render(res)
    (args.out / "porcine_holds.md").write_text(text)
    print(text)
    return 0


def render(res: dict) -> str:
    """The Markdown table of a results dict (also of a partial run's JSON: ``--render FILE.json``)."""
    names = list(dict.fromkeys(r["model"] for r in res["fits"]))
    seeds = list(dict.fromkeys(r["seed"] for r in res["fits"]))
    commit, samples, max_steps = res["commit"], res["samples"], res["max_steps"]
    lines = ["# Porcine compression along + across the fibres with the 300 s holds (Wang et al. 2023 group means)",
             "", f"commit {commit}; TMCMC N = {samples}, max_steps = {max_steps}, seeds {seeds} (finished fits); "
             "energy form, cone reading; script workflows/benchmarks/porcine_holds.py; CPU = process time on a "
             "shared machine (2 cores, other jobs running).", "",
             "| model | seed | CPU s | evaluations | log Z |", "|---|---|---|---|---|"]
    for r in res["fits"]:
        lines.append(f"| {r['model']} | {r['seed']} | {r['cpu_s']:.0f} | {r['evaluations']} | "
                     f"{r['log_evidence']:.1f} +- {r['log_evidence_se']:.1f} |")
    lines += ["", "Per test: rmse/max of the posterior-mean prediction, cov90 (medians over the finished seeds of "
              "each model; rmse/max = rmse / largest |stress| of that test):", "",
              "| test | " + " | ".join(names) + " |", "|---|" + "---|" * len(names)]
    first = {r["model"]: r for r in res["fits"] if r["seed"] == seeds[0]}
    for k, t in enumerate(first[names[0]]["quality"]):
        cells = []
        for n in names:
            q = [r["quality"][k] for r in res["fits"] if r["model"] == n]
            cells.append(f"{np.median([x['rmse_rel'] for x in q]):.3f}, {np.median([x['coverage90'] for x in q]):.2f}")
        lines.append(f"| {t['short']} ({t['points']} pts) | " + " | ".join(cells) + " |")
    lines += ["", "Posterior 5/50/95 % of the relaxation parameters (first seed):", ""]
    for n in names:
        post = first[n]["posterior_q05_50_95"]
        for p in ("G1", "LOGTAU1", "G2", "LOGTAU2"):
            if p in post:
                lines.append(f"- {n}: {p} " + " / ".join(f"{v:.3g}" for v in post[p]))
    return "\n".join(lines) + "\n"


if __name__ == "__main__":
    sys.exit(main())
