"""Specimen CSV I/O, validation, protocols, synthetic specimens and the shipped stand-ins."""

from __future__ import annotations

import importlib.util
import json
from pathlib import Path

import numpy as np
import pytest
import xarray as xr
from scipy.stats import spearmanr

import hbm
from hbm.data import (
    cycle, hold, load_specimen, load_specimens, protocol, provenance, ramp, save_specimen, specimen_loading,
    synthetic_specimen)
from hbm.errors import DataError, HbmError

ROOT = Path(__file__).resolve().parents[1]
SPECIMENS = ROOT / "data" / "specimens"
GOOD = "# id: s1\n# source: measured in lab\nstrain,stress\n" + "".join(
    f"{0.1 * i},{0.01 * i * i}\n" for i in range(6))
THETA = dict(VOLF=0.9, EOPT=0.15, P1=0.06, T1=1.0, T2=14.0, THETA=60.0, GF=0.03, GM=0.02)


def write(tmp_path: Path, text: str, name: str = "spec.csv") -> Path:
    p = tmp_path / name
    p.write_text(text)
    return p


# ---------------------------------------------------------------------------------- loading
def test_load_good_file(tmp_path):
    ds = load_specimen(write(tmp_path, GOOD))
    assert ds.n_points == 6
    np.testing.assert_array_equal(ds.strain, [0.1 * i for i in range(6)])
    np.testing.assert_array_equal(ds.stress, [0.01 * i * i for i in range(6)])
    assert ds.id == "s1" and ds.attrs["id"] == "s1" and ds.attrs["source"] == "measured in lab"
    assert ds.source_file.endswith("spec.csv")
    assert ds.time is None and ds.test is None
    assert provenance(ds) == "measured"


def test_column_order_case_and_id_from_stem(tmp_path):
    text = "Test,stress,TIME,strain\n" + "".join(f"1,{0.01 * i},{2.0 * i},{0.05 * i}\n" for i in range(5))
    ds = load_specimen(write(tmp_path, text, "my_rat.csv"))
    assert ds.attrs["id"] == "my_rat"
    np.testing.assert_array_equal(ds.time, 2.0 * np.arange(5))
    assert ds.test.dtype.kind == "i"
    np.testing.assert_allclose(ds.strain, 0.05 * np.arange(5))
    assert provenance(ds) == "unknown"


ROWS5 = "".join(f"{0.1 * i},{0.01 * i}\n" for i in range(5))


