"""The Specimen type (hbm.data.specimen): validation, tests, the xarray view, the result key and the file."""

from __future__ import annotations

import dataclasses
import hashlib
import json
import pickle
from pathlib import Path

import numpy as np
import pytest
import xarray as xr

import hbm
from hbm import io
from hbm.data import Series, Specimen, Test, as_specimen, load_specimen, protocol, ramp
from hbm.errors import DataError
from hbm.io.identity import MEANING_ATTRS, data_key

ROOT = Path(__file__).resolve().parents[1]
SHIPPED = sorted((ROOT / "data" / "specimens").glob("*.csv"))


def _spec(**kw) -> Specimen:
    base = dict(id="s", strain=np.linspace(0, 0.3, 6), time=np.arange(6.0), test=np.array([1, 1, 1, 2, 2, 2]),
                observed={"stress": Series.known("stress", np.linspace(0, 0.1, 6))}, attrs={"source": "lab"})
    base.update(kw)
    return Specimen(**base)


def test_validation_refuses_what_is_not_a_specimen():
    with pytest.raises(DataError, match="reappears"):
        _spec(test=np.array([1, 1, 2, 2, 1, 1]))
    with pytest.raises(DataError, match="6"):
        _spec(time=np.arange(5.0))
    with pytest.raises(DataError, match="finite"):
        _spec(strain=np.array([0, 0.1, np.nan, 0.2, 0.3, 0.4]))
    with pytest.raises(DataError, match="integer test ids"):
        _spec(test=np.array([1, 1, 1.5, 2, 2, 2]))
    with pytest.raises(DataError, match="expected 6"):
        _spec(observed={"stress": Series.known("stress", np.zeros(5))})
    with pytest.raises(DataError, match="holds the series"):
        _spec(observed={"stress": Series.known("stress_2", np.zeros(6))})
    with pytest.raises(DataError, match="attrs"):
        _spec(attrs={"id": "other"})
    with pytest.raises(DataError, match="do not cover"):
        _spec(tests=(Test(1, None, 0, 6),))


def test_frozen_arrays_and_fields():
    s = _spec()
    with pytest.raises(ValueError):
        s.strain[0] = 1.0            # read-only: a likelihood or figure cannot edit the data
    with pytest.raises(ValueError):
        s.stress[0] = 1.0
    with pytest.raises(dataclasses.FrozenInstanceError):
        s.id = "t"
    assert s.strain.dtype == np.float64 and s.test.dtype == np.int64


def test_tests_labels_load_cases_and_loading():
    s = _spec(attrs={"test_labels": json.dumps(["ramp", "hold", "unused"])}, test=np.array([1, 1, 0, 0, 0, 0]))
    assert [(t.id, t.label, t.start, t.stop, t.load_case) for t in s.tests] == [
        (1, "hold", 0, 2, "uniaxial_f"), (0, "ramp", 2, 6, "uniaxial_f")]
    assert s.load_cases == ("uniaxial_f",)
    one = Specimen("one", np.linspace(0, 0.2, 4))          # no test column: one test, no series
    assert one.tests == (Test(0, None, 0, 4),) and not one.has_stress
    with pytest.raises(DataError, match="stress"):
        one.stress
    assert s.loading is s.loading                          # built once
    np.testing.assert_array_equal(s.loading.history, [0, 0, 0, 0, 0, 0])   # time continues: one history
    assert _spec(time=np.array([0, 1, 2, 0, 1, 2.0])).loading.history.tolist() == [0, 0, 0, 1, 1, 1]


def test_dataset_round_trip_and_unknown_variables():
    s = _spec()
    ds = s.to_dataset()
    assert list(ds.data_vars) == ["strain", "stress", "time", "test"]
    assert ds["stress"].attrs == {"units": "MPa", "long_name": "Cauchy stress along the fibers"}
    back = Specimen.from_dataset(ds.assign(stress_clean=("point", np.zeros(6))))   # not an observable
    assert list(back.observed) == ["stress"] and dict(back.attrs) == dict(s.attrs)
    for v in ("strain", "stress", "time", "test"):
        np.testing.assert_array_equal(getattr(back, v), getattr(s, v))
    assert as_specimen(s) is s
    assert as_specimen({"strain": [0.0, 0.1], "stress": [0.0, 0.01]}).id == "specimen"
    with pytest.raises(DataError, match="strain"):
        as_specimen(xr.Dataset({"stress": ("point", np.zeros(3))}))
    with pytest.raises(DataError, match="equal length"):
        as_specimen({"strain": [0.0, 0.1], "stress": [0.0]})


