#!/usr/bin/env python
"""Cost of the hierarchical layer against the number of stage-1 samples per specimen (issue 6).

The layer (:func:`hbm.samplers.hierarchical.hierarchical`) evaluates, for a whole population of
hyperparameters ψ at once, Σ_i log mean_j r_ij(ψ) as one matrix product per specimen
(coef(ψ) (n_ψ × K) @ F(θ_i)ᵀ (K × N_i)) with a chunked log-sum-exp, so one likelihood call should
cost ∝ n_ψ · Σ_i N_i and the whole layer ∝ N at a fixed number of calls.

Setup, as ``hbm run --pool all`` calls the layer (hbm/population/driver.py ``run_population``; the
heaviest case: 8 pooled columns, where the default ``--pool combinations`` pools 5): the six shipped
specimens (``data/specimens``), stage-1 = default TMCMC of the base model with iid noise and the
workflow's common sigma box, pooled = the 8 model parameters with the workflow's transforms
(``DEFAULT_TRANSFORMS``) and sd range, ``n_samples = RunConfig.hier_samples`` (1000) ψ draws and
``max_steps = RunConfig.hier_max_steps``.  Stage-1 posteriors are drawn once at the largest N
(cached in ``--cache``); the smaller N are nested random subsets of them (equally valid
posterior samples), so only N changes between rows.

Two measurements per N:

* **fixed call**: the layer's likelihood at a fixed population of n_ψ = 1000 ψ drawn uniformly
  from the hyperprior box, repeated ``--repeats`` times (median) — the pure per-call cost;
* **whole layer**: ``hierarchical(...)`` end to end, with the sampler's calls to the layer
  likelihood timed through the ``sampler=`` hook (number of calls, mean time per call, share of
  the layer spent in them).

Wall and CPU (process) time are both reported; pin to one core for timing::

    OMP_NUM_THREADS=1 OPENBLAS_NUM_THREADS=1 taskset -c 1 \\
        python workflows/benchmarks/hierarchical_scaling.py

Writes ``results/benchmarks/hierarchical_scaling.md`` (and ``.json``).  ``--quick`` runs a tiny
smoke version (N = 200, 400; stage-1 N = 400) into ``hierarchical_scaling_quick.*``.
"""

from __future__ import annotations

import argparse
import json
import os
import tempfile
import statistics
import sys
import time
import warnings
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[2]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from hbm.data import load_specimens  # noqa: E402
from hbm.likelihood import make_likelihood  # noqa: E402
from hbm.model import spyrou_model  # noqa: E402
from hbm.samplers.tmcmc import tmcmc  # noqa: E402
from hbm.samplers.hierarchical import HierarchicalModel, hierarchical  # noqa: E402
from hbm.runtime.files import atomic_write_text  # noqa: E402
from hbm.population import DEFAULT_SD_RANGE, DEFAULT_TRANSFORMS  # noqa: E402
from hbm.workflow.run import RunConfig, _common_sigma_box  # noqa: E402


def stage1_samples(n_max: int, seed: int, cache: Path, progress: bool = True) -> tuple[dict, list, np.ndarray]:
    """{specimen: (samples (n_max, d), log Z, SE)}, names, bounds: default TMCMC per specimen (cached)."""
    datasets = load_specimens(ROOT / "data" / "specimens")
    sig = _common_sigma_box(datasets)
    model = spyrou_model()
    f = cache / f"stage1_N{n_max}_seed{seed}.npz"
    if f.exists():
        z = np.load(f, allow_pickle=False)
        names, bounds = [str(s) for s in z["names"]], z["bounds"]
        out = {sid: (z[f"x_{sid}"], float(z[f"lz_{sid}"]), float(z[f"se_{sid}"])) for sid in datasets}
        return out, names, bounds
    out, arrays = {}, {}
    seeds = np.random.SeedSequence(seed).spawn(len(datasets))
    for (sid, ds), ss in zip(datasets.items(), seeds):
        lik = make_likelihood(model, ds, noise="iid", sigma_bounds=sig)
        t = time.perf_counter()
        res = tmcmc(lik, lik.bounds, n_max, seed=int(ss.generate_state(1)[0]), progress=False)
        if progress:
            print(f"stage 1 {sid}: N={n_max}, {time.perf_counter() - t:.1f} s, log Z {res.log_evidence:.2f}",
                  file=sys.stderr, flush=True)
        out[sid] = (np.asarray(res.samples), float(res.log_evidence), float(res.log_evidence_se))
        arrays.update({f"x_{sid}": out[sid][0], f"lz_{sid}": out[sid][1], f"se_{sid}": out[sid][2]})
        names, bounds = list(lik.names), np.asarray(lik.bounds)
    cache.mkdir(parents=True, exist_ok=True)
    tmp = cache / (f.name + ".tmp.npz")
    np.savez(tmp, names=np.array(names), bounds=bounds, **arrays)
    os.replace(tmp, f)  # atomic
    return out, names, bounds


