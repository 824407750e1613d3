"""Validation of the detective on data it has never seen (issue 17).

Every hidden effect here is coded from scratch (numpy only), not with hbm's effect classes:
a partial rupture (a multiplicative stress drop once the strain first passes ε_r), a locking
structure (a sigmoid step of extra load), a load-cell drift in time, quasi-linear
viscoelastic (QLV) relaxation by its own hereditary-integral recursion, Mullins-type
softening below the previous maximum strain, a constant offset, and a file in kPa instead of
MPa.  The base curves come from the Spyrou base model (the model under test) at parameter
sets, point counts, protocols and noise types (iid, AR(1), heteroscedastic, Student-t) that
neither the tests nor the demo use.

Targets (issue 17):

* false alarms <= 5 % of clean curves;
* never "adequate" while the command's own misfit windows are significant;
* out-of-library misfits reported as unexplained (or, for kPa, as a data problem) with a
  window containing them in >= 80 %;
* two hidden effects both named;
* ``--power`` on the demo's three-rate protocol reports a viscoelastic limit, and a QLV
  relaxation 1.5x that limit is named in >= 80 % of seeds.

Run from the repository root (the ``--hbm`` option diagnoses with another checkout, e.g. the
code before a change, for a before/after table)::

    PYTHONPATH=. python workflows/detective_validation.py                 # everything
    PYTHONPATH=. python workflows/detective_validation.py --groups clean  # one group
"""

from __future__ import annotations

import argparse
import json
import sys
import time as _time
from pathlib import Path

import numpy as np

OUT = Path("results/detective_validation.md")

# base parameter sets: neither the tests' nor the demo's
PARAM_SETS = [
    dict(VOLF=0.85, EOPT=0.12, P1=0.14, T1=1.1, T2=11.0, THETA=59.0, GF=0.013, GM=0.010),
    dict(VOLF=0.75, EOPT=0.08, P1=0.20, T1=0.6, T2=18.0, THETA=58.0, GF=0.02, GM=0.008),
    dict(VOLF=0.92, EOPT=0.15, P1=0.10, T1=2.0, T2=7.0, THETA=60.0, GF=0.010, GM=0.012),
]
NAMES = ("VOLF", "EOPT", "P1", "T1", "T2", "THETA", "GF", "GM")


# =========================================================================================
# protocols (strain, time, test), built here without hbm.data
# =========================================================================================
def _ramp(e0: float, e1: float, rate: float, n: int, t0: float, first: bool):
    """Points of a constant-rate ramp e0 -> e1; a continuing ramp omits its start point."""
    e = np.linspace(e0, e1, n + (0 if first else 1))
    e = e if first else e[1:]
    t = t0 + np.abs(e - e0) / rate
    return e, t


def make_protocol(kind: str, n: int, eps_max: float = 0.36) -> dict:
    """``kind``: single | two_rates | three_rates | lur (load-unload-reload, one history)."""
    es, ts, tests = [], [], []
    if kind in ("single", "two_rates", "three_rates"):
        rates = {"single": [1e-3], "two_rates": [1e-3, 1e-2], "three_rates": [1e-3, 1e-2, 1e-1]}[kind]
        for k, r in enumerate(rates):
            e, t = _ramp(0.0, eps_max, r, n, 0.0, True)
            es.append(e), ts.append(t), tests.append(np.full(n, k + 1))
    elif kind == "lur":
        t0 = 0.0
        for k, (a, b) in enumerate([(0.0, 0.8 * eps_max), (0.8 * eps_max, 0.1), (0.1, eps_max)]):
            e, t = _ramp(a, b, 1e-3, n, t0, k == 0)
            t0 = t[-1]
            es.append(e), ts.append(t), tests.append(np.full(e.size, k + 1))
    else:  # pragma: no cover
        raise ValueError(kind)
    return {"strain": np.concatenate(es), "time": np.concatenate(ts), "test": np.concatenate(tests)}


def _histories(p: dict) -> np.ndarray:
    """History id per point: a new history where the time restarts."""
    starts = np.r_[True, np.diff(p["time"]) < 0]
    return np.cumsum(starts) - 1


