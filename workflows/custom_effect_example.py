"""A user-written effect, end to end: define it, screen it with ``diagnose``, add it with ``extend``.

Nothing in hbm is edited.  The effect below lives in *this* file; it is passed

* from Python as an instance (``diagnose(data, candidates=[..., LoadCellDrift()])``), and
* on the command line as ``--candidate workflows/custom_effect_example.py:LoadCellDrift``.

The effect: a load cell whose zero drifts linearly in time after it was tared at the start of
each test, σ_measured = σ + D·t.  On two ramps at different rates the drift leaves a different
offset at the end of each test — a signature no library effect has.

Run from the repository root::

    PYTHONPATH=. python workflows/custom_effect_example.py
"""

from __future__ import annotations

import json
import sys
import tempfile
from pathlib import Path

import numpy as np

import hbm
from hbm.errors import HbmError
from hbm.runtime.files import atomic_write_text


class LoadCellDrift(hbm.Effect):
    """Load-cell zero drift: σ + D·(t − t_start of the test).  Null D = 0."""

    name = "load_cell_drift"
    stage = "output"
    description = "load-cell zero drifting linearly in time since the tare at each test start"
    parameters = (hbm.Parameter("DRIFT", -1e-4, 1e-4, "MPa/s", "zero drift rate of the load cell", null=0.0),)

    def modify(self, state, p, stress):
        loading = state.loading
        if loading.time is None:
            raise HbmError("load_cell_drift needs a 'time' column")
        t = loading.time
        tests = loading.test if loading.test is not None else loading.history
        # time since the first point of the current test (vectorised: index of each test start)
        start = np.r_[True, tests[1:] != tests[:-1]]
        t0 = t[np.maximum.accumulate(np.where(start, np.arange(t.size), 0))]
        return stress + p["DRIFT"] * (t - t0)


def main() -> int:
    from hbm.data import protocol, ramp, save_specimen, synthetic_specimen
    from hbm.detective import diagnose, extend

    base = hbm.spyrou_model()
    truth = dict(VOLF=0.88, EOPT=0.12, P1=0.1, T1=1.0, T2=11.0, THETA=59.3, GF=0.01, GM=0.012, DRIFT=2.5e-5)
    prot = protocol(ramp(0.35, 1e-3, 50), ramp(0.35, 1e-2, 50))   # 350 s and 35 s ramps
    ds = synthetic_specimen(base + LoadCellDrift(), truth, prot, 0.0015, seed=7,
                            attrs={"id": "drift_example"})

    # 1. Python: the user's effect is one more candidate next to library ids
    dg = diagnose(ds, candidates=["offset", "viscoelastic", "series_compliance", LoadCellDrift()], seed=7)
    print(dg.summary())

    # 2. the command line: --candidate path.py:ClassName (file loaded with importlib, no hbm edit)
    from hbm import cli
    with tempfile.TemporaryDirectory() as tmp:
        csv = save_specimen(ds, Path(tmp) / "drift_example.csv")
        argv = ["diagnose", str(csv), "--candidates", "offset",
                "--candidate", f"{Path(__file__).resolve()}:LoadCellDrift", "--json"]
        print("\n$ hbm " + " ".join(argv))
        if "diagnose" in cli.COMMANDS:
            cli.main(argv)
        else:
            print("(the 'diagnose' subcommand is not registered in hbm.cli.COMMANDS yet)")

    # 3. add it and watch the error fall
    ext = extend(ds, add=[LoadCellDrift()], seed=7)
    print("\n" + ext.table())
    out = Path("results/hidden_effect")
    ext.plot(out / "custom_effect_extend.png")
    dg.plot(out / "custom_effect_diagnosis.png")
    atomic_write_text(out / "custom_effect_diagnosis.json", json.dumps(dg.to_dict(), indent=1) + "\n")
    print(f"figures: {out}/custom_effect_diagnosis.png, {out}/custom_effect_extend.png")
    return 0


if __name__ == "__main__":
    sys.exit(main())