@pytest.mark.parametrize("text, fragments", [
    ("", ["empty file"]),
    ("   \n\n", ["empty file"]),
    ("# id: a\n", ["no header"]),
    ("0,0\n" + ROWS5, ["line 1", "expected a header", "numeric row"]),
    ("strain,force\n" + ROWS5, ["line 1", "'force' is a force", "cross-sectional area"]),
    ("stress\n" + "".join(f"{i}\n" for i in range(5)), ["line 1", "no 'strain' column"]),
    ("strain,time\n" + ROWS5, ["line 1", "no 'stress' column"]),
    ("strain,stress,strain\n" + "".join(f"{i/10},{i},{i/10}\n" for i in range(5)),
     ["line 1", "column 3", "duplicate column name 'strain'"]),
    ("strain,stress\n0,0\n0.1,0.1\nstrain,stress\n0.2,0.2\n0.3,0.3\n0.4,0.4\n",
     ["line 4", "duplicate header"]),
    ("strain,stress\n0,0\n0.1,abc\n0.2,0.2\n0.3,0.3\n0.4,0.4\n", ["line 3", "'stress'", "expected a number", "'abc'"]),
    ("strain,stress\n0,0\n0.1,\n0.2,0.2\n0.3,0.3\n0.4,0.4\n", ["line 3", "'stress'", "expected a number"]),
    ("strain,stress\n0,0\n0.1,0.1\n0.2,nan\n0.3,0.3\n0.4,0.4\n", ["line 4", "'stress'", "finite"]),
    ("strain,stress\n0,0\n0.1,0.1\ninf,0.2\n0.3,0.3\n0.4,0.4\n", ["line 4", "'strain'", "finite"]),
    ("strain,stress\n0,0\n10,0.1\n20,0.2\n30,0.3\n40,0.4\n", ["line 3", "'strain'", "[-0.5, 2.0]", "percent"]),
    ("strain,stress\n-0.6,0\n0.1,0.1\n0.2,0.2\n0.3,0.3\n0.4,0.4\n", ["line 2", "'strain'"]),
    ("strain,stress,time\n0,0,0\n0.1,0.1,1\n0.2,0.2,0.5\n0.3,0.3,3\n0.4,0.4,4\n",
     ["line 4", "'time'", "decreasing time"]),
    ("strain,stress,time,test\n0,0,0,1\n0.1,0.1,1,1\n0.2,0.2,2,1\n0.1,0.1,0.5,2\n0.2,0.2,3,2\n",
     ["line 5", "'time'", "restart at exactly 0"]),
    ("strain,stress,time,test\n0,0,0,1\n0.1,0.1,1,1\n0.2,0.2,0,1\n0.1,0.1,1,2\n0.2,0.2,3,2\n",
     ["line 4", "'time'", "decreasing time"]),
    ("strain,stress,test\n0,0,1\n0.1,0.1,2\n0.2,0.2,1\n0.3,0.3,1\n0.4,0.4,1\n",
     ["line 4", "'test'", "contiguous"]),
    ("strain,stress,test\n0,0,1\n0.1,0.1,1.5\n0.2,0.2,1\n0.3,0.3,1\n0.4,0.4,1\n",
     ["line 3", "'test'", "integer"]),
    ("strain,stress\n0,0\n0.1,0.1\n0.2,0.2\n0.3,0.3\n", ["4 data rows", "at least 5"]),
    ("strain,stress\n", ["0 data rows", "at least 5"]),
    ("# this is a note\nstrain,stress\n" + ROWS5, ["line 1", "unknown metadata format", "'# key: value'"]),
    ("#id value\nstrain,stress\n" + ROWS5, ["line 1", "unknown metadata format"]),
    ("# id: a\n# id: b\nstrain,stress\n" + ROWS5, ["line 2", "repeated"]),
    ("strain,stress\n0,0\n# note: late\n" + ROWS5, ["line 3", "after the header"]),
    ("strain,stress\n0,0\n0.1,0.1,7\n0.2,0.2\n0.3,0.3\n0.4,0.4\n", ["line 3", "ragged", "3 cells", "expected 2"]),
    ("strain,stress\n0,0\n0.1\n0.2,0.2\n0.3,0.3\n0.4,0.4\n", ["line 3", "ragged"]),
    ("strain,stress\n0,0\n0.1,-0.01\n0.2,-0.04\n0.3,-0.09\n0.4,-0.16\n",
     ["line 6", "'stress'", "opposite sign", "flip the sign"]),
    ("strain,stress\n0,0\n-0.1,0.01\n-0.2,0.04\n-0.3,0.09\n-0.4,0.16\n",
     ["line 6", "opposite sign", "compression (strain < 0)"]),
    ("strain_percent,stress\n0,0\n10,0.1\n20,0.2\n300,0.3\n40,0.4\n",
     ["line 5", "'strain_percent'", "percent within [-50, 200]", "300"]),
])
def test_validation_errors(tmp_path, text, fragments):
    p = write(tmp_path, text)
    with pytest.raises(DataError) as info:
        load_specimen(p)
    msg = str(info.value)
    assert "\n" not in msg
    assert msg.startswith(str(p))
    for frag in fragments:
        assert frag in msg, (frag, msg)


def test_strain_percent_and_noise_signs(tmp_path):
    """Strain in percent (whole numbers allowed) is ε = value/100, recorded; a flipped small
    stress near zero strain (noise) is kept, only a flipped peak is refused."""
    p = write(tmp_path, "strain_percent,stress\n0,-0.0004\n5,0.002\n10,0.006\n15,0.013\n20,0.021\n30,0.05\n")
    ds = load_specimen(p)
    np.testing.assert_allclose(ds.strain, [0, 0.05, 0.1, 0.15, 0.2, 0.3])
    assert ds.attrs["deformation_input"] == "strain_percent"
    assert ds.stress[0] == -0.0004


def test_missing_file_and_directory(tmp_path):
    with pytest.raises(DataError, match="not found"):
        load_specimen(tmp_path / "nope.csv")
    with pytest.raises(DataError, match="directory"):
        load_specimen(tmp_path)


