#!/usr/bin/env python
"""Gold check of the hierarchical layer: the layer against a joint NUTS model of the same definition (issue 15).

Population (known generator, ``--pop-seed``): six synthetic specimens of the base Spyrou model whose
pooled columns x = (log G, log c·P1, log (1−c)·T1, T2, THETA) are drawn from the population model of
``hbm run --pool combinations`` with the hyper-parameters ``TRUTH`` (in the layer's transformed
coordinates: identity for the logs and THETA, logit on [0, 200] for T2), the other directions from
the uniform box prior given x (``hbm.identifiability.combinations.sample_conditional``; EOPT uniform).  c·P1 is
small (population median 0.004 MPa), so in several specimens the fibre term is buried in the noise
and the data bound c·P1 only from above — the case of the issue.  Strain 0–0.44 (45 points), iid
noise 1.5 % of the maximum stress, as the shipped specimens.

Stage 1: ``hbm.fit.specimen.fit_specimen`` as ``hbm run`` calls it (TMCMC N = 2000, common sigma box; CMA-ES
skipped: it only seeds figures), cached in ``--cache``.  Layer: ``hbm.population.run_population``
(default settings: ``--pool combinations``, 1000 ψ draws), over ``--layer-seeds`` seeds.

Gold: ``hierarchical_gold_peer.py`` in the bench venv (PyMC + nutpie, never imports hbm): the joint
posterior of (ψ, θ_1..θ_6) with the real likelihoods, 3 chains; first its pytensor p0(φ) is checked
against ``hbm.identifiability.combinations.log_density``.  Cached in ``--cache`` (keyed by the spec).

Variants (``--variant`` label): ``--exact none`` plain reuse (+ fresh TMCMC of flagged specimens), the
default the joint sampler (batched Metropolis-within-Gibbs, every specimen with its real likelihood, issue
37; ``--layer-*`` its schedule).  The exact fallback of issues 15/27 that it replaced is at commit 68827b1
(its variants' records stay in the json).

Output: ``results/benchmarks/hierarchical_gold.md`` and ``.json``: per hyper-parameter the median,
5 % and 95 % quantiles, layer vs NUTS, differences in NUTS posterior sd; the updated individuals'
quantiles of log c·P1 (and the other pooled columns) in the same units; the layer's seconds.

    OMP_NUM_THREADS=1 OPENBLAS_NUM_THREADS=1 python workflows/benchmarks/hierarchical_gold.py
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import tempfile
import subprocess
import sys
import time
import warnings
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[2]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from hbm import io  # noqa: E402
from hbm.identifiability.combinations import COMBINATION_PARAMS, log_density, sample_conditional, support_hull  # noqa: E402
from hbm.data import synthetic_specimen  # noqa: E402
from hbm.fit import fit_specimen  # noqa: E402
from hbm.model import spyrou_model  # noqa: E402
from hbm.population import COMBINATION_COLUMNS, DEFAULT_SD_RANGE, JOINT_SD_RANGE, run_population  # noqa: E402
from hbm.samplers.hierarchical import HierarchicalModel  # noqa: E402
from hbm.runtime.files import atomic_write_text  # noqa: E402
from hbm.workflow.run import _common_sigma_box  # noqa: E402

PEER = Path(__file__).with_name("hierarchical_gold_peer.py")
#: known hyper-parameters (mu, sd) in the layer's coordinates (all sds inside the hyperprior ranges)
TRUTH = {"log_G": (np.log(0.01), 0.5), "log_VOLF*P1": (np.log(0.004), 1.0),
         "log_(1-VOLF)*T1": (np.log(0.15), 0.8), "T2": (np.log(10.0 / 190.0), 1.0), "THETA": (58.0, 1.0)}
STRAIN = np.round(np.arange(45) * 0.01, 10)
NOISE_REL = 0.015


def _bench_python() -> Path | None:
    env = os.environ.get("HBM_PYMC_PYTHON")
    for p in ([Path(env)] if env else []) + [ROOT.parent / "bench-venv/bin/python",
                                              ROOT / ".venv-pymc/bin/python"]:
        if p.exists():
            return p
    return None


def draw_population(model, seed: int, n: int = 6, truth=TRUTH) -> tuple[dict, np.ndarray]:
    """Datasets of ``n`` specimens drawn from the population model with hyper-parameters ``truth``."""
    rng = np.random.default_rng(seed)
    names = list(model.parameter_names)
    box = model.bounds
    hull = np.log(support_hull(box, names))
    cb = np.array([box[names.index(p)] for p in COMBINATION_PARAMS])
    out, thetas = {}, []
    while len(thetas) < n:
        phi = np.array([rng.normal(*truth[c]) for c in COMBINATION_COLUMNS])
        zt2 = rng.normal(*truth["T2"])
        theta_deg = rng.normal(*truth["THETA"])
        if not (np.all((phi >= hull[:, 0]) & (phi <= hull[:, 1])) and 55.0 <= theta_deg <= 60.0):
            continue  # truncated normals of the population model
        if not np.isfinite(log_density(phi[None], cb)[0]):
            continue  # outside the prior support of the combinations: no parameters (the layer rejects it too)
        parts = sample_conditional(phi[None], cb, rng)[0]
        th = dict(zip(COMBINATION_PARAMS, parts))
        th.update(T2=200.0 / (1.0 + np.exp(-zt2)), THETA=theta_deg, EOPT=rng.uniform(*box[names.index("EOPT")]))
        clean = model.stress(STRAIN, np.array([th[k] for k in names]))
        sid = f"gold{len(thetas) + 1}"
        out[sid] = synthetic_specimen(model, th, STRAIN, NOISE_REL, int(rng.integers(2**31)), relative=True,
                                      attrs={"id": sid})
        thetas.append([th[k] for k in names])
        del clean
    return out, np.array(thetas)


def stage1(datasets: dict, model, cache: Path, samples: int, seed: int) -> dict:
    """fit_specimen per specimen (cached netCDF)."""
    box = _common_sigma_box(datasets)
    res = {}
    for k, (sid, ds) in enumerate(sorted(datasets.items())):
        path = cache / f"{sid}.nc"
        if not io.is_complete(path):
            t = time.perf_counter()
            fit_specimen(ds, model=model, samples=samples, seed=seed + k, restarts=0, sigma_bounds=box,
                         progress=False, out=path)
            print(f"  stage 1 {sid}: {time.perf_counter() - t:.1f} s", file=sys.stderr)
        res[sid] = io.read_specimen_result(path)
    return res


def layer(results, datasets, model, seed: int, **cfg) -> tuple:
    """The layer (written to a scratch file and read back: the ArviZ diagnostics are those of the file)."""
    import tempfile

    t = time.perf_counter()
    c = time.process_time()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        with tempfile.TemporaryDirectory() as tmp:
            _, path = run_population(results, datasets, model, seed=seed, progress=False, out=tmp, **cfg)
            hf = io.read_hierarchical(path)
            hf.attrs["arviz"] = _arviz(path)
    return hf, time.perf_counter() - t, time.process_time() - c


def _arviz(path) -> dict:
    """Max R-hat and min bulk ESS over the hyper-parameters, by ArviZ from ``hierarchical.nc``."""
    try:
        import arviz as az
    except ImportError:  # pragma: no cover - a test extra
        return {}
    post = az.from_netcdf(path).posterior
    rhat, ess = az.rhat(post), az.ess(post, method="bulk")  # unrounded (az.summary rounds to 2 decimals)
    return {"rhat_max": float(max(rhat[v] for v in rhat.data_vars)),
            "ess_bulk_min": float(min(ess[v] for v in ess.data_vars)), "chains": int(post.sizes["chain"])}


def _sd_range(hf) -> tuple:
    """The hyperprior sd range the layer of ``hf`` used: the joint sampler's or the reuse layer's default."""
    return JOINT_SD_RANGE if hf.attrs.get("layer") else DEFAULT_SD_RANGE


def peer_spec(results, datasets, hf) -> dict:
    """Everything the NUTS peer needs: data, box, pooled columns with transforms and hyperprior ranges."""
    first = next(iter(results.values()))
    names = list(first.names)
    box = {n: list(map(float, first.bounds[j])) for j, n in enumerate(names)}
    pooled = list(hf.attrs["pooled"])
    pb = hf.attrs["bounds"]
    tr = hf.attrs["transforms"]
    hm = HierarchicalModel(pooled, np.array([pb[p] for p in pooled]), transforms=tr, sd_range=_sd_range(hf))
    cols = []
    for k, p in enumerate(pooled):
        zlo, zhi = float(hm.zlo[k]), float(hm.zhi[k])
        cols.append({"name": p, "transform": tr[p], "bounds": list(map(float, pb[p])),
                     "zbox": [zlo if np.isfinite(zlo) else None, zhi if np.isfinite(zhi) else None],
                     "mu_range": [float(hm.mu_lo[k]), float(hm.mu_hi[k])],
                     "sd_range": [float(hm.sd_lo[k]), float(hm.sd_hi[k])]})
    specs = [{"id": sid, "strain": datasets[sid].strain.tolist(),
              "stress": datasets[sid].stress.tolist()} for sid in hf.specimen_ids]
    return {"box": box, "pooled": cols, "specimens": specs}


def run_peer(spec: dict, cache: Path, draws: int, tune: int, seed: int) -> tuple[dict, dict]:
    py = _bench_python()
    if py is None:
        raise SystemExit("no bench python (set HBM_PYMC_PYTHON or create ../bench-venv next to the repository, see README.md)")
    key = hashlib.sha256(json.dumps([spec, draws, tune, seed], sort_keys=True).encode()).hexdigest()[:12]
    spath, npz, meta = cache / f"spec-{key}.json", cache / f"nuts-{key}.npz", cache / f"nuts-{key}.json"
    spath.write_text(json.dumps(spec))
    if not (npz.exists() and meta.exists()):
        t = time.perf_counter()
        out = subprocess.run([str(py), str(PEER), "run", "--spec", str(spath), "--out", str(npz), "--draws",
                              str(draws), "--tune", str(tune), "--chains", "3", "--seed", str(seed)],
                             capture_output=True, text=True, check=False)
        if out.returncode != 0:
            raise SystemExit(f"peer failed:\n{out.stderr[-3000:]}")
        info = json.loads(out.stdout.strip().splitlines()[-1])
        info["wall_s"] = time.perf_counter() - t
        meta.write_text(json.dumps(info))
    info = json.loads(meta.read_text())
    z = np.load(npz)
    return info, {k: np.asarray(z[k]) for k in z.files}


def check_p0(spec: dict, results, cache: Path) -> tuple[float, float]:
    """Largest |peer − hbm| of log p0(φ) over 240 stage-1 φ rows, and of the population log ratio
    log p(θ|ψ)/p0(θ) at 40 (θ, ψ) pairs (ψ from the hyperprior box): the peer's density is the
    layer's, term by term (independent implementations)."""
    py = _bench_python()
    first = next(iter(results.values()))
    names = list(first.names)
    x = np.concatenate([r.samples[:40] for r in results.values()])
    f = np.log(np.column_stack([x[:, names.index("VOLF")] * x[:, names.index("GF")]
                                + (1 - x[:, names.index("VOLF")]) * x[:, names.index("GM")],
                                x[:, names.index("VOLF")] * x[:, names.index("P1")],
                                (1 - x[:, names.index("VOLF")]) * x[:, names.index("T1")]]))
    ours = log_density(f, first.bounds, names)
    pooled = [p["name"] for p in spec["pooled"]]
    aug_names = names + list(COMBINATION_COLUMNS)
    aug_bounds = np.vstack([first.bounds, [spec["pooled"][k]["bounds"] for k in range(3)]])
    hm = HierarchicalModel(aug_names, aug_bounds, pooled=pooled, sd_range=DEFAULT_SD_RANGE,
                           transforms={p["name"]: p["transform"] for p in spec["pooled"]})
    rng = np.random.default_rng(0)
    xs = x[rng.choice(len(x), 40, replace=False)]
    raw = rng.uniform(hm.box[:, 0], hm.box[:, 1], (40, hm.box.shape[0]))
    xa = np.hstack([xs, np.log(np.column_stack([
        xs[:, names.index("VOLF")] * xs[:, names.index("GF")] + (1 - xs[:, names.index("VOLF")]) * xs[:, names.index("GM")],
        xs[:, names.index("VOLF")] * xs[:, names.index("P1")], (1 - xs[:, names.index("VOLF")]) * xs[:, names.index("T1")]]))])
    extra = [n for n in pooled if n in names]
    lp = log_density(xa[:, -3:], first.bounds, names) - sum(np.log(np.ptp(first.bounds[names.index(n)])) for n in extra)
    F, c = hm.features(xa, lp)
    coef, cc = hm.coefficients(raw)
    ours_r = np.einsum("ij,ij->i", coef, F) + cc + c
    nat = hm.natural(raw)
    d = len(pooled)
    sp_pop = [{"theta": dict(zip(names, map(float, xs[j]))), "mu": nat[j, :d].tolist(), "sd": nat[j, d:2 * d].tolist()}
              for j in range(40)]
    sp = dict(spec, check_phi=f.tolist(), check_pop=sp_pop)
    path = cache / "check.json"
    path.write_text(json.dumps(sp))
    out = subprocess.run([str(py), str(PEER), "check", "--spec", str(path)], capture_output=True, text=True)
    if out.returncode != 0:
        raise SystemExit(f"peer check failed:\n{out.stderr[-3000:]}")
    got = json.loads(out.stdout.strip().splitlines()[-1])
    return (float(np.max(np.abs(np.array(got["log_p0"]) - ours))),
            float(np.max(np.abs(np.array(got["log_ratio"]) - ours_r))))


