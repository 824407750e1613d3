"""Tests as data (issue 35, item 1): the per-test columns of a specimen CSV, their conversions and refusals."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from hbm.cli import main
from hbm.data import load_specimen, save_specimen
from hbm.errors import DataError
from hbm.io.identity import data_key

ROOT = Path(__file__).resolve().parents[1]

HEAD = "strain,stress_kPa,test,mode,stress_measure,strain_2,stress_2,strain_c,strain_f\n"
ROWS = [  # strain, stress (kPa), test, mode, measure, strain_2, stress_2 (kPa), strain_c, strain_f
    (0.02, 0.1, "along", "uniaxial", "", "", "", -0.0099, ""),
    (0.05, 0.4, "along", "uniaxial", "", "", "", -0.0243, ""),
    (0.10, 1.2, "along", "uniaxial", "", "", "", "", ""),
    (0.02, 0.5, "across", "uniaxial_c", "nominal", "", "", "", -0.004),
    (0.05, 2.0, "across", "uniaxial_c", "nominal", "", "", "", -0.012),
    (-0.10, -3.0, "across", "uniaxial_c", "nominal", "", "", "", ""),
    (0.10, 0.3, "sh", "shear_fs", "nominal", "", "", "", ""),
    (0.20, 0.7, "sh", "shear_fc", "nominal", "", "", "", ""),
    (0.10, 1.0, "bi", "biaxial_fc", "nominal", "", 2.0, "", ""),
    (0.20, 3.0, "bi", "biaxial_fc", "nominal", 0.05, 5.0, "", ""),
    (0.10, 1.0, "pl", "planar_c_hold_f", "nominal", "", 0.5, "", ""),
    (0.20, "", "pl", "planar_c_hold_f", "nominal", "", 0.9, "", ""),
]


def _write(path: Path, rows=ROWS, head=HEAD, meta="") -> Path:
    path.write_text(meta + head + "".join(",".join(map(str, r)) + "\n" for r in rows))
    return path


def test_modes_units_measures_and_empty_cells(tmp_path):
    s = load_specimen(_write(tmp_path / "m.csv"))
    assert [t.load_case for t in s.tests] == ["uniaxial_f", "uniaxial_c", "shear_fc", "biaxial_fc", "planar_c_hold_f"]
    assert [t.label for t in s.tests] == ["along", "across", "sh", "bi", "pl"]
    stress, e = s.observed["stress"].values, s.strain
    # Cauchy along the load = λ·P in stretch modes, P in simple shear (kPa -> MPa)
    expect = np.array([0.1, 0.4, 1.2, 0.5 * 1.02, 2.0 * 1.05, -3.0 * 0.9, 0.3, 0.7, 1.0 * 1.1, 3.0 * 1.2, 1.1,
                       np.nan]) / 1e3
    np.testing.assert_allclose(stress, expect, rtol=1e-15)
    assert np.isnan(stress[-1])  # an empty cell is "not measured"
    # stress_2: biaxial along strain_2 (equal to strain where empty), planar on the held faces (λ = 1)
    s2 = s.observed["stress_2"].values
    np.testing.assert_allclose(s2[8:], np.array([2.0 * 1.1, 5.0 * 1.05, 0.5, 0.9]) / 1e3, rtol=1e-15)
    assert np.isnan(s2[:8]).all()
    np.testing.assert_array_equal(s.strain_2[8:10], [0.1, 0.05])
    assert np.isnan(s.strain_2[:8]).all() and np.isnan(s.strain_2[10:]).all()
    assert s.observed["strain_c"].unit == "-" and np.isnan(s.observed["strain_c"].values[2:]).all()
    assert np.isclose(s.observed["strain_f"].values[3], -0.004)
    assert e[6] == 0.1  # the shear test's control is γ
    assert json.loads(s.attrs["test_load_cases"])[2] == "shear_fc"


def test_roundtrip_and_key(tmp_path):
    s = load_specimen(_write(tmp_path / "m.csv"))
    back = load_specimen(save_specimen(s, tmp_path / "out.csv"))
    assert back.tests == s.tests
    for k, ser in s.observed.items():
        np.testing.assert_array_equal(back.observed[k].values, ser.values)
    np.testing.assert_array_equal(back.strain_2, s.strain_2)
    assert data_key(back) == data_key(s)
    # the modes enter the key: the same numbers read as another mode are other data
    other = _write(tmp_path / "o.csv", [r[:3] + (("shear_cn",) if r[2] == "sh" else r[3:4]) + r[4:] for r in ROWS])
    assert data_key(load_specimen(other)) != data_key(s)
    ds = s.to_dataset()
    from hbm.data import as_specimen
    assert as_specimen(ds).tests == s.tests


def test_old_file_unchanged(tmp_path):
    """A file without the new columns takes today's path: same attributes, tests, key inputs."""
    f = ROOT / "data" / "specimens" / "calvo2010_rat1.csv"
    s = load_specimen(f)
    assert "test_load_cases" not in s.attrs and s.strain_2 is None and list(s.observed) == ["stress"]
    assert all(t.load_case == "uniaxial_f" for t in s.tests) and s.key_extras() == {}


