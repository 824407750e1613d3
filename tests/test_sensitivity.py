"""Sobol indices: the SALib plumbing against closed forms (Ishigami, a linear per-point model)
and the thesis Table 3.6 ranking on a Hawkins-like specimen."""

import numpy as np
import pytest
import xarray as xr

from hbm.errors import HbmError
from hbm.model import Effect, Model, Parameter, spyrou_model
from hbm.fit.sensitivity import relevance_class, sobol

PI = np.pi


class Ishigami(Effect):
    """Stress = Ishigami function of (X1, X2, X3), the same at every strain point."""

    name = "ishigami"
    stage = "elastic"
    parameters = tuple(Parameter(f"X{i}", -PI, PI) for i in (1, 2, 3))

    def stress(self, state, p):
        y = np.sin(p["X1"]) + 7.0 * np.sin(p["X2"]) ** 2 + 0.1 * p["X3"] ** 4 * np.sin(p["X1"])
        return y + 0.0 * state.eps


class Linear(Effect):
    """Stress = ε·A + (1 − ε)·B: per-point S1_A = ε²/(ε² + (1 − ε)²)."""

    name = "linear"
    stage = "elastic"
    parameters = (Parameter("A", 0.0, 1.0), Parameter("B", 0.0, 1.0), Parameter("C", 0.0, 1.0))

    def stress(self, state, p):
        return state.eps * p["A"] + (1.0 - state.eps) * p["B"]


def test_ishigami_indices_match_closed_form():
    a, b = 7.0, 0.1
    v = a**2 / 8 + b * PI**4 / 5 + b**2 * PI**8 / 18 + 0.5
    v1 = 0.5 * (1 + b * PI**4 / 5) ** 2
    v2 = a**2 / 8
    v13 = b**2 * PI**8 * (1 / 18 - 1 / 50)
    s1 = np.array([v1, v2, 0.0]) / v
    st = np.array([v1 + v13, v2, v13]) / v
    res = sobol(Model([Ishigami()]), np.array([0.0, 1.0]), n=8192, seed=1, per_point=False)
    got1 = np.array([res.S1[k] for k in ("X1", "X2", "X3")])
    gott = np.array([res.ST[k] for k in ("X1", "X2", "X3")])
    np.testing.assert_allclose(got1, s1, atol=0.03)
    np.testing.assert_allclose(gott, st, atol=0.03)
    # reported confidence half-widths are of the size of the actual error (not absurdly small)
    assert all(0 < res.ST_conf[k] < 0.1 for k in res.names)
    assert res.n_evaluations == 8192 * (3 + 2)


def test_per_point_indices_of_a_linear_model():
    eps = np.linspace(0.0, 1.0, 11)
    res = sobol(Model([Linear()]), eps, n=4096, seed=0)
    expect_a = eps**2 / (eps**2 + (1 - eps) ** 2)
    np.testing.assert_allclose(res.per_point["S1"][:, 0], expect_a, atol=0.02)
    np.testing.assert_allclose(res.per_point["ST"][:, 1], 1 - expect_a, atol=0.02)
    np.testing.assert_allclose(res.per_point["ST"][:, 2], 0.0, atol=1e-6)  # C does nothing
    # integrated stress Q = ∫ σ dε = A/2 + B/2 -> S1 = 1/2 each
    assert res.S1["A"] == pytest.approx(0.5, abs=0.02)
    assert res.S1["B"] == pytest.approx(0.5, abs=0.02)
    assert res.relevance["C"] == "irrelevant"


@pytest.mark.parametrize("st, label", [(0.95, "very important"), (0.8, "very important"),
                                       (0.6, "important"), (0.5, "important"), (0.31, "unimportant"),
                                       (0.29, "irrelevant"), (-0.01, "irrelevant")])
def test_relevance_classes_of_thesis_table_2_1(st, label):
    assert relevance_class(st) == label


