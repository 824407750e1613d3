#!/usr/bin/env python
"""Time-to-accuracy of hbm's TMCMC on the real muscle posterior (issue 6, DESIGN.md §6).

Problem: ``../shared/bench/muscle_benchmark.csv`` (``$HBM_BENCH_DIR``) (40 points), the base Spyrou model, iid Gaussian
noise with unknown ``sigma`` in [1e-4, 0.05], uniform prior box; gold answer in
``muscle_benchmark_gold.json`` (log-evidence 163.90 ± 0.29 and the posterior means/sds of the
identifiable combinations).

For every configuration and seed the script runs :func:`hbm.samplers.tmcmc.tmcmc` and records wall time,
stages, likelihood evaluations, the share of the wall time spent inside the likelihood, log Ẑ ± SE,
|log Ẑ − gold| and the largest |posterior mean − gold mean| / gold sd over the combinations
(1−VOLF)·T1, VOLF·P1, G, EOPT, T2, THETA, sigma.  It prints a Markdown table (medians over seeds)
and saves it to ``results/benchmarks/muscle_posterior.md`` (plus a JSON with every run).

Pin to one core for timing::

    OMP_NUM_THREADS=1 OPENBLAS_NUM_THREADS=1 MKL_NUM_THREADS=1 taskset -c 0 \\
        python workflows/benchmarks/muscle_posterior.py

Options: ``--quick`` (small smoke run), ``--seeds K``, ``--configs NAME,...``, ``--n N`` (override
N of every config), ``--out DIR``, ``--peers`` (also PyMC 5 ``sample_smc`` at N = 2000 and 10,000,
run by ``pymc_peer.py`` in a separate benchmark environment: ``$HBM_PYMC_PYTHON``, else
``../bench-venv/bin/python`` or ``.venv-pymc/bin/python``; see README.md in this folder),
``--peer-seeds K`` (default 3), ``--peers-only``, ``--fresh``.  The saved table accumulates: rows of
configurations not re-run are kept from the existing JSON unless ``--fresh``.
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
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[2]
for _p in (str(ROOT), str(Path(__file__).resolve().parent)):
    if _p not in sys.path:
        sys.path.insert(0, _p)

import hbm  # noqa: E402
from experimental_moves import DifferentialEvolution  # noqa: E402
from hbm.samplers.tmcmc import tmcmc  # noqa: E402
from hbm.runtime.files import atomic_write_text  # noqa: E402

BENCH = Path(os.environ.get("HBM_BENCH_DIR", ROOT.parent / "shared" / "bench"))
SIGMA_BOUNDS = (1e-4, 0.05)
GOLD_KEYS = {"(1-VOLF)*T1": "(1-VOLF)*T1", "VOLF*P1": "VOLF*P1", "G": "G=VOLF*GF+(1-VOLF)*GM",
             "EOPT": "EOPT", "T2": "T2", "THETA": "THETA", "sigma": "sigma"}

# name -> tmcmc keyword arguments (besides seed); "default" = the library defaults.
# "_seeds" caps the number of seeds of an expensive configuration.
CONFIGS: dict[str, dict] = {
    "default": {},
    "default-N1000": {"n_samples": 1000},
    "default-N10k": {"n_samples": 10000, "_seeds": 2},
    "logit-30steps-N2k": {"n_samples": 2000, "n_steps": 30},
    "default-N1500": {"n_samples": 1500},
    "box-adaptive-N2k": {"n_samples": 2000, "transform": "none"},
    "box-rw-3steps-N10k": {"n_samples": 10000, "transform": "none", "n_steps": 3, "adapt_scale": False,
                           "n_islands": 1},
    "box-rw-20steps-N10k": {"n_samples": 10000, "transform": "none", "n_steps": 20, "adapt_scale": False,
                            "n_islands": 1, "_seeds": 3},
    "manifold-20steps-N1500": {"move": "manifold", "n_steps": 20, "_seeds": 1},
    # levers measured for the default (see README.md, "Levers tried")
    "cov1.5-N2k": {"n_samples": 2000, "cov_target": 1.5},
    "cov1.25-N2k": {"n_samples": 2000, "cov_target": 1.25},
    "cov2-N2k": {"n_samples": 2000, "cov_target": 2.0},
    "cov0.5-max35-N2k": {"n_samples": 2000, "cov_target": 0.5, "max_steps": 35},
    "de0.5-N2k": {"n_samples": 2000, "move": DifferentialEvolution(fraction=0.5)},  # was de_fraction=0.5
    # "llrank-N2k" (mixing="ll_rank") is gone with the mixing measures other than the default max
    # correlation (no public hook: the stopping rule is part of step()); its row in the results
    # file was made by commit 287c749
    "max60-N2k": {"n_samples": 2000, "max_steps": 60},
}
QUICK_CONFIGS = ["default"]


def read_curve(path: Path) -> tuple[np.ndarray, np.ndarray, dict]:
    """strain, stress and the ``# key: value`` header of a benchmark CSV."""
    meta, rows = {}, []
    header_seen = False
    for line in path.read_text().splitlines():
        s = line.strip()
        if not s:
            continue
        if s.startswith("#"):
            k, _, v = s[1:].partition(":")
            meta[k.strip()] = v.strip()
            continue
        if not header_seen:
            cols = [c.strip() for c in s.split(",")]
            if cols[:2] != ["strain", "stress"]:
                raise hbm.errors.DataError(f"{path}: expected columns 'strain,stress', got {s!r}")
            header_seen = True
            continue
        rows.append([float(v) for v in s.split(",")[:2]])
    a = np.asarray(rows, dtype=float)
    return a[:, 0], a[:, 1], meta