def _set(rows, test, col, value, only=None):
    """Rows with column ``col`` of test ``test`` set to ``value`` (on its ``only``-th row, or on all)."""
    out, k = [], 0
    for r in rows:
        if r[2] == test:
            if only is None or k == only:
                r = r[:col] + (value,) + r[col + 1:]
            k += 1
        out.append(r)
    return out


@pytest.mark.parametrize("change, message", [
    (lambda r: _set(r, "along", 3, "tension_q"), "column 'mode': unknown mode 'tension_q'"),
    (lambda r: _set(r, "along", 3, "uniaxial_c", only=1), "mode changes within test 'along'"),
    (lambda r: _set(r, "along", 3, "", only=1), "mode changes within test 'along' ('uniaxial' on line 2, '' here)"),
    (lambda r: _set(r, "along", 3, "", only=0), "within test 'along' ('' on line 2, 'uniaxial' here)"),
    (lambda r: _set(r, "along", 6, 0.3, only=0), "mode uniaxial_f (test 'along') defines no observable stress_2"),
    (lambda r: _set(r, "sh", 5, 0.1, only=0), "mode shear_fc (test 'sh') defines no control strain_2"),
    (lambda r: _set(r, "across", 7, 0.01, only=0), "defines no observable strain_c"),
    (lambda r: _set(r, "across", 4, "true"), "expected one of cauchy, nominal"),
    (lambda r: _set(r, "across", 4, "", only=2), "stress_measure changes within test 'across'"),
    (lambda r: _set(r, "bi", 5, -1.0, only=1), "-1 is a stretch <= 0; expected strain_2 > -1"),
    (lambda r: _set(_set(r, "along", 1, "", only=2), "along", 7, "", only=2), None),
])
def test_refusals(tmp_path, change, message):
    f = _write(tmp_path / "bad.csv", change(list(ROWS)))
    if message is None:  # an all-empty row inside a measured test is fine: not measured
        assert np.isnan(load_specimen(f).observed["stress"].values[2])
        return
    with pytest.raises(DataError, match=message.replace("(", r"\(").replace(")", r"\)")):
        load_specimen(f)


def test_protocol_and_measure_conflict(tmp_path):
    rows = [r if r[2] != "sh" else (r[0], "", *r[2:]) for r in ROWS]  # a test without values: a protocol
    s = load_specimen(_write(tmp_path / "a.csv", rows))
    assert np.isnan(s.observed["stress"].values[6:8]).all() and s.tests[2].load_case == "shear_fc"
    with pytest.raises(DataError, match="test 'across' says nominal but the file declares cauchy"):
        load_specimen(_write(tmp_path / "b.csv", meta="# stress_measure: cauchy\n"))


def test_cli_check_shows_modes_and_errors(tmp_path, capsys):
    f = _write(tmp_path / "m.csv")
    assert main(["data", "check", str(f)]) == 0
    out = capsys.readouterr().out
    assert "tests by mode:" in out and "shear_fc: 1 test(s) (sh; measured stress)" in out
    assert main(["data", "check", str(f), "--json"]) == 0
    got = json.loads(capsys.readouterr().out)
    modes = got["specimens"][0]["tests_by_mode"]
    assert list(modes) == ["uniaxial_f", "uniaxial_c", "shear_fc", "biaxial_fc", "planar_c_hold_f"]
    assert modes["uniaxial_f"][0]["measured"] == {"stress": 3, "strain_c": 2}
    bad = _write(tmp_path / "bad.csv", _set(ROWS, "along", 3, "tension_q"))
    assert main(["data", "check", str(bad)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("hbm: error: ") and "unknown mode 'tension_q'" in err[0]