def _phi_cols(names, x) -> dict:
    """Pooled columns of θ rows (natural units) by name."""
    c = x[..., names.index("VOLF")]
    return {"log_G": np.log(c * x[..., names.index("GF")] + (1 - c) * x[..., names.index("GM")]),
            "log_VOLF*P1": np.log(c * x[..., names.index("P1")]),
            "log_(1-VOLF)*T1": np.log((1 - c) * x[..., names.index("T1")]),
            "T2": x[..., names.index("T2")], "THETA": x[..., names.index("THETA")]}


Q = (0.05, 0.5, 0.95)


def compare(hfs: list, nuts: dict, names: list, specimen_ids: list) -> dict:
    """Hyper-parameter and updated-individual quantiles: layer (per seed) vs NUTS, in NUTS sd."""
    rows = {}
    for hn in hfs[0][0].hyper_names:
        g = nuts[hn].reshape(-1)
        gq, gsd = np.quantile(g, Q), float(g.std())
        lay = [np.quantile(hf.hyper(hn), Q) for hf, _ in hfs]
        rows[hn] = {"nuts": gq.tolist(), "nuts_sd": gsd, "layer": [q.tolist() for q in lay],
                    "diff_sd": [((q - gq) / gsd).tolist() for q in lay]}
    indiv = {}
    for i, sid in enumerate(specimen_ids):
        th = np.stack([nuts[n][..., i].reshape(-1) for n in names], axis=1)
        gcols = _phi_cols(names, th)
        for col, g in gcols.items():
            gq, gsd = np.quantile(g, Q), float(g.std())
            lay = [np.quantile(_phi_cols(names, hf.updated[:, i, :])[col], Q) for hf, _ in hfs]
            indiv[f"{sid}:{col}"] = {"nuts": gq.tolist(), "nuts_sd": gsd, "layer": [q.tolist() for q in lay],
                                     "diff_sd": [((q - gq) / gsd).tolist() for q in lay]}
    return {"hyper": rows, "individuals": indiv}