def _reference_key(strain, stress, time, test, attrs) -> str:
    """The result key of hbm before the Specimen (commit 68827b1), written out independently."""
    h = hashlib.sha256()
    parts = [np.asarray(a, float).tobytes() if a is not None else b"-" for a in (strain, stress, time, test)]
    meaning = {k: attrs[k] for k in MEANING_ATTRS if k in attrs}
    parts.append(json.dumps(dict(sorted(meaning.items())), sort_keys=True, separators=(",", ":")).encode())
    for p in parts:
        h.update(len(p).to_bytes(8, "little"))
        h.update(p)
    return h.hexdigest()[:16]


@pytest.mark.parametrize("path", SHIPPED, ids=[p.stem for p in SHIPPED])
def test_key_of_a_stress_only_specimen_is_the_old_key(path):
    s = load_specimen(path)
    assert data_key(s) == _reference_key(s.strain, s.stress, s.time, s.test, s.attrs)
    assert data_key(s.to_dataset()) == data_key(s)     # a Dataset is keyed as its Specimen


def test_extra_series_and_load_cases_enter_the_key():
    s = _spec()
    key = data_key(s)
    assert key == _reference_key(s.strain, s.stress, s.time, s.test, s.attrs)
    two = s.with_series("stress_2", np.full(6, np.nan), unit="MPa", long_name="second stress")
    assert data_key(two) != key
    assert data_key(s.with_series("stress_2", np.ones(6), unit="MPa")) != data_key(two)
    cases = (Test(1, None, 0, 3, "uniaxial_c"), Test(2, None, 3, 6))
    assert data_key(Specimen(s.id, s.strain, s.time, s.test, s.observed, s.attrs, cases)) != key


def test_pickle_select_and_protocol():
    s = _spec()
    back = pickle.loads(pickle.dumps(s))
    assert back.id == s.id and dict(back.attrs) == dict(s.attrs) and data_key(back) == data_key(s)
    part = s.select(s.test == 2)
    assert part.n_points == 3 and part.tests == (Test(2, None, 0, 3),)
    np.testing.assert_array_equal(part.stress, s.stress[3:])
    p = protocol(ramp(0.2, 1e-2, 5), ramp(0.2, 1e-1, 5))
    assert p.observed == {} and [t.id for t in p.tests] == [1, 2]
    assert p.with_series("stress", np.zeros(10)).has_stress


def test_result_file_holds_one_observed_variable_per_series(tmp_path):
    model = hbm.spyrou_model()
    theta = dict(VOLF=0.9, EOPT=0.1, P1=0.13, T1=1.5, T2=9.3, THETA=59.9, GF=0.012, GM=0.009)
    s = hbm.synthetic_specimen(model, theta, np.linspace(0, 0.4, 12), 0.002, seed=3)
    r = io.SpecimenResult(specimen_id=s.id, names=["VOLF"], samples=np.full((4, 1), 0.9), log_likelihood=np.zeros(4),
                          log_evidence=0.0, log_evidence_se=0.0, bounds=np.array([[0.5, 0.99]]), data=s)
    p = io.write_specimen_result(r, tmp_path / "one.nc")
    obs = xr.open_datatree(p)["observed_data"].ds
    assert list(obs.data_vars) == ["stress"] and obs["stress"].attrs["units"] == "MPa"
    two = s.with_series("strain_c", np.linspace(0, -0.1, 12), unit="-", long_name="lateral strain")
    r.data = two
    back = io.read_specimen_result(io.write_specimen_result(r, tmp_path / "two.nc"))
    assert list(back.data.observed) == ["stress", "strain_c"]
    assert back.data.observed["strain_c"].unit == "1" and back.data.observed["strain_c"].long_name == "lateral strain"
    np.testing.assert_array_equal(back.data.observed["strain_c"].values, two.observed["strain_c"].values)
    np.testing.assert_array_equal(back.data.strain, s.strain)
