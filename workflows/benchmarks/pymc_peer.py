#!/usr/bin/env python
"""PyMC SMC peer for the muscle-posterior benchmark (runs in the separate bench venv, not in hbm's).

PyMC is *not* an hbm dependency: ``muscle_posterior.py --peers`` calls this file with the bench
environment's python (see README.md in this folder).  It imports only numpy, pymc and pytensor, so
it never imports hbm.

The model is a re-implementation in pytensor of the base Spyrou model of
``hbm/model/spyrou.py`` (iso_factor 1), term by term and with the same numerics (expm1, the
exponent clipped at 700, λH² = cos²θ·(λ² − 1/λ) + 1/λ)::

    σ = (c·GF + (1−c)·GM)(λ² − 1/λ) + λ·c·P1·⟨ε − EOPT⟩₊ + λ·(1−c)·T1·expm1(min(T2·⟨λH − 1⟩₊, 700))

with λ = 1 + ε, c = VOLF; iid Gaussian noise with unknown sd ``sigma``; independent uniform priors
on the box of ``muscle_benchmark_gold.json`` (PyMC's default interval transform, which leaves the
evidence unchanged).

Modes (each prints one JSON line on stdout):

``run --bench DIR --n N --seed S [--kernel imh|mh]``
    ``pm.sample_smc(draws=N, chains=1, cores=1, random_seed=S)``; reports wall and CPU (process)
    time of the ``sample_smc`` call (includes the kernel's compilation of the logp functions,
    ~1 s, cached by pytensor between runs), the log marginal likelihood (last stage's
    ``idata.sample_stats["log_marginal_likelihood"]``; the other stages hold NaN), stages,
    MH steps per stage, likelihood evaluations, posterior means of the benchmark combinations.
``check --bench DIR --theta FILE.json``
    Evaluates the pytensor mean stress and the log-likelihood *through the PyMC model's own
    ``datalogp``* (value variables forward-transformed) at the parameter rows of ``FILE.json``
    (list of dicts name -> value) so the caller can compare them with hbm's numpy model.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

NAMES = ("VOLF", "EOPT", "P1", "T1", "T2", "THETA", "GF", "GM", "sigma")
EXP_CLIP = 700.0  # same clip as hbm.model.spyrou._EXP_CLIP


def read_bench(bench: Path):
    """strain, stress and the prior box (dict name -> (lo, hi)) of the benchmark."""
    rows, header = [], False
    for line in (bench / "muscle_benchmark.csv").read_text().splitlines():
        s = line.strip()
        if not s or s.startswith("#"):
            continue
        if not header:
            header = True
            continue
        rows.append([float(v) for v in s.split(",")[:2]])
    eps, obs = np.asarray(rows, float).T
    gold = json.loads((bench / "muscle_benchmark_gold.json").read_text())
    box = {}
    # "VOLF[0.5,0.99] EOPT[0,0.2] ..." in gold["problem"]: the single source of the prior box
    for tok in gold["problem"].split(":", 1)[1].split():
        if "[" in tok:
            name, rng = tok.split("[")
            lo, hi = rng.rstrip("]").split(",")
            box[name] = (float(lo), float(hi))
    missing = [n for n in NAMES if n not in box]
    if missing:
        raise SystemExit(f"error: prior box for {missing} not found in muscle_benchmark_gold.json 'problem'")
    return eps, obs, box, gold


def spyrou_stress(pt, eps: np.ndarray, p: dict):
    """Base Spyrou model (iso_factor 1) in pytensor; ``p`` maps name -> scalar tensor."""
    lam = 1.0 + eps
    nh = lam * lam - 1.0 / lam  # neo-Hookean factor λ² − 1/λ (constant: strain is data)
    c = p["VOLF"]
    matrix = (c * p["GF"] + (1.0 - c) * p["GM"]) * nh
    fibers = lam * c * p["P1"] * pt.maximum(eps - p["EOPT"], 0.0)
    c2 = pt.cos(p["THETA"] * (np.pi / 180.0)) ** 2
    x = pt.maximum(pt.sqrt(c2 * nh + 1.0 / lam) - 1.0, 0.0)
    collagen = lam * (1.0 - c) * p["T1"] * pt.expm1(pt.minimum(p["T2"] * x, EXP_CLIP))
    return matrix + fibers + collagen


def build_model(eps, obs, box):
    import pymc as pm
    import pytensor.tensor as pt

    with pm.Model() as model:
        p = {k: pm.Uniform(k, *box[k]) for k in NAMES}
        pm.Normal("y", mu=spyrou_stress(pt, eps, p), sigma=p["sigma"], observed=obs)
    return model


def check(bench: Path, theta_file: Path) -> dict:
    import pytensor
    import pytensor.tensor as pt

    eps, obs, box, _ = read_bench(bench)
    rows = json.loads(theta_file.read_text())
    # 1) the stress expression on plain scalar inputs
    sym = {k: pt.dscalar(k) for k in NAMES}
    f_mu = pytensor.function([sym[k] for k in NAMES], spyrou_stress(pt, eps, sym), on_unused_input="ignore")
    stress = [np.asarray(f_mu(*[r[k] for k in NAMES])).tolist() for r in rows]
    # 2) the log-likelihood exactly as the SMC kernel sees it: model.datalogp of the value vars
    model = build_model(eps, obs, box)
    f_ll = model.compile_fn(model.datalogp, point_fn=True)
    ll = []
    for r in rows:
        point = {}
        for rv in model.free_RVs:
            value = model.rvs_to_values[rv]
            tr = model.rvs_to_transforms.get(rv)
            x = pt.as_tensor_variable(np.float64(r[rv.name]))
            point[value.name] = float(tr.forward(x, *rv.owner.inputs).eval()) if tr is not None else r[rv.name]
        ll.append(float(f_ll(point)))
    return {"stress": stress, "log_likelihood": ll}


def run(bench: Path, n: int, seed: int, kernel: str) -> dict:
    import pymc as pm

    eps, obs, box, gold = read_bench(bench)
    model = build_model(eps, obs, box)
    base = pm.smc.kernels.IMH if kernel == "imh" else pm.smc.kernels.MH
    steps: list[int] = []

    class Counted(base):  # records the MH steps of each stage; the algorithm is unchanged
        def mutate(self):
            super().mutate()
            steps.append(int(self.n_steps) - 1)  # n_steps starts at 1 and counts one extra

    with model:
        t, c = time.perf_counter(), time.process_time()
        idata = pm.sample_smc(draws=n, kernel=Counted, chains=1, cores=1, random_seed=seed,
                              progressbar=False, compute_convergence_checks=False)
        wall, cpu = time.perf_counter() - t, time.process_time() - c
    ss = idata.sample_stats
    lml = np.concatenate([np.atleast_1d(np.asarray(v, float)) for v in np.asarray(ss["log_marginal_likelihood"]).ravel()])
    finite = lml[np.isfinite(lml)]
    betas = np.concatenate([np.atleast_1d(np.asarray(v, float)) for v in np.asarray(ss["beta"]).ravel()])
    post = {k: np.asarray(idata.posterior[k]).ravel() for k in NAMES}
    c = post["VOLF"]
    comb = {"(1-VOLF)*T1": (1 - c) * post["T1"], "VOLF*P1": c * post["P1"],
            "G=VOLF*GF+(1-VOLF)*GM": c * post["GF"] + (1 - c) * post["GM"]}
    for k in ("EOPT", "T2", "THETA", "sigma"):
        comb[k] = post[k]
    g = gold["posterior_mean_and_sd"]
    errs = {k: float(abs(comb[k].mean() - g[k][0]) / g[k][1]) for k in g}
    import pymc
    return {"N": n, "seed": seed, "kernel": kernel, "pymc": pymc.__version__, "wall": wall, "cpu": cpu,
            "log_evidence": float(finite[-1]) if finite.size else float("nan"),
            "stages": int(betas.size), "steps_per_stage": steps,
            "evaluations": int(n * (1 + sum(steps))),
            "max_mean_err_sd": max(errs.values()), "mean_err_sd": errs}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = ap.add_subparsers(dest="mode", required=True)
    r = sub.add_parser("run", help="one pm.sample_smc run")
    r.add_argument("--bench", required=True)
    r.add_argument("--n", type=int, required=True)
    r.add_argument("--seed", type=int, required=True)
    r.add_argument("--kernel", choices=("imh", "mh"), default="imh")
    k = sub.add_parser("check", help="pytensor stress and PyMC log-likelihood at given parameter rows")
    k.add_argument("--bench", required=True)
    k.add_argument("--theta", required=True)
    a = ap.parse_args(argv)
    if a.mode == "run":
        out = run(Path(a.bench), a.n, a.seed, a.kernel)
    else:
        out = check(Path(a.bench), Path(a.theta))
    print(json.dumps(out))
    return 0


if __name__ == "__main__":
    sys.exit(main())