def compare_stored(hfs: list, gold: dict, names: list, specimen_ids: list) -> dict:
    """:func:`compare` against the NUTS quantiles stored in a record of ``hierarchical_gold.json`` (the
    same population seed: its datasets are the generator's, so its joint posterior is the same)."""
    out = {"hyper": {}, "individuals": {}}
    for key, rows in (("hyper", gold["hyper"]), ("individuals", gold["individuals"])):
        for name, r in rows.items():
            if key == "hyper":
                lay = [np.quantile(hf.hyper(name), Q) for hf, _ in hfs]
            else:
                sid, col = name.split(":", 1)
                i = specimen_ids.index(sid)
                lay = [np.quantile(_phi_cols(names, hf.updated[:, i, :])[col], Q) for hf, _ in hfs]
            gq, gsd = np.asarray(r["nuts"]), float(r["nuts_sd"])
            out[key][name] = {"nuts": gq.tolist(), "nuts_sd": gsd, "layer": [q.tolist() for q in lay],
                              "diff_sd": [((q - gq) / gsd).tolist() for q in lay]}
    return out


def _worst(rows: dict) -> tuple[float, float]:
    """Largest |median diff| and largest |5 %/95 % diff| (in NUTS sd) over rows and seeds."""
    d = np.array([r["diff_sd"] for r in rows.values()])  # (rows, seeds, 3)
    return float(np.abs(d[..., 1]).max()), float(np.abs(d[..., [0, 2]]).max())


