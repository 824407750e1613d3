"""The 3-D base model in every loading mode (issue 35): cost per (particle · point), and DESIGN.md §8's claims.

1. **Cost.** CPU time (``time.process_time``, best of ``--repeat``) of
   ``hbm.model.loadcases.predict_observables`` for each mode and collagen reading on a population of
   ``--n`` parameter sets drawn uniformly from the prior box (``numpy.random.default_rng(35)``) × 40
   strains, interleaved with today's 1-D model (``spyrou_model(form="energy").stress``) on the same
   population.  For ``uniaxial_c`` also the principal-stress evaluations per (particle · point) of its
   Newton solve (the compiled solver's count, and the numpy solver's, counted by a subclass of ``Energy3D``).
2. **cone vs gst** at the Calvo-like parameters of the brief (VOLF 0.9, EOPT 0.18, P1 0.13, T1 1.5, T2 9.3,
   THETA 60, GF 0.012, GM 0.009) and at the six shipped specimens' generating parameters: cross-fibre
   tension at 20 % and the three shears at γ = 0.2 (stress ratio cone/gst), and cross- vs along-fibre
   tension at 20 %.
3. **N fibre families** (what FE cards discretise) against the exact cone: the largest |Δσ| of the loaded
   stress (``stress``) and of the reaction (``stress_2``, planar and biaxial modes) over every mode at
   strains (γ) of ±2 %..±20 %, relative to that series' largest |σ| (worst mode in brackets).
4. **Fisher identifiability** (2 % noise, Calvo rat-1 generating parameters, cone): the identifiable set
   φ = (ln G, ln c·P1, ln (1−c)·T1, EOPT, ln T2, THETA) (c enters W only through them); each series
   (one observable of one test) has 40 points and noise sd = 2 % of its largest |value|; the Jacobian by
   central differences (relative step 1e-5 in φ); sd(φ_k) = sqrt(diag(F⁻¹)), F = JᵀJ/sd².

Usage::

    OMP_NUM_THREADS=1 taskset -c 0 python workflows/benchmarks/loadcases.py [--n 2000] [--repeat 5]
        [--out results/benchmarks] [--quick]

Writes ``loadcases.md`` / ``loadcases.json`` to ``--out`` and prints the tables.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import re
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))

from hbm.model import spyrou_model  # noqa: E402
from hbm.model.energy3d import COLLAGEN_READINGS, ConeFamilies, Energy3D  # noqa: E402
from hbm.model.loadcases import LOAD_CASES, predict_observables  # noqa: E402
from hbm.model.loadcases.uniaxial_c import _lateral_root_compiled  # noqa: E402
from hbm.runtime.files import atomic_write_text  # noqa: E402

CALVO_LIKE = dict(VOLF=0.9, EOPT=0.18, P1=0.13, T1=1.5, T2=9.3, THETA=60.0, GF=0.012, GM=0.009)
N_POINTS = 40
STRAIN_MAX = 0.44       # the Calvo stand-ins' largest strain


class CountingEnergy(Energy3D):
    """Energy3D on the numpy path that counts the elements of every principal-stress evaluation (the compiled
    uniaxial_c solver reports its own count, :func:`hbm.model.loadcases.uniaxial_c._lateral_root_compiled`)."""

    evaluations = 0
    kernel = None

    def principal(self, p, e, tangent=False):
        CountingEnergy.evaluations += np.broadcast(*e, *p.values()).size
        return super().principal(p, e, tangent)


def controls(mode: str) -> tuple[np.ndarray, np.ndarray | None]:
    s = np.linspace(STRAIN_MAX / N_POINTS, STRAIN_MAX, N_POINTS)
    return s, None


def cost_table(n: int, repeat: int) -> list[dict]:
    model = spyrou_model(form="energy")
    lo, hi = model.bounds.T
    theta = lo + (hi - lo) * np.random.default_rng(35).random((n, model.n_params))
    p = model._params(theta)
    strain = np.linspace(STRAIN_MAX / N_POINTS, STRAIN_MAX, N_POINTS)
    jobs = {("1-D model (energy form)", "-"): lambda: model.stress(strain, theta)}
    for reading in COLLAGEN_READINGS:
        energy = Energy3D(collagen3d=reading)
        for mode in LOAD_CASES:
            jobs[(mode, reading)] = (lambda e=energy, m=mode: predict_observables(e, m, p, strain))
    best = {k: np.inf for k in jobs}
    for fn in jobs.values():
        fn()                                      # warm-up
    for _ in range(repeat):                       # interleaved: every job sees the same machine load
        for k, fn in jobs.items():
            t = time.process_time()
            fn()
            best[k] = min(best[k], time.process_time() - t)
    rows = []
    base = best[("1-D model (energy form)", "-")]
    for (mode, reading), t in best.items():
        row = dict(mode=mode, reading=reading, cpu_s=t, ns_per_particle_point=1e9 * t / (n * N_POINTS),
                   vs_1d=t / base)
        if mode == "uniaxial_c":
            CountingEnergy.evaluations = 0
            predict_observables(CountingEnergy(collagen3d=reading), mode, p, strain)
            row["principal_evals_per_particle_point_numpy"] = CountingEnergy.evaluations / (n * N_POINTS)
            compiled = _lateral_root_compiled(Energy3D(collagen3d=reading), p, strain, (n, N_POINTS))[2]
            row["principal_evals_per_particle_point"] = compiled.sum() / (n * N_POINTS)
        rows.append(row)
    return rows


def shipped_parameters() -> dict[str, dict]:
    out = {"calvo-like (brief)": CALVO_LIKE}
    for f in sorted((ROOT / "data" / "specimens").glob("*.csv")):
        line = next(x for x in f.read_text().splitlines() if x.startswith("# parameters:"))
        out[f.stem] = {k: float(v) for k, v in re.findall(r'"(\w+)": ([-\d.e]+)', line)}
    return out


def readings_table() -> list[dict]:
    rows = []
    for name, prm in shipped_parameters().items():
        at = np.array([0.2])
        val = {}
        for reading in ("cone", "gst"):
            e = Energy3D(collagen3d=reading)
            for mode in ("uniaxial_f", "uniaxial_c", "shear_fc", "shear_cf", "shear_cn"):
                val[mode, reading] = float(predict_observables(e, mode, prm, at)["stress"][0])
        row = dict(parameters=name, T2=prm["T2"])
        for mode in ("uniaxial_c", "shear_fc", "shear_cf", "shear_cn"):
            row[f"{mode} cone/gst"] = val[mode, "cone"] / val[mode, "gst"]
        row["cross/along cone"] = val["uniaxial_c", "cone"] / val["uniaxial_f", "cone"]
        row["cross/along gst"] = val["uniaxial_c", "gst"] / val["uniaxial_f", "gst"]
        rows.append(row)
    return rows


def families_table(ns=(6, 24, 96)) -> list[dict]:
    strain = np.concatenate([np.linspace(-0.2, -0.02, 10), np.linspace(0.02, 0.2, 10)])
    rows = []
    exact = Energy3D(collagen3d="cone")
    for name, prm in shipped_parameters().items():
        row = dict(parameters=name, T2=prm["T2"])
        for n in ns:
            fam = Energy3D(collagen3d=ConeFamilies(n))
            worst = {"stress": (0.0, ""), "stress_2": (0.0, "")}
            for mode, case in LOAD_CASES.items():
                a, b = (predict_observables(e, mode, prm, strain) for e in (exact, fam))
                for k in worst:
                    if k in a:
                        err = float(np.max(np.abs(b[k] - a[k])) / np.max(np.abs(a[k])))
                        worst[k] = max(worst[k], (err, mode))
            for k, (err, mode) in worst.items():
                row[f"N={n} {k}"] = f"{err:.2g} ({mode})"
        rows.append(row)
    return rows


PHI = ("ln G", "ln c*P1", "ln (1-c)*T1", "EOPT", "ln T2", "THETA")


def _params_from_phi(phi: np.ndarray, c: float) -> dict:
    """Base parameters from φ (..., 6) at volume fraction c (GF = GM = G; P1, T1 from the amplitudes)."""
    g, af, am = np.exp(phi[..., 0]), np.exp(phi[..., 1]), np.exp(phi[..., 2])
    cols = dict(VOLF=np.full_like(g, c), EOPT=phi[..., 3], P1=af / c, T1=am / (1 - c), T2=np.exp(phi[..., 4]),
                THETA=phi[..., 5], GF=g, GM=g)
    return {k: v[..., None] for k, v in cols.items()}


DESIGNS = {
    "along-fibre tension (uniaxial_f, 0-44 %)": [("uniaxial_f", 0.44, ("stress",))],
    "+ cross-fibre tension (uniaxial_c, 0-20 %)": [("uniaxial_f", 0.44, ("stress",)),
                                                   ("uniaxial_c", 0.20, ("stress",))],
    "+ shear along the fibres (shear_fc, 0-44 %)": [("uniaxial_f", 0.44, ("stress",)),
                                                    ("uniaxial_c", 0.20, ("stress",)),
                                                    ("shear_fc", 0.44, ("stress",))],
    "all ten modes (stresses; stretch modes to 20 %, shears to 44 %)": [
        (m, 0.44 if (m == "uniaxial_f" or m.startswith("shear")) else 0.20, tuple(
            o.name for o in LOAD_CASES[m].observables if o.is_stress)) for m in LOAD_CASES],
    "all ten modes + uniaxial_c lateral strains (noise 2 % of max)": [
        (m, 0.44 if (m == "uniaxial_f" or m.startswith("shear")) else 0.20, tuple(
            o.name for o in LOAD_CASES[m].observables if o.is_stress or m == "uniaxial_c")) for m in LOAD_CASES],
}


def fisher_table(reading: str = "cone", noise: float = 0.02) -> list[dict]:
    prm = shipped_parameters()["calvo2010_rat1"]
    c = prm["VOLF"]
    phi0 = np.array([np.log(c * prm["GF"] + (1 - c) * prm["GM"]), np.log(c * prm["P1"]),
                     np.log((1 - c) * prm["T1"]), prm["EOPT"], np.log(prm["T2"]), prm["THETA"]])
    step = 1e-5 * np.maximum(np.abs(phi0), 1.0)
    pert = np.vstack([phi0, phi0 + np.diag(step), phi0 - np.diag(step)])     # (13, 6)
    p = _params_from_phi(pert, c)
    energy = Energy3D(collagen3d=reading)
    rows = []
    for design, tests in DESIGNS.items():
        blocks = []
        for mode, top, names in tests:
            strain = np.linspace(top / N_POINTS, top, N_POINTS)
            out = predict_observables(energy, mode, p, strain)
            for k in names:
                y = out[k]
                sd = noise * np.abs(y[0]).max()
                blocks.append((y[1:7] - y[7:13]) / (2 * step[:, None]) / sd)    # (6, n) scaled sensitivities
        J = np.concatenate(blocks, axis=1).T
        cov = np.linalg.inv(J.T @ J)
        sd = np.sqrt(np.diag(cov))
        rows.append(dict(design=design, **{f"sd({k})": float(v) for k, v in zip(PHI, sd)},
                         condition=float(np.linalg.cond(J.T @ J))))
    return rows


def _fmt(v) -> str:
    if isinstance(v, float):
        return f"{v:.3g}"
    return str(v)


def markdown(title: str, rows: list[dict]) -> str:
    keys = list(rows[0])
    for r in rows:
        keys += [k for k in r if k not in keys]
    out = [f"### {title}", "", "| " + " | ".join(keys) + " |", "|" + "---|" * len(keys)]
    out += ["| " + " | ".join(_fmt(r.get(k, "")) for k in keys) + " |" for r in rows]
    return "\n".join(out) + "\n"


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n", type=int, default=2000, help="parameter sets of the cost population")
    ap.add_argument("--repeat", type=int, default=5)
    ap.add_argument("--out", default=str(ROOT / "results" / "benchmarks"))
    ap.add_argument("--quick", action="store_true", help="n = 200, 2 repeats (smoke run)")
    a = ap.parse_args(argv)
    n, repeat = (200, 2) if a.quick else (a.n, a.repeat)
    load = os.getloadavg()[0] if hasattr(os, "getloadavg") else float("nan")
    aff = sorted(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else "?"
    try:
        commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=ROOT, capture_output=True, text=True,
                                check=True).stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        commit = "unknown"
    head = (f"{time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())}, commit {commit}, "
            f"Python {platform.python_version()}, "
            f"numpy {np.__version__}, CPU affinity {aff}, OMP_NUM_THREADS={os.environ.get('OMP_NUM_THREADS')}, "
            f"load {load:.2f}; n = {n} parameter sets x {N_POINTS} points, best of {repeat} (CPU time)")
    cost = cost_table(n, repeat)
    ratios = readings_table()
    families = families_table()
    fisher = {r: fisher_table(r) for r in ("cone", "gst")}
    text = "\n".join([
        "# Loading modes of the 3-D base model (issue 35)", "", head, "",
        markdown("Cost per (particle · point), one core (diagonal modes compiled, shear numpy)", cost),
        markdown("cone vs gst (stress ratios at strain or gamma = 0.2)", ratios),
        markdown("N equally spaced fibre families vs the exact cone (max relative error, |strain| <= 0.2)",
                 families),
        markdown("Fisher identifiability, cone (2 % noise, Calvo rat 1, 40 points per series)", fisher["cone"]),
        markdown("Fisher identifiability, gst (same designs)", fisher["gst"]),
    ])
    print(text)
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    atomic_write_text(out / "loadcases.md", text)
    atomic_write_text(out / "loadcases.json", json.dumps(dict(header=head, cost=cost, readings=ratios,
                                                              families=families, fisher=fisher), indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
