"""Input adapters of the specimen loader (units, nominal stress, stretch, sarcomere length, test
labels), the plausibility check, the shipped measured curves and the hardening against bad files.

Expected values are computed here from the raw numbers with plain Python, independently of the
loader's numpy code.
"""

from __future__ import annotations

import hashlib
import json
import os
import threading
import warnings
from pathlib import Path

import numpy as np
import pytest

from hbm.cli import main
from hbm.data import input_summary, load_specimen, load_specimens, save_specimen, specimen_loading
from hbm.errors import DataError, HbmWarning

ROOT = Path(__file__).resolve().parents[1]
MEASURED = ROOT / "data" / "measured"
# the shipped curves are byte-for-byte copies of the raw files (as the paper reports them)
MEASURED_SHA256 = {
    "smith2011_gracilis_bundles.csv": "1f14972198e0e175b4e502068eda44f1f3a68c08f6ce593a00a79910c0c2a273",
    "smith2011_gracilis_fibres.csv": "1fcd0318b32078ae2619e92b09956a9df4c7a1949ae59d98e851b1dd333605e1",
}

E = [0.0, 0.05, 0.1, 0.15, 0.2, 0.3]  # strain used by the small files below
S = [0.0, 1.5, 4.0, 9.25, 20.0, 48.0]  # stress numbers as written in those files


def write(tmp_path: Path, text: str, name: str = "spec.csv") -> Path:
    p = tmp_path / name
    p.write_text(text)
    return p


def rows(*cols) -> str:
    return "".join(",".join(map(repr, r)) + "\n" for r in zip(*cols))


def refused(path: Path, fragments=(), **kwargs) -> str:
    """The DataError message of loading ``path``: one line, naming the file, with every fragment."""
    with pytest.raises(DataError) as info:
        load_specimen(path, **kwargs)
    msg = str(info.value)
    assert msg.startswith(str(path)) and "\n" not in msg, msg
    for frag in fragments:
        assert frag in msg, (frag, msg)
    return msg


def raw_table(path: Path) -> tuple[list[str], list[list[float]]]:
    """Header and float rows of a simple file, parsed with plain Python."""
    lines = [ln for ln in path.read_text().splitlines() if ln.strip() and not ln.startswith("#")]
    return lines[0].split(","), [[float(c) for c in ln.split(",")] for ln in lines[1:]]


# ------------------------------------------------------------------ shipped measured curves
@pytest.mark.parametrize("fname, n", [("smith2011_gracilis_bundles.csv", 21),
                                      ("smith2011_gracilis_fibres.csv", 16)])
def test_measured_curves_load_raw_and_match_hand_conversion(fname, n):
    path = MEASURED / fname
    assert hashlib.sha256(path.read_bytes()).hexdigest() == MEASURED_SHA256[fname]
    header, table = raw_table(path)
    assert header == ["sarcomere_length_um", "nominal_stress_kPa"] and len(table) == n
    ds = load_specimen(path, sl0=2.0)
    # hand conversion: lambda = SL / 2.0 um, Cauchy = lambda * nominal, kPa -> MPa
    lam = [sl / 2.0 for sl, _ in table]
    strain = [x - 1.0 for x in lam]
    stress = [x * p * 1e-3 for x, (_, p) in zip(lam, table)]
    assert ds.n_points == n
    np.testing.assert_allclose(ds.strain, strain, rtol=0, atol=1e-9)
    np.testing.assert_allclose(ds.stress, stress, rtol=0, atol=1e-9)
    a = ds.attrs
    assert (a["units_stress"], a["units_stress_original"]) == ("MPa", "kPa")
    assert (a["stress_measure"], a["stress_measure_original"]) == ("cauchy", "nominal")
    assert a["deformation_input"] == "sarcomere_length_um" and a["reference_sarcomere_length_um"] == "2.0"
    assert a["id"] == fname[:-4] and "Smith LR" in a["source"] and "MIT" in a["source"]
    assert input_summary(ds) == ("stress kPa->MPa, nominal->Cauchy; strain from sarcomere_length_um "
                                 "(SL0 2.0 um)")
    # the raw files name no reference: refused with the line that fixes it
    refused(path, ["line 7", "# reference_sarcomere_length_um:"])


