"""Two porcine-like 150-point compression records for timing the detective (issue 28).

Base model in the energy form (``--form energy``) + QLV viscoelasticity (G1 0.5, log10 τ 1.0),
relative iid noise 2 % of the peak: three ramps to ε = −0.2 at 0.1, 1 and 10 %/s, or three ramps at
1 %/s to ε = −0.1, −0.2, −0.3, each ramp (25 points) followed by a 120 s relaxation hold (25 points).
The generating model and parameters are left out of the files (a lab file does not carry them).

Run from the repository root::

    PYTHONPATH=. python workflows/benchmarks/compression_records.py --out /tmp/records
    hbm diagnose /tmp/records/compression_three_rates.csv --form energy
"""

from __future__ import annotations

import argparse
from pathlib import Path

from hbm.data import hold, protocol, ramp, save_specimen, synthetic_specimen
from hbm.effects import make_effect
from hbm.model.spyrou import spyrou_model

THETA = dict(VOLF=0.8, EOPT=0.1, P1=0.15, T1=0.8, T2=14.0, THETA=58.5, GF=0.015, GM=0.01, G1=0.5, LOGTAU1=1.0)
HIDDEN = ("# model:", "# effects:", "# parameters:", "# generator:")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", required=True, help="folder for the two CSV files")
    args = ap.parse_args(argv)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    model = spyrou_model(form="energy") + make_effect("viscoelastic")
    records = {
        "compression_three_rates": (protocol(*[[ramp(-0.2, r, 25), hold(120.0, 25)] for r in (1e-3, 1e-2, 1e-1)]), 3),
        "compression_three_magnitudes": (protocol(*[[ramp(-a, 1e-2, 25), hold(120.0, 25)] for a in (0.1, 0.2, 0.3)]), 4),
    }
    for name, (prot, seed) in records.items():
        path = out / f"{name}.csv"
        save_specimen(synthetic_specimen(model, THETA, prot, 0.02, seed=seed, relative=True), path)
        lines = [ln for ln in path.read_text().splitlines(keepends=True) if not ln.startswith(HIDDEN)]
        path.write_text("".join(lines))
        print(path)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
