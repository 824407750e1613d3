"""A testing machine's record in: force and displacement with the specimen's geometry (issue 36).

Truth: the hand conversion (strain = -position / height, nominal stress = -load / (π d²/4), Cauchy
= (1 + strain) × nominal) written out here with plain floats, on the measured raw record copied to
``tests/data`` (its header and ``tests/data/README.md`` give the provenance).
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest

from hbm import cli
from hbm.data import input_summary, load_specimen, save_specimen
from hbm.errors import DataError

RAW = Path(__file__).parent / "data" / "annemil2025_porcine_compression_raw_machine.csv"


def _rows(path: Path) -> tuple[list[str], np.ndarray]:
    lines = path.read_text().splitlines()
    meta = [ln for ln in lines if ln.startswith("#")]
    data = [ln for ln in lines if ln and not ln.startswith("#")][1:]
    return meta, np.array([[float(c) for c in ln.split(",")] for ln in data])


def test_raw_record_loads_to_the_hand_conversion_with_the_steps_recorded():
    ds = load_specimen(RAW)
    _, a = _rows(RAW)
    t, load, position = a.T
    height, area = 21.0, math.pi * 7.0 ** 2
    strain = [-p / height for p in position]
    nominal = [-f / area for f in load]
    cauchy = [(1 + e) * s for e, s in zip(strain, nominal)]
    assert ds.n_points == len(t) == 219
    np.testing.assert_allclose(ds.strain, strain, rtol=0, atol=1e-9)
    np.testing.assert_allclose(ds.stress, cauchy, rtol=0, atol=1e-9)
    np.testing.assert_array_equal(ds.time, t)
    assert not np.signbit(ds.strain[0])          # 0, not -0
    at = ds.attrs
    assert at["deformation_input"] == "displacement_mm" and at["stress_input"] == "force_N"
    assert float(at["cross_section_mm2"]) == pytest.approx(area, rel=1e-15)
    assert at["stress_measure_original"] == "nominal" and at["stress_measure"] == "cauchy"
    steps = json.loads(at["conversion_steps"])
    assert len(steps) == 3 and "Position (mm)" in steps[0] and "gauge_length_mm 21.0" in steps[0]
    assert "Load (N)" in steps[1] and "diameter_mm 14.0" in steps[1] and "negated" in steps[1]
    assert "(1 + strain)" in steps[2]
    summary = input_summary(ds)
    assert "displacement (mm) / gauge length 21.0 mm" in summary and "cross-section 153.94 mm2" in summary
    assert "compression magnitudes negated" in summary


def _machine(tmp_path, meta: str, head: str, rows: str, name: str = "m.csv") -> Path:
    p = tmp_path / name
    p.write_text(meta + head + "\n" + rows)
    return p


F = [0.0, 0.4, 1.1, 2.0, 3.2, 4.6]          # N
D = [0.0, 0.5, 1.0, 1.5, 2.0, 2.5]          # mm
ROWS = "".join(f"{0.5 * i},{f},{d}\n" for i, (f, d) in enumerate(zip(F, D)))


@pytest.mark.parametrize("meta, head, scale_f, scale_d, area, l0", [
    ("# area_mm2: 20\n# gauge_length_mm: 25\n", "Time (s),Force (N),Extension (mm)", 1.0, 1.0, 20.0, 25.0),
    ("# width_mm: 5\n# thickness_mm: 4\n# gauge_length_mm: 25\n", "time,force_mN,displacement_um", 1e-3, 1e-3,
     20.0, 25.0),
    ("# diameter_mm: 5\n# gauge_length_mm: 25\n# loading: tension\n", "Time [s],Load [kN],Position [µm]", 1e3, 1e-3,
     math.pi * 6.25, 25.0),
])
def test_force_and_displacement_units_and_geometry(tmp_path, meta, head, scale_f, scale_d, area, l0):
    rows = "".join(f"{0.5 * i},{f / scale_f!r},{d / scale_d!r}\n" for i, (f, d) in enumerate(zip(F, D)))
    ds = load_specimen(_machine(tmp_path, meta, head, rows))
    strain = [(d / scale_d) * scale_d / l0 for d in D]
    stress = [(1 + e) * (f / scale_f) * scale_f / area for e, f in zip(strain, F)]
    np.testing.assert_allclose(ds.strain, strain, rtol=1e-14)
    np.testing.assert_allclose(ds.stress, stress, rtol=1e-14)


@pytest.mark.parametrize("meta, head, fragments", [
    ("# gauge_length_mm: 21\n", "Time (s),Load (N),Position (mm)",
     ["line 2, column 2", "'Load (N)' is a force", "cross-sectional area", "# area_mm2:"]),
    ("# diameter_mm: 14\n", "Time (s),Load (N),Position (mm)",
     ["line 2, column 3", "'Position (mm)' is a displacement", "# gauge_length_mm:"]),
    ("# diameter_mm: 14\n# area_mm2: 150\n# gauge_length_mm: 21\n", "Time (s),Load (N),Position (mm)",
     ["lines 1, 2", "given 2 ways", "expected one of"]),
    ("# width_mm: 4\n# gauge_length_mm: 21\n", "Time (s),Load (N),Position (mm)",
     ["'# width_mm:' without '# thickness_mm:'"]),
    ("# diameter_mm: -3\n# gauge_length_mm: 21\n", "Time (s),Load (N),Position (mm)",
     ["line 1", "diameter_mm is '-3'", "positive number"]),
    ("# diameter_mm: 14\n# gauge_length_mm: 21\n# loading: shear\n", "Time (s),Load (N),Position (mm)",
     ["line 3", "loading is 'shear'", "tension or compression"]),
    ("# diameter_mm: 14\n# gauge_length_mm: 1\n", "Time (s),Load (N),Position (mm)",
     ["column 'Position (mm)'", "strain 2.5", "change of length"]),
    ("", "Time (s),Load,Position (mm)", ["column 2", "'Load' is a force (no unit)"]),
    ("", "Time (s),Load (lbf),Position (mm)", ["column 2", "unit 'lbf'", "N, mN or kN"]),
    ("", "Time (s),Stress (kPa),Position (in)", ["column 3", "unit 'in'", "mm or um"]),
])
def test_machine_records_refused_with_one_line(tmp_path, meta, head, fragments):
    with pytest.raises(DataError) as err:
        load_specimen(_machine(tmp_path, meta, head, ROWS))
    msg = str(err.value)
    assert "\n" not in msg and msg.startswith(str(tmp_path))
    for frag in fragments:
        assert frag in msg, (frag, msg)


def test_compression_magnitudes_must_be_magnitudes(tmp_path):
    signed = "".join(f"{0.5 * i},{-f},{-d}\n" for i, (f, d) in enumerate(zip(F, D)))
    meta = "# area_mm2: 20\n# gauge_length_mm: 25\n"
    with pytest.raises(DataError, match="reads the machine's columns as magnitudes"):
        load_specimen(_machine(tmp_path, meta + "# loading: compression\n", "time,force_N,displacement_mm", signed))
    ds = load_specimen(_machine(tmp_path, meta, "time,force_N,displacement_mm", signed, "signed.csv"))
    np.testing.assert_allclose(ds.strain, [-d / 25 for d in D], rtol=1e-14)


def test_converted_record_saves_and_loads_back_to_the_same_numbers(tmp_path):
    ds = load_specimen(RAW)
    back = load_specimen(save_specimen(ds, tmp_path / "saved.csv"))
    for v in ("strain", "stress", "time"):
        np.testing.assert_array_equal(getattr(back, v), getattr(ds, v))
    assert input_summary(back) == input_summary(ds)


def test_data_check_lists_the_row_and_prints_series_record_and_flags(capsys):
    assert cli.main(["data", "check", str(RAW)]) == 0
    out = capsys.readouterr().out
    assert "line 10: pre-test reading" in out and "0 specimen(s) OK, 1 with artefact rows" in out
    assert cli.main(["data", "check", str(RAW), "--json"]) == 0
    obj = json.loads(capsys.readouterr().out)
    sp = obj["specimens"][0]
    ds = load_specimen(RAW)
    assert sp["series"]["strain"] == ds.strain.tolist() and sp["series"]["stress"] == ds.stress.tolist()
    assert sp["series"]["time"] == ds.time.tolist() and sp["units"]["stress"] == "MPa (Cauchy)"
    assert sp["conversion"]["stress_input"] == "force_N" and len(sp["conversion"]["steps"]) == 3
    assert [(a["kind"], a["rows"], a["lines"]) for a in sp["artefacts"]] == [("pre-test reading", [0], [10])]
    assert obj["errors"] == []