def test_measured_folder_and_reference_in_file_agree(tmp_path):
    curves = load_specimens(MEASURED, sl0=2.0)
    assert list(curves) == ["smith2011_gracilis_bundles", "smith2011_gracilis_fibres"]
    # the same reference as a metadata line gives bit-identical arrays
    text = (MEASURED / "smith2011_gracilis_fibres.csv").read_text()
    f = write(tmp_path, "# reference_sarcomere_length_um: 2\n" + text)
    ds = load_specimen(f)
    for v in ("strain", "stress"):
        np.testing.assert_array_equal(getattr(ds, v), getattr(curves["smith2011_gracilis_fibres"], v))
    assert load_specimen(f, sl0=2.0).attrs["reference_sarcomere_length_um"] == "2.0"
    with pytest.raises(DataError, match=r"line 1: .*contradicts sl0=2\.1"):
        load_specimen(f, sl0=2.1)


def test_shipped_specimens_equal_plain_float_parse():
    """The stand-ins (strain, MPa, Cauchy) load bit-identically to float() of their cells."""
    for path in sorted((ROOT / "data" / "specimens").glob("*.csv")):
        header, table = raw_table(path)
        ds = load_specimen(path)
        for j, col in enumerate(header):
            np.testing.assert_array_equal(getattr(ds, col), [r[j] for r in table])
        assert input_summary(ds) == "" and "units_stress_original" not in ds.attrs


# ------------------------------------------------------------------ units, measures, deformations
@pytest.mark.parametrize("head, meta, factor", [
    ("strain,stress", "# units_stress: kPa\n", 1e-3),
    ("strain,stress_kPa", "", 1e-3),
    ("strain,Stress_KPA", "# units_stress: kPa\n", 1e-3),  # agreeing declarations are fine
    ("strain,stress", "# units_stress: Pa\n", 1e-6),
    ("strain,stress_Pa", "", 1e-6),
    ("strain,stress_MPa", "", 1.0),
    ("strain,stress", "# units_stress: MPa\n", 1.0),
])
def test_stress_units(tmp_path, head, meta, factor):
    scale = {1e-3: 1.0, 1e-6: 1e3, 1.0: 1e-3}[factor]  # keep the MPa value plausible
    written = [s * scale for s in S]
    ds = load_specimen(write(tmp_path, meta + head + "\n" + rows(E, written)))
    np.testing.assert_allclose(ds.stress, [w * factor for w in written], rtol=1e-15, atol=0)
    np.testing.assert_array_equal(ds.strain, E)
    unit = {1e-3: "kPa", 1e-6: "Pa", 1.0: "MPa"}[factor]
    assert ds.attrs["units_stress"] == "MPa"
    assert ds.attrs.get("units_stress_original") == (None if unit == "MPa" else unit)


@pytest.mark.parametrize("head, meta", [("strain,nominal_stress_kPa", ""),
                                        ("strain,stress", "# stress_measure: nominal\n# units_stress: kPa\n"),
                                        ("strain,nominal_stress", "# units_stress: kPa\n")])
def test_nominal_stress_becomes_cauchy(tmp_path, head, meta):
    ds = load_specimen(write(tmp_path, meta + head + "\n" + rows(E, S)))
    np.testing.assert_allclose(ds.stress, [(1 + e) * s / 1000 for e, s in zip(E, S)], rtol=1e-15)
    assert ds.attrs["stress_measure"] == "cauchy" and ds.attrs["stress_measure_original"] == "nominal"


def test_cauchy_declared_is_unchanged(tmp_path):
    ds = load_specimen(write(tmp_path, "# stress_measure: Cauchy\nstrain,cauchy_stress_kpa\n" + rows(E, S)))
    np.testing.assert_allclose(ds.stress, [s / 1000 for s in S], rtol=1e-15)
    assert ds.attrs["stress_measure"] == "cauchy" and "stress_measure_original" not in ds.attrs


