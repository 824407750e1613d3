"""The shared porcine compression data along and across the fibres, fitted jointly (issue 35, "Data").

``../shared/realdata/wang2023_porcine_compression_rates_{along,across}.csv`` (folder: ``HBM_REALDATA``,
default ``../shared/realdata`` next to the repository) hold group-mean unconfined compression to -30 % at
0.5, 1 and 5 %/s, each ramp followed by a 300 s hold.  The 3-D fit takes the base model only (no
viscoelastic effect in other modes than along the fibres), so it fits the three *ramps* of each direction
as quasi-static curves: along = ``uniaxial_f``, across = ``uniaxial_c`` (negative strain), combined with
:func:`hbm.data.modes.combine_tests` -- the same as concatenating the two files' ramp rows with a ``mode``
column (the combined CSV is written next to the results: ``hbm fit porcine_ramps.csv --form energy`` is
the one command).  Fits: joint (cone and gst readings: their log-evidence), along alone, across alone;
leave-one-direction-out: each single-direction posterior predicts the other direction.

usage::

    OMP_NUM_THREADS=1 python workflows/benchmarks/porcine_modes.py          # ~10 min CPU
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
from hbm.fit.modes import fit_modes
from hbm.likelihood.modes import make_modes_likelihood
from hbm.model import spyrou_model

ROOT = Path(__file__).resolve().parents[2]
DATA = Path(os.environ.get("HBM_REALDATA", ROOT.parent / "shared" / "realdata"))
MODEL = spyrou_model(form="energy")


def ramps(spec):
    """The ramp tests (odd ids) of a ramp + hold file."""
    return spec.select(spec.test % 2 == 1)


def fit(spec, args, reading="cone"):
    t0 = time.process_time()
    f = fit_modes(spec, model=MODEL, collagen3d=reading, samples=args.samples, seed=args.seed, progress=False,
                  tmcmc_options={"max_steps": args.max_steps})
    return f, time.process_time() - t0


def held_out(fit_one, joint_lik, direction_mode):
    """The single-direction posterior's prediction of the other direction's series (model band, no noise)."""
    rows = np.ones((fit_one.samples.shape[0], joint_lik.d))
    rows[:, : joint_lik.n_model] = fit_one.samples[:, : fit_one.likelihood.n_model]
    pred = joint_lik.predict_series(joint_lik.from_natural(rows))
    out = []
    for s, m in zip(joint_lik.series, pred):
        if s.test.load_case != direction_mode:
            continue
        mean = m.mean(axis=0)
        lo, hi = np.quantile(m, [0.05, 0.95], axis=0)
        peak = int(np.argmax(np.abs(s.observed)))
        out.append({"test": s.test.label, "rmse_rel": float(np.sqrt(np.mean((mean - s.observed) ** 2)) /
                                                              np.max(np.abs(s.observed))),
                    "peak_ratio": float(mean[peak] / s.observed[peak]),
                    "inside_model_band90": float(np.mean((s.observed >= lo) & (s.observed <= hi)))})
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--samples", type=int, default=400)
    ap.add_argument("--max-steps", type=int, default=15)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", type=Path, default=ROOT / "results" / "benchmarks")
    args = ap.parse_args(argv)
    commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=ROOT, capture_output=True,
                            text=True).stdout.strip()
    along = ramps(load_specimen(DATA / "wang2023_porcine_compression_rates_along.csv"))
    across = ramps(load_specimen(DATA / "wang2023_porcine_compression_rates_across.csv"))
    joint = combine_tests([(along, "uniaxial_f"), (across, "uniaxial_c")], "wang2023_porcine_ramps")
    args.out.mkdir(parents=True, exist_ok=True)
    save_specimen(joint, args.out / "porcine_ramps.csv")
    only_along = combine_tests([(along, "uniaxial_f")], "along")
    only_across = combine_tests([(across, "uniaxial_c")], "across")
    res = {"commit": commit, "samples": args.samples, "max_steps": args.max_steps, "seed": args.seed, "fits": {}}
    fits = {}
    for name, spec, reading in (("joint_cone", joint, "cone"), ("joint_gst", joint, "gst"),
                                ("along_cone", only_along, "cone"), ("across_cone", only_across, "cone")):
        f, cpu = fit(spec, args, reading)
        fits[name] = f
        res["fits"][name] = {"cpu_s": cpu, "evaluations": f.n_evaluations, "stages": len(f.stages),
                             "log_evidence": f.log_evidence, "log_evidence_se": f.log_evidence_se,
                             "quality": f.quality(),
                             "posterior_mean": dict(zip(f.names, map(float, f.samples.mean(axis=0)))),
                             "combinations90": {k: list(map(float, f.interval(v))) for k, v in f.combinations().items()}}
        print(f"{name}: {cpu:.1f} s CPU, {f.n_evaluations} evaluations, log Z {f.log_evidence:.2f}", flush=True)
    jl = make_modes_likelihood(MODEL, joint)
    res["leave_one_out"] = {"across_from_along": held_out(fits["along_cone"], jl, "uniaxial_c"),
                            "along_from_across": held_out(fits["across_cone"], jl, "uniaxial_f")}
    (args.out / "porcine_modes.json").write_text(json.dumps(res, indent=1, default=str))
    lines = [f"# Porcine compression along + across the fibres (Wang et al. 2023 group means), ramps only", "",
             f"commit {commit}; TMCMC N = {args.samples}, max_steps = {args.max_steps}, seed {args.seed}; "
             "base model, energy form; script workflows/benchmarks/porcine_modes.py; CPU = process time on a "
             "shared machine.", "", "| fit | CPU s | evaluations | log Z | per test: rmse/max, cov90 |",
             "|---|---|---|---|---|"]
    for name, r in res["fits"].items():
        q = "; ".join(f"{t['label'].split('_')[-1]} {t['rmse_rel']:.2f}, {t['coverage90']:.2f}" for t in r["quality"])
        lines.append(f"| {name} | {r['cpu_s']:.0f} | {r['evaluations']} | {r['log_evidence']:.1f} "
                     f"+- {r['log_evidence_se']:.1f} | {q} |")
    lines += ["", "Leave one direction out (posterior-mean prediction of the held-out ramps; peak ratio = "
                  "predicted / measured stress at -30 %; share of points inside the 90 % model band):", ""]
    for k, rows in res["leave_one_out"].items():
        for r in rows:
            lines.append(f"- {k}: {r['test']}: rmse/max {r['rmse_rel']:.2f}, peak ratio {r['peak_ratio']:.3g}, "
                         f"inside band {r['inside_model_band90']:.2f}")
    text = "\n".join(lines) + "\n"
    (args.out / "porcine_modes.md").write_text(text)
    print(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
