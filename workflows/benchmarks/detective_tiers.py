"""Wall and CPU time of ``hbm diagnose`` under the full and the collapsed likelihood tier (issue 28
item 2, issue 27 item 4), interleaved case by case so that both see the same machine load.

Cases: the shipped 150-point three-rate relaxation record (``results/multirate_relaxation``), the
measured curves given with ``--measured`` (e.g. ../shared/realdata/*.csv), and the cases of the
hidden-effect demo (``workflows/hidden_effect_demo.py``, its seeds).  Each diagnosis is the
default one (CLI defaults: ``--max-time 300``) with ``tier=`` each tier in turn.

    PYTHONPATH=. nice -n 10 python workflows/benchmarks/detective_tiers.py --json /tmp/tiers.json \\
        --measured ../shared/realdata/*.csv --demo viscoelastic clean

CPU is the process time of the diagnosis (what one free core would take); wall includes waiting
for a shared machine.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
import warnings
from pathlib import Path

RECORD = Path("results/multirate_relaxation/three_rate_relaxation.csv")
MAX_TIME = 300.0


def _row(name: str, tier: str, dg, wall: float, cpu: float) -> dict:
    js = dg.to_dict()
    named = {c["effect"]: [c["delta_log_evidence"], c["delta_log_evidence_se"], c["evidence_method"],
                           (c.get("likelihood_tier") or {}).get("tier")]
             for c in js["candidates"] if c["refit"]}
    return {"case": name, "tier": tier, "verdict": js["verdict"], "selected": js["selected"],
            "message": js["message"], "wall": round(wall, 1), "cpu": round(cpu, 1),
            "base_tier": js["base"]["likelihood_tier"]["tier"], "base_log_z": js["base"]["log_evidence"],
            "refits": named, "stopped": bool(js.get("stopped"))}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--tiers", default="full,auto")
    ap.add_argument("--measured", nargs="*", default=[])
    ap.add_argument("--demo", nargs="*", default=["viscoelastic"], help="hidden-effect demo cases")
    ap.add_argument("--no-record", action="store_true")
    ap.add_argument("--sl0", type=float, default=2.0, help="reference sarcomere length (um) of --measured files")
    ap.add_argument("--json", required=True)
    args = ap.parse_args(argv)
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
    import hidden_effect_demo as demo
    from hbm.data import load_specimen
    from hbm.detective import diagnose
    cases = [] if args.no_record else [("three_rate_relaxation_150", load_specimen(RECORD), None, 0)]
    # sarcomere-length files: the reference SL0 the README's measured examples use (--sl0 2.0)
    cases += [(Path(p).stem, load_specimen(p, sl0=args.sl0), None, 0) for p in args.measured]
    for name in args.demo:
        k = demo.CASES.index(name)
        ds, fix, _, _, _ = demo.case(name, 2026 + k)
        cases.append((f"demo_{name}", ds, fix, 2026 + k))
    rows = []
    for name, ds, fix, seed in cases:
        for tier in args.tiers.split(","):
            t, c = time.perf_counter(), time.process_time()
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                dg = diagnose(ds, fix=fix, seed=seed, max_time=MAX_TIME, tier=tier)
            rows.append(_row(name, tier, dg, time.perf_counter() - t, time.process_time() - c))
            r = rows[-1]
            print(f"{name:<28} {tier:<5} {r['verdict']:<12} {','.join(r['selected']):<20} wall {r['wall']:>6} s "
                  f"cpu {r['cpu']:>6} s{' STOPPED' if r['stopped'] else ''}", flush=True)
            Path(args.json).write_text(json.dumps(rows, indent=1, default=str))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
