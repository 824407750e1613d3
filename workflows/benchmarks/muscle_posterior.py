#!/usr/bin/env python
"""Time-to-accuracy of hbm's TMCMC on the real muscle posterior (issue 6, DESIGN.md §6).

Problem: ``/work/shared/bench/muscle_benchmark.csv`` (40 points), the base Spyrou model, iid Gaussian
noise with unknown ``sigma`` in [1e-4, 0.05], uniform prior box; gold answer in
``muscle_benchmark_gold.json`` (log-evidence 163.90 ± 0.29 and the posterior means/sds of the
identifiable combinations).

For every configuration and seed the script runs :func:`hbm.samplers.tmcmc` and records wall time,
stages, likelihood evaluations, the share of the wall time spent inside the likelihood, log Ẑ ± SE,
|log Ẑ − gold| and the largest |posterior mean − gold mean| / gold sd over the combinations
(1−VOLF)·T1, VOLF·P1, G, EOPT, T2, THETA, sigma.  It prints a Markdown table (medians over seeds)
and saves it to ``results/benchmarks/muscle_posterior.md`` (plus a JSON with every run).

Pin to one core for timing::

    OMP_NUM_THREADS=1 OPENBLAS_NUM_THREADS=1 MKL_NUM_THREADS=1 taskset -c 0 \\
        python workflows/benchmarks/muscle_posterior.py

Options: ``--quick`` (small smoke run), ``--seeds K``, ``--configs NAME,...``, ``--n N`` (override
N of every config), ``--out DIR``, ``--peers`` (PyMC SMC from the separate env ``.venv-pymc``; see
README.md in this folder).
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[2]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

import hbm  # noqa: E402
from hbm.samplers import tmcmc  # noqa: E402
from hbm.utils import atomic_write_text  # noqa: E402

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
    "manifold-20steps-N1500": {"kernel": "manifold", "n_steps": 20, "_seeds": 1},
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


class InlineLikelihood:
    """iid Gaussian log-likelihood of the base model (fallback if hbm.likelihood is missing)."""

    def __init__(self, model, strain, stress):
        self.model, self.strain, self.stress = model, strain, stress
        self.names = tuple(model.parameter_names) + ("sigma",)
        self.bounds = np.vstack([model.bounds, [SIGMA_BOUNDS]])

    def __call__(self, theta):
        theta = np.asarray(theta, dtype=float)
        n = self.stress.size
        with np.errstate(all="ignore"):
            r = self.stress - self.model.stress(self.strain, theta[:, :-1])
            s = theta[:, -1]
            out = -n * np.log(s) - 0.5 * n * np.log(2 * np.pi) - np.einsum("ij,ij->i", r, r) / (2 * s * s)
        return np.where(np.isfinite(out), out, -np.inf)

    def gradient_fim(self, theta):
        theta = np.asarray(theta, dtype=float)
        n = self.stress.size
        s = theta[:, -1]
        with np.errstate(all="ignore"):
            r = self.stress - self.model.stress(self.strain, theta[:, :-1])
            jac = self.model.stress_jacobian(self.strain, theta[:, :-1])
            g = np.empty(theta.shape)
            g[:, :-1] = np.einsum("np,npk->nk", r, jac) / (s * s)[:, None]
            g[:, -1] = -n / s + np.einsum("ij,ij->i", r, r) / s ** 3
            f = np.zeros(theta.shape + (theta.shape[1],))
            f[:, :-1, :-1] = np.einsum("npi,npj->nij", jac, jac) / (s * s)[:, None, None]
            f[:, -1, -1] = 2 * n / (s * s)
        return g, f


def make_problem():
    """(log-likelihood object with .names/.bounds/.gradient_fim, gold dict, which likelihood)."""
    strain, stress, _ = read_curve(BENCH / "muscle_benchmark.csv")
    gold = json.loads((BENCH / "muscle_benchmark_gold.json").read_text())
    model = hbm.spyrou_model()
    try:
        import xarray as xr
        from hbm.likelihood import make_likelihood
        ds = xr.Dataset({"strain": ("point", strain), "stress": ("point", stress)}, attrs={"id": "bench"})
        lik = make_likelihood(model, ds, noise="iid", sigma_bounds=SIGMA_BOUNDS)
        kind = "hbm.likelihood.make_likelihood"
    except ImportError:
        lik = InlineLikelihood(model, strain, stress)
        kind = "inline"
    return lik, gold, kind


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
    gf = lik.gradient_fim if kw.get("kernel") == "manifold" else None
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
            "steps_per_stage": [s["n_steps"] for s in res.stages],
            "acceptance": [round(s["acceptance_rate"], 3) for s in res.stages]}


def table(rows: list[dict], gold_logz: float) -> str:
    """Markdown table of medians over seeds per configuration."""
    out = ["| config | N | seeds | wall s | CPU s | stages | evaluations | share in likelihood | log Ẑ ± SE "
           "| \\|error\\| | SE covers error | max mean err (gold sd) |",
           "|---|---|---|---|---|---|---|---|---|---|---|---|"]
    by = {}
    for r in rows:
        by.setdefault(r["config"], []).append(r)
    for name, rs in by.items():
        med = lambda k: statistics.median(r[k] for r in rs)  # noqa: E731
        covered = sum(r["abs_error"] <= max(2 * r["log_evidence_se"], 1e-12) for r in rs)
        out.append(
            f"| {name} | {rs[0]['N']} | {len(rs)} | {med('wall'):.2f} | {med('cpu'):.2f} | {med('stages'):.0f} | "
            f"{med('evaluations'):.3g} | {100 * med('lik_share'):.0f}% | "
            f"{med('log_evidence'):.2f} ± {med('log_evidence_se'):.2f} | {med('abs_error'):.2f} | "
            f"{covered}/{len(rs)} (2 SE) | {med('max_mean_err_sd'):.2f} |")
    out.append("")
    out.append(f"Gold: log Z = {gold_logz} (sd between long runs 0.29). Medians over seeds; "
               "'SE covers error' counts runs with |error| ≤ 2·SE. CPU s = process time (robust to "
               "other jobs on the machine); wall s is what a user waits.")
    return "\n".join(out)


# Runs inside the separate PyMC environment (PyMC is not an hbm dependency): the base model
# written in pytensor, uniform priors on the gold box, iid Gaussian noise, pm.sample_smc.
PEER_CODE = r"""
import json, sys, time
import numpy as np, pymc as pm, pytensor.tensor as pt
bench, n, seed = sys.argv[1], int(sys.argv[2]), int(sys.argv[3])
rows = [l for l in open(bench + "/muscle_benchmark.csv") if l.strip() and not l.startswith("#")][1:]
eps, obs = np.array([[float(v) for v in r.split(",")[:2]] for r in rows]).T
gold = json.load(open(bench + "/muscle_benchmark_gold.json"))
lam = 1.0 + eps
box = dict(VOLF=(0.5, 0.99), EOPT=(0, 0.2), P1=(1e-4, 0.5), T1=(0, 20), T2=(0, 200), THETA=(55, 60),
           GF=(1e-4, 0.1), GM=(1e-4, 0.1), sigma=(1e-4, 0.05))