def test_stretch_and_sarcomere_length(tmp_path):
    lam = [1 + e for e in E]
    ds = load_specimen(write(tmp_path, "stretch,nominal_stress_kPa\n" + rows(lam, S)))
    np.testing.assert_allclose(ds.strain, E, rtol=0, atol=1e-15)
    np.testing.assert_allclose(ds.stress, [x * s / 1000 for x, s in zip(lam, S)], rtol=1e-15)
    assert ds.attrs["deformation_input"] == "stretch" and "reference_sarcomere_length_um" not in ds.attrs

    sl = [2.2 * x for x in lam]
    with_ref = write(tmp_path, "# reference_sarcomere_length_um: 2.2\nsarcomere_length_um,stress\n"
                     + rows(sl, [s / 100 for s in S]), "sl.csv")
    ds = load_specimen(with_ref)
    np.testing.assert_allclose(ds.strain, [x / 2.2 - 1 for x in sl], rtol=0, atol=1e-15)
    np.testing.assert_array_equal(ds.stress, [s / 100 for s in S])  # Cauchy MPa: untouched
    assert ds.attrs["reference_sarcomere_length_um"] == "2.2"
    assert ds.attrs["deformation_input"] == "sarcomere_length_um"

    without = write(tmp_path, "sarcomere_length_um,stress\n" + rows(sl, [s / 100 for s in S]), "sl0.csv")
    refused(without, ["line 1", "reference_sarcomere_length_um", "sl0"])
    ds2 = load_specimen(without, sl0=2.2)
    np.testing.assert_array_equal(ds2.strain, ds.strain)
    # sl0 only matters for a sarcomere-length column
    plain = write(tmp_path, "strain,stress\n" + rows(E, [s / 100 for s in S]), "plain.csv")
    assert "reference_sarcomere_length_um" not in load_specimen(plain, sl0=2.2).attrs


def test_sarcomere_length_in_nanometres_is_out_of_range(tmp_path):
    f = write(tmp_path, "sarcomere_length_um,stress\n" + rows([2000 + 100 * i for i in range(6)],
                                                               [s / 100 for s in S]))
    with pytest.raises(DataError, match=r"line 2, column 'sarcomere_length_um': expected a sarcomere length "
                                        r"in micrometres within \[1, 6\]"):
        load_specimen(f, sl0=2.0)


# ------------------------------------------------------------------ test labels
def test_test_labels_in_order_of_appearance(tmp_path):
    text = ("strain,stress,time,test\n0,0,0,load\n0.1,0.01,1,load\n0.2,0.03,2,load\n0.1,0.01,3,unload\n"
            "0.05,0.002,4,unload\n0.15,0.02,5,reload\n0.25,0.05,6,reload\n"
            "0,0,0,ramp_0.01\n0.1,0.02,10,ramp_0.01\n0.1,0.015,30,hold 600 s\n")
    ds = load_specimen(write(tmp_path, text))
    np.testing.assert_array_equal(ds.test, [0, 0, 0, 1, 1, 2, 2, 3, 3, 4])
    assert ds.test.dtype == np.int64
    assert json.loads(ds.attrs["test_labels"]) == ["load", "unload", "reload", "ramp_0.01", "hold 600 s"]
    # load/unload/reload continue in time: one history; ramp_0.01 restarts at 0 and the hold continues it
    np.testing.assert_array_equal(specimen_loading(ds).history, [0] * 7 + [1] * 3)
    assert input_summary(ds) == "tests labelled load, unload, reload, ramp_0.01, hold 600 s"


@pytest.mark.parametrize("cells, fragments", [
    (["load", "load", "unload", "load", "load"], ["line 5", "test 'load' reappears", "contiguous"]),
    (["1", "1", "load", "load", "load"], ["line 4", "expected an integer test id like the rows above"]),
    (["load", "load", "2", "2", "2"], ["line 4", "expected a test label", "the number '2'"]),
    (["load", "load", "@x", "@x", "@x"], ["line 4", "expected an integer test id or a test label"]),
    (["load", "load", "", "x", "x"], ["line 4", "test label", "got ''"]),
    (["99999999999999999999"] * 5, ["line 2", "out of range"]),
    (["1e30"] * 5, ["line 2", "out of range"]),
    (["-9223372036854775809"] * 5, ["line 2", "out of range"]),
])
def test_bad_test_cells(tmp_path, cells, fragments):
    text = "strain,stress,test\n" + "".join(f"{0.1 * i},{0.01 * i},{c}\n" for i, c in enumerate(cells))
    p = write(tmp_path, text)
    refused(p, fragments)