def table(cmp: dict, key: str, seeds: list) -> list[str]:
    lines = ["| quantity | NUTS 5 % / 50 % / 95 % | NUTS sd | layer 5 % / 50 % / 95 % (seed 1) | "
             "Δ 5 % (sd) | Δ 50 % (sd) | Δ 95 % (sd) |", "|---|---|---|---|---|---|---|"]
    for name, r in cmp[key].items():
        d = np.array(r["diff_sd"])
        fmt = lambda j: " / ".join(f"{v:+.2f}" for v in d[:, j])  # noqa: E731 - per-seed values
        lines.append(f"| {name} | {' / '.join(f'{v:.3g}' for v in r['nuts'])} | {r['nuts_sd']:.3g} | "
                     f"{' / '.join(f'{v:.3g}' for v in r['layer'][0])} | {fmt(0)} | {fmt(1)} | {fmt(2)} |")
    return lines


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--cache", default=str(Path(tempfile.gettempdir()) / "hbm_hierarchical_gold"))
    ap.add_argument("--out", default=str(ROOT / "results/benchmarks"))
    ap.add_argument("--pop-seed", type=int, default=15)
    ap.add_argument("--samples", type=int, default=2000)
    ap.add_argument("--layer-seeds", default="1,2,3")
    ap.add_argument("--draws", type=int, default=1000)
    ap.add_argument("--tune", type=int, default=1000)
    ap.add_argument("--exact", default=None, choices=("gibbs", "none"),
                    help="PopulationConfig.exact: gibbs = the joint sampler (default), none = reuse + refinements")
    ap.add_argument("--layer-chains", type=int, default=None, help="PopulationConfig.layer_chains")
    ap.add_argument("--layer-keep", type=int, default=None, help="PopulationConfig.layer_keep (kept draws per chain)")
    ap.add_argument("--layer-burn", type=int, default=None, help="PopulationConfig.layer_burn (burn-in rounds)")
    ap.add_argument("--layer-thin", type=int, default=None, help="PopulationConfig.layer_thin (rounds per kept draw)")
    ap.add_argument("--layer-extend", type=float, default=None,
                    help="PopulationConfig.layer_extend (the chains go on until converged, up to this many times "
                         "their planned draws; 1: never)")
    ap.add_argument("--nuts-from", default=None, metavar="VARIANT",
                    help="compare with the NUTS quantiles stored under VARIANT in hierarchical_gold.json (same "
                         "population seed) instead of running the peer (no PyMC needed)")
    ap.add_argument("--variant", default="default", help="label of the layer settings in the output")
    ap.add_argument("--stage1-only", action="store_true")
    a = ap.parse_args(argv)
    cache = Path(a.cache) / f"pop{a.pop_seed}"
    cache.mkdir(parents=True, exist_ok=True)
    model = spyrou_model()
    datasets, thetas = draw_population(model, a.pop_seed)
    results = stage1(datasets, model, cache, a.samples, 1000 * a.pop_seed)
    if a.stage1_only:
        return 0
    seeds = [int(s) for s in a.layer_seeds.split(",")]
    # the reference-rows and second-pass variants left hbm with issue 25 (their code: commit 287c749,
    # hbm/population.py _reference_rows / _mixture_pass; results/benchmarks/hierarchical_gold.md)
    cfg = {}
    if a.exact:
        cfg["exact"] = None if a.exact == "none" else a.exact
    for key in ("layer_chains", "layer_keep", "layer_burn", "layer_thin"):
        if getattr(a, key) is not None:
            cfg[key] = int(getattr(a, key))
    if a.layer_extend is not None:
        cfg["layer_extend"] = float(a.layer_extend)
    hfs = [layer(results, datasets, model, s, **cfg)[0:3:2] for s in seeds]  # (hf, cpu seconds)
    names = list(next(iter(results.values())).names)
    if a.nuts_from:
        gold = json.loads((Path(a.out) / "hierarchical_gold.json").read_text())[a.nuts_from]
        if int(gold["pop_seed"]) != a.pop_seed:
            raise SystemExit(f"--nuts-from {a.nuts_from}: population seed {gold['pop_seed']}, not {a.pop_seed}")
        cmp = compare_stored(hfs, gold, names, hfs[0][0].specimen_ids)
        write_variant(a.variant, a.pop_seed, seeds, hfs, gold["nuts"], None, tuple(gold["p0_check_max_abs"]),
                      thetas, names, Path(a.out), cmp=cmp)
        return 0
    spec = peer_spec(results, datasets, hfs[0][0])
    p0_err = check_p0(spec, results, cache)
    info, nuts = run_peer(spec, cache, a.draws, a.tune, seed=a.pop_seed)
    write_variant(a.variant, a.pop_seed, seeds, hfs, info, nuts, p0_err, thetas, names, Path(a.out))
    return 0


