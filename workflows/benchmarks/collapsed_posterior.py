#!/usr/bin/env python
"""The collapsed likelihood on the muscle benchmark (issue 27): evaluations, accuracy and CPU.

Settings, interleaved seed by seed in one run:

* ``collapsed TMCMC`` -- TMCMC over (VOLF, EOPT, T2, THETA, sigma) on the likelihood with the three
  amplitudes integrated out (:mod:`hbm.likelihood.collapsed`), N = 1000, at most 10 MH steps per stage; the
  full posterior completed by drawing the amplitudes and the original parameters given φ.
* ``collapsed + IS`` -- N = 500, at most 5 MH steps per stage, and an importance-sampling finish
  (up to 10 000 draws in the sampler's logit coordinates: 30 % from a t proposal fitted to the
  pilot, whose weighted draws refit a 3-component t mixture for the next 50 %; the last 20 %
  only when that estimate is refused): its evidence and its resampled draws as the posterior
  when k̂ ≤ 0.7 and ESS ≥ 200, else TMCMC's.
* ``IS, one refitted t (before)`` -- the same with the finish as it was before the mixture and
  the reserve (10 000 draws, 30 % refit one t), the baseline of that change (``--with-before``).
* ``full default`` -- today's full-space TMCMC at its defaults (N = 2000), the baseline.

Per run: evaluations (basis evaluations count as model evaluations; the completion's full-model
evaluations are included), CPU (process time) and wall seconds, |log Ẑ − gold|, the worst
posterior-mean error of the seven gold quantities in gold sd (``muscle_posterior.summarise``),
whether the reported SE covers the error (|error| ≤ 2 SE, as ``evaluations_to_accuracy.py``)
and whether the run reached |Δlog Ẑ| ≤ 0.3 and worst mean ≤ 0.3 sd.  Then the CPU of a whole
default ``fit_specimen`` (CMA-ES, TMCMC, predictive) with ``tier="auto"`` (collapsed) and
``"full"`` on the benchmark curve, interleaved over ``--fit-seeds`` seeds.

A section is appended to ``results/benchmarks/evaluations_to_accuracy.md`` and every run is written
to ``results/benchmarks/collapsed_posterior.json``.

Usage::

    HBM_BENCH_DIR=../shared/bench nice -n 10 python workflows/benchmarks/collapsed_posterior.py [--seeds 10]
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import statistics
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[2]
HERE = Path(__file__).resolve().parent
for p in (str(ROOT), str(HERE)):
    if p not in sys.path:
        sys.path.insert(0, p)

import muscle_posterior as mp  # noqa: E402
import xarray as xr  # noqa: E402
from hbm.runtime.blas import single_thread_blas  # noqa: E402
from hbm.likelihood.collapsed import CollapsedLikelihood, sample_collapsed  # noqa: E402
from hbm.likelihood.collapsed import sampling as collapse_sampling  # noqa: E402
from hbm.fit import fit_specimen  # noqa: E402
from hbm.samplers.tmcmc import tmcmc  # noqa: E402
from hbm.runtime.files import atomic_write_text  # noqa: E402

TARGET_LOGZ, TARGET_MEAN = 0.3, 0.3
BEFORE = "IS, one refitted t (before)"
#: setting -> (TMCMC N, max MH steps per stage, importance draws, evaluation target)
SETTINGS = {"collapsed TMCMC (N=1000, ≤10 steps)": (1000, 10, 0, 75_000),
            "collapsed N=500, ≤5 steps + IS (10k draws)": (500, 5, 10_000, 30_000),
            BEFORE: (500, 5, 10_000, 30_000)}
BASELINE = "full default (N=2000)"
DEFAULT_SETTINGS = [k for k in SETTINGS if k != BEFORE] + [BASELINE]


@contextlib.contextmanager
def _finish_before():
    """The importance finish before the mixture refit and the reserve (one refitted t)."""
    old = collapse_sampling.FINISH_MIXTURE, collapse_sampling.FINISH_RESERVE
    collapse_sampling.FINISH_MIXTURE, collapse_sampling.FINISH_RESERVE = 0, 0.0
    try:
        yield
    finally:
        collapse_sampling.FINISH_MIXTURE, collapse_sampling.FINISH_RESERVE = old


def _row(setting, seed, evaluations, cpu, wall, log_z, se, natural_samples, names, gold, **extra) -> dict:
    means = mp.summarise(names, natural_samples)
    worst = max(abs(means[k] - gold["posterior_mean_and_sd"][g][0]) / gold["posterior_mean_and_sd"][g][1]
                for k, g in mp.GOLD_KEYS.items())
    err = abs(log_z - gold["log_evidence"])
    both = float(np.hypot(se, gold.get("log_evidence_se", 0.0)))
    return {"setting": setting, "seed": seed, "evaluations": int(evaluations), "cpu": cpu, "wall": wall,
            "log_evidence": float(log_z), "log_evidence_se": float(se), "abs_error": float(err),
            "max_mean_err_sd": float(worst), "covered_2se": bool(np.isfinite(se) and err <= 2 * se),
            "covered_2se_with_gold": bool(np.isfinite(se) and err <= 2 * both),
            "reached": bool(err <= TARGET_LOGZ and worst <= TARGET_MEAN), **extra}


def run_collapsed(lik, cl, gold, setting, seed) -> dict:
    n, steps, importance, _ = SETTINGS[setting]
    c, w = time.process_time(), time.perf_counter()
    with _finish_before() if setting == BEFORE else contextlib.nullcontext():
        f = sample_collapsed(cl, n, seed=seed, max_steps=steps, importance_draws=importance)
    cpu, wall = time.process_time() - c, time.perf_counter() - w
    extra = {"tmcmc_log_evidence": f.tmcmc.log_evidence, "tmcmc_se": f.tmcmc.log_evidence_se,
             "tmcmc_evaluations": f.tmcmc.n_evaluations, "evidence_source": f.evidence_source,
             "quadrature_error": f.quadrature_error, "stages": f.tmcmc.n_stages}
    if f.importance is not None:
        extra["importance"] = f.importance.to_dict()
    return _row(setting, seed, f.n_evaluations, cpu, wall, f.log_evidence, f.log_evidence_se,
                lik.to_natural(f.samples), lik.names, gold, **extra)


def run_full(lik, gold, seed) -> dict:
    c, w = time.process_time(), time.perf_counter()
    r = tmcmc(lik, lik.bounds, 2000, seed=seed, progress=False)
    cpu, wall = time.process_time() - c, time.perf_counter() - w
    return _row(BASELINE, seed, r.n_evaluations, cpu, wall, r.log_evidence, r.log_evidence_se,
                r.samples, lik.names, gold, stages=r.n_stages)


def run_fits(seeds) -> list[dict]:
    """CPU of a default fit_specimen, collapsed vs full, interleaved."""
    strain, stress, _ = mp.read_curve(mp.BENCH / "muscle_benchmark.csv")
    ds = xr.Dataset({"strain": ("point", strain), "stress": ("point", stress)}, attrs={"id": "bench"})
    out = []
    for seed in seeds:
        for tier in ("auto", "full"):
            c, w = time.process_time(), time.perf_counter()
            res = fit_specimen(ds, seed=seed, progress=False, tier=tier, sigma_bounds=mp.SIGMA_BOUNDS)
            out.append({"setting": f"fit_specimen default, tier={tier}", "seed": seed,
                        "cpu": time.process_time() - c, "wall": time.perf_counter() - w,
                        "tier": res.result.config["likelihood_tier"],
                        "evaluations": res.result.config["n_evaluations"],
                        "log_evidence": res.log_evidence, "log_evidence_se": res.log_evidence_se,
                        "route": (res.result.config.get("collapsed") or {}).get("route", "full TMCMC"),
                        "timings": res.timings})
            _say(out[-1])
    return out


def _say(r: dict) -> None:
    print(f"{r['setting']:<40} seed {r['seed']}: {r['evaluations']:>8} evals, CPU {r['cpu']:6.1f} s, "
          f"wall {r['wall']:6.1f} s, log Z {r['log_evidence']:.3f} ± {r['log_evidence_se']:.3f}"
          + (f", |err| {r['abs_error']:.3f}, worst {r['max_mean_err_sd']:.2f} sd" if "abs_error" in r else ""),
          flush=True)


def _markdown(head: list[str], rows: list[dict], cells) -> str:
    """A markdown table: one line per setting (rows grouped by "setting") from ``cells(name, rows)``."""
    by: dict[str, list[dict]] = {}
    for r in rows:
        by.setdefault(r["setting"], []).append(r)
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    lines += ["| " + " | ".join(cells(name, rs)) + " |" for name, rs in by.items()]
    return "\n".join(lines)


def _med(rs, k):
    return statistics.median(r[k] for r in rs)


def table(rows: list[dict]) -> str:
    head = ["setting", "seeds", "evaluations (median)", "CPU s (median)", "wall s (median)", "median \\|Δlog Ẑ\\|",
            "max \\|Δlog Ẑ\\|", "worst mean err, median / max (gold sd)", "reached target", "SE covers (2 SE)",
            "covers with the gold's SE"]
    return _markdown(head, rows, lambda name, rs: [
        name, str(len(rs)), f"{_med(rs, 'evaluations'):.3g}", f"{_med(rs, 'cpu'):.2f}", f"{_med(rs, 'wall'):.1f}",
        f"{_med(rs, 'abs_error'):.3f}", f"{max(r['abs_error'] for r in rs):.3f}",
        f"{_med(rs, 'max_mean_err_sd'):.2f} / {max(r['max_mean_err_sd'] for r in rs):.2f}",
        f"{sum(r['reached'] for r in rs)}/{len(rs)}", f"{sum(r['covered_2se'] for r in rs)}/{len(rs)}",
        f"{sum(r.get('covered_2se_with_gold', False) for r in rs)}/{len(rs)}"])


def fit_table(rows: list[dict]) -> str:
    head = ["fit", "seeds", "tier", "evaluations (median)", "CPU s (median)", "wall s (median)", "log Ẑ (median)"]
    return _markdown(head, rows, lambda name, rs: [
        name, str(len(rs)), rs[0]["tier"], f"{_med(rs, 'evaluations'):.3g}", f"{_med(rs, 'cpu'):.1f}",
        f"{_med(rs, 'wall'):.1f}", f"{_med(rs, 'log_evidence'):.2f}"])


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=10)
    ap.add_argument("--first-seed", type=int, default=0, help="seeds FIRST .. FIRST + SEEDS − 1")
    ap.add_argument("--fit-seeds", type=int, default=3)
    ap.add_argument("--only", choices=list(SETTINGS) + [BASELINE], action="append",
                    help="run only these settings (repeatable; default all and the baseline)")
    ap.add_argument("--with-before", action="store_true", help=f"also run {BEFORE!r} (interleaved)")
    ap.add_argument("--out", default=str(ROOT / "results" / "benchmarks" / "evaluations_to_accuracy.md"))
    args = ap.parse_args(argv)
    lik, gold, _ = mp.make_problem()
    cl = CollapsedLikelihood(lik)
    t0 = time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime())
    names = args.only or DEFAULT_SETTINGS[:-1] + ([BEFORE] if args.with_before else []) + [BASELINE]
    rows = []
    with single_thread_blas():  # CPU of one thread: the ratio does not depend on BLAS threads
        cl(cl.bounds.mean(axis=1)[None])  # the compiled kernels load before anything is timed
        for seed in range(args.first_seed, args.first_seed + args.seeds):  # interleaved: every setting of a seed before the next seed
            for name in names:
                r = run_full(lik, gold, seed) if name == BASELINE else run_collapsed(lik, cl, gold, name, seed)
                rows.append(r)
                _say(r)
        fits = run_fits(range(args.fit_seeds)) if args.fit_seeds else []
    load = os.getloadavg()[0]
    by = {}
    for r in rows:
        by.setdefault(r["setting"], []).append(r)
    notes = []
    for name, (_, _, _, limit) in SETTINGS.items():
        rs = by.get(name)
        if not rs:
            continue
        ok = sum(r["reached"] for r in rs)
        ev = statistics.median(r["evaluations"] for r in rs)
        notes.append(f"- {name}: median {ev:.3g} evaluations (target ≤ {limit:,}), {ok}/{len(rs)} seeds in target "
                     f"(needed ≥ 9/10), SE covers the error in {sum(r['covered_2se'] for r in rs)}/{len(rs)}.")
    for name, rs in by.items():
        imp = [r for r in rs if "importance" in r]
        if not imp:
            continue
        refused = [r for r in imp if not r["importance"]["accepted"]]
        ess = [r["importance"]["ess"] for r in imp]
        notes.append(f"- importance finish of {name}: ESS {min(ess):.0f}–{max(ess):.0f}, k̂ "
                     f"{min(r['importance']['khat'] for r in imp):.2f}–{max(r['importance']['khat'] for r in imp):.2f}; "
                     f"draws {min(r['importance']['n_evaluations'] for r in imp)}–"
                     f"{max(r['importance']['n_evaluations'] for r in imp)}; "
                     f"refused (TMCMC evidence kept) in {len(refused)}/{len(imp)}"
                     + ("".join(f"; seed {r['seed']}: {r['importance']['reason']}" for r in refused)))
    if args.seeds > 10:  # the verdict per set of 10 seeds
        for a in range(args.first_seed, args.first_seed + args.seeds, 10):
            cells = []
            for name, rs in by.items():
                sub = [r for r in rs if a <= r["seed"] < a + 10]
                cells.append(f"{name}: {sum(r['reached'] for r in sub)}/{len(sub)} in target, SE covers "
                             f"{sum(r['covered_2se'] for r in sub)}/{len(sub)} "
                             f"({sum(r['covered_2se_with_gold'] for r in sub)}/{len(sub)} with the gold's SE)")
            notes.append(f"- seeds {a}–{min(a + 9, args.first_seed + args.seeds - 1)}: " + "; ".join(cells))
    qe = max([r.get("quadrature_error", 0.0) for r in rows] or [0.0])
    notes.append(f"- largest quadrature error estimate of log L_c over the posterior rows checked: {qe:.1e} nats.")
    fa = [r["cpu"] for r in fits if r["tier"] == "collapsed"]
    ff = [r["cpu"] for r in fits if r["tier"] == "full"]
    if fa and ff:
        notes.append(f"- CPU of a default fit (fit_specimen, N = 2000, 4 CMA-ES restarts; process time, one BLAS "
                     f"thread): collapsed {statistics.median(fa):.2f} s vs full {statistics.median(ff):.2f} s (median "
                     f"of {len(fa)} interleaved seeds; ratio {statistics.median(fa) / statistics.median(ff):.2f}; "
                     f"per seed {', '.join(f'{a / b:.2f}' for a, b in zip(fa, ff))}).")
    section = "\n".join([
        "", f"## Collapsed likelihood: amplitudes integrated exactly, TMCMC over φ only (issue 27; {t0})", "",
        "`workflows/benchmarks/collapsed_posterior.py --seeds "
        f"{args.seeds} --first-seed {args.first_seed} --fit-seeds {args.fit_seeds}"
        f"{' --with-before' if args.with_before else ''}` on the muscle benchmark against the gold log Z {gold['log_evidence']}; one process, "
        f"settings interleaved per seed; machine load at the end {load:.1f} (wall times suffer, CPU times do not). "
        "Evaluations count basis evaluations X(φ) as model evaluations, plus the full-model evaluations of the "
        "completed posterior.", "",
        table(rows), "", *notes, "", fit_table(fits) if fits else "", ""])
    out = Path(args.out)
    prev = out.read_text() if out.exists() else ""
    atomic_write_text(out, prev.rstrip("\n") + "\n" + section)
    js = out.with_name("collapsed_posterior.json")
    rounds = json.loads(js.read_text()).get("rounds", []) if js.exists() else []
    rounds.append({"measured": t0, "load": load, "gold": gold["log_evidence"], "runs": rows, "fits": fits})
    atomic_write_text(js, json.dumps({"rounds": rounds}, indent=1, default=float))
    print(section)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