def test_largest_int64_test_id_loads(tmp_path):
    text = "strain,stress,test\n" + "".join(f"{0.1 * i},{0.01 * i},9223372036854775807\n" for i in range(5))
    assert load_specimen(write(tmp_path, text)).test[0] == 2 ** 63 - 1


# ------------------------------------------------------------------ plausibility
# stress per unit strain (secant, Cauchy/strain) of passive muscle: 0.002-3 MPa (hbm.data.plausibility)
@pytest.mark.parametrize("head, meta, values, fragments", [
    ("strain,stress", "", [s for s in S], ["line 7", "stress 48 (no unit declared, read as MPa)",
                                           "at the peak 160 MPa", "add '# units_stress: kPa'"]),
    ("strain,stress", "", [s * 1e3 for s in S], ["line 7", "48000", "add '# units_stress: Pa'"]),
    ("strain,nominal_stress", "", [0.1, 0.2, 0.5, 1, 2, 4.5], ["4.5", "nominal", "Cauchy stress of 5.85 MPa"]),
])
def test_implausible_undeclared_stress_is_refused(tmp_path, head, meta, values, fragments):
    refused(write(tmp_path, meta + head + "\n" + rows(E, values)), ["passive muscle", *fragments])


@pytest.mark.parametrize("head, meta, values, fragments", [
    ("strain,stress", "# units_stress: kPa\n", [s * 1e3 for s in S],
     ["line 8", "48000 kPa", "48 MPa", "write '# units_stress: Pa'", "loaded as declared: kPa"]),
    ("strain,stress_kPa", "", [s * 1e3 for s in S], ["rename the column to 'stress_Pa'"]),
    ("strain,stress", "# units_stress: Pa\n", [s * 1e6 for s in S], ["check the values and their unit"]),
    ("strain,stress", "# units_stress: kPa\n", [s * 1e-3 for s in S], ["below the", "'# units_stress: MPa'"]),
])
def test_implausible_declared_stress_loads_with_a_warning(tmp_path, head, meta, values, fragments):
    """A declared unit is the user's decision: outside the plausible range a warning, never a refusal."""
    with pytest.warns(HbmWarning) as seen:
        ds = load_specimen(write(tmp_path, meta + head + "\n" + rows(E, values)))
    text = " ".join(str(w.message) for w in seen)
    assert all(f in text for f in ["passive muscle", *fragments]), text
    factor = {"kPa": 1e-3, "Pa": 1e-6}[ds.attrs["units_stress_original"]]
    assert ds.stress[-1] == pytest.approx(values[-1] * factor)


def test_stiffness_just_below_the_limit_loads(tmp_path):
    # peak 0.897 MPa at strain 0.3 (2.99 MPa per unit strain); toe 0.2/0.1 = 2 MPa
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        ds = load_specimen(write(tmp_path, "strain,stress\n" + rows(E, [0, 0.1, 0.2, 0.3, 0.5, 0.897])))
    assert ds.stress.max() == 0.897
    refused(write(tmp_path, "strain,stress\n" + rows(E, [0, 0.1, 0.2, 0.3, 0.5, 0.903])), ["3.01 MPa"])


