"""Units judged from the physics (issue 26): stress per unit strain in the toe and at the peak
against passive muscle (hbm.data.plausibility), in the loader, `hbm data check`, `hbm fit` and the
detective's data-problem rule alike.  Test files are the shipped rat curve rescaled."""

from __future__ import annotations

import glob
import warnings
import os
from pathlib import Path

import numpy as np
import pytest

import hbm.cli as cli
from hbm.data import load_specimen
from hbm.detective.inputs import as_data, unit_anomaly
from hbm.errors import DataError, HbmWarning
from hbm.data.plausibility import PLAUSIBLE_MODULUS, edges_suggest_units, secant_moduli

ROOT = Path(__file__).resolve().parents[1]
RAT = ROOT / "data" / "specimens" / "calvo2010_rat1.csv"


def rescaled(tmp_path: Path, name: str, peak: float, meta: str = "") -> Path:
    """calvo2010_rat1 with its stress column scaled to ``peak`` (the numbers as written)."""
    body = [ln for ln in RAT.read_text().splitlines() if ln and not ln.startswith("#")]
    rows = [ln.split(",") for ln in body[1:]]
    top = max(float(r[1]) for r in rows)
    text = f"# id: {name}\n{meta}{body[0]}\n" + "".join(
        f"{r[0]},{float(r[1]) * peak / top:.6g},{','.join(r[2:])}\n" for r in rows)
    path = tmp_path / f"{name}.csv"
    path.write_text(text)
    return path


def test_secant_moduli_by_hand():
    e = np.array([0.0, 0.1, 0.2, 0.3, 0.4])
    s = np.array([0.0, 0.01, 0.03, 0.07, 0.2])
    m = secant_moduli(e, s)
    assert m["peak"][0] == pytest.approx(0.2 / 0.4) and m["toe"][0] == pytest.approx(0.01 / 0.1)


def test_kpa_file_read_without_units_is_refused_with_the_fix(tmp_path, capsys):
    path = rescaled(tmp_path, "kpa4", 4.0)  # kPa numbers, no unit: read as MPa
    for argv in (["data", "check", path], ["fit", path, "--samples", "20", "--restarts", "0", "--no-plot",
                                           "--out", tmp_path / "k.nc"]):
        capsys.readouterr()
        assert cli.main([str(a) for a in argv]) == 2
        err = capsys.readouterr().err.splitlines()
        assert len(err) == 1 and err[0].startswith("hbm: error: "), err
        assert "stress 4 (no unit declared, read as MPa)" in err[0] and "add '# units_stress: kPa'" in err[0]
    assert not (tmp_path / "k.nc").exists()
    ds = load_specimen(rescaled(tmp_path, "kpa4d", 4.0, "# units_stress: kPa\n"))  # declared: fine, silent
    assert ds.stress.max() == pytest.approx(0.004)


def test_declared_mpa_above_the_range_loads_with_a_warning(tmp_path, capsys):
    path = rescaled(tmp_path, "stiff", 5.009, "# units_stress: MPa\n")
    with pytest.warns(HbmWarning, match=r"above the .* range of passive muscle.*loaded as declared: MPa"):
        ds = load_specimen(path)
    assert ds.stress.max() == pytest.approx(5.009)
    capsys.readouterr()
    assert cli.main(["data", "check", str(path)]) == 0
    out, err = capsys.readouterr()
    assert "1 specimen(s) OK" in out and err.startswith("hbm: warning: ") and len(err.splitlines()) == 1
    # the detective's data-problem rule is the same check
    assert "above the" in unit_anomaly(as_data(ds)) and "kPa" in unit_anomaly(as_data(ds))
    with pytest.raises(DataError):  # the same numbers without the declaration: refused
        load_specimen(rescaled(tmp_path, "stiff2", 5.009))


def test_shipped_and_measured_curves_load_without_warnings():
    files = sorted(glob.glob(str(ROOT / "data" / "specimens" / "*.csv")))
    files += sorted(glob.glob(str(ROOT / "data" / "measured" / "*.csv")))
    # the measured curves kept beside the repository for development ($HBM_REALDATA, default ../shared/realdata)
    realdata = Path(os.environ.get("HBM_REALDATA", ROOT.parent / "shared" / "realdata"))
    files += sorted(str(p) for p in realdata.glob("*.csv") if "raw_machine" not in p.name)
    assert len(files) >= 8
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        for f in files:
            ds = load_specimen(f, sl0=2.0 if "smith2011" in f else None)
            assert unit_anomaly(as_data(ds)) is None, f
            lo, hi = PLAUSIBLE_MODULUS
            moduli = secant_moduli(ds.strain, ds.stress)
            # the peak within the range; the toe never too stiff, but it may be slack (physics, not a
            # unit: porcine compression along the fibres has a toe secant of 1.4 kPa at 9 % strain)
            assert lo <= moduli["peak"][0] <= hi, f
            assert "toe" not in moduli or moduli["toe"][0] <= hi, f


def test_parameters_on_opposite_edges_suggest_a_unit_error():
    items = [{"parameter": p, "side": s} for p, s in
             (("VOLF", "upper"), ("P1", "lower"), ("T1", "lower"), ("GF", "upper"), ("GM", "lower"), ("T2", "upper"))]
    msg = edges_suggest_units(items, 8)
    assert msg is not None and "6 of 8 parameters" in msg and "units_stress" in msg
    assert edges_suggest_units(items[:4], 8) is not None
    assert edges_suggest_units([i for i in items if i["side"] == "lower"], 8) is None  # one side only
    assert edges_suggest_units(items[:3], 8) is None  # one upper, two lower: the toy fit's pattern