def make_problem():
    """(log-likelihood object with .names/.bounds/.gradient_fim, gold dict, which likelihood)."""
    strain, stress, _ = read_curve(BENCH / "muscle_benchmark.csv")
    gold = json.loads((BENCH / "muscle_benchmark_gold.json").read_text())
    import xarray as xr
    from hbm.likelihood import make_likelihood

    ds = xr.Dataset({"strain": ("point", strain), "stress": ("point", stress)}, attrs={"id": "bench"})
    lik = make_likelihood(hbm.spyrou_model(), ds, noise="iid", sigma_bounds=SIGMA_BOUNDS)
    return lik, gold, "hbm.likelihood.core.make_likelihood"


def summarise(names, samples) -> dict[str, float]:
    """Posterior means of the identifiable combinations."""
    col = {n: samples[:, i] for i, n in enumerate(names)}
    c = col["VOLF"]
    combos = {"(1-VOLF)*T1": (1 - c) * col["T1"], "VOLF*P1": c * col["P1"],
              "G": c * col["GF"] + (1 - c) * col["GM"], "EOPT": col["EOPT"], "T2": col["T2"],
              "THETA": col["THETA"], "sigma": col["sigma"]}
    return {k: float(np.mean(v)) for k, v in combos.items()}


def run_one(lik, gold, name, kwargs, seed, n_override=None) -> dict:
    kw = {k: v for k, v in kwargs.items() if not k.startswith("_")}
    if n_override is not None:
        kw["n_samples"] = int(n_override)
    n = kw.pop("n_samples", None)
    args = (lik, lik.bounds) if n is None else (lik, lik.bounds, n)
    gf = lik.gradient_fim if kw.get("move") == "manifold" else None
    t, c = time.perf_counter(), time.process_time()
    res = tmcmc(*args, seed=seed, gradient_fim=gf, progress=False, **kw)
    wall, cpu = time.perf_counter() - t, time.process_time() - c
    means = summarise(lik.names, res.samples)
    errs = {k: abs(means[k] - gold["posterior_mean_and_sd"][g][0]) / gold["posterior_mean_and_sd"][g][1]
            for k, g in GOLD_KEYS.items()}
    return {"config": name, "seed": seed, "N": res.config.n_samples, "wall": wall, "cpu": cpu,
            "stages": res.n_stages, "evaluations": res.n_evaluations,
            "lik_share": res.likelihood_time / wall, "log_evidence": res.log_evidence,
            "log_evidence_se": res.log_evidence_se,
            "abs_error": abs(res.log_evidence - gold["log_evidence"]),
            "max_mean_err_sd": max(errs.values()), "mean_err_sd": errs,
            "steps_per_stage": [s.n_steps for s in res.stages],
            "acceptance": [round(s.acceptance_rate, 3) for s in res.stages]}


