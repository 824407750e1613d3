"""Calibrated verdicts (issue 38): false alarms on clean curves of many designs, and periodic ripples.

Clean curves: the Spyrou base model (the model under test, parameter sets of
``detective_validation.py``) on protocols of five kinds -- one ramp, multi-rate ramps, a ramp and
a relaxation hold, a staircase (ramp-hold steps), load-unload-reload -- with point counts from 20
to 400, and noise of three kinds coded here with numpy: iid, proportional (sd ∝ a floor + the
stress) and AR(1) (ρ 0.5 within each history).  A correct verdict is "adequate"; the calibrated
detective's false-alarm rate should be within a binomial interval of its stated 5 %.

Ripples: 5 % of the peak stress, period 9 s, on a staircase and on a ramp-hold protocol (iid
noise of 0.5 % of the peak, and AR(1) noise of 1 %, ρ 0.5); a correct verdict is "unexplained" with the periodic shape and its period within 5 %.

Run from the repository root (each case in this process)::

    PYTHONPATH=. python workflows/calibration_validation.py --json /tmp/cal.json

or interleaved with another checkout, one fresh process per case and checkout::

    python workflows/benchmarks/detective_before_after.py --before /tmp/before --after . \\
        --module calibration_validation --groups clean_designs ripple --json /tmp/ba_cal.json
"""

from __future__ import annotations

import argparse
import json
import re
import sys
import time as _time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import detective_validation as V  # noqa: E402  (parameter sets, base model, dataset)

RIPPLE_PERIOD = 9.0
KINDS = ("ramp", "multi_rate", "ramp_hold", "staircase", "lur")
NOISES = ("iid", "proportional", "ar1")
POINTS = (20, 30, 45, 60, 90, 120, 200, 400)