def test_time_rules_continuation_and_restart(tmp_path):
    # test 2 continues test 1 (same history); test 3 restarts at 0 (new history)
    text = ("strain,stress,time,test\n0,0,0,1\n0.1,0.1,1,1\n0.2,0.2,2,1\n0.2,0.15,2,2\n0.2,0.14,5,2\n"
            "0,0,0,3\n0.1,0.1,0.5,3\n")
    ds = load_specimen(write(tmp_path, text))
    loading = specimen_loading(ds)
    np.testing.assert_array_equal(loading.history, [0, 0, 0, 0, 0, 1, 1])
    np.testing.assert_array_equal(loading.test, [1, 1, 1, 2, 2, 3, 3])


def test_load_specimens_sorted_and_errors(tmp_path):
    write(tmp_path, GOOD.replace("# id: s1", "# id: zeta"), "a.csv")
    write(tmp_path, GOOD.replace("# id: s1", "# id: alpha"), "b.csv")
    out = load_specimens(tmp_path)
    assert list(out) == ["alpha", "zeta"]
    write(tmp_path, GOOD.replace("# id: s1", "# id: alpha"), "c.csv")
    with pytest.raises(DataError, match="duplicate specimen id 'alpha'"):
        load_specimens(tmp_path)
    empty = tmp_path / "empty"
    empty.mkdir()
    with pytest.raises(DataError, match="no \\*.csv"):
        load_specimens(empty)
    with pytest.raises(DataError, match="not a directory"):
        load_specimens(tmp_path / "missing")


# ---------------------------------------------------------------------------------- round trip
def test_round_trip_exact(tmp_path):
    rng = np.random.default_rng(3)
    n = 25
    ds = xr.Dataset({"strain": ("point", np.sort(rng.uniform(0, 0.5, n))),
                     "stress": ("point", rng.standard_normal(n) * 1e-3 + 1 / 3),
                     "time": ("point", np.cumsum(rng.uniform(0.1, 1, n)) * np.pi),
                     "test": ("point", np.repeat([4, 7], [10, 15]))},
                    attrs={"id": "rt", "note": "a: b, c", "seed": 12})
    p = save_specimen(ds, tmp_path / "sub" / "rt.csv")
    back = load_specimen(p)
    for v in ("strain", "stress", "time", "test"):
        np.testing.assert_array_equal(getattr(back, v), getattr(ds, v))  # bit-exact
    assert back.test.dtype.kind == "i"
    assert back.attrs["note"] == "a: b, c" and back.attrs["seed"] == "12" and back.attrs["id"] == "rt"
    # a second save of the loaded set reproduces the file byte for byte
    p2 = save_specimen(back, tmp_path / "rt2.csv")
    assert p2.read_bytes() == p.read_bytes()
    assert not [f for f in (tmp_path / "sub").iterdir() if f.name != "rt.csv"]  # no temp files left


def test_save_rejects_multiline_attr(tmp_path):
    ds = xr.Dataset({"strain": ("point", np.arange(5.0) / 10), "stress": ("point", np.arange(5.0))},
                    attrs={"note": "two\nlines"})
    with pytest.raises(HbmError, match="one line"):
        save_specimen(ds, tmp_path / "x.csv")
    assert not (tmp_path / "x.csv").exists()


# ---------------------------------------------------------------------------------- protocols
def test_protocol_ramps_holds_cycles():
    ds = protocol(ramp(0.4, 1e-3, 5), [ramp(0.3, 1e-2, 4), hold(60.0, 3)],
                  cycle(0.4, 0.01, 3, eps_min=0.1, reload_to=0.5))
    strain, time, test = ds.strain, ds.time, ds.test
    # ramp from rest at 1e-3 /s: 0, 0.1, ... 0.4 at 0, 100, ... 400 s
    np.testing.assert_allclose(strain[:5], [0, 0.1, 0.2, 0.3, 0.4])
    np.testing.assert_allclose(time[:5], [0, 100, 200, 300, 400])
    # second history: ramp 0->0.3 at 1e-2 (30 s), then a hold continuing in time
    np.testing.assert_allclose(strain[5:12], [0, 0.1, 0.2, 0.3, 0.3, 0.3, 0.3])
    np.testing.assert_allclose(time[5:12], [0, 10, 20, 30, 50, 70, 90])
    # cycle: load 0->0.4, unload to 0.1, reload to 0.5, time continuous at 0.01 /s
    np.testing.assert_allclose(strain[12:], [0, 0.2, 0.4, 0.3, 0.2, 0.1, 0.23333333, 0.36666667, 0.5])
    np.testing.assert_allclose(np.diff(time[12:]), np.abs(np.diff(strain[12:])) / 0.01)
    np.testing.assert_array_equal(test, [1] * 5 + [2] * 4 + [3] * 3 + [4] * 3 + [5] * 3 + [6] * 3)
    loading = specimen_loading(ds)
    np.testing.assert_array_equal(np.unique(loading.history[test == 6]), [2])
    np.testing.assert_array_equal(loading.history, [0] * 5 + [1] * 7 + [2] * 9)