# ------------------------------------------------------------------ bad metadata values
@pytest.mark.parametrize("meta, head, fragments", [
    ("# units_stress: kg", "strain,stress", ["line 1", "units_stress is 'kg'", "MPa, kPa, Pa"]),
    ("# units_stress:", "strain,stress", ["line 1", "units_stress is ''"]),
    ("# units_stress: N/mm2", "strain,stress", ["line 1", "expected one of MPa, kPa, Pa"]),
    ("# stress_measure: engineering", "strain,stress", ["line 1", "stress_measure is 'engineering'",
                                                         "cauchy, nominal"]),
    ("# stress_measure: true", "strain,stress", ["line 1", "stress_measure"]),
    ("# reference_sarcomere_length_um: -2", "sarcomere_length_um,stress", ["line 1", "positive"]),
    ("# reference_sarcomere_length_um: 0", "sarcomere_length_um,stress", ["line 1", "positive"]),
    ("# reference_sarcomere_length_um: 2.0 um", "sarcomere_length_um,stress", ["line 1", "'2.0 um'"]),
    ("# reference_sarcomere_length_um: nan", "strain,stress", ["line 1", "micrometres"]),
    ("# reference_sarcomere_length_um: inf", "strain,stress", ["line 1", "positive"]),
    ("# units_stress: MPa", "strain,stress_kPa", ["line 1", "contradicts column 'stress_kPa' (kPa)"]),
    ("# stress_measure: cauchy", "strain,nominal_stress", ["line 1", "contradicts column 'nominal_stress'"]),
    ("# units_stress: kPa\n# units_stress_original: Pa", "strain,stress",
     ["line 2", "units_stress_original is 'Pa'", "'kPa'"]),
    ("# id: x", "strain,stretch,stress", ["line 2", "column 2", "second deformation column 'stretch'"]),
    ("# id: x", "strain,stress,stress_kPa", ["line 2", "column 3", "second stress column"]),
    ("# id: x", "sarcomere_length,stress", ["line 2", "'sarcomere_length'", "needs its unit, micrometres"]),
    ("# id: x", "stretch,time", ["line 2", "no 'stress' column"]),
])
def test_bad_metadata_values(tmp_path, meta, head, fragments):
    first = {"strain": E, "stretch": [1 + e for e in E], "sarcomere_length_um": [2 + 2 * e for e in E],
             "sarcomere_length": E}[head.split(",")[0]]
    body = rows(*([first] + [[s / 100 for s in S]] * (len(head.split(",")) - 1)))
    p = write(tmp_path, meta + "\n" + head + "\n" + body)
    refused(p, fragments)


@pytest.mark.parametrize("sl0", [-1.0, 0.0, float("nan"), float("inf"), "abc", True, [2.0]])
def test_bad_sl0_argument(tmp_path, sl0):
    p = write(tmp_path, "sarcomere_length_um,stress\n" + rows([2 + 2 * e for e in E], [s / 100 for s in S]))
    with pytest.raises(DataError, match="sl0: expected a positive reference sarcomere length"):
        load_specimen(p, sl0=sl0)
    with pytest.raises(DataError, match="sl0: expected"):
        load_specimens(tmp_path, sl0=sl0)


# ------------------------------------------------------------------ records round trip
def test_converted_dataset_saves_and_loads_back(tmp_path):
    src = write(tmp_path, "# id: rt\n# reference_sarcomere_length_um: 2.5\n"
                "sarcomere_length_um,nominal_stress_kPa,test\n"
                + "".join(f"{2.5 + 0.1 * i!r},{3.0 * i * i!r},{'load' if i < 4 else 'unload'}\n" for i in range(7)))
    ds = load_specimen(src)
    saved = save_specimen(ds, tmp_path / "out" / "rt.csv")
    text = saved.read_text()
    assert "# units_stress_original: kPa" in text and "\nstrain,stress,test\n" in text
    back = load_specimen(saved)
    for v in ("strain", "stress", "test"):
        np.testing.assert_array_equal(getattr(back, v), getattr(ds, v))
    assert {k: v for k, v in back.attrs.items() if k != "source_file"} == \
        {k: v for k, v in ds.attrs.items() if k != "source_file"}
    assert save_specimen(back, tmp_path / "rt2.csv").read_bytes() == saved.read_bytes()


# ------------------------------------------------------------------ hardening (issue 14)
@pytest.mark.parametrize("body, fragments", [
    ("0,01,0,5\n0,02,0,6\n0,03,0,7\n0,04,0,8\n0,05,0,9\n", ["line 2", "'stress'", "'01'", "decimal comma"]),
    ("0,5,0,3\n1,5,1,3\n0,6,0,3\n1,6,1,3\n0,7,0,3\n", ["lines 2-6", "'strain'", "whole number", "0,01"]),
    ("0,01;0,5\n0,02;0,6\n0,03;0,7\n0,04;0,8\n0,05;0,9\n", ["line 2", "ragged", "numbers use '.'"]),
])
def test_decimal_comma_files_are_refused(tmp_path, body, fragments):
    refused(write(tmp_path, "strain,stress,time,test\n" + body), fragments)


