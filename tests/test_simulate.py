"""``hbm simulate`` (issue 35, item 3) against the independent implementation (tests/independent3d.py)."""

from __future__ import annotations

import csv
import json
import sys
from pathlib import Path

import numpy as np
import pytest

from hbm.cli import main
from hbm.data import load_specimen
from hbm.errors import HbmError
from hbm.fit.simulate import simulate_tests
from hbm.model import spyrou_model

sys.path.insert(0, str(Path(__file__).resolve().parent))
import independent3d as ind  # noqa: E402

MODES = ("uniaxial_f", "uniaxial_c", "planar_f_hold_c", "planar_c_hold_f", "planar_c_hold_n", "biaxial_fc",
         "biaxial_cn", "shear_fc", "shear_cf", "shear_cn")
# tension and compression, away from the fibres' kink at EOPT (the reference differentiates numerically)
STRAINS = (-0.15, 0.07, 0.25)


def _protocol(path: Path) -> Path:
    """Every mode, three points each; biaxial tests with an explicit strain_2 on one row; no measurements."""
    lines = ["strain,stress,test,mode,strain_2"]
    for k, mode in enumerate(MODES):
        for i, e in enumerate(STRAINS):
            s2 = "0.04" if mode.startswith("biaxial") and i == 1 else ""
            lines.append(f"{e},,{k},{mode},{s2}")
    path.write_text("\n".join(lines) + "\n")
    return path


@pytest.mark.parametrize("reading", ["cone", "gst"])
def test_cli_matches_independent_every_mode(tmp_path, capsys, reading):
    prm = dict(ind.random_box(7))
    prm["EOPT"] = 0.12
    theta = ",".join(f"{k}={v!r}" for k, v in prm.items())
    out = tmp_path / "sim.csv"
    assert main(["simulate", str(_protocol(tmp_path / "p.csv")), "--theta", theta, "--form", "energy",
                 "--collagen3d", reading, "--out", str(out)]) == 0
    assert f"collagen3d={reading}" in capsys.readouterr().out
    with out.open() as fh:
        meta = [ln for ln in fh if ln.startswith("#")]
    assert json.loads(next(m for m in meta if "simulated_theta" in m).split(": ", 1)[1]) == prm
    rows = list(csv.DictReader(ln for ln in out.open() if not ln.startswith("#")))
    checked = 0
    for r in rows:
        e = float(r["strain"])
        s2 = float(r["strain_2"]) if r["strain_2"] else None
        ref = ind.predict(r["mode"], e, prm, reading, s2)
        for k, v in ref.items():
            got = float(r[f"{k}_model"])
            assert abs(got - v) <= 1e-6 * abs(v) + 1e-13, (r["mode"], e, k, got, v)
            checked += 1
        defined = {f"{k}_model" for k in ref}
        assert all(r[c] == "" for c in r if c.endswith("_model") and c not in defined)
    assert checked == 3 * (3 + 3 + 3 * 2 + 2 * 2 + 3 * 1)  # every observable of every row


def test_refusals_before_computation(tmp_path):
    spec = load_specimen(_protocol(tmp_path / "p.csv"))
    with pytest.raises(HbmError, match="mode uniaxial_c needs the energy form"):
        simulate_tests(spec, ind.CALVO, model=spyrou_model())
    with pytest.raises(HbmError, match="missing GM"):
        simulate_tests(spec, {k: v for k, v in ind.CALVO.items() if k != "GM"}, model=spyrou_model(form="energy"))
    with pytest.raises(HbmError, match="outside the model's box: VOLF=2"):
        simulate_tests(spec, {**ind.CALVO, "VOLF": 2.0}, model=spyrou_model(form="energy"))
    # the thesis form along the fibres is today's model
    along = load_specimen(ROOT_SPECIMEN)
    m = spyrou_model()
    got = simulate_tests(along, ind.CALVO, model=m)["stress_model"]
    np.testing.assert_allclose(got, m.stress(along.loading, np.array([ind.CALVO[n] for n in m.parameter_names])),
                               rtol=5e-14, atol=1e-17)


ROOT_SPECIMEN = Path(__file__).resolve().parents[1] / "data" / "specimens" / "calvo2010_rat1.csv"