with pm.Model():
    p = {k: pm.Uniform(k, lo, hi) for k, (lo, hi) in box.items()}
    c, th = p["VOLF"], p["THETA"] * np.pi / 180
    lh = pt.sqrt(pt.cos(th) ** 2 * lam ** 2 + pt.sin(th) ** 2 / lam)
    mu = ((c * p["GF"] + (1 - c) * p["GM"]) * (lam ** 2 - 1 / lam)
          + lam * c * p["P1"] * pt.maximum(eps - p["EOPT"], 0)
          + lam * (1 - c) * p["T1"] * (pt.exp(p["T2"] * pt.maximum(lh - 1, 0)) - 1))
    pm.Normal("y", mu, p["sigma"], observed=obs)
    t = time.perf_counter()
    idata = pm.sample_smc(draws=n, chains=1, random_seed=seed, progressbar=False)
    wall = time.perf_counter() - t
post = idata.posterior
lz = np.asarray(idata.sample_stats["log_marginal_likelihood"]).ravel()
lz = float([v for v in np.concatenate([np.atleast_1d(x) for x in lz]) if np.isfinite(v)][-1])
c = post["VOLF"].values.ravel()
comb = {"(1-VOLF)*T1": (1 - c) * post["T1"].values.ravel(), "VOLF*P1": c * post["P1"].values.ravel(),
        "G=VOLF*GF+(1-VOLF)*GM": c * post["GF"].values.ravel() + (1 - c) * post["GM"].values.ravel()}
