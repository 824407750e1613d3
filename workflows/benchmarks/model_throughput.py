"""Throughput of the vectorised muscle model and likelihood (issues 2 and 6).

Measures, on one core, strain-point evaluations per second of

* ``Model.stress`` of the base Spyrou model (θ population (n, 8) × n_points strains),
* ``Model.stress_jacobian``,
* the iid-Gaussian log-likelihood ``hbm.make_likelihood(...)(theta)`` on an (n, 9) population,

and, when numba is importable (it is NOT an hbm dependency: install it in a separate environment to
measure, e.g. ``../bench-venv/bin/pip install numba`` and run this script with that python plus
``PYTHONPATH=.``), a fused numba kernel of the same base-model log-likelihood, checked against hbm's
to 1e-9 relative before it is timed.  The point of the numba row is the issue-6 decision "numba only
if it pays ≥ 3× on what the sampler really calls".

Usage::

    OMP_NUM_THREADS=1 taskset -c 0 python workflows/benchmarks/model_throughput.py [--n 10000]
        [--points 40] [--repeat 20] [--out results/benchmarks]

Writes ``model_throughput.md`` / ``.json`` to ``--out`` and prints the table.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))

import hbm  # noqa: E402
from hbm.runtime.files import atomic_write_text  # noqa: E402


def _best_time(fn, repeat: int) -> float:
    """Best of ``repeat`` wall times (the least disturbed run; one warm-up call first)."""
    fn()
    best = np.inf
    for _ in range(repeat):
        t = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - t)
    return best


def _numba_loglik():
    """A fused numba kernel of the base-model iid log-likelihood, or None without numba."""
    try:
        import numba
    except ImportError:
        return None, None

    @numba.njit(cache=False, fastmath=False)
    def loglik(theta, strain, stress):  # pragma: no cover - timed only
        n, m = theta.shape[0], strain.size
        out = np.empty(n)
        for i in range(n):
            c, eopt, p1, t1, t2, th, gf, gm, sig = theta[i]
            g = c * gf + (1.0 - c) * gm
            c2 = np.cos(np.deg2rad(th)) ** 2
            ss = 0.0
            for k in range(m):
                e = strain[k]
                lam = 1.0 + e
                nh = lam * lam - 1.0 / lam
                s = g * nh
                if e > eopt:
                    s += lam * c * p1 * (e - eopt)
                x = np.sqrt(c2 * nh + 1.0 / lam) - 1.0
                if x > 0.0:
                    s += lam * (1.0 - c) * t1 * np.expm1(min(t2 * x, 700.0))
                r = stress[k] - s
                ss += r * r
            out[i] = -0.5 * ss / (sig * sig) - m * np.log(sig) - 0.5 * m * np.log(2.0 * np.pi)
        return out

    return loglik, numba.__version__


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--n", type=int, default=10_000, help="population size (default 10000)")
    ap.add_argument("--points", type=int, default=40, help="strain points (default 40)")
    ap.add_argument("--repeat", type=int, default=20, help="timed repeats, best taken (default 20)")
    ap.add_argument("--out", default=str(ROOT / "results" / "benchmarks"), help="output folder")
    args = ap.parse_args(argv)

    model = hbm.spyrou_model()
    rng = np.random.default_rng(0)
    strain = np.linspace(0.0, 0.45, args.points)
    b = model.bounds
    theta = rng.uniform(b[:, 0], b[:, 1], (args.n, b.shape[0]))
    truth = np.array([0.9, 0.18, 0.13, 1.5, 9.3, 59.9, 0.012, 0.009])
    data = hbm.synthetic_specimen(model, truth, strain, noise_sd=0.002, seed=1)
    lik = hbm.make_likelihood(model, data, noise="iid", sigma_bounds=(1e-4, 0.05))
    th9 = np.column_stack([theta, rng.uniform(1e-3, 0.01, args.n)])
    pts = args.n * args.points

    rows = []

    def add(what, seconds, note=""):
        rows.append({"what": what, "seconds": seconds, "us_per_particle": 1e6 * seconds / args.n,
                     "M_strain_points_per_s": pts / seconds / 1e6, "note": note})

    add("Model.stress (numpy)", _best_time(lambda: model.stress(strain, theta), args.repeat))
    add("Model.stress_jacobian (numpy, analytic)", _best_time(lambda: model.stress_jacobian(strain, theta),
                                                              max(3, args.repeat // 4)))
    t_lik = _best_time(lambda: lik(th9), args.repeat)
    add("log-likelihood, iid (numpy, hbm.make_likelihood)", t_lik, "what TMCMC calls")
    nb, nb_version = _numba_loglik()
    if nb is not None:
        x = np.ascontiguousarray(th9)
        s_obs = np.asarray(data.stress, float)
        ref, got = lik(th9), nb(x, strain, s_obs)
        ok = np.isfinite(ref)
        rel = float(np.max(np.abs(got[ok] - ref[ok]) / np.maximum(np.abs(ref[ok]), 1.0)))
        if rel > 1e-9:
            raise SystemExit(f"numba kernel disagrees with hbm's likelihood (max rel {rel:.3g})")
        t_nb = _best_time(lambda: nb(x, strain, s_obs), args.repeat)
        add(f"log-likelihood, iid (fused numba {nb_version}, base model only)", t_nb,
            f"{t_lik / t_nb:.2f}x hbm numpy; agrees to {rel:.1e}")

    meta = {"n": args.n, "points": args.points, "repeat": args.repeat, "python": platform.python_version(),
            "numpy": np.__version__, "machine": platform.machine(), "cpu_affinity": sorted(os.sched_getaffinity(0)),
            "omp_threads": os.environ.get("OMP_NUM_THREADS"), "load_avg": os.getloadavg(),
            "measured": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime())}
    lines = [f"# Model throughput (n = {args.n} particles × {args.points} strain points, best of {args.repeat})",
             "", f"{meta['measured']}, Python {meta['python']}, numpy {meta['numpy']}, CPU affinity "
             f"{meta['cpu_affinity']}, OMP_NUM_THREADS={meta['omp_threads']}, load {meta['load_avg'][0]:.2f}.", "",
             "| what | s per call | µs per particle | M strain-point evals / s | note |", "|---|---|---|---|---|"]
    lines += [f"| {r['what']} | {r['seconds']:.4f} | {r['us_per_particle']:.3f} | {r['M_strain_points_per_s']:.1f} | "
              f"{r['note']} |" for r in rows]
    text = "\n".join(lines) + "\n"
    print(text)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    atomic_write_text(out / "model_throughput.md", text)
    atomic_write_text(out / "model_throughput.json", json.dumps({"meta": meta, "rows": rows}, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
