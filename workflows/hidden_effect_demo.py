"""Hidden-effect demo: generate data with an effect switched on, diagnose, extend, report.

For each case a synthetic specimen is generated from the base model plus a *hidden* effect
(or none, or an effect that is not in the library), with a protocol that can reveal it
(DESIGN.md §2: several rates for viscoelasticity, load–unload–reload for damage, EOPT pinned
for slack).  ``hbm.diagnose`` is run with all eight library candidates, then ``hbm.extend``
adds the named effect (or, if nothing was named, the true one, to show what adding it would
have bought).  Figures and a summary table go to ``results/hidden_effect/``.

Run from the repository root::

    PYTHONPATH=. python workflows/hidden_effect_demo.py            # all cases
    PYTHONPATH=. python workflows/hidden_effect_demo.py --cases offset damage
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

import hbm  # noqa: F401  (package import check)
from hbm.data import cycle, protocol, ramp, synthetic_specimen
from hbm.detective import diagnose, extend
from hbm.effects import make_effect
from hbm.model.core import Effect, Parameter
from hbm.model.spyrou import spyrou_model
from hbm.runtime.files import atomic_write_text

OUT = Path("results/hidden_effect")

# Calvo-1-like base parameters (DESIGN.md §1), not those of tests/test_detective.py
THETA = dict(VOLF=0.9, EOPT=0.14, P1=0.13, T1=1.5, T2=9.3, THETA=59.6, GF=0.012, GM=0.009)


class Plateau(Effect):
    """An effect NOT in the library: a local stress plateau (smooth step up and down) between
    ε = 0.18 and 0.26 — e.g. a transient stiffening from sliding filaments."""

    name = "plateau"
    stage = "output"
    parameters = (Parameter("PL", 0.0, 0.05, "MPa", "plateau height", null=0.0),)

    def modify(self, state, p, stress):
        e = state.loading.strain
        up = 1 / (1 + np.exp(-(e - 0.18) / 0.01))
        down = 1 / (1 + np.exp(-(e - 0.26) / 0.01))
        return stress + p["PL"] * (up - down)


def case(name: str, seed: int):
    """(dataset, fix, hidden effect id or None, true noise sd, description)."""
    m, th, fix, sd, noise, rho = spyrou_model(), dict(THETA), None, 0.002, "iid", 0.0
    rates = protocol(ramp(0.38, 1e-3, 45), ramp(0.38, 1e-2, 45))
    if name == "clean":
        prot, hidden, desc = rates, None, "no hidden effect, two rates"
    elif name == "clean_ar1":
        prot, hidden, desc = rates, None, "no hidden effect, AR(1) noise rho 0.7"
        noise, rho = "ar1", 0.7
    elif name == "offset":
        m, hidden = m + make_effect("offset"), "offset"
        th["S0"] = 0.008
        prot, desc = protocol(ramp(0.38, 1e-3, 70)), "load-cell offset 0.008 MPa, one ramp"
    elif name == "viscoelastic":
        m, hidden = m + make_effect("viscoelastic"), "viscoelastic"
        th.update(G1=0.4, LOGTAU1=1.8)
        prot = protocol(ramp(0.38, 1e-3, 35), ramp(0.38, 1e-2, 35), ramp(0.38, 1e-1, 35))
        desc = "QLV g=0.4, tau=63 s, ramps at 0.1/1/10 %/s"
    elif name == "damage":
        m, hidden = m + make_effect("damage"), "damage"
        th["DMG"] = 0.35
        prot = protocol(cycle(0.32, 1e-3, 35, eps_min=0.1, reload_to=0.38))
        desc = "Mullins damage 0.35, load-unload-reload"
    elif name == "slack":
        m, hidden = m + make_effect("slack"), "slack"
        th.update(EOPT=0.04, P1=0.35, T1=0.25, T2=7.0, THETA=59.4, SLACK=0.035)
        fix, sd = {"EOPT": 0.04}, 0.0015
        prot, desc = rates, "slack 0.035 with EOPT pinned at 0.04"
    elif name == "unknown":
        m, hidden = m + Plateau(), "plateau (not in library)"
        th["PL"] = 0.008
        prot, desc = rates, "local plateau 0.008 MPa in eps 0.18-0.26 (not in the library)"
    else:
        raise SystemExit(f"unknown case {name!r}")
    ds = synthetic_specimen(m, th, prot, sd, seed=seed, noise=noise, rho=rho,
                            attrs={"id": f"hidden_{name}"})
    return ds, fix, hidden, sd, desc


CASES = ["clean", "clean_ar1", "offset", "viscoelastic", "damage", "slack", "unknown"]


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cases", nargs="*", default=CASES)
    ap.add_argument("--seed", type=int, default=2026)
    ap.add_argument("--out", default=str(OUT))
    args = ap.parse_args(argv)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    rows = []
    for k, name in enumerate(args.cases):
        ds, fix, hidden, sd, desc = case(name, args.seed + k)
        t0 = time.perf_counter()
        # the three-rate case also reports what its protocol and noise could reveal (--power)
        dg = diagnose(ds, fix=fix, seed=args.seed + k, power=name == "viscoelastic")
        t_diag = time.perf_counter() - t0
        dg.plot(out / f"{name}_diagnosis.png")
        atomic_write_text(out / f"{name}_diagnosis.txt", dg.summary() + "\n")
        atomic_write_text(out / f"{name}_diagnosis.json", json.dumps(dg.to_dict(), indent=1) + "\n")
        if dg.power:
            atomic_write_text(out / f"{name}_power.txt", dg.power_text() + "\n")
        add = dg.selected or ([dg.group[0]] if dg.group else [])
        if not add and hidden in ("offset", "viscoelastic", "damage", "slack"):
            add = [hidden]
        ext = None
        if add:
            ext = extend(ds, add=add, fix=fix, seed=args.seed + k)
            ext.plot(out / f"{name}_extend.png")
            atomic_write_text(out / f"{name}_extend.txt", ext.table() + "\n")
        best = max((c for c in dg.candidates if c.refit), key=lambda c: c.delta_log_evidence, default=None)
        rows.append({
            "case": name, "hidden": hidden or "none", "description": desc, "noise_sd": sd,
            "verdict": dg.verdict, "named": ",".join(dg.selected or dg.group) or "-",
            "message": dg.message,
            "best_candidate": best.effect if best else "-",
            "best_delta_log_z": round(best.delta_log_evidence, 2) if best else None,
            "best_delta_log_z_se": round(best.delta_log_evidence_se, 2) if best else None,
            "best_delta_log_z_laplace": round(best.delta_log_evidence_laplace, 2) if best else None,
            "rmse_before": dg.base.rmse,
            "rmse_after": ext.steps[-1].rmse if ext else None,
            "extended_with": ",".join(add) or "-",
            "misfit_windows": dg.misfit_windows,
            "diagnose_seconds": round(t_diag, 1),
            "diagnose_cpu_seconds": round(dg.timings.get("cpu", float("nan")), 1),
        })
        print(f"{name:<14} hidden={hidden or 'none':<26} verdict={dg.verdict:<12} named={rows[-1]['named']:<20} "
              f"RMSE {dg.base.rmse:.4g} -> {rows[-1]['rmse_after'] or float('nan'):.4g} (noise {sd})  "
              f"[{t_diag:.1f} s]", flush=True)
    lines = ["# Hidden-effect demo", "",
             "Generated by `workflows/hidden_effect_demo.py` (synthetic data; base parameters Calvo-1-like).",
             "Δlog Z: the TMCMC difference against the best base (the decision number) ± its SE calibrated",
             "to the seed-to-seed scatter; in brackets the Laplace screen's estimate.  Times: wall / CPU seconds",
             "of `diagnose` with all eight candidates and the four generic controls (wall times include waiting",
             "for a shared, loaded machine; CPU is what one free core would take).",
             "", "| case | hidden effect | verdict | named | best candidate: Δlog Z ± SE (Laplace) | RMSE before | "
             "RMSE after (extended with) | noise sd | diagnose wall / CPU (s) |",
             "|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        dz = "-" if r["best_delta_log_z"] is None else (
            f"{r['best_candidate']}: {r['best_delta_log_z']:.1f} ± {r['best_delta_log_z_se']:.1f} "
            f"({r['best_delta_log_z_laplace']:.1f})")
        after = "-" if r["rmse_after"] is None else f"{r['rmse_after']:.4g} ({r['extended_with']})"
        lines.append(f"| {r['case']} | {r['description']} | {r['verdict']} | {r['named']} | {dz} | "
                     f"{r['rmse_before']:.4g} | {after} | {r['noise_sd']} | {r['diagnose_seconds']} / "
                     f"{r['diagnose_cpu_seconds']} |")
    lines += ["", "Verdict messages:", ""] + [f"- **{r['case']}**: {r['message']}" for r in rows]
    atomic_write_text(out / "summary.md", "\n".join(lines) + "\n")
    atomic_write_text(out / "summary.json", json.dumps(rows, indent=1, default=float) + "\n")
    print(f"wrote {out}/summary.md")
    return 0


if __name__ == "__main__":
    sys.exit(main())