def _segments(kind: str, n: int):
    """Strain, time, test of a protocol of ``kind`` with about ``n`` points in all."""
    from hbm.data import cycle, hold, protocol, ramp
    if kind == "ramp":
        ds = protocol(ramp(0.35, 1e-3, n))
    elif kind == "multi_rate":
        k = 3 if n >= 45 else 2
        ds = protocol(*[ramp(0.34, r, n // k) for r in (1e-3, 1e-2, 1e-1)[:k]])
    elif kind == "ramp_hold":
        ds = protocol([ramp(0.3, 2e-3, max(n // 3, 4)), hold(150.0, n - max(n // 3, 4))])
    elif kind == "staircase":
        per = max(n // 4, 5)
        segs = []
        for j in range(4):
            segs += [ramp(0.09 * (j + 1), 1e-2, max(per // 3, 2)), hold(60.0, per - max(per // 3, 2))]
        ds = protocol(segs)
    elif kind == "lur":
        ds = protocol(cycle(0.34, 2e-3, max(n // 3, 4), eps_min=0.08))
    else:  # pragma: no cover
        raise ValueError(kind)
    return {"strain": ds["strain"].values, "time": ds["time"].values, "test": ds["test"].values}


def add_noise(rng, p: dict, s: np.ndarray, kind: str, rel: float) -> np.ndarray:
    """iid | proportional (sd ∝ 0.2 + |s|/max|s|) | ar1 (ρ 0.5 within histories), sd ``rel`` × peak."""
    if kind == "proportional":
        sd = rel * np.max(np.abs(s)) * (0.2 + np.abs(s) / np.max(np.abs(s))) / 1.2
        return s + sd * rng.standard_normal(s.size)
    return V.add_noise(rng, p, s, kind, rel)


def cases(groups) -> list[dict]:
    out = []
    if "clean_designs" in groups:
        for i in range(45):
            out.append(dict(group="clean_designs", name=f"design_{i}", kind=KINDS[i % 5], noise=NOISES[(i // 5) % 3],
                            n=POINTS[(i * 3) % len(POINTS)], pset=i % 3, rel=[0.01, 0.02, 0.03][(i // 3) % 3],
                            expect="adequate"))
    if "ripple" in groups:
        for i, kind in enumerate(("staircase", "ramp_hold", "staircase", "ramp_hold")):
            out.append(dict(group="ripple", name=f"ripple_{kind}_{i}", kind=kind, noise="iid",
                            n=[130, 110, 100, 140][i], pset=i % 3, rel=0.005, expect="unexplained", ripple=0.05))
        # correlated noise (AR(1), ρ 0.5) of 1 % of the peak: the AR(1) fit absorbs part of the ripple
        for i, kind in enumerate(("staircase", "ramp_hold")):
            out.append(dict(group="ripple", name=f"ripple_{kind}_ar1_{i}", kind=kind, noise="ar1",
                            n=[120, 120][i], pset=(i + 1) % 3, rel=0.01, expect="unexplained", ripple=0.05))
    return out


def generate(c: dict, seed: int):
    p = _segments(c["kind"], c["n"])
    s = V.base_stress(p, V.PARAM_SETS[c["pset"]])
    if c.get("ripple"):
        s = s + c["ripple"] * np.max(np.abs(s)) * np.sin(2 * np.pi * p["time"] / RIPPLE_PERIOD + 0.4)
    rng = np.random.default_rng(seed)
    return V.dataset(p, add_noise(rng, p, s, c["noise"], c["rel"]), c["name"]), s


def judge(c: dict, dg: dict) -> dict:
    v = dg["verdict"]
    if c["expect"] == "adequate":
        return {"ok": v == "adequate", "adequate_with_windows": v == "adequate" and bool(dg.get("misfit_windows"))}
    u = dg.get("unexplained_window") or {}
    m = re.search(r"period ([0-9.]+) s", dg.get("message", ""))
    period_ok = m is not None and abs(float(m.group(1)) / RIPPLE_PERIOD - 1) <= 0.05
    return {"ok": bool(v == "unexplained" and u.get("control") == "periodic" and period_ok),
            "adequate_with_windows": False, "period": float(m.group(1)) if m else None}


def run_case(c: dict, seed: int, diagnose, **kw) -> dict:
    ds, _ = generate(c, seed)
    t0, c0 = _time.perf_counter(), _time.process_time()
    try:
        dg = diagnose(ds, seed=seed, progress=False, **kw).to_dict()
    except Exception as exc:  # a crash is a wrong verdict, recorded
        dg = {"verdict": f"error: {type(exc).__name__}: {exc}", "selected": [], "misfit_windows": []}
    cal = dg.get("calibration") or {}
    row = {"case": c["name"], "group": c["group"], "expect": c["expect"], "verdict": dg["verdict"],
           "kind": c["kind"], "noise": c["noise"], "n": int(ds.sizes["point"]),
           "selected": list(dg.get("selected") or []), "message": dg.get("message", ""),
           "seconds": round(_time.perf_counter() - t0, 1),
           "cpu_seconds": round(float((dg.get("timings") or {}).get("cpu", float("nan"))), 1),
           "calibration_seconds": round(float((dg.get("timings") or {}).get("calibration", 0.0)), 2),
           "method": cal.get("method", "fixed (code before issue 38)"),
           "p_family": ((cal.get("rounds") or [{}])[0] or {}).get("p_family")}
    row.update(judge(c, dg))
    return row


def clopper_pearson(k: int, n: int, level: float = 0.95) -> tuple[float, float]:
    """Exact binomial interval of a rate k/n."""
    from scipy import stats
    a = (1 - level) / 2
    lo = 0.0 if k == 0 else float(stats.beta.ppf(a, k, n - k + 1))
    hi = 1.0 if k == n else float(stats.beta.ppf(1 - a, k + 1, n - k))
    return lo, hi


def _stats(rows: list[dict], key: str) -> str:
    import statistics
    v = [r[key] for r in rows if isinstance(r.get(key), (int, float)) and r[key] == r[key]]
    return f"{statistics.median(v):.1f} / {max(v):.1f}" if v else "-"


def report(designs: list[dict], validation: dict | None, commit: str) -> str:
    """Markdown section of issue 38: false alarms on the clean designs (binomial interval), the
    ripples, and the validation sets before/after (verdicts right, CPU and wall medians)."""
    lines = [f"## Calibrated verdicts (issue 38, code {commit})", ""]
    for label, rows in (("calibrated", [r for r in designs if r.get("method") == "calibrated"]),
                        ("before (fixed thresholds)", [r for r in designs if r.get("method") != "calibrated"])):
        clean = [r for r in rows if r["group"] == "clean_designs"]
        fa = sum(not r["ok"] for r in clean)
        lo, hi = clopper_pearson(fa, len(clean)) if clean else (0.0, 1.0)
        if not clean and any(r["group"] == "ripple" for r in rows):
            lines.append(f"- **{label}**, ripples:")
        elif clean:
            lines.append(f"- **{label}**, {len(clean)} clean curves of new designs (ramps, multi-rate ramps, ramp-holds, "
                     f"staircases, load-unload-reload; iid, proportional, AR(1) noise; 20-400 points): false alarms "
                     f"{fa}/{len(clean)} = {fa / len(clean):.1%}, 95 % Clopper-Pearson interval [{lo:.1%}, {hi:.1%}] "
                     f"({'contains' if lo <= 0.05 <= hi else 'does not contain'} the stated 5 %); CPU s median / max "
                     f"{_stats(clean, 'cpu_seconds')}; ripples:")
        for r in [r for r in rows if r["group"] == "ripple"]:
            lines.append(f"  - {r['case']} ({r['n']} points): {r['verdict']}, period {r.get('period')} s "
                         f"({'ok' if r['ok'] else 'WRONG'})")
    if validation:
        lines += ["", "Validation sets of `workflows/detective_validation.py`, before (68827b1, fixed thresholds) and "
                  "after, interleaved case by case in fresh processes (`workflows/benchmarks/detective_before_after.py`):",
                  "", "| group | right before | right after | CPU s median / max before | after | wall s median before | after |",
                  "|---|---|---|---|---|---|---|"]
        for g in ("clean", "unknown", "library", "two"):
            b = [r for r in validation["before"] if r.get("group") == g]
            a = [r for r in validation["after"] if r.get("group") == g]
            if not a:
                continue
            lines.append(f"| {g} ({len(a)}) | {f'{sum(r[chr(111) + chr(107)] for r in b)}/{len(b)}' if b else '-'} | "
                         f"{sum(r['ok'] for r in a)}/{len(a)} | "
                         f"{_stats(b, 'cpu_seconds')} | {_stats(a, 'cpu_seconds')} | {_stats(b, 'seconds')} | "
                         f"{_stats(a, 'seconds')} |")
        lines += ["", "| case | verdict before | after | CPU s before | after |", "|---|---|---|---|---|"]
        bb = {r["case"]: r for r in validation["before"]}
        for r in validation["after"]:
            b = bb.get(r["case"], {})
            if b.get("verdict") != r["verdict"] or not r["ok"]:
                lines.append(f"| {r['case']} | {b.get('verdict')} {','.join(b.get('selected') or [])} | {r['verdict']} "
                             f"{','.join(r['selected'])}{'' if r['ok'] else ' (WRONG)'} | {b.get('cpu_seconds')} | "
                             f"{r['cpu_seconds']} |")
    lines += ["", "| design case | protocol | noise | points | verdict | family-wise p | CPU s |", "|---|---|---|---|---|---|---|"]
    for r in designs:
        pf = r.get("p_family")
        lines.append(f"| {r['case']} | {r['kind']} | {r['noise']} | {r['n']} | {r['verdict']}{'' if r['ok'] else ' (WRONG)'} | "
                     f"{'-' if pf is None else f'{pf:.3f}'} | {r['cpu_seconds']} |")
    return "\n".join(lines) + "\n"


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--groups", nargs="*", default=["clean_designs", "ripple"])
    ap.add_argument("--seed", type=int, default=17)
    ap.add_argument("--calibration", default=None, help="on | off (default: diagnose's own default)")
    ap.add_argument("--json", default=None)
    ap.add_argument("--report", nargs="*", default=None, metavar="JSON",
                    help="write the issue-38 section from these JSON files (rows of this script, and before/after "
                         "rows of detective_before_after.py) instead of running; to stdout")
    ap.add_argument("--commit", default="HEAD")
    ap.add_argument("--cases", default=None, metavar="START:STOP",
                    help="run only these cases of the enumeration (seeds unchanged), e.g. to shard a run")
    args = ap.parse_args(argv)
    if args.report is not None:
        designs, validation = [], {"before": [], "after": []}
        for f in args.report:
            got = json.loads(Path(f).read_text())
            if isinstance(got, list):
                designs += got
            elif "rows" in got:           # detective_validation.py's own run (after only)
                validation["after"] += got["rows"]
            elif got["after"] and got["after"][0].get("kind"):
                designs += got["after"] + got["before"]
            else:
                for k in ("before", "after"):
                    validation[k] += got[k]
        # a case run twice (shards that overlapped): its first row
        seen: set = set()
        designs = [r for r in designs if not ((r["case"], r.get("method")) in seen or seen.add((r["case"], r.get("method"))))]
        print(report(designs, validation if validation["after"] else None, args.commit))
        return 0
    from hbm.detective import diagnose
    kw = {} if args.calibration is None else {"calibration": args.calibration}
    rows = []
    every = list(enumerate(cases(args.groups)))
    if args.cases:
        a, b = (int(x) if x else None for x in args.cases.split(":"))
        every = every[a:b]
    for k, c in every:
        r = run_case(c, args.seed + k, diagnose, **kw)
        rows.append(r)
        print(f"{r['case']:<22} {r['kind']:<10} {r['noise']:<12} n={r['n']:<4} {r['verdict']:<12} "
              f"{'ok' if r['ok'] else 'WRONG'} [{r['seconds']} s, cpu {r['cpu_seconds']} s]", flush=True)
        if args.json:
            Path(args.json).write_text(json.dumps(rows, indent=1, default=str))
    return 0


if __name__ == "__main__":
    sys.exit(main())