for k in ("EOPT", "T2", "THETA", "sigma"):
    comb[k] = post[k].values.ravel()
g = gold["posterior_mean_and_sd"]
err = max(abs(comb[k].mean() - g[k][0]) / g[k][1] for k in g)
print(json.dumps({"N": n, "seed": seed, "wall": wall, "log_evidence": lz, "max_mean_err_sd": err}))
"""


def run_peers(seeds: list[int], quick: bool) -> list[str]:
    """PyMC SMC in the separate environment ``.venv-pymc`` (see README.md); one line per run."""
    py = Path(os.environ.get("HBM_PYMC_PYTHON", ROOT / ".venv-pymc" / "bin" / "python"))
    if not py.exists():
        return [f"PyMC peer skipped: environment {py} is missing "
                "(python -m venv .venv-pymc && .venv-pymc/bin/pip install pymc)."]
    lines = []
    for n in ([500] if quick else [2000, 10000]):
        for seed in seeds[:1] if quick else seeds[:3]:
            p = subprocess.run([str(py), "-c", PEER_CODE, str(BENCH), str(n), str(seed)],
                               capture_output=True, text=True)
            out = p.stdout.strip().splitlines()[-1] if p.stdout.strip() else p.stderr.strip()[-300:]
            lines.append(f"PyMC SMC N={n} seed={seed}: {out}")
    return lines


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--quick", action="store_true", help="small smoke run (N=500, 1 seed, default config)")
    ap.add_argument("--seeds", type=int, default=5, help="number of seeds per configuration (default 5)")
    ap.add_argument("--configs", default=None, help=f"comma-separated subset of {', '.join(CONFIGS)}")
    ap.add_argument("--n", type=int, default=None, help="override N of every configuration")
    ap.add_argument("--out", default=str(ROOT / "results" / "benchmarks"), help="output folder")
    ap.add_argument("--peers", action="store_true", help="also run PyMC SMC from .venv-pymc")
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
    lik, gold, kind = make_problem()
    rows = []
    for name in names:
        for seed in seeds[: CONFIGS[name].get("_seeds", len(seeds))]:
            r = run_one(lik, gold, name, CONFIGS[name], seed, n_override)
            rows.append(r)
            print(f"{name:>18} seed {seed}: {r['wall']:.2f} s, {r['stages']} stages, "
                  f"log Z {r['log_evidence']:.2f} ± {r['log_evidence_se']:.2f}, "
                  f"max mean err {r['max_mean_err_sd']:.2f} sd", file=sys.stderr, flush=True)
    md = ["# TMCMC on the muscle benchmark posterior", "",
          f"Likelihood: {kind}; threads: OMP_NUM_THREADS={os.environ.get('OMP_NUM_THREADS', 'unset')}, "
          f"CPU affinity: {sorted(os.sched_getaffinity(0)) if hasattr(os, 'sched_getaffinity') else '?'}; "
          f"{time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())}.", "",
          table(rows, gold["log_evidence"])]
    if args.peers:
        md += ["", "## Peers", ""] + ["- " + s for s in run_peers(seeds, args.quick)]
    text = "\n".join(md) + "\n"
    print(text)
    out = Path(args.out)
    stem = "muscle_posterior_quick" if args.quick else "muscle_posterior"
    atomic_write_text(out / f"{stem}.md", text)
    atomic_write_text(out / f"{stem}.json", json.dumps(rows, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