def test_protocol_saves_and_loads(tmp_path):
    ds = protocol(ramp(0.3, 1e-2, 6), [ramp(0.3, 1e-2, 6), hold(100.0, 5, spacing="log")])
    ds = ds.with_series("stress", ds.strain * 0.5)
    back = load_specimen(save_specimen(ds, tmp_path / "p.csv"))  # passes the time rules
    np.testing.assert_array_equal(back.time, ds.time)
    t_hold = ds.time[ds.test == 3]
    assert np.all(np.diff(t_hold) > 0) and t_hold[-1] == pytest.approx(130.0)
    assert t_hold[0] - 30.0 < 1.0  # geometric spacing starts close to the hold onset


def test_protocol_bad_input():
    with pytest.raises(HbmError):
        ramp(0.3, 0.0, 5)
    with pytest.raises(HbmError):
        hold(-1.0, 5)
    with pytest.raises(HbmError):
        protocol([ramp(0.3, 1e-2, 5), hold(10.0, 3, at=0.2)])
    with pytest.raises(HbmError):
        protocol()


# ---------------------------------------------------------------------------------- synthetic
def test_synthetic_iid_noise_and_attrs():
    model = hbm.spyrou_model()
    strain = np.linspace(0, 0.42, 4000)
    ds = synthetic_specimen(model, THETA, strain, 0.002, 7)
    clean = model.stress(strain, np.array([THETA[k] for k in model.parameter_names]))
    r = ds.stress - clean
    assert abs(r.std() - 0.002) < 0.002 * 5 / np.sqrt(2 * 4000)
    assert abs(np.corrcoef(r[:-1], r[1:])[0, 1]) < 4 / np.sqrt(4000)
    assert ds.attrs["provenance"] == "synthetic" and ds.attrs["seed"] == "7" and ds.attrs["noise"] == "iid"
    assert json.loads(ds.attrs["parameters"]) == pytest.approx(THETA)
    again = synthetic_specimen(model, THETA, strain, 0.002, 7)
    np.testing.assert_array_equal(again.stress, ds.stress)
    other = synthetic_specimen(model, THETA, strain, 0.002, np.random.SeedSequence(7).spawn(2)[1])
    assert not np.array_equal(other.stress, ds.stress)
    assert json.loads(other.attrs["seed"]) == {"entropy": 7, "spawn_key": [1]}


def test_synthetic_relative_noise():
    model = hbm.spyrou_model()
    strain = np.linspace(0, 0.42, 50)
    ds = synthetic_specimen(model, THETA, strain, 0.03, 1, relative=True)
    smax = model.stress(strain, np.array([THETA[k] for k in model.parameter_names])).max()
    assert float(ds.attrs["noise_sd"]) == pytest.approx(0.03 * smax, rel=1e-12)


def test_synthetic_ar1_marginal_sd_correlation_and_restart():
    model = hbm.spyrou_model()
    prot = protocol(*[ramp(0.4, 1e-3, 2000) for _ in range(3)])
    clean = model.stress(specimen_loading(prot), np.array([THETA[k] for k in model.parameter_names]))
    ds = synthetic_specimen(model, THETA, prot, 0.004, 11, noise="ar1", rho=0.8)
    r = (ds.stress - clean).reshape(3, 2000)
    assert r.std() == pytest.approx(0.004, rel=0.1)
    lag1 = np.mean([np.corrcoef(x[:-1], x[1:])[0, 1] for x in r])
    assert lag1 == pytest.approx(0.8, abs=0.04)
    # histories are independent: correlation across the boundary vanishes
    assert ds.time is not None and ds.test is not None
    # the first point of each history has the marginal sd (stationary start), checked over seeds
    firsts = np.array([synthetic_specimen(model, THETA, prot, 0.004, s, noise="ar1", rho=0.8).stress[[0, 2000, 4000]]
                       for s in range(300)]) - clean[[0, 2000, 4000]]
    assert firsts.std() == pytest.approx(0.004, rel=0.1)
    assert abs(np.corrcoef(firsts[:, 0], firsts[:, 1])[0, 1]) < 0.2