def base_stress(p: dict, th: dict) -> np.ndarray:
    """The base (Spyrou) model's stress on the protocol: the model under test, no effect."""
    from hbm.model.spyrou import spyrou_model
    m = spyrou_model()
    return np.asarray(m.stress(p["strain"], np.array([th[k] for k in NAMES]), p["time"], p["test"]))


# =========================================================================================
# hidden effects coded from scratch
# =========================================================================================
def _sigmoid(x):
    return 0.5 * (1.0 + np.tanh(0.5 * x))


def _running_max(p: dict, a: np.ndarray) -> np.ndarray:
    out = np.empty_like(a)
    for h in np.unique(_histories(p)):
        i = _histories(p) == h
        out[i] = np.maximum.accumulate(a[i])
    return out


def rupture(p, s, eps_r=0.2, frac=0.2, w=0.004):
    """Partial rupture: the stress drops by ``frac`` once the strain first passes eps_r (for good)."""
    return s * (1.0 - frac * _sigmoid((_running_max(p, p["strain"]) - eps_r) / w))


def locking(p, s, eps_l=0.22, amp=0.08, w=0.006):
    """A locking structure engaging at eps_l: a sigmoid step of extra load, ``amp`` × max stress."""
    return s + amp * float(np.max(np.abs(s))) * _sigmoid((p["strain"] - eps_l) / w)


def drift(p, s, total=0.1):
    """Load-cell drift proportional to time, ``total`` × max stress over the whole file."""
    return s + total * np.max(np.abs(s)) * p["time"] / np.max(p["time"])


def qlv(p, s, g=0.15, tau=60.0):
    """Quasi-linear viscoelasticity: σ = (1−g)·σe + g·∫exp(−(t−s)/τ) dσe(s), by its recursion
    (σe piecewise linear in time within each step); each history starts from rest."""
    out = np.empty_like(s)
    t = p["time"]
    hist = _histories(p)
    for h in np.unique(hist):
        idx = np.flatnonzero(hist == h)
        q = s[idx[0]]
        out[idx[0]] = s[idx[0]]
        for a, b in zip(idx[:-1], idx[1:]):
            dt = t[b] - t[a]
            x = dt / tau
            decay = np.exp(-x)
            weight = 1.0 if x < 1e-12 else (1.0 - decay) / x
            q = decay * q + (s[b] - s[a]) * weight
            out[b] = (1.0 - g) * s[b] + g * q
    return out


def mullins(p, s, dmg=0.15):
    """Mullins-type softening below the previous maximum strain: factor 1 − D·(1 − ε/ε_max)."""
    e = p["strain"]
    emax = _running_max(p, e)
    below = e < emax - 1e-12
    f = np.where(below, 1.0 - dmg * (1.0 - e / np.maximum(emax, 1e-12)), 1.0)
    return s * f


def offset(p, s, s0=0.006):
    """A constant load-cell offset."""
    return s + s0


# =========================================================================================
# noise types
# =========================================================================================
def add_noise(rng: np.random.Generator, p: dict, s: np.ndarray, kind: str, rel: float) -> np.ndarray:
    """Noise of sd ``rel`` × max stress: iid | ar1 (ρ 0.5 within histories) | hetero
    (sd ∝ floor + stress) | t5 (Student t, 5 dof, same sd)."""
    sd = rel * float(np.max(np.abs(s)))
    n = s.size
    if kind == "iid":
        return s + sd * rng.standard_normal(n)
    if kind == "ar1":
        rho, e = 0.5, rng.standard_normal(n)
        x = np.empty(n)
        starts = np.r_[True, np.diff(_histories(p)) != 0]
        for i in range(n):
            x[i] = e[i] if starts[i] else rho * x[i - 1] + np.sqrt(1 - rho * rho) * e[i]
        return s + sd * x
    if kind == "hetero":
        scale = 0.3 + 1.4 * np.abs(s) / np.max(np.abs(s))
        return s + sd * scale * rng.standard_normal(n)
    if kind == "t5":
        return s + sd * np.sqrt(3.0 / 5.0) * rng.standard_t(5, n)
    raise ValueError(kind)  # pragma: no cover


def dataset(p: dict, stress: np.ndarray, name: str):
    from hbm.data import Series, Specimen
    return Specimen(name, p["strain"], p["time"], p["test"], {"stress": Series.known("stress", stress)})


