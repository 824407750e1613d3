#!/usr/bin/env python
"""Joint NUTS peer of the hierarchical layer (runs in the separate bench venv, never imports hbm).

``hierarchical_gold.py`` writes a JSON spec (data of every specimen, the stage-1 box, the pooled
columns with their transforms, truncation boxes and hyperprior ranges) and calls this file with the
bench environment's python (PyMC + nutpie, see README.md).  The model is the definition of
``hbm/samplers/hierarchical/`` with ``--pool combinations`` (``hbm/population/pooling.py``), written out
as one joint density over (ψ, θ_1..θ_S):

* θ_i = (VOLF, EOPT, P1, T1, T2, THETA, GF, GM, sigma) uniform on the stage-1 box (p0(θ));
* data: iid Normal(spyrou(θ_i), sigma_i) (the base Spyrou model of ``pymc_peer.py``);
* population: the pooled columns x(θ) = (log G, log c·P1, log (1−c)·T1, T2, THETA[, EOPT]) with
  z_k = g_k(x_k) (identity, log or logit on the box) and
  p(θ|ψ) = Π_k N_trunc(z_k; mu_k, sd_k)|g_k'| · p0(θ) / p0(x(θ)), where p0(x) is the density that
  the uniform box prior induces on the pooled columns: p0(φ) by the same breakpoint-split
  Gauss–Legendre quadrature over c as ``hbm/identifiability/combinations.py`` (re-implemented here in pytensor,
  16 nodes × 2 sub-pieces per breakpoint interval), times the uniform densities of T2, THETA;
* hyperprior: mu_k uniform on its range, log sd_k uniform on [log sd_lo, log sd_hi].

Modes (one JSON line on stdout):

``check --spec FILE``  log p0(φ) at the spec's ``check_phi`` rows (the caller compares with hbm).
``run --spec FILE --out FILE.npz [--draws N --tune N --chains 3 --seed S]``
    nutpie NUTS; writes the draws of every hyperparameter (mu_*, sd_*) and of every θ_i column
    to ``--out`` and prints R-hat, ESS, divergences and the wall time.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from pymc_peer import NAMES, spyrou_stress  # noqa: E402  (the base model in pytensor, numpy-only import)


def log_p0_phi(pt, y3, y1, y2, box, n_nodes: int = 16, n_sub: int = 2):
    """log p0(φ) of φ = (log G, log c·P1, log (1−c)·T1) under the uniform box prior, per row (vectors).

    Breakpoints in c: the support limits of y1 and y2 and the trapezoid kinks of G | c; those with a
    zero denominator do not depend on c and are left out (hbm puts them at the box start, a
    zero-width piece).  Each interval is split in ``n_sub`` and integrated by Gauss–Legendre.
    """
    (ca, cb), (pa, pb), (ta, tb), (fa, fb), (ma, mb) = box
    G, e1, e2 = pt.exp(y3), pt.exp(y1), pt.exp(y2)
    bp = [e1 / pb, 1.0 - e2 / tb]
    if pa > 0:
        bp.append(e1 / pa)
    if ta > 0:
        bp.append(1.0 - e2 / ta)
    for num_m, den in ((ma, fa - ma), (ma, fb - ma), (mb, fa - mb), (mb, fb - mb)):
        if den != 0:
            bp.append((G - num_m) / den)
    bp.append(pt.ones_like(G) * ((mb - ma) / ((fb - fa) + (mb - ma))))
    inner = pt.clip(pt.stack(bp, axis=1), ca, cb)  # (S, nb)
    ones = pt.ones_like(G)[:, None]
    edges = pt.sort(pt.concatenate([ones * ca, inner, ones * cb], axis=1), axis=1)
    t = np.arange(n_sub) / n_sub
    lo, hi = edges[:, :-1, None], edges[:, 1:, None]
    sub_lo = (lo + (hi - lo) * t[None, None, :]).reshape((G.shape[0], -1))
    sub_hi = (lo + (hi - lo) * (t[None, None, :] + 1.0 / n_sub)).reshape((G.shape[0], -1))
    x, w = np.polynomial.legendre.leggauss(n_nodes)
    half = 0.5 * (sub_hi - sub_lo)
    c = (sub_lo[:, :, None] + half[:, :, None] * (x + 1.0)).reshape((G.shape[0], -1))
    wt = (half[:, :, None] * w).reshape((G.shape[0], -1))
    e1, e2, G = e1[:, None], e2[:, None], G[:, None]
    p1v, t1v = e1 / c, e2 / (1.0 - c)
    d1 = pt.switch((p1v >= pa) & (p1v <= pb), p1v / (pb - pa), 0.0)
    d2 = pt.switch((t1v >= ta) & (t1v <= tb), t1v / (tb - ta), 0.0)
    w1, w2 = c * (fb - fa), (1.0 - c) * (mb - ma)
    xx = G - c * fa - (1.0 - c) * ma
    d3 = G * pt.maximum(0.0, pt.minimum(pt.minimum(xx, w1 + w2 - xx), pt.minimum(w1, w2))) / (w1 * w2)
    return pt.log(pt.sum(wt * d1 * d2 * d3, axis=1) / (cb - ca))


def _log_norm_mass(a, b):
    """log(Φ(b) − Φ(a)) (pytensor), via PyMC's stable log-CDF."""
    from pymc.distributions.dist_math import normal_lcdf
    from pymc.math import logdiffexp

    return logdiffexp(normal_lcdf(0.0, 1.0, b), normal_lcdf(0.0, 1.0, a))


