#!/usr/bin/env python
"""A second benchmark posterior: a three-rate ramp-and-hold curve with quasi-linear viscoelasticity.

The muscle benchmark (``../shared/bench``, ``$HBM_BENCH_DIR``) is one monotonic ramp of the base model.  Here the
collapse of the linear amplitudes works differently: the viscoelastic history effect filters every
amplitude column, and its two parameters (G1, LOGTAU1) join the sampled nonlinear parameters.

Subcommands
-----------
``make``   write ``results/benchmarks/qlv_benchmark.csv`` (synthetic, labelled; seeded).
``gold``   long full-space TMCMC runs (N, Metropolis steps per stage and seeds as options) into
           ``results/benchmarks/qlv_benchmark_gold.json``: log-evidence (mean and between-run sd)
           and the posterior means/sds of the identifiable combinations, G1, LOGTAU1 and sigma.

Run with ``nice`` and one BLAS thread::

    OMP_NUM_THREADS=1 nice -n 10 python workflows/benchmarks/qlv_posterior.py gold --n 8000 --steps 80 --seeds 2
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[2]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

import hbm  # noqa: E402
from hbm.data import hold, load_specimen, protocol, ramp, save_specimen, synthetic_specimen  # noqa: E402
from hbm.effects import make_effect  # noqa: E402
from hbm.likelihood import make_likelihood  # noqa: E402
from hbm.samplers.tmcmc import tmcmc  # noqa: E402
from hbm.runtime.files import atomic_write_text  # noqa: E402

OUT = ROOT / "results" / "benchmarks"
CURVE = OUT / "qlv_benchmark.csv"
GOLD = OUT / "qlv_benchmark_gold.json"
SIGMA_BOUNDS = (1e-4, 0.05)
#: Calvo-like base parameters (DESIGN.md §1) and a relaxation of 35 % with τ = 20 s
TRUTH = {"VOLF": 0.9, "EOPT": 0.184, "P1": 0.13, "T1": 1.5, "T2": 9.3, "THETA": 60.0, "GF": 0.012, "GM": 0.009,
         "G1": 0.35, "LOGTAU1": 1.3}
SEED = 20261126


def model() -> hbm.Model:
    return hbm.spyrou_model() + make_effect("viscoelastic")


def make() -> Path:
    """Three ramps to 30 % strain a decade apart in rate, each followed by a 200 s hold (150 points)."""
    prot = protocol([ramp(0.3, 1e-3, 30), hold(200.0, 20)],
                    [ramp(0.3, 1e-2, 30), hold(200.0, 20)],
                    [ramp(0.3, 1e-1, 30), hold(200.0, 20)])
    ds = synthetic_specimen(model(), TRUTH, prot, 0.02, SEED, relative=True,
                            attrs={"id": "qlv_benchmark",
                                   "source": "synthetic benchmark curve (three-rate ramp and hold, QLV), "
                                             "not a measurement; workflows/benchmarks/qlv_posterior.py make"})
    save_specimen(ds, CURVE)
    return CURVE


def likelihood():
    return make_likelihood(model(), load_specimen(CURVE), noise="iid", sigma_bounds=SIGMA_BOUNDS)


def combinations(names, samples) -> dict[str, np.ndarray]:
    col = {n: samples[:, i] for i, n in enumerate(names)}
    c = col["VOLF"]
    return {"(1-VOLF)*T1": (1 - c) * col["T1"], "VOLF*P1": c * col["P1"], "G": c * col["GF"] + (1 - c) * col["GM"],
            "EOPT": col["EOPT"], "T2": col["T2"], "THETA": col["THETA"], "G1": col["G1"],
            "LOGTAU1": col["LOGTAU1"], "sigma": col["sigma"]}


def gold(n: int, steps: int, seeds: list[int], path: Path = GOLD) -> dict:
    lik = likelihood()
    runs = []
    for seed in seeds:
        t, c = time.perf_counter(), time.process_time()
        res = tmcmc(lik, lik.bounds, n, seed=seed, n_steps=steps, progress=False)
        comb = combinations(lik.names, res.samples)
        runs.append({"seed": seed, "log_evidence": res.log_evidence, "log_evidence_se": res.log_evidence_se,
                     "evaluations": res.n_evaluations, "stages": res.n_stages,
                     "wall_s": time.perf_counter() - t, "cpu_s": time.process_time() - c,
                     "mean": {k: float(v.mean()) for k, v in comb.items()},
                     "sd": {k: float(v.std()) for k, v in comb.items()}})
        print(f"seed {seed}: log Z {res.log_evidence:.3f} ± {res.log_evidence_se:.3f}, "
              f"{res.n_evaluations} evaluations, {runs[-1]['cpu_s']:.0f} s CPU", flush=True)
    logz = [r["log_evidence"] for r in runs]
    keys = runs[0]["mean"]
    out = {"problem": f"{CURVE.name}: base model + viscoelastic (1 Prony term), iid Gaussian noise with unknown "
                      f"sd 'sigma' in {list(SIGMA_BOUNDS)}, the library's uniform prior box",
           "log_evidence": statistics.fmean(logz),
           "log_evidence_sd_between_runs": statistics.stdev(logz) if len(logz) > 1 else None,
           "posterior_mean_and_sd": {k: [statistics.fmean(r["mean"][k] for r in runs),
                                         statistics.fmean(r["sd"][k] for r in runs)] for k in keys},
           "how_obtained": f"full-space random-walk TMCMC, N={n}, {steps} Metropolis steps per stage, "
                           f"seeds {seeds}, pooled (means of the runs)",
           "runs": runs}
    atomic_write_text(path, json.dumps(out, indent=1) + "\n")
    return out


def _errors(gold_: dict, names, samples, log_z: float) -> tuple[float, float]:
    """(|log Ẑ − gold|, worst |mean − gold mean| / gold sd over the combinations)."""
    comb = combinations(names, samples)
    ref = gold_["posterior_mean_and_sd"]
    worst = max(abs(float(comb[k].mean()) - m) / sd for k, (m, sd) in ref.items())
    return abs(log_z - gold_["log_evidence"]), worst


def gold_collapsed(n: int, steps: int, draws: int, seeds: list[int], path: Path) -> dict:
    """The gold by the collapsed route: TMCMC over φ at large N, importance finish with many draws."""
    from hbm.likelihood.collapsed import CollapsedLikelihood, sample_collapsed

    lik = likelihood()
    cl = CollapsedLikelihood(lik)
    runs = []
    for seed in seeds:
        c = time.process_time()
        fit = sample_collapsed(cl, n, seed=seed, importance_draws=draws, max_steps=steps)
        nat = lik.to_natural(fit.samples)
        comb = combinations(lik.names, nat)
        runs.append({"seed": seed, "log_evidence": fit.log_evidence, "log_evidence_se": fit.log_evidence_se,
                     "evidence_source": fit.evidence_source, "evaluations": fit.n_evaluations,
                     "cpu_s": time.process_time() - c, "quadrature_error": fit.quadrature_error,
                     "mean": {k: float(v.mean()) for k, v in comb.items()},
                     "sd": {k: float(v.std()) for k, v in comb.items()}})
        print(f"seed {seed}: log Z {fit.log_evidence:.4f} ± {fit.log_evidence_se:.4f} ({fit.evidence_source})",
              flush=True)
    keys = runs[0]["mean"]
    logz = [r["log_evidence"] for r in runs]
    out = {"log_evidence": statistics.fmean(logz),
           "log_evidence_sd_between_runs": statistics.stdev(logz) if len(logz) > 1 else None,
           "posterior_mean_and_sd": {k: [statistics.fmean(r["mean"][k] for r in runs),
                                         statistics.fmean(r["sd"][k] for r in runs)] for k in keys},
           "how_obtained": f"collapsed likelihood (amplitudes integrated exactly), TMCMC over the nonlinear "
                           f"parameters N={n}, <= {steps} steps per stage, importance finish with {draws} draws, "
                           f"seeds {seeds}",
           "runs": runs}
    atomic_write_text(path, json.dumps(out, indent=1) + "\n")
    return out


def compare(seeds: list[int], path: Path) -> list[dict]:
    """Today's default full-space TMCMC against the collapsed tier (TMCMC alone and with the IS finish)."""
    from hbm.likelihood.collapsed import CollapsedLikelihood, sample_collapsed

    gold_ = json.loads(GOLD.read_text())
    lik = likelihood()
    cl = CollapsedLikelihood(lik)
    rows = []
    for seed in seeds:   # interleaved: every setting on the same seed before the next seed
        c = time.process_time()
        res = tmcmc(lik, lik.bounds, seed=seed, progress=False)
        dz, dm = _errors(gold_, lik.names, lik.to_natural(res.samples), res.log_evidence)
        rows.append({"setting": "full space, default (N=2000)", "seed": seed, "evaluations": res.n_evaluations,
                     "cpu_s": time.process_time() - c, "log_evidence": res.log_evidence,
                     "log_evidence_se": res.log_evidence_se, "abs_error": dz, "worst_mean_sd": dm})
        for name, kw in (("collapsed, N=1000, <= 10 steps", {"importance_draws": 0}),
                         ("collapsed, N=1000, <= 10 steps + IS 10k", {"importance_draws": 10000}),
                         ("collapsed, N=500, <= 10 steps + IS 10k", {"importance_draws": 10000, "_n": 500})):
            c = time.process_time()
            n = kw.pop("_n", 1000)
            fit = sample_collapsed(cl, n, seed=seed, max_steps=10, **kw)
            dz, dm = _errors(gold_, lik.names, lik.to_natural(fit.samples), fit.log_evidence)
            rows.append({"setting": name, "seed": seed, "evaluations": fit.n_evaluations,
                         "cpu_s": time.process_time() - c, "log_evidence": fit.log_evidence,
                         "log_evidence_se": fit.log_evidence_se, "evidence_source": fit.evidence_source,
                         "abs_error": dz, "worst_mean_sd": dm})
        for r in rows[-4:]:
            print(f"seed {seed} {r['setting']:<42} evals {r['evaluations']:>9} cpu {r['cpu_s']:6.1f} s "
                  f"|dlogZ| {r['abs_error']:.3f} (SE {r['log_evidence_se']:.3f}) worst mean {r['worst_mean_sd']:.2f} sd",
                  flush=True)
    atomic_write_text(path, json.dumps(rows, indent=1) + "\n")
    return rows


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    sub = ap.add_subparsers(dest="cmd", required=True)
    sub.add_parser("make")
    g = sub.add_parser("gold")
    g.add_argument("--n", type=int, default=8000)
    g.add_argument("--steps", type=int, default=80)
    g.add_argument("--seeds", type=int, default=2)
    g.add_argument("--first-seed", type=int, default=0)
    g.add_argument("--out", type=Path, default=GOLD)
    gc = sub.add_parser("gold-collapsed")
    gc.add_argument("--n", type=int, default=4000)
    gc.add_argument("--steps", type=int, default=30)
    gc.add_argument("--draws", type=int, default=100000)
    gc.add_argument("--seeds", type=int, default=3)
    gc.add_argument("--out", type=Path, default=OUT / "qlv_benchmark_gold_collapsed.json")
    cp = sub.add_parser("compare")
    cp.add_argument("--seeds", type=int, default=10)
    cp.add_argument("--out", type=Path, default=OUT / "qlv_posterior.json")
    a = ap.parse_args(argv)
    if a.cmd == "make":
        print(make())
    elif a.cmd == "gold-collapsed":
        print(json.dumps(gold_collapsed(a.n, a.steps, a.draws, list(range(a.seeds)), a.out), indent=1)[:1500])
    elif a.cmd == "compare":
        compare(list(range(a.seeds)), a.out)
    else:
        print(json.dumps(gold(a.n, a.steps, list(range(a.first_seed, a.first_seed + a.seeds)), a.out), indent=1)[:2000])
    return 0


if __name__ == "__main__":
    sys.exit(main())