def table(rows: list[dict], gold_logz: float) -> str:
    """Markdown table of medians over seeds per configuration."""
    out = ["| config | N | seeds | wall s | CPU s | stages | evaluations | share in likelihood | log Ẑ ± SE "
           "| sd of log Ẑ over seeds | \\|error\\| | SE covers error | max mean err (gold sd) | measured |",
           "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    by = {}
    for r in rows:
        by.setdefault(r["config"], []).append(r)
    for name, rs in by.items():
        med = lambda k: statistics.median(r[k] for r in rs)  # noqa: E731
        has_se = all(r.get("log_evidence_se") is not None for r in rs)
        has_share = all(r.get("lik_share") is not None for r in rs)
        covered = (f"{sum(r['abs_error'] <= max(2 * r['log_evidence_se'], 1e-12) for r in rs)}/{len(rs)} (2 SE)"
                   if has_se else "no SE")
        lz = f"{med('log_evidence'):.2f} ± {med('log_evidence_se'):.2f}" if has_se else f"{med('log_evidence'):.2f}"
        sd = f"{statistics.stdev(r['log_evidence'] for r in rs):.2f}" if len(rs) > 1 else "–"
        share = f"{100 * med('lik_share'):.0f}%" if has_share else "–"
        when = sorted({(f"{r['measured']} (load {r['load']:.1f})" if "load" in r else r["measured"])
                       if "measured" in r else "before 06:00 (load ≈ 10)" for r in rs})
        out.append(
            f"| {name} | {rs[0]['N']} | {len(rs)} | {med('wall'):.2f} | {med('cpu'):.2f} | {med('stages'):.0f} | "
            f"{med('evaluations'):.3g} | {share} | "
            f"{lz} | {sd} | {med('abs_error'):.2f} | {covered} | {med('max_mean_err_sd'):.2f} | {', '.join(when)} |")
    out.append("")
    out.append(f"Gold: log Z = {gold_logz} (sd between long runs 0.29). Medians over seeds; "
               "'SE covers error' counts runs with |error| ≤ 2·SE (PyMC reports no SE: its between-seed sd "
               "is the column before). CPU s = process time (robust to other jobs on the machine); wall s "
               "is what a user waits. 'measured' = UTC time of the run and the machine's 1-min load average at its end (the rows without one were measured "
               "earlier on a machine with load ≈ 10, so their wall times are ~4–5× their CPU times).")
    return "\n".join(out)


# ---------------------------------------------------------------------------------------------
# PyMC SMC peers: pymc_peer.py runs in a separate benchmark environment (PyMC is not an hbm
# dependency).  Its pytensor model is checked against hbm's numpy likelihood before any run.
# ---------------------------------------------------------------------------------------------
PEER_SCRIPT = Path(__file__).resolve().with_name("pymc_peer.py")
PEER_TOL = 1e-10  # relative agreement demanded of the pytensor re-implementation
PEER_SIZES, PEER_SEEDS = (2000, 10000), 3
PEER_PROTOCOL = ("PyMC timed after one warm-up run (pytensor's compiled-code cache is warm, as for any repeated "
                 "use); time = the pm.sample_smc call with draws=N, chains=1, cores=1, the default IMH kernel "
                 "(threshold 0.5, correlation_threshold 0.01); evaluations = N·(1 + Σ IMH steps per stage).")


def peer_python() -> Path:
    """Python of the bench environment: $HBM_PYMC_PYTHON, else ../bench-venv or .venv-pymc."""
    env = os.environ.get("HBM_PYMC_PYTHON")
    if env:
        return Path(env)
    for cand in (ROOT.parent / "bench-venv" / "bin" / "python", ROOT / ".venv-pymc" / "bin" / "python"):
        if cand.exists():
            return cand
    return ROOT.parent / "bench-venv" / "bin" / "python"


def _peer_call(py: Path, args: list[str], timeout: float = 3600) -> dict:
    p = subprocess.run([str(py), str(PEER_SCRIPT), *args], capture_output=True, text=True, timeout=timeout)
    lines = p.stdout.strip().splitlines()
    if p.returncode != 0 or not lines:
        tail = p.stderr.strip().splitlines()[-1:] or ["no output"]
        raise RuntimeError(f"pymc_peer.py {args[0]} failed (exit {p.returncode}): {tail[0][:300]}")
    return json.loads(lines[-1])


def check_peer_model(py: Path, lik, tmp: Path) -> tuple[float, str]:
    """Largest relative difference between the PyMC model and hbm (stress and log-likelihood).

    Parameter rows: the benchmark's generating parameters, a point near the gold posterior, one
    with slack collagen wherever λ < 1.30 (THETA = 60; the ⟨λH − 1⟩₊ branch), one with T2 = 0
    (collagen term exactly zero), and three uniform draws from the box (extreme stresses).
    """
    names = list(lik.names)
    rows = [dict(VOLF=0.9, EOPT=0.184, P1=0.13, T1=1.5, T2=9.3, THETA=60, GF=0.012, GM=0.009, sigma=0.00297),
            dict(VOLF=0.7, EOPT=0.165, P1=0.14, T1=0.23, T2=19.5, THETA=59.3, GF=0.008, GM=0.007, sigma=0.0024),
            dict(VOLF=0.6, EOPT=0.05, P1=0.3, T1=5.0, T2=50.0, THETA=60.0, GF=0.05, GM=1e-3, sigma=0.01),
            dict(VOLF=0.6, EOPT=0.0, P1=0.3, T1=5.0, T2=0.0, THETA=55.0, GF=0.05, GM=1e-3, sigma=0.01)]
    rng = np.random.default_rng(12345)
    rows += [dict(zip(names, map(float, rng.uniform(lik.bounds[:, 0], lik.bounds[:, 1])))) for _ in range(3)]
    f = tmp / "peer_theta.json"
    atomic_write_text(f, json.dumps(rows))
    out = _peer_call(py, ["check", "--bench", str(BENCH), "--theta", str(f)])
    theta = np.array([[r[k] for k in names] for r in rows])
    ref_s = lik.predict(theta)
    ref_l = lik(theta)
    ds = np.abs(np.asarray(out["stress"]) - ref_s) / np.maximum(np.abs(ref_s), 1e-12)
    dl = np.abs(np.asarray(out["log_likelihood"]) - ref_l) / np.maximum(np.abs(ref_l), 1.0)
    worst = float(max(ds.max(), dl.max()))
    return worst, (f"pytensor model vs hbm at {len(rows)} parameter sets: max relative difference "
                   f"{ds.max():.1e} (stress), {dl.max():.1e} (log-likelihood via the PyMC model's datalogp)")


def run_peers(gold: dict, lik, peer_seeds: list[int], quick: bool) -> tuple[list[dict], list[str]]:
    """PyMC ``sample_smc`` (IMH, chains=1, cores=1) rows in the table's format, and notes."""
    py = peer_python()
    if not py.exists():
        return [], [f"PyMC peer skipped: bench environment python {py} is missing (see README.md: "
                    "python3.11 -m venv ../bench-venv && ../bench-venv/bin/pip install 'pymc>=5.20,<6')."]
    try:
        with tempfile.TemporaryDirectory() as tmp:
            worst, msg = check_peer_model(py, lik, Path(tmp))
    except Exception as e:  # noqa: BLE001 - a broken bench env must not break the hbm benchmark
        return [], [f"PyMC peer skipped: {e}"]
    notes = [msg]
    if not worst <= PEER_TOL:
        return [], notes + [f"PyMC peer not run: the pytensor model disagrees with hbm (> {PEER_TOL:g})."]
    # warm-up: the first sample_smc compiles the logp functions with g++ (~13 s, in child processes
    # that process_time does not see); pytensor caches them, so the timed runs measure sampling
    try:
        _peer_call(py, ["run", "--bench", str(BENCH), "--n", "100", "--seed", "999"])
    except Exception as e:  # noqa: BLE001
        return [], notes + [f"PyMC peer warm-up failed: {e}"]
    notes.append(PEER_PROTOCOL)
    rows = []
    for n in ([300] if quick else PEER_SIZES):
        for seed in peer_seeds:
            try:
                r = _peer_call(py, ["run", "--bench", str(BENCH), "--n", str(n), "--seed", str(seed)])
            except Exception as e:  # noqa: BLE001
                notes.append(f"PyMC SMC N={n} seed={seed} failed: {e}")
                continue
            r.update(config=f"PyMC {r['pymc']} SMC IMH N={n}", lik_share=None, log_evidence_se=None,
                     abs_error=abs(r["log_evidence"] - gold["log_evidence"]), model_check=msg)
            rows.append(r)
            print(f"{r['config']:>18} seed {seed}: {r['wall']:.2f} s, {r['stages']} stages, "
                  f"log Z {r['log_evidence']:.2f}, max mean err {r['max_mean_err_sd']:.2f} sd",
                  file=sys.stderr, flush=True)
    return rows, notes


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--quick", action="store_true", help="small smoke run (N=500, 1 seed, default config)")
    ap.add_argument("--seeds", type=int, default=5, help="number of seeds per configuration (default 5)")
    ap.add_argument("--configs", default=None, help=f"comma-separated subset of {', '.join(CONFIGS)}")
    ap.add_argument("--n", type=int, default=None, help="override N of every configuration")
    ap.add_argument("--out", default=str(ROOT / "results" / "benchmarks"), help="output folder")
    ap.add_argument("--peers", action="store_true",
                    help="also run PyMC SMC (N = 2000, 10000) from the bench environment (README.md)")
    ap.add_argument("--peer-seeds", type=int, default=PEER_SEEDS, help=f"seeds per PyMC size (default {PEER_SEEDS})")
    ap.add_argument("--peers-only", action="store_true", help="run only the PyMC peers (implies --peers)")
    ap.add_argument("--table-only", action="store_true",
                    help="run nothing: re-render the Markdown table from the saved JSON")
    ap.add_argument("--fresh", action="store_true",
                    help="do not keep rows of configurations not re-run from an existing table")
    args = ap.parse_args(argv)

    names = list(CONFIGS) if args.configs is None else [c.strip() for c in args.configs.split(",")]
    for c in names:
        if c not in CONFIGS:
            print(f"error: unknown config {c!r}; choose from {', '.join(CONFIGS)}", file=sys.stderr)
            return 2
    n_override = args.n
    seeds = list(range(args.seeds))
    if args.quick:
        names = names if args.configs else QUICK_CONFIGS
        seeds = seeds[:1] if args.seeds == 5 else seeds
        n_override = n_override or 500
    if args.peers_only:
        names, args.peers = [], True
    if args.table_only:
        names, args.peers, args.fresh = [], False, False
    out = Path(args.out)
    stem = "muscle_posterior_quick" if args.quick else "muscle_posterior"
    stamp = time.strftime("%Y-%m-%d %H:%M", time.gmtime())
    lik, gold, kind = make_problem()
    rows = []
    for name in names:
        for seed in seeds[: CONFIGS[name].get("_seeds", len(seeds))]:
            r = run_one(lik, gold, name, CONFIGS[name], seed, n_override)
            r["measured"] = stamp
            rows.append(r)
            print(f"{name:>18} seed {seed}: {r['wall']:.2f} s, {r['stages']} stages, "
                  f"log Z {r['log_evidence']:.2f} ± {r['log_evidence_se']:.2f}, "
                  f"max mean err {r['max_mean_err_sd']:.2f} sd", file=sys.stderr, flush=True)
    notes: list[str] = []
    if args.peers:
        peer_seeds = seeds[:1] if args.quick else list(range(args.peer_seeds))
        prow, notes = run_peers(gold, lik, peer_seeds, args.quick)
        for r in prow:
            r["measured"] = stamp
        rows += prow
    # keep the rows of configurations not re-run now (the table accumulates across invocations)
    old_path = out / f"{stem}.json"
    if not args.fresh and old_path.exists():
        try:
            old = json.loads(old_path.read_text())
        except ValueError:
            old = []
        rerun = {r["config"] for r in rows}
        rows = [r for r in old if r.get("config") not in rerun] + rows
    # hbm configurations in CONFIGS order, then the peers (stable: seeds keep their order)
    order = {c: i for i, c in enumerate(CONFIGS)}
    rows.sort(key=lambda r: order.get(r["config"], len(order)))
    load = os.getloadavg() if hasattr(os, "getloadavg") else (float("nan"),) * 3
    for r in rows:  # 1-min load average of the 2-core machine at the end of this invocation
        if r.get("measured") == stamp and "load" not in r:
            r["load"] = float(load[0])
    if args.table_only:
        head = f"Likelihood: {kind}. Table re-rendered {stamp} UTC from the saved runs (times: column 'measured')."
    else:
        head = (f"Likelihood: {kind}. Last invocation {stamp} UTC: OMP_NUM_THREADS="
                f"{os.environ.get('OMP_NUM_THREADS', 'unset')}, CPU affinity "
                f"{sorted(os.sched_getaffinity(0)) if hasattr(os, 'sched_getaffinity') else '?'}, load average at "
                f"the end {load[0]:.2f} (1 min) / {load[1]:.2f} (5 min) on 2 cores.")
    md = ["# TMCMC on the muscle benchmark posterior", "", head, "", table(rows, gold["log_evidence"])]
    # the model check and timing protocol of peer rows kept from earlier invocations
    for r in rows:
        for note in ((r["model_check"], PEER_PROTOCOL) if r.get("model_check") else ()):
            if note not in notes:
                notes.append(note)
    if notes:
        md += ["", "## Peers", ""] + ["- " + s for s in notes]
    text = "\n".join(md) + "\n"
    print(text)
    atomic_write_text(out / f"{stem}.md", text)
    atomic_write_text(out / f"{stem}.json", json.dumps(rows, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