def pooled_columns(pt, th: dict, pooled: list) -> list:
    """Values of the pooled columns (natural units) from the θ of one specimen."""
    c = th["VOLF"]
    phi = {"log_G": pt.log(c * th["GF"] + (1.0 - c) * th["GM"]), "log_VOLF*P1": pt.log(c * th["P1"]),
           "log_(1-VOLF)*T1": pt.log((1.0 - c) * th["T1"])}
    return [phi[p["name"]] if p["name"] in phi else th[p["name"]] for p in pooled]


def log_population_ratio(pt, th: dict, spec: dict, mu: list, sd: list):
    """log p(θ|ψ) − log p0(θ) = Σ_k log N_trunc(z_k)|g_k'| − log p0(pooled columns)."""
    pooled = spec["pooled"]
    cols = pooled_columns(pt, th, pooled)
    out = 0.0
    for p, x, m, s in zip(pooled, cols, mu, sd):
        lo, hi = p["bounds"]
        if p["transform"] == "identity":
            z, logjac = x, 0.0
        elif p["transform"] == "log":
            z, logjac = pt.log(x), -pt.log(x)
        else:
            u = (x - lo) / (hi - lo)
            z = pt.log(u) - pt.log1p(-u)
            logjac = -(pt.log(u) + pt.log1p(-u) + np.log(hi - lo))
        out = out - 0.5 * ((z - m) / s) ** 2 - pt.log(s) - 0.5 * np.log(2 * np.pi) + logjac
        zlo, zhi = p["zbox"]
        if zlo is not None and zhi is not None:  # truncation to the transformed box
            out = out - _log_norm_mass((zlo - m) / s, (zhi - m) / s)
        if not p["name"].startswith("log_"):
            out = out + np.log(hi - lo)  # uniform stage-1 density of a raw parameter column
    th_box = spec["box"]
    lp0 = log_p0_phi(pt, cols[0], cols[1], cols[2], [th_box[k] for k in ("VOLF", "P1", "T1", "GF", "GM")])
    return out - lp0  # (S,): one value per specimen