# =========================================================================================
# the cases
# =========================================================================================
def cases(groups) -> list[dict]:
    """Every validation case: generator settings and what a correct verdict is."""
    out = []
    protos = [("two_rates", 40), ("three_rates", 30), ("single", 80), ("lur", 35), ("two_rates", 25)]
    noises = ["iid", "ar1", "hetero", "t5"]
    if "clean" in groups:
        for i in range(20):
            pk, n = protos[i % 5]
            out.append(dict(group="clean", name=f"clean_{i}", pset=i % 3, proto=pk, n=n, noise=noises[(i // 5) % 4],
                            rel=[0.02, 0.03][i % 2], effects=[], expect="adequate"))
    if "unknown" in groups:
        for i in range(4):
            out.append(dict(group="unknown", name=f"rupture_{i}", pset=i % 3, proto=["two_rates", "single"][i % 2],
                            n=[45, 90][i % 2], noise=["iid", "t5"][i // 2], rel=0.006,
                            effects=[("rupture", {"eps_r": [0.26, 0.3, 0.28, 0.24][i], "frac": 0.2})],
                            expect="unexplained", where=[0.26, 0.3, 0.28, 0.24][i]))
            out.append(dict(group="unknown", name=f"locking_{i}", pset=(i + 1) % 3, proto=["two_rates", "single"][i % 2],
                            n=[45, 90][i % 2], noise=["iid", "hetero"][i // 2], rel=0.008,
                            effects=[("locking", {"eps_l": [0.22, 0.15, 0.28, 0.2][i], "amp": 0.12})],
                            expect="unexplained", where=[0.22, 0.15, 0.28, 0.2][i]))
            out.append(dict(group="unknown", name=f"drift_{i}", pset=(i + 2) % 3, proto="lur", n=[35, 50][i % 2],
                            noise="iid", rel=0.015, effects=[("drift", {"total": [0.12, 0.2, 0.15, 0.25][i]})],
                            expect="unexplained", where=None))
            out.append(dict(group="unknown", name=f"kpa_{i}", pset=i % 3, proto=["two_rates", "single"][i % 2],
                            n=[40, 70][i % 2], noise="iid", rel=0.02, effects=[("kpa", {})], expect="data_problem",
                            where=None))
    if "library" in groups:
        for i in range(4):
            out.append(dict(group="library", name=f"qlv_{i}", pset=i % 3, proto="three_rates", n=35, noise="iid",
                            rel=0.015, effects=[("qlv", {"g": 0.3, "tau": [60.0, 30.0, 100.0, 45.0][i]})],
                            expect="effect", named=["viscoelastic"]))
            out.append(dict(group="library", name=f"mullins_{i}", pset=(i + 1) % 3, proto="lur", n=40, noise="iid",
                            rel=0.01, effects=[("mullins", {"dmg": 0.3})], expect="effect", named=["damage"]))
    if "two" in groups:
        for i in range(4):
            out.append(dict(group="two", name=f"offset+qlv_{i}", pset=i % 3, proto="three_rates", n=35, noise="iid",
                            rel=0.012, effects=[("offset", {"s0": 0.006}), ("qlv", {"g": 0.35, "tau": 60.0})],
                            expect="effect", named=["offset", "viscoelastic"]))
    if "two_dev" in groups:
        # development set of the two-effect rule (issue 17 follow-up): other pairs, orders (an
        # offset before the QLV relaxes with the tissue, after it is a load-cell zero), protocols,
        # point counts and noise types than the "two" group, which stays held out
        dev = [("qlv>offset", 1, "three_rates", 30, "iid", 0.012,
                [("qlv", {"g": 0.3, "tau": 40.0}), ("offset", {"s0": 0.005})], ["viscoelastic", "offset"]),
               ("offset>qlv", 2, "two_rates", 50, "hetero", 0.01,
                [("offset", {"s0": 0.008}), ("qlv", {"g": 0.3, "tau": 100.0})], ["offset", "viscoelastic"]),
               ("mullins>offset", 0, "lur", 40, "iid", 0.01,
                [("mullins", {"dmg": 0.3}), ("offset", {"s0": 0.006})], ["offset", "damage"]),
               ("qlv+mullins", 1, "lur", 40, "iid", 0.01,
                [("qlv", {"g": 0.3, "tau": 60.0}), ("mullins", {"dmg": 0.3})], ["viscoelastic", "damage"]),
               ("qlv+drift", 2, "lur", 40, "iid", 0.012,
                [("qlv", {"g": 0.3, "tau": 60.0}), ("drift", {"total": 0.15})], ["viscoelastic"]),
               ("offset>qlv_t5", 0, "three_rates", 45, "t5", 0.012,
                [("offset", {"s0": 0.004}), ("qlv", {"g": 0.4, "tau": 30.0})], ["offset", "viscoelastic"])]
        for name, pset, proto, n, nz, rel, effs, named in dev:
            out.append(dict(group="two_dev", name=name, pset=pset, proto=proto, n=n, noise=nz, rel=rel,
                            effects=effs, expect="effect", named=named))
    return out


GENERATORS = {"rupture": rupture, "locking": locking, "drift": drift, "qlv": qlv, "mullins": mullins,
              "offset": offset}


def generate(c: dict, seed: int):
    """(dataset, noise-free stress) of a case."""
    p = make_protocol(c["proto"], c["n"])
    th = PARAM_SETS[c["pset"]]
    s = base_stress(p, th)
    for kind, kw in c["effects"]:
        if kind in GENERATORS:
            s = GENERATORS[kind](p, s, **kw)
    rng = np.random.default_rng(seed)
    y = add_noise(rng, p, s, c["noise"], c["rel"])
    if any(k == "kpa" for k, _ in c["effects"]):
        y = y * 1000.0   # the file is in kPa
    return dataset(p, y, c["name"]), s


def judge(c: dict, dg: dict) -> dict:
    """Is the verdict right?  ``dg``: the diagnosis JSON."""
    v = dg["verdict"]
    named = list(dg.get("selected") or [])
    wins = [(w[0], w[1]) for w in dg.get("misfit_windows") or []]
    unexpl = dg.get("unexplained_window")
    ok = False
    if c["expect"] == "adequate":
        ok = v == "adequate"
    elif c["expect"] == "unexplained":
        ok = v == "unexplained"
        if ok and c.get("where") is not None:
            where = c["where"]
            spans = ([tuple(unexpl["range"])] if unexpl and unexpl.get("axis") == "strain" else []) + wins
            ok = any(a - 0.01 <= where <= b + 0.01 for a, b in spans)
    elif c["expect"] == "data_problem":
        ok = v == "data_problem"
    elif c["expect"] == "effect":
        ok = v in ("effect", "effects") and set(c["named"]) <= set(named)
    inconsistent = v == "adequate" and bool(wins)
    return {"ok": bool(ok), "adequate_with_windows": inconsistent}


def run_case(c: dict, seed: int, diagnose, **kw) -> dict:
    ds, _ = generate(c, seed)
    t0 = _time.perf_counter()
    try:
        dg = diagnose(ds, seed=seed, **kw).to_dict()
    except Exception as exc:  # a crash is a wrong verdict, recorded
        dg = {"verdict": f"error: {type(exc).__name__}: {exc}", "selected": [], "misfit_windows": []}
    wall = _time.perf_counter() - t0
    row = {"case": c["name"], "group": c["group"], "expect": c["expect"], "verdict": dg["verdict"],
           "selected": list(dg.get("selected") or []), "message": dg.get("message", ""),
           "windows": len(dg.get("misfit_windows") or []), "seconds": round(wall, 1),
           "cpu_seconds": round(float((dg.get("timings") or {}).get("cpu", float("nan"))), 1),
           # wall time of the refined evidence reruns of decisive comparisons (part of "seconds")
           "refine_seconds": round(float((dg.get("timings") or {}).get("refine", 0.0)), 1)}
    row.update(judge(c, dg))
    # the likelihood tier and Δlog Z of each refit (tier comparisons: the same quantity estimated twice)
    base = dg.get("base") or {}
    row["base_tier"] = (base.get("likelihood_tier") or {}).get("tier")
    row["refits"] = {c["effect"]: {"dlogz": c.get("delta_log_evidence"), "se": c.get("delta_log_evidence_se"),
                                   "tier": (c.get("likelihood_tier") or {}).get("tier")}
                     for c in dg.get("candidates") or [] if c.get("refit")}
    return row


# =========================================================================================
# power on the demo's three-rate protocol
# =========================================================================================
def power_check(seed: int, n_seeds: int, diagnose) -> dict:
    """``diagnose(power=True)`` on the demo's three-rate protocol (clean data, demo parameters and
    noise), then a from-scratch QLV at 1.5× the reported viscoelastic limit (τ = 10 s, the
    limit's LOGTAU1 = 1), over seeds."""
    p = make_protocol("three_rates", 35, eps_max=0.38)
    th = dict(VOLF=0.9, EOPT=0.14, P1=0.13, T1=1.5, T2=9.3, THETA=59.6, GF=0.012, GM=0.009)
    s = base_stress(p, th)
    rng = np.random.default_rng(seed)
    ds = dataset(p, s + 0.002 * rng.standard_normal(s.size), "power_demo")
    t0 = _time.perf_counter()
    dg = diagnose(ds, seed=seed, power=True)
    t_power = _time.perf_counter() - t0
    lim = next((r for r in dg.power["effects"] if r["effect"] == "viscoelastic"), None)
    out = {"power_seconds": round(t_power, 1), "limit": lim, "power_text": dg.power_text()}
    if lim is None or lim.get("limit") is None:
        return out
    g = 1.5 * float(lim["limit"])
    hits = []
    for k in range(n_seeds):
        rng = np.random.default_rng(seed + 100 + k)
        y = qlv(p, s, g=g, tau=10.0) + 0.002 * rng.standard_normal(s.size)
        d2 = diagnose(dataset(p, y, f"qlv_{k}"), seed=seed + 100 + k)
        hits.append("viscoelastic" in (d2.selected or []))
    out.update(g=g, named=int(sum(hits)), seeds=n_seeds)
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--groups", nargs="*", default=["clean", "unknown", "library", "two", "power"])
    ap.add_argument("--seed", type=int, default=17)
    ap.add_argument("--run-groups", nargs="*", default=None,
                    help="run only these groups, in this order (seeds as in the enumeration of --groups)")
    ap.add_argument("--hbm", default=None, help="diagnose with the hbm package at this checkout (before/after)")
    ap.add_argument("--label", default="after")
    ap.add_argument("--json", default=None, help="write the rows to this JSON file")
    ap.add_argument("--out", default=str(OUT))
    ap.add_argument("--compare", default=None, help="JSON rows of a 'before' run to put next to these")
    ap.add_argument("--compare-label", default="the code before issue 17", help="what the 'before' run was")
    ap.add_argument("--power-seeds", type=int, default=10)
    ap.add_argument("--tier", "--likelihood", dest="tier", default=None,
                    help="likelihood tier(s) of diagnose, comma-separated (e.g. 'full,auto': each case is "
                         "diagnosed with each tier in turn, interleaved, and the first tier's rows are the "
                         "'before' column); default: diagnose's own default")
    args = ap.parse_args(argv)
    if args.hbm:
        sys.path.insert(0, args.hbm)
    from hbm.detective import diagnose
    rows = []
    # every case keeps the seed of its place in the enumeration of --groups, whatever is run
    seeded = [(args.seed + k, c) for k, c in enumerate(cases(args.groups))]
    run = args.run_groups if args.run_groups is not None else args.groups
    todo = [sc for g in run for sc in seeded if sc[1]["group"] == g]
    tiers = args.tier.split(",") if args.tier else [None]
    by_tier: dict = {t: [] for t in tiers}
    for seed, c in todo:
        for tier in tiers:     # interleaved: both tiers see the same machine load
            r = run_case(c, seed, diagnose, **({} if tier is None else {"tier": tier}))
            r["likelihood"] = tier or "default"
            by_tier[tier].append(r)
            rows.append(r)
            print(f"{r['case']:<16} expect {r['expect']:<12} got {r['verdict']:<13} {','.join(r['selected']):<26}"
                  f" {'ok' if r['ok'] else 'WRONG'}  [{r['seconds']} s, cpu {r['cpu_seconds']} s, {r['likelihood']}]",
                  flush=True)
        if args.json:       # after every case: a long run stopped early keeps what it did
            Path(args.json).write_text(json.dumps({"rows": rows, "power": None}, indent=1, default=str))
    power = power_check(args.seed, args.power_seeds, diagnose) if "power" in run else None
    if args.json:
        Path(args.json).write_text(json.dumps({"rows": rows, "power": power}, indent=1, default=str))
    if args.hbm is None:
        before = json.loads(Path(args.compare).read_text())["rows"] if args.compare else None
        if len(tiers) > 1:   # the first tier is the baseline of the last
            before, rows = by_tier[tiers[0]], by_tier[tiers[-1]]
            args.compare_label = f"--tier {tiers[0]} (same code, interleaved)"
        Path(args.out).write_text(report(rows, power, before, args.compare_label))
        print(f"wrote {args.out}")
    return 0


def _rate(rows, key="ok") -> str:
    return f"{sum(r[key] for r in rows)}/{len(rows)}" if rows else "-"


def report(rows: list[dict], power: dict | None, before: list[dict] | None,
           before_label: str = "the code before issue 17") -> str:
    """The markdown report: targets, then the table of cases × verdicts (before/after)."""
    by = {g: [r for r in rows if r["group"] == g] for g in ("clean", "unknown", "library", "two", "two_dev")}
    bb = {r["case"]: r for r in (before or [])}
    clean = by["clean"]
    fa = sum(not r["ok"] for r in clean)
    lines = ["# Detective validation on independently generated data (issue 17)", "",
             "Generated by `workflows/detective_validation.py`: every hidden effect is coded from scratch "
             "(numpy), the base curves use parameter sets, protocols, point counts and noise types (iid, "
             "AR(1) ρ 0.5, heteroscedastic, Student-t 5) of neither the tests nor the demo.", "",
             "## Targets", "",
             f"- false alarms on clean curves: {fa}/{len(clean)} (target <= 5 %)",
             f"- 'adequate' while the command's own windows are significant: "
             f"{sum(r['adequate_with_windows'] for r in rows)} (target 0)",
             f"- out-of-library misfits reported as unexplained / data problem with the right window: "
             f"{_rate(by['unknown'])} (target >= 80 %)",
             f"- in-library physics coded from scratch named: {_rate(by['library'])}",
             f"- two hidden effects both named: {_rate(by['two'])}"]
    if by["two_dev"]:
        lines.append(f"- development set of other effect pairs (`--groups two_dev`), all expected effects named: "
                     f"{_rate(by['two_dev'])}")
    if power:
        lim = power.get("limit") or {}
        lines.append(f"- power (demo three-rate protocol): viscoelastic limit "
                     f"{lim.get('limit')} ({lim.get('parameter', 'G1')}), computed in {power.get('power_seconds')} s; "
                     f"QLV at 1.5× the limit (g = {power.get('g', float('nan')):.3g}) named in "
                     f"{power.get('named')}/{power.get('seeds')} seeds (target >= 80 %)")
    lines += ["", "## Cases", "",
              "| case | group | expected | verdict" + (" before | verdict after" if before else "")
              + " | named | windows | ok | s |", "|---|---|---|---" + ("|---" if before else "") + "|---|---|---|---|"]
    for r in rows:
        b = bb.get(r["case"])
        bcol = f" {b['verdict']} {','.join(b['selected'])} ({'ok' if b['ok'] else 'wrong'}) |" if before else ""
        lines.append(f"| {r['case']} | {r['group']} | {r['expect']} |{bcol} {r['verdict']} | "
                     f"{','.join(r['selected']) or '-'} | {r['windows']} | {'ok' if r['ok'] else 'WRONG'} | "
                     f"{r['seconds']} |")
    if before:
        lines += ["", f"Before (same cases and seeds, {before_label}): "
                  + ", ".join(f"{g}: {_rate([bb[r['case']] for r in by[g] if r['case'] in bb])}" for g in by)]
    lines += ["", "## Messages", ""] + [f"- **{r['case']}**: {r['verdict']} — {r['message']}" for r in rows]
    if power and power.get("power_text"):
        lines += ["", "## Power report (demo three-rate protocol)", "", "```", power["power_text"], "```"]
    return "\n".join(lines) + "\n"


if __name__ == "__main__":
    sys.exit(main())