def test_synthetic_errors():
    model = hbm.spyrou_model()
    with pytest.raises(HbmError, match="unknown parameters"):
        synthetic_specimen(model, dict(THETA, FOO=1.0), np.linspace(0, 0.4, 10), 0.001, 1)
    with pytest.raises(HbmError, match="no value"):
        synthetic_specimen(model, {"VOLF": 0.9}, np.linspace(0, 0.4, 10), 0.001, 1)
    with pytest.raises(HbmError, match="noise"):
        synthetic_specimen(model, THETA, np.linspace(0, 0.4, 10), 0.001, 1, noise="pink")
    with pytest.raises(HbmError, match="seed"):
        synthetic_specimen(model, THETA, np.linspace(0, 0.4, 10), 0.001, 1.5)


# ---------------------------------------------------------------------------------- shipped data
def test_shipped_specimens_load_and_are_plausible():
    specs = load_specimens(SPECIMENS)
    assert len(specs) == 6
    assert sum("hawkins" in k for k in specs) == 1
    assert sorted(k for k in specs if k.startswith("calvo2010_rat")) == [f"calvo2010_rat{i}" for i in range(1, 6)]
    for sid, ds in specs.items():
        a = ds.attrs
        assert "synthetic stand-in" in a["source"] and provenance(ds) == "synthetic"
        assert ("Hawkins D, Bey M (1994)" in a["citation"]) == ("hawkins" in sid)
        assert ("J Biomech 43:318-325" in a["citation"]) == ("calvo" in sid)
        params = json.loads(a["parameters"])
        assert set(params) == set(hbm.spyrou_model().parameter_names)
        assert "seed" in a and "noise_sd" in a and a["iso_factor"] == "1.0"
        n = ds.n_points
        assert 30 <= n <= 60
        strain, stress = ds.strain, ds.stress
        assert 0.05 <= stress.max() <= 0.3
        # the collagen engages: data beyond the onset strain
        onset = hbm.model.collagen_onset_stretch(params["THETA"]) - 1.0
        assert strain.max() > onset + 0.08
        # monotone-ish: the last quarter is far above the first quarter, the curve rises
        assert spearmanr(np.arange(n), stress)[0] > 0.8
        smooth = np.convolve(stress, np.ones(5) / 5, "valid")
        assert np.diff(smooth).min() > -0.02 * stress.max()
        assert stress[-n // 4:].mean() > 5 * abs(stress[: n // 4].mean()) + 0.03
        # residual against the generating model has the recorded noise sd
        model = hbm.spyrou_model(float(a["iso_factor"]))
        clean = model.stress(strain, np.array([params[k] for k in model.parameter_names]))
        sd = float(a["noise_sd"])
        assert np.abs(stress - clean).max() < 5 * sd
        if "calvo" in sid:
            np.testing.assert_allclose(ds.time, strain / 2.2e-4, atol=1e-3)
            assert "0.022 %/s" in a["strain_rate"]


def test_generator_reproduces_files(tmp_path):
    spec = importlib.util.spec_from_file_location("make_specimens", ROOT / "workflows" / "make_specimens.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    assert mod.main(["--out", str(tmp_path)]) == 0
    made = sorted(p.name for p in tmp_path.glob("*.csv"))
    shipped = sorted(p.name for p in SPECIMENS.glob("*.csv"))
    assert made == shipped and len(made) == 6
    for name in made:
        assert (tmp_path / name).read_bytes() == (SPECIMENS / name).read_bytes(), name


def test_synthetic_with_hidden_effect_on_multirate_protocol():
    from hbm.effects import make_effect

    model = hbm.spyrou_model() + make_effect("viscoelastic")
    prot = protocol(ramp(0.42, 1e-3, 20), ramp(0.42, 1e-1, 20))
    ds = synthetic_specimen(model, dict(THETA, G1=0.4, LOGTAU1=1.5), prot, 0.0, 5)
    th = model.null_theta(dict(THETA, G1=0.4, LOGTAU1=1.5))
    np.testing.assert_array_equal(ds.stress, model.stress(specimen_loading(prot), th))
    assert ds.stress[39] > ds.stress[19]  # the fast ramp is stiffer
    assert json.loads(ds.attrs["parameters"])["G1"] == 0.4
    np.testing.assert_array_equal(ds.test, [1] * 20 + [2] * 20)