def build_model(spec: dict):
    import pymc as pm
    import pytensor.tensor as pt

    box = spec["box"]
    with pm.Model() as model:
        mu, sd = [], []
        for p in spec["pooled"]:
            mu.append(pm.Uniform(f"mu_{p['name']}", *p["mu_range"]))
            lsd = pm.Uniform(f"logsd_{p['name']}", np.log(p["sd_range"][0]), np.log(p["sd_range"][1]))
            sd.append(pm.Deterministic(f"sd_{p['name']}", pt.exp(lsd)))
        # all specimens at once (one graph, vectors over specimens): the strains must be shared
        S = len(spec["specimens"])
        eps = np.asarray(spec["specimens"][0]["strain"], float)
        if any(not np.array_equal(np.asarray(s["strain"], float), eps) for s in spec["specimens"]):
            raise SystemExit("error: the peer needs the same strain points for every specimen")
        obs = np.array([s["stress"] for s in spec["specimens"]], float)
        th = {k: pm.Uniform(k, *box[k], shape=S) for k in NAMES}
        col = {k: v[:, None] for k, v in th.items()}
        pm.Normal("y", mu=spyrou_stress(pt, eps[None, :], col), sigma=col["sigma"], observed=obs)
        pm.Potential("pop", pt.sum(log_population_ratio(pt, th, spec, mu, sd)))
    return model


def check(spec: dict) -> dict:
    import pytensor
    import pytensor.tensor as pt

    y = pt.dvector("y")
    box = [spec["box"][k] for k in ("VOLF", "P1", "T1", "GF", "GM")]
    y = pt.dmatrix("y")
    f = pytensor.function([y], log_p0_phi(pt, y[:, 0], y[:, 1], y[:, 2], box))
    out = {"log_p0": f(np.asarray(spec["check_phi"], float)).tolist()}
    if spec.get("check_pop"):  # log p(θ|ψ)/p0(θ) at (θ, ψ) rows
        th = {k: pt.dvector(k) for k in NAMES}
        npool = len(spec["pooled"])
        mu, sd = pt.dmatrix("mu"), pt.dmatrix("sd")  # one ψ per row
        g = pytensor.function([*th.values(), mu, sd],
                              log_population_ratio(pt, th, spec, [mu[:, k] for k in range(npool)],
                                                   [sd[:, k] for k in range(npool)]), on_unused_input="ignore")
        rows = spec["check_pop"]
        out["log_ratio"] = g(*[np.array([r["theta"][k] for r in rows]) for k in NAMES],
                             np.array([r["mu"] for r in rows]), np.array([r["sd"] for r in rows])).tolist()
    return out


def run(spec: dict, out: Path, draws: int, tune: int, chains: int, seed: int) -> dict:
    import arviz as az
    import nutpie

    model = build_model(spec)
    t0 = time.perf_counter()
    compiled = nutpie.compile_pymc_model(model)
    t1 = time.perf_counter()
    idata = nutpie.sample(compiled, draws=draws, tune=tune, chains=chains, seed=seed, cores=1,
                          progress_bar=False, target_accept=0.9)
    t2 = time.perf_counter()
    post = idata.posterior
    keep = [v for v in post.data_vars if not v.startswith("logsd_")]
    np.savez_compressed(out, **{v: np.asarray(post[v]) for v in keep})
    hyper = [v for v in keep if v.startswith(("mu_", "sd_"))]
    rhat = az.rhat(idata, var_names=hyper)
    ess = az.ess(idata, var_names=hyper)
    rhat_all = az.rhat(idata)
    worst = max(float(np.nanmax(np.asarray(rhat_all[v]))) for v in rhat_all.data_vars)
    div = int(np.asarray(idata.sample_stats["diverging"]).sum())
    return {"compile_s": t1 - t0, "sample_s": t2 - t1, "draws": draws, "tune": tune, "chains": chains,
            "rhat": {v: float(rhat[v]) for v in hyper}, "ess_bulk": {v: float(ess[v]) for v in hyper},
            "rhat_max_all": worst, "divergences": div}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("mode", choices=("check", "run"))
    ap.add_argument("--spec", required=True)
    ap.add_argument("--out")
    ap.add_argument("--draws", type=int, default=1500)
    ap.add_argument("--tune", type=int, default=1500)
    ap.add_argument("--chains", type=int, default=3)
    ap.add_argument("--seed", type=int, default=1)
    a = ap.parse_args(argv)
    spec = json.loads(Path(a.spec).read_text())
    res = check(spec) if a.mode == "check" else run(spec, Path(a.out), a.draws, a.tune, a.chains, a.seed)
    print(json.dumps(res))
    return 0


if __name__ == "__main__":
    sys.exit(main())