def subsets(stage1: dict, n: int, seed: int) -> dict:
    """Nested random subsets: the first n of one fixed permutation per specimen."""
    out = {}
    for k, (sid, (x, lz, se)) in enumerate(stage1.items()):
        perm = np.random.default_rng([seed, k]).permutation(x.shape[0])
        out[sid] = (x[perm[:n]], lz, se)
    return out


def fixed_call(stage1: dict, names, bounds, pooled, transforms, n_psi: int, repeats: int, seed: int) -> dict:
    """Median wall/CPU time of the layer likelihood at a fixed ψ population (as in hierarchical())."""
    hm = HierarchicalModel(names, bounds, pooled=pooled, transforms=transforms, sd_range=DEFAULT_SD_RANGE)
    feats = [hm.features(x) for x, _, _ in stage1.values()]
    logN = np.log([x.shape[0] for x, _, _ in stage1.values()])
    rng = np.random.default_rng(seed)
    psi = rng.uniform(hm.box[:, 0], hm.box[:, 1], (n_psi, hm.box.shape[0]))

    def call():
        raw = hm.expand(psi)
        coef, cconst = hm.coefficients(raw)
        tot = np.zeros(n_psi)
        for (F, c), ln in zip(feats, logN):
            lse, _ = hm.log_ratio_stats(F, c, coef, cconst)
            tot += lse - ln
        return tot

    call()  # warm-up (BLAS thread setup, page faults of the feature arrays)
    walls, cpus = [], []
    for _ in range(repeats):
        t, c = time.perf_counter(), time.process_time()
        call()
        walls.append(time.perf_counter() - t)
        cpus.append(time.process_time() - c)
    return {"wall": statistics.median(walls), "cpu": statistics.median(cpus)}


def whole_layer(stage1: dict, names, bounds, pooled, transforms, seed: int, cfg: RunConfig) -> dict:
    """hierarchical(...) as ``hbm run --pool all`` calls it, with the sampler's likelihood calls timed."""
    calls = []

    def timed_sampler(target, box, n, **kw):
        def timed(x):
            t, c = time.perf_counter(), time.process_time()
            out = target(x)
            calls.append((np.atleast_2d(x).shape[0], time.perf_counter() - t, time.process_time() - c))
            return out
        return tmcmc(timed, box, n, **kw)

    t, c = time.perf_counter(), time.process_time()
    with warnings.catch_warnings(record=True) as caught:  # ESS warnings: counted, not printed
        warnings.simplefilter("always")
        h = hierarchical(stage1, names, bounds, transforms=transforms, pooled=pooled,
                         n_samples=int(cfg.hier_samples), seed=seed, progress=False,
                         sd_range=tuple(cfg.hier_sd_range or DEFAULT_SD_RANGE), sampler=timed_sampler,
                         tmcmc_options={"max_steps": int(cfg.hier_max_steps)})
    wall, cpu = time.perf_counter() - t, time.process_time() - c
    rows = np.array([k[0] for k in calls], float)
    cw = np.array([k[1] for k in calls])
    cc = np.array([k[2] for k in calls])
    return {"wall": wall, "cpu": cpu, "calls": len(calls), "psi_rows": int(rows.sum()),
            "call_wall_mean": float(cw.mean()), "call_cpu_mean": float(cc.mean()),
            "share_in_calls": float(cw.sum() / wall), "stages": len(h.sampler_result.stages),
            "log_evidence": float(h.log_evidence), "log_evidence_se": float(h.log_evidence_se),
            "ess_min_q10": float(min(v["q10"] for v in h.ess_summary.values())),
            "ess_collapsed": sum(bool(v) for v in h.ess_collapsed.values()), "warnings": len(caught),
            "ess_summary": {k: {q: v if isinstance(v, str) else float(v) for q, v in d.items()}
                            for k, d in h.ess_summary.items()},
            "timings": {k: float(v) for k, v in h.timings.items()}}


