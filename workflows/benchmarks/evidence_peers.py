#!/usr/bin/env python
"""Evidence peers for the evaluations-to-accuracy benchmark (runs in the bench venv, not in hbm's).

pocoMC, nautilus and dynesty are *not* hbm dependencies: ``evaluations_to_accuracy.py --peers``
calls this file with the bench environment's python (``$HBM_PEER_PYTHON``, else
``../bench-venv/bin/python`` next to the repository).  It imports numpy, scipy and the peer package only — never hbm.

The likelihood is the base Spyrou model (iso_factor 1) with iid Gaussian noise of unknown sd
``sigma``, written here in numpy term by term as in ``pymc_peer.py`` (same numerics: expm1, the
exponent clipped at 700), vectorised over parameter rows; the prior is the uniform box of
``muscle_benchmark_gold.json``.  ``check`` mode prints the log-likelihood at given rows so the
caller can compare it with hbm's own likelihood.

Modes (each prints one JSON line on stdout):

``run --bench DIR --peer pocomc|nautilus|dynesty --seed S [--size K] [--timeout T]``
    One run; reports CPU (process) and wall time of the sampling call, likelihood evaluations
    (rows passed to the likelihood), log Ẑ and the peer's own error bar, and the worst
    posterior-mean error of the benchmark combinations in gold sd.  ``--size`` is the peer's
    main accuracy knob (pocoMC ``n_effective`` with ``n_active = n_effective/2``; nautilus
    ``n_live``; dynesty ``nlive``).
``check --bench DIR --theta FILE.json``
    Log-likelihood at the rows of ``FILE.json`` (list of dicts name -> value).
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from pymc_peer import EXP_CLIP, NAMES, read_bench  # noqa: E402  (numpy-only helpers, no hbm)


class Likelihood:
    """Vectorised log-likelihood of the benchmark, counting the rows it evaluates."""

    def __init__(self, bench: Path, progress: Path | None = None):
        self.eps, self.obs, box, self.gold = read_bench(bench)
        self.progress, self._last = progress, 0.0
        self.lo = np.array([box[k][0] for k in NAMES])
        self.hi = np.array([box[k][1] for k in NAMES])
        self.rows = 0

    def __call__(self, theta: np.ndarray) -> np.ndarray:
        th = np.atleast_2d(np.asarray(theta, float))
        self.rows += len(th)
        if self.progress is not None and time.perf_counter() - self._last > 2.0:
            # throttled progress record, so a run stopped by the caller's time cap still tells
            # how many evaluations and how much CPU it had spent
            self._last = time.perf_counter()
            tmp = self.progress.with_suffix(".tmp")
            tmp.write_text(json.dumps({"evaluations": self.rows, "cpu": time.process_time()}))
            tmp.replace(self.progress)
        p = {k: th[:, i:i + 1] for i, k in enumerate(NAMES)}
        lam = 1.0 + self.eps[None, :]
        nh = lam * lam - 1.0 / lam
        c = p["VOLF"]
        matrix = (c * p["GF"] + (1.0 - c) * p["GM"]) * nh
        fibers = lam * c * p["P1"] * np.maximum(self.eps[None, :] - p["EOPT"], 0.0)
        c2 = np.cos(p["THETA"] * (np.pi / 180.0)) ** 2
        x = np.maximum(np.sqrt(c2 * nh + 1.0 / lam) - 1.0, 0.0)
        collagen = lam * (1.0 - c) * p["T1"] * np.expm1(np.minimum(p["T2"] * x, EXP_CLIP))
        mu = matrix + fibers + collagen
        s = p["sigma"][:, 0]
        r = (self.obs[None, :] - mu) / p["sigma"]
        n = self.obs.size
        ll = -0.5 * np.sum(r * r, axis=1) - n * np.log(s) - 0.5 * n * math.log(2 * math.pi)
        inside = np.all((th >= self.lo) & (th <= self.hi), axis=1)
        return np.where(inside & np.isfinite(ll), ll, -np.inf)

    def mean_errors(self, samples: np.ndarray, weights: np.ndarray) -> dict:
        """|weighted posterior mean − gold mean| / gold sd of the benchmark combinations."""
        w = weights / weights.sum()
        col = {k: samples[:, i] for i, k in enumerate(NAMES)}
        c = col["VOLF"]
        comb = {"(1-VOLF)*T1": (1 - c) * col["T1"], "VOLF*P1": c * col["P1"],
                "G=VOLF*GF+(1-VOLF)*GM": c * col["GF"] + (1 - c) * col["GM"]}
        for k in ("EOPT", "T2", "THETA", "sigma"):
            comb[k] = col[k]
        g = self.gold["posterior_mean_and_sd"]
        return {k: float(abs(w @ comb[k] - g[k][0]) / g[k][1]) for k in g}


def run_pocomc(lik: Likelihood, seed: int, size: int, timeout: float, total: int | None = None):
    import pocomc
    from scipy.stats import uniform

    prior = pocomc.Prior([uniform(lo, hi - lo) for lo, hi in zip(lik.lo, lik.hi)])
    sampler = pocomc.Sampler(prior=prior, likelihood=lik, vectorize=True, random_state=seed,
                             n_effective=size, n_active=size // 2)
    # n_total / n_evidence: pocoMC's own defaults (4096) unless given; the flow's importance-sampling
    # evidence (n_evidence draws) is what sampler.evidence() returns
    kw = {} if total is None else {"n_total": total, "n_evidence": total}
    sampler.run(progress=False, **kw)
    x, w, _, _ = sampler.posterior()
    logz, logz_err = sampler.evidence()
    return x, np.asarray(w, float), float(logz), float(logz_err), {"completed": True}


def run_nautilus(lik: Likelihood, seed: int, size: int, timeout: float, total: int | None = None):
    from nautilus import Prior, Sampler

    prior = Prior()
    for k, lo, hi in zip(NAMES, lik.lo, lik.hi):
        prior.add_parameter(k, dist=(lo, hi))
    sampler = Sampler(prior, lik, n_live=size, vectorized=True, pass_dict=False, seed=seed)
    # discard_exploration=True: nautilus's documented setting for an unbiased posterior and evidence
    t = time.perf_counter()
    sampler.run(verbose=False, timeout=timeout, discard_exploration=True)
    completed = time.perf_counter() - t < timeout  # run() returns silently when the timeout is hit
    x, log_w, _ = sampler.posterior()
    # nautilus reports no error bar of log Z; its documentation states ~0.01–0.1 for n_eff 10⁴
    return x, np.exp(log_w - log_w.max()), float(sampler.log_z), float("nan"), {
        "completed": bool(completed), "n_eff": float(sampler.n_eff)}


def run_dynesty(lik: Likelihood, seed: int, size: int, timeout: float, total: int | None = None):
    import dynesty

    width = lik.hi - lik.lo

    def transform(u):
        return lik.lo + u * width

    def loglike(theta):
        return float(lik(theta[None, :])[0])

    s = dynesty.NestedSampler(loglike, transform, len(NAMES), nlive=size, rstate=np.random.default_rng(seed))
    s.run_nested(dlogz=0.1, print_progress=False)
    r = s.results
    w = np.exp(r.logwt - r.logz[-1])
    return r.samples, w, float(r.logz[-1]), float(r.logzerr[-1]), {"completed": True, "iterations": int(r.niter)}


PEERS = {"pocomc": run_pocomc, "nautilus": run_nautilus, "dynesty": run_dynesty}


def run(bench: Path, peer: str, seed: int, size: int, timeout: float, progress: Path | None = None,
        total: int | None = None) -> dict:
    lik = Likelihood(bench, progress)
    mod = __import__(peer)
    t, c = time.perf_counter(), time.process_time()
    x, w, logz, logz_err, info = PEERS[peer](lik, seed, size, timeout, total)
    wall, cpu = time.perf_counter() - t, time.process_time() - c
    errs = lik.mean_errors(np.asarray(x, float), np.asarray(w, float))
    return {"peer": peer, "version": getattr(mod, "__version__", "?"), "size": size, "seed": seed,
            "wall": wall, "cpu": cpu, "evaluations": int(lik.rows), "log_evidence": logz,
            "log_evidence_se": logz_err, "max_mean_err_sd": max(errs.values()), "mean_err_sd": errs, **info}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = ap.add_subparsers(dest="mode", required=True)
    r = sub.add_parser("run", help="one peer run")
    r.add_argument("--bench", required=True)
    r.add_argument("--peer", choices=sorted(PEERS), required=True)
    r.add_argument("--seed", type=int, required=True)
    r.add_argument("--size", type=int, default=None, help="n_effective / n_live / nlive (peer default)")
    r.add_argument("--timeout", type=float, default=600.0, help="nautilus: stop after this many seconds")
    r.add_argument("--progress-file", default=None, help="JSON {evaluations, cpu} updated every ~2 s")
    r.add_argument("--total", type=int, default=None, help="pocoMC n_total and n_evidence (default: pocoMC's, 4096)")
    k = sub.add_parser("check", help="log-likelihood at given parameter rows")
    k.add_argument("--bench", required=True)
    k.add_argument("--theta", required=True)
    a = ap.parse_args(argv)
    if a.mode == "run":
        size = a.size or {"pocomc": 512, "nautilus": 2000, "dynesty": 500}[a.peer]
        out = run(Path(a.bench), a.peer, a.seed, size, a.timeout,
                  Path(a.progress_file) if a.progress_file else None, a.total)
    else:
        lik = Likelihood(Path(a.bench))
        rows = json.loads(Path(a.theta).read_text())
        out = {"log_likelihood": lik(np.array([[row[k] for k in NAMES] for row in rows])).tolist()}
    print(json.dumps(out))
    return 0


if __name__ == "__main__":
    sys.exit(main())