def write_variant(variant: str, pop_seed: int, seeds: list, hfs: list, info: dict, nuts: dict | None, p0_err, thetas,
                  names: list, out: Path, cmp: dict | None = None) -> str:
    """Compare one layer variant (``hfs``: (HierarchicalFile, CPU s) per seed) with the NUTS draws (or the
    precomputed comparison ``cmp``) and write its record into ``hierarchical_gold.json`` and its section into
    ``hierarchical_gold_<variant>.md.part``."""
    cmp = compare(hfs, nuts, names, hfs[0][0].specimen_ids) if cmp is None else cmp
    wh, wt = _worst(cmp["hyper"])
    rec = {"variant": variant, "pop_seed": pop_seed, "layer_seeds": seeds, "truth": {k: list(v) for k, v in TRUTH.items()},
           "thetas": np.asarray(thetas).tolist(), "p0_check_max_abs": p0_err, "nuts": info,
           "layer_cpu_s": [c for _, c in hfs],
           "reuse": [hf.reuse for hf, _ in hfs], "refined": [hf.attrs.get("refined") for hf, _ in hfs],
           "exact": [{k: v for k, v in (hf.attrs.get("exact") or {}).items() if k not in ("rhat", "ess")}
                     for hf, _ in hfs],
           "layer": [{k: v for k, v in (hf.attrs.get("layer") or {}).items() if k not in ("hyper", "specimens")}
                     for hf, _ in hfs],
           "arviz": [hf.attrs.get("arviz", {}) for hf, _ in hfs],
           "worst_median_sd": wh, "worst_tail_sd": wt, **cmp}
    jpath = out / "hierarchical_gold.json"
    allrec = json.loads(jpath.read_text()) if jpath.exists() else {}
    allrec[variant] = rec
    atomic_write_text(jpath, json.dumps(allrec, indent=1, default=float))
    md = [f"### variant `{variant}` (population seed {pop_seed}, layer seeds {seeds})", "",
          f"NUTS: {info['chains']} chains × {info['draws']} draws (tune {info['tune']}), max R-hat (hyper) "
          f"{max(info['rhat'].values()):.3f}, max R-hat (all) {info['rhat_max_all']:.3f}, min bulk ESS (hyper) "
          f"{min(info['ess_bulk'].values()):.0f}, divergences {info['divergences']}, {info['sample_s']:.0f} s. "
          f"Peer vs hbm, max |Δ|: log p0(φ) {p0_err[0]:.1e}, log p(θ|ψ)/p0(θ) {p0_err[1]:.1e}.", "",
          f"Layer CPU s per seed: {', '.join(f'{c:.1f}' for _, c in hfs)}; refined: "
          f"{[hf.attrs.get('refined') for hf, _ in hfs]}.  Worst |Δ median| {wh:.2f} sd, worst |Δ 5 %/95 %| {wt:.2f} sd "
          f"(target 0.2 / 0.5).", ""]
    lay = [hf.attrs.get("layer") for hf, _ in hfs]
    if any(lay):
        md += ["Joint sampler per seed: " + "; ".join(
            f"{e['chains']} chains × {e['n_keep']} kept (burn-in {e['n_burn']}, thin {e['thin']}), "
            f"{e['evaluations']:,} model evaluations, {e['cpu_s']:.0f} CPU s / {e['wall_s']:.0f} s wall, ArviZ from the "
            f"file: max R-hat {hf.attrs.get('arviz', {}).get('rhat_max', float('nan')):.3f}, min bulk ESS "
            f"{hf.attrs.get('arviz', {}).get('ess_bulk_min', float('nan')):.0f} (hyper-parameters); max R-hat over "
            f"the specimens' columns {e['rhat_specimen_max']:.3f}" if e else "not run"
            for e, (hf, _) in zip(lay, hfs)) + ".", ""]
    ex = [hf.attrs.get("exact") for hf, _ in hfs]
    if any(ex):
        md += ["Exact fallback (joint Metropolis-within-Gibbs) per seed: " + "; ".join(
            f"real likelihoods for {', '.join(e['exact'])}, {e['n_chains']} chains × {e['n_keep']} kept "
            f"(burn-in {e['n_burn']}, thin {e['thin']}), {sum(e['evaluations'].values())} likelihood evaluations, "
            f"{e['cpu_s']:.0f} CPU s / {e['wall_s']:.0f} s wall, max R-hat {e['rhat_max']:.3f}, min bulk ESS "
            f"{e['ess_min']:.0f}" if e else "not run" for e in ex) + ".", ""]
    md += ["Hyper-parameters (Δ per layer seed, in NUTS posterior sd):", ""] + table(cmp, "hyper", seeds) + [""]
    md += ["Updated individuals (pooled columns):", ""] + table(cmp, "individuals", seeds) + [""]
    md += ["Reuse diagnostic per specimen against the gold (worst |Δ| of the individual's 5 %/50 %/95 % "
           "over its pooled columns and the layer seeds, in NUTS sd; flags per layer seed):", "",
           "| specimen | worst Δ (sd) | k̂ median | population beyond samples | posterior beyond samples | ESS 10 % "
           "| flagged | refined |", "|---|---|---|---|---|---|---|---|"]
    for sid in hfs[0][0].specimen_ids:
        d = np.array([r["diff_sd"] for k, r in cmp["individuals"].items() if k.startswith(sid + ":")])
        r0 = hfs[0][0].reuse.get(sid, {})
        md.append(f"| {sid} | {np.abs(d).max():.2f} | {r0.get('khat_median', np.nan):.2f} | "
                  f"{r0.get('population_beyond', np.nan):.2f} | {r0.get('uncovered', np.nan):.3f} | "
                  f"{r0.get('ess_q10', np.nan):.0f} | "
                  f"{' / '.join('yes' if hf.reuse.get(sid, {}).get('unreliable') else 'no' for hf, _ in hfs)} | "
                  f"{' / '.join('yes' if sid in (hf.attrs.get('refined') or []) else 'no' for hf, _ in hfs)} |")
    md.append("")
    text = "\n".join(md)
    print(text)
    atomic_write_text(out / f"hierarchical_gold_{variant}.md.part", text + "\n")
    return text


if __name__ == "__main__":
    sys.exit(main())