def test_semicolon_and_tab_files_with_decimal_commas_mean_what_they_say(tmp_path):
    """A header without ',' fixes tab or ';' as the separator; cells then may use decimal commas."""
    expected_strain = [e for e in E]
    for sep, comma in ((";", True), ("\t", True), ("\t", False)):
        body = "".join(sep.join((repr(e) if not comma else repr(e).replace(".", ","),
                                 repr(x) if not comma else repr(x).replace(".", ","))) + "\n" for e, x in zip(E, S))
        ds = load_specimen(write(tmp_path, f"strain{sep}stress_kPa\n" + body))
        assert ds.strain.tolist() == expected_strain
        assert ds.stress.tolist() == [x / 1000 for x in S]
    # one row of a ';' file: read, then refused for its size (no longer as an unknown column)
    refused(write(tmp_path, "strain;stress\n0.1;0.2\n"), ["1 data rows", "at least 5"])
    # a comma header keeps ',' as the separator: decimal commas there stay an error
    refused(write(tmp_path, "strain,stress\n" + "".join(f"0,{k};0,{k}\n" for k in range(1, 7))), ["ragged"])


@pytest.mark.parametrize("head, strain_factor, stress_factor", [
    ("Strain (%),Nominal stress (kPa),Time (s)", 0.01, "nominal_kpa"),
    ("Strain [-],Cauchy stress [MPa],time [sec]", 1.0, 1.0),
    ("Engineering strain,True stress (N/mm2),Time (s)", 1.0, 1.0),
    ("Stretch ratio,Stress (Pa),Time (s)", "stretch", 1e-6),
    ("Sarcomere length (um),Engineering stress [mN/mm2],Time (s)", "sl", "nominal_kpa"),
    ("strain_percent,Stress [kPa],Time (seconds)", 0.01, 1e-3),
])
def test_lab_headers_with_units_in_brackets(tmp_path, head, strain_factor, stress_factor):
    """Headers as labs write them map to the documented columns, and the numbers convert accordingly
    (expected values computed here from the raw numbers)."""
    raw_def = {0.01: [100 * e for e in E], 1.0: E, "stretch": [1 + e for e in E], "sl": [2.5 * (1 + e) for e in E]}[
        strain_factor]
    raw_stress = [x / 10 for x in S] if stress_factor in (1.0, 1e-3, "nominal_kpa") else [x * 1000 for x in S]
    body = rows(raw_def, raw_stress, [10.0 * k for k in range(len(E))])
    meta = "# reference_sarcomere_length_um: 2.5\n" if strain_factor == "sl" else ""
    ds = load_specimen(write(tmp_path, meta + head + "\n" + body))
    strain = {0.01: [v / 100 for v in raw_def], 1.0: raw_def, "stretch": [v - 1 for v in raw_def],
              "sl": [v / 2.5 - 1 for v in raw_def]}[strain_factor]
    np.testing.assert_allclose(ds.strain, strain, rtol=1e-14, atol=1e-15)
    if stress_factor == "nominal_kpa":  # Cauchy = (1 + strain) * nominal, kPa -> MPa
        stress = [(1 + e) * x / 1000 for e, x in zip(strain, raw_stress)]
    else:
        stress = [x * stress_factor for x in raw_stress]
    np.testing.assert_allclose(ds.stress, stress, rtol=1e-14, atol=1e-18)
    assert ds.time.tolist() == [10.0 * k for k in range(len(E))]


@pytest.mark.parametrize("head, fragments", [
    ("Strain (%),Force (N)", ["column 2", "'Force (N)' is a force", "cross-sectional area"]),
    ("strain,load", ["column 2", "is a force"]),
    ("Strain (mm),Stress (kPa)", ["column 1", "strain unit 'mm'", "'%'"]),
    ("Strain (%),Stress (g/mm2)", ["column 2", "stress unit 'g/mm2'", "kPa (mN/mm2)"]),
    ("Strain (%),Stress (kPa),Time (ms)", ["column 3", "time unit 'ms'", "seconds"]),
    ("Sarcomere length,Stress (kPa)", ["column 1", "micrometres"]),
    ("Stretch (mm),Stress (kPa)", ["column 1", "no unit"]),
])
def test_lab_headers_with_units_hbm_does_not_convert_are_refused(tmp_path, head, fragments):
    n = len(head.split(","))
    body = rows(*([[100 * e for e in E]] + [[x / 10 for x in S]] * (n - 1)))
    refused(write(tmp_path, head + "\n" + body), ["line 1"] + fragments)