def test_hawkins_like_ranking_thesis_table_3_6():
    """THETA first, GF, GM (and P1) irrelevant: thesis Table 3.6 for the Hawkins data.

    Sub-ranges as in the thesis's Hawkins analysis: EOPT fixed at 0.192 (Hawkins & Bey),
    P1 in [1e-4, 0.01] (Table 3.5), T1 in [0, 0.3] (Table 3.3), T2 near 162 (Table 3.5);
    THETA, VOLF, GF, GM over their full prior boxes.
    """
    model = spyrou_model()
    truth = np.array([0.97, 0.192, 0.005, 0.127, 162.0, 59.8, 0.006, 0.006])
    e = np.linspace(0.0, 0.42, 40)
    ds = xr.Dataset({"strain": ("point", e), "stress": ("point", model.stress(e, truth))})
    bounds = {"P1": (1e-4, 0.01), "T1": (0.0, 0.3), "T2": (150.0, 175.0)}
    res = sobol(model, data=ds, bounds=bounds, fix={"EOPT": 0.192}, n=1024, seed=0)
    assert "EOPT" not in res.ST
    assert res.ranking[0] == "THETA"
    for k in ("GF", "GM", "P1"):
        assert res.relevance[k] == "irrelevant"
        assert res.ST[k] < 0.05
    assert res.relevance["THETA"] in ("very important", "important")
    assert res.per_point["ST"].shape == (40, 7)
    assert np.isnan(res.per_point["ST"][0]).all()  # ε = 0: stress is 0 for every sample
    # the misfit QoI ranks THETA first as well
    mis = sobol(model, data=ds, bounds=bounds, fix={"EOPT": 0.192}, n=512, seed=0, qoi="misfit",
                per_point=False)
    assert mis.ranking[0] == "THETA"
    d = res.to_dict()
    assert set(d) >= {"S1", "ST", "S1_conf", "ST_conf", "relevance"}


def test_bad_arguments():
    m = spyrou_model()
    with pytest.raises(HbmError, match="power of 2"):
        sobol(m, np.linspace(0, 0.3, 5), n=1000)
    with pytest.raises(HbmError, match="qoi"):
        sobol(m, np.linspace(0, 0.3, 5), qoi="energy")
    with pytest.raises(HbmError, match="needs data"):
        sobol(m, np.linspace(0, 0.3, 5), qoi="misfit", n=64)
    with pytest.raises(HbmError, match="unknown parameter"):
        sobol(m, np.linspace(0, 0.3, 5), n=64, fix={"XX": 1.0})


@pytest.mark.slow
def test_shipped_hawkins_specimen_ranking():
    """The shipped Hawkins stand-in, thesis sub-ranges, N = 4096: THETA first, GF/GM/P1 irrelevant."""
    from pathlib import Path

    data = pytest.importorskip("hbm.data")
    path = Path(__file__).resolve().parents[1] / "data" / "specimens" / "hawkins1994_rat.csv"
    if not path.exists():
        pytest.skip("shipped specimen missing")
    ds = data.load_specimen(path)
    res = sobol(spyrou_model(), data=ds, fix={"EOPT": 0.192}, n=4096, seed=1,
                bounds={"P1": (1e-4, 0.01), "T1": (0.0, 0.3), "T2": (150.0, 175.0)})
    assert res.ranking[0] == "THETA"
    assert all(res.relevance[k] == "irrelevant" for k in ("GF", "GM", "P1"))


class Exponential(Effect):
    """Stress = (1 + ε)·exp(2A + B): log W = 2A + B + const, additive in A and B."""

    name = "exponential"
    stage = "elastic"
    parameters = (Parameter("A", 0.0, 1.0), Parameter("B", 0.0, 1.0))

    def stress(self, state, p):
        return (1.0 + state.eps) * np.exp(2.0 * p["A"] + p["B"])


def test_log_integrated_stress_is_additive_closed_form():
    """For log W = 2A + B + c with A, B ~ U(0, 1): S1 = ST = 4/5 and 1/5 exactly; the raw W is
    not additive (ST_A > S1_A), so the two QoIs must differ."""
    model = Model([Exponential()])
    strain = np.linspace(0.0, 0.3, 7)
    res = sobol(model, strain, n=2048, qoi="log_integrated_stress", seed=3, per_point=False)
    np.testing.assert_allclose([res.S1["A"], res.S1["B"]], [0.8, 0.2], atol=0.03)
    np.testing.assert_allclose([res.ST["A"], res.ST["B"]], [0.8, 0.2], atol=0.03)
    raw = sobol(model, strain, n=2048, qoi="integrated_stress", seed=3, per_point=False)
    assert raw.ST["A"] - raw.S1["A"] > 0.02