def fit_line(what: str, x, y, n_psi: int | None) -> str:
    """One Markdown bullet: least-squares a + b·x, b per (ψ · sample), and the largest relative residual."""
    x, y = np.asarray(x, float), np.asarray(y, float)
    if x.size < 3:
        return f"- {what}: fewer than 3 sizes, no fit"
    b, a = np.polyfit(x, y, 1)
    res = np.max(np.abs(a + b * x - y) / y)
    per = f" = {1e9 * b / n_psi:.2f} ns per (ψ · sample)" if n_psi else ""
    return (f"- {what}: a = {a:.3g} s, b = {1e6 * b:.3g} µs per stage-1 sample{per}; "
            f"largest relative residual {100 * res:.1f}%")


def render(rows: list[dict], meta: dict) -> str:
    base = rows[0]
    out = ["# Hierarchical layer: cost against stage-1 samples per specimen", "",
           f"{meta['n_specimens']} specimens, {meta['n_pooled']} pooled parameters ({', '.join(meta['pooled'])}), "
           f"ψ population {meta['n_psi']} (RunConfig.hier_samples), max {meta['max_steps']} MH steps per stage; "
           f"stage 1 = default TMCMC at N = {meta['n_stage1']} per specimen, smaller N = nested random subsets. "
           f"OMP_NUM_THREADS={meta['omp']}, CPU affinity {meta['affinity']}, load average at the end "
           f"{meta['load']}; {meta['when']} UTC.", "",
           "## One likelihood call at a fixed ψ population (median of repeats)", "",
           "| N per specimen | Σ N | wall s | CPU s | CPU ns per (ψ · sample) | CPU ratio to first row | N ratio |",
           "|---|---|---|---|---|---|---|"]
    for r in rows:
        f = r["fixed"]
        out.append(f"| {r['N']} | {r['N_total']} | {f['wall']:.3f} | {f['cpu']:.3f} | "
                   f"{1e9 * f['cpu'] / (meta['n_psi'] * r['N_total']):.2f} | "
                   f"{f['cpu'] / base['fixed']['cpu']:.2f} | {r['N'] / base['N']:.0f} |")
    out += ["", "## Whole layer (`hierarchical(...)` as `hbm run --pool all` calls it: the heaviest case, 8 pooled "
            "columns; the default `--pool combinations` pools 5 and its cost is in the run report)", "",
            "| N per specimen | wall s | CPU s | CPU ratio to first row | likelihood calls | ψ rows evaluated "
            "| mean call wall s | mean call CPU s | CPU ns per (ψ · sample) | share of wall in calls "
            "| TMCMC stages | log hyper-evidence ± SE | ESS q10 (min over specimens) | specimens with collapsed ESS |",
            "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        w = r["layer"]
        out.append(f"| {r['N']} | {w['wall']:.2f} | {w['cpu']:.2f} | {w['cpu'] / base['layer']['cpu']:.2f} | "
                   f"{w['calls']} | {w['psi_rows']:.3g} | {w['call_wall_mean']:.3f} | {w['call_cpu_mean']:.3f} | "
                   f"{1e9 * w['call_cpu_mean'] * w['calls'] / (w['psi_rows'] * r['N_total']):.2f} | "
                   f"{100 * w['share_in_calls']:.0f}% | {w['stages']} | "
                   f"{w['log_evidence']:.2f} ± {w['log_evidence_se']:.2f} | {w['ess_min_q10']:.0f} | "
                   f"{w['ess_collapsed']} of {meta['n_specimens']} |")
    if all("ess_summary" in r["layer"] for r in rows):
        specs = list(rows[0]["layer"]["ess_summary"])
        out += ["", "## Importance ESS per specimen (10% quantile / median over the ψ draws)", "",
                "| N per specimen | " + " | ".join(specs) + " |", "|---|" + "---|" * len(specs)]
        for r in rows:
            e = r["layer"]["ess_summary"]
            out.append(f"| {r['N']} | " + " | ".join(f"{e[k]['q10']:.0f} / {e[k]['median']:.0f}" for k in specs) + " |")
    out += ["", "## Affine fit CPU = a + b·ΣN (least squares over the rows)", ""]
    out += [fit_line("one call at fixed ψ", [r["N_total"] for r in rows], [r["fixed"]["cpu"] for r in rows], meta["n_psi"]),
            fit_line("whole layer", [r["N_total"] for r in rows], [r["layer"]["cpu"] for r in rows], None)]
    out += ["", "Linear scaling shows as a constant 'CPU ns per (ψ · sample)' column at large N, or as a small "
            "residual of the affine fit (the intercept a is the per-call work that does not depend on the "
            "stage-1 samples: coefficients of the ψ population, truncation normalisers, TMCMC bookkeeping). The whole-layer time also "
            "depends on the number of calls the adaptive TMCMC over ψ makes (stages × steps), which changes a little "
            "with N because the estimated target changes. CPU s = process time (robust to other jobs on the "
            "shared 2-core machine); wall s is what a user waits."]
    return "\n".join(out) + "\n"


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--sizes", default="2000,10000,50000", help="stage-1 samples per specimen (comma list)")
    ap.add_argument("--repeats", type=int, default=3, help="repeats of the fixed call (median)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--cache", default=str(Path(tempfile.gettempdir()) / "hbm_hierarchical_scaling"), help="stage-1 sample cache folder")
    ap.add_argument("--out", default=str(ROOT / "results" / "benchmarks"))
    ap.add_argument("--quick", action="store_true", help="smoke run: N = 200, 400, ψ population 100")
    ap.add_argument("--table-only", action="store_true", help="re-render the Markdown from the saved JSON")
    args = ap.parse_args(argv)
    stem = "hierarchical_scaling_quick" if args.quick else "hierarchical_scaling"
    out = Path(args.out)
    if args.table_only:
        saved = json.loads((out / f"{stem}.json").read_text())
        text = render(saved["rows"], saved["meta"])
        print(text)
        atomic_write_text(out / f"{stem}.md", text)
        return 0
    sizes = [200, 400] if args.quick else [int(s) for s in args.sizes.split(",")]
    cfg = RunConfig(quick=args.quick)
    if args.quick:
        cfg = cfg.replace(hier_samples=100, hier_max_steps=5)
    n_max = max(sizes)
    stage1, names, bounds = stage1_samples(n_max, args.seed, Path(args.cache))
    model_names = list(spyrou_model().parameter_names)
    pooled = [n for n in names if n in model_names]
    transforms = {n: DEFAULT_TRANSFORMS.get(n, "logit") for n in pooled}
    rows = []
    for n in sizes:
        sub = subsets(stage1, n, args.seed)
        fixed = fixed_call(sub, names, bounds, pooled, transforms, int(cfg.hier_samples), args.repeats, args.seed)
        layer = whole_layer(sub, names, bounds, pooled, transforms, args.seed, cfg)
        rows.append({"N": n, "N_total": n * len(sub), "fixed": fixed, "layer": layer})
        print(f"N={n}: fixed call {fixed['cpu']:.3f} s CPU; layer {layer['wall']:.1f} s wall, {layer['cpu']:.1f} s CPU, "
              f"{layer['calls']} calls", file=sys.stderr, flush=True)
    meta = {"n_specimens": len(stage1), "n_pooled": len(pooled), "pooled": pooled, "n_psi": int(cfg.hier_samples),
            "max_steps": int(cfg.hier_max_steps), "n_stage1": n_max,
            "omp": os.environ.get("OMP_NUM_THREADS", "unset"),
            "affinity": sorted(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else "?",
            "load": " / ".join(f"{v:.2f}" for v in os.getloadavg()), "when": time.strftime("%Y-%m-%d %H:%M", time.gmtime())}
    text = render(rows, meta)
    print(text)
    atomic_write_text(out / f"{stem}.md", text)
    atomic_write_text(out / f"{stem}.json", json.dumps({"meta": meta, "rows": rows}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