@pytest.mark.parametrize("content, fragment", [
    (b"strain,stress\n0.1," + b"1" * 140_000 + b"\n" + b"0.2,0.1\n" * 5, "line 2: unreadable CSV row"),
    (b"strain,stress\n" + b"0.1,0.1\n" * 3 + b"\xff\xfe\x00junk\n", "not a UTF-8 text file"),
    (bytes(range(256)) * 4, "not a UTF-8 text file"),
    (b"strain,stress\n" + b"0.1,0.\x001\n" * 5, "expected a number"),
    (b"\x00\x00\x00\n", "line 1"),
    (b"strain,stress\n" + b"9" * 5000 + b",0.1\n" + b"0.1,0.1\n" * 5, "line 2, column 'strain'"),
])
def test_junk_ends_as_data_error(tmp_path, content, fragment):
    p = tmp_path / "junk.csv"
    p.write_bytes(content)
    assert len(refused(p, [fragment])) < 600


def test_fifo_is_refused_without_blocking(tmp_path):
    fifo = tmp_path / "pipe.csv"
    os.mkfifo(fifo)
    result: dict = {}

    def target():
        try:
            load_specimen(fifo)
        except Exception as exc:  # noqa: BLE001 - the type is asserted below
            result["exc"] = exc

    thread = threading.Thread(target=target, daemon=True)
    thread.start()
    thread.join(10.0)
    if thread.is_alive():  # release a blocked open() so that the thread can end
        os.close(os.open(fifo, os.O_WRONLY | os.O_NONBLOCK))
        pytest.fail("load_specimen blocked on a FIFO")
    assert isinstance(result.get("exc"), DataError) and "not a regular file" in str(result["exc"])
    # a folder holding a FIFO named *.csv is refused as well, not hung on
    thread = threading.Thread(target=lambda: result.update(folder=_catch(load_specimens, tmp_path)), daemon=True)
    thread.start()
    thread.join(10.0)
    assert not thread.is_alive() and isinstance(result["folder"], DataError)


def _catch(fn, *args):
    try:
        fn(*args)
    except Exception as exc:  # noqa: BLE001
        return exc
    return None


def test_symlink_to_a_regular_file_loads(tmp_path):
    target = write(tmp_path, "strain,stress\n" + rows(E, [s / 100 for s in S]), "real.csv")
    link = tmp_path / "link.csv"
    link.symlink_to(target)
    np.testing.assert_array_equal(load_specimen(link).strain, E)


def test_metadata_keys_with_spaces(tmp_path):
    ds = load_specimen(write(tmp_path, "# reference sarcomere length: about 2 um\n# units stress: kPa\n"
                                       "strain,stress\n" + rows(E, S)))
    assert ds.attrs["reference_sarcomere_length"] == "about 2 um"
    np.testing.assert_allclose(ds.stress, [s / 1000 for s in S], rtol=1e-15)


# ------------------------------------------------------------------ hbm data check
def test_data_check_prints_conversions(tmp_path, capsys):
    write(tmp_path, "# id: sl_kpa\n# reference_sarcomere_length_um: 2.0\n"
          "sarcomere_length_um,nominal_stress_kPa\n" + rows([2 + 2 * e for e in E], S), "a.csv")
    write(tmp_path, "# id: plain\nstrain,stress\n" + rows(E, [s / 100 for s in S]), "b.csv")
    assert main(["data", "check", str(tmp_path)]) == 0
    out = capsys.readouterr().out
    lines = out.splitlines()
    assert "input" in lines[0].split()
    row = next(ln for ln in lines if ln.startswith("sl_kpa "))
    assert "kPa,nominal,SL/2.0um" in row.split()
    # max Cauchy stress: (1 + 0.3) * 48 kPa = 0.0624 MPa
    assert "0.0624" in row.split()
    assert next(ln for ln in lines if ln.startswith("plain ")).split()[6] == "-"
    assert ("  sl_kpa: stress kPa->MPa, nominal->Cauchy; strain from sarcomere_length_um (SL0 2.0 um)"
            in lines)
    assert "2 specimen(s) OK" in out
