"""The six-rat workflow from Python (the API version of ``hbm run``).

Run from the repository root::

    python workflows/six_rats.py                 # all cores, results/ (a few minutes on 2 cores)
    python workflows/six_rats.py --quick         # smoke run
    python workflows/six_rats.py --workers 2 --out /tmp/six

For every specimen in data/specimens: CMA-ES optima with a VOLF bound sweep, the TMCMC
posterior with log-evidence, Sobol indices -- one dask task each -- then the hierarchical
layer, identifiable combinations, VOLF-T1 manifolds, figures and results/report.md.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path


def main(argv=None) -> int:
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # run from a checkout without installing
    from hbm.workflow import RunConfig, run_workflow

    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", default="data/specimens")
    ap.add_argument("--out", default="results")
    ap.add_argument("--workers", type=int, default=None)
    ap.add_argument("--samples", type=int, default=2000)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--quick", action="store_true")
    a = ap.parse_args(argv)

    cfg = RunConfig(data=a.data, out=a.out, workers=a.workers, samples=a.samples, seed=a.seed, quick=a.quick)

    def my_section(wres) -> str:
        # report hook: any callable wres -> markdown is appended to report.md (e.g. organ predictions)
        best = max(wres.results.values(), key=lambda r: r.log_evidence)
        return f"## Note\n\nHighest log-evidence: {best.specimen_id} ({best.log_evidence:.2f})."

    res = run_workflow(cfg, extra_sections=[my_section])
    print(f"report: {res.report_path}; hierarchical: {res.hierarchical_path}; "
          f"{len(res.figures)} figures; total {res.timings['total']:.1f} s")
    return 0 if not res.errors else 1


if __name__ == "__main__":  # required: dask worker processes re-import this file
    sys.exit(main())
