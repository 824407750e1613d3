"""The Spyrou–Agoras–Danas model against independent closed forms, and effect composition."""

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

import hbm
from hbm.model import collagen_onset_stretch, helical_stretch

NAMES = ("VOLF", "EOPT", "P1", "T1", "T2", "THETA", "GF", "GM")


def closed_form(eps, VOLF, EOPT, P1, T1, T2, THETA, GF, GM, k=1.0):
    """Scalar re-derivation of DESIGN.md §1, written independently of hbm (math module only)."""
    lam = 1.0 + eps
    c = VOLF
    G = c * GF + (1 - c) * GM
    th = THETA * math.pi / 180.0
    lh = math.sqrt(math.cos(th) ** 2 * lam ** 2 + math.sin(th) ** 2 / lam)
    pf = P1 * (eps - EOPT) if eps > EOPT else 0.0
    pm = T1 * (math.exp(T2 * (lh - 1.0)) - 1.0) if lh > 1.0 else 0.0
    return k * G * (lam ** 2 - 1.0 / lam) + lam * (c * pf + (1 - c) * pm)


POINTS = [
    dict(VOLF=0.9, EOPT=0.184, P1=0.13, T1=1.5, T2=9.3, THETA=60.0, GF=0.012, GM=0.009),
    dict(VOLF=0.97, EOPT=0.192, P1=0.005, T1=0.127, T2=162.0, THETA=59.8, GF=0.006, GM=0.006),
    dict(VOLF=0.55, EOPT=0.0, P1=0.0001, T1=20.0, T2=200.0, THETA=55.0, GF=0.1, GM=0.0001),
    dict(VOLF=0.7, EOPT=0.05, P1=0.4, T1=3.0, T2=16.0, THETA=57.3, GF=0.035, GM=0.03),
]
STRAINS = [0.0, 0.01, 0.1, 0.184, 0.2, 0.3, 0.35, 0.42, 0.6, 1.0]


@pytest.mark.parametrize("k", [1.0, 2.0 / 3.0])
@pytest.mark.parametrize("point", POINTS)
def test_stress_matches_closed_form(point, k):
    model = hbm.spyrou_model(iso_factor=k)
    theta = np.array([point[n] for n in NAMES])
    got = model.stress(np.array(STRAINS), theta)
    want = [closed_form(e, **point, k=k) for e in STRAINS]
    np.testing.assert_allclose(got, want, rtol=1e-12, atol=1e-15)


def test_iso_factor_scales_only_the_matrix():
    p = dict(POINTS[0], P1=1e-4, T1=0.0)  # matrix only (fibers negligible, collagen off)
    theta = np.array([p[n] for n in NAMES])
    eps = np.array([0.1, 0.15])
    s1 = hbm.spyrou_model(1.0).stress(eps, theta)
    s23 = hbm.spyrou_model(2 / 3).stress(eps, theta)
    # eps < EOPT (fibers off) and T1 = 0 (collagen off): only the matrix remains
    np.testing.assert_allclose(s23, (2 / 3) * s1, rtol=1e-12)


def test_parameter_table():
    model = hbm.spyrou_model()
    assert model.parameter_names == NAMES
    assert model.bounds.shape == (8, 2)
    assert model.bounds.dtype == float
    b = dict(zip(NAMES, model.bounds.tolist()))
    assert b["T1"] == [0.0, 20.0] and b["T2"] == [0.0, 200.0] and b["THETA"] == [55.0, 60.0]
    assert b["VOLF"] == [0.5, 0.99] and b["P1"] == [1e-4, 0.5] and b["GF"] == [1e-4, 0.1]
    assert model.units["THETA"] == "deg" and model.units["P1"] == "MPa"
    assert all(model.meanings[n] for n in NAMES)


@pytest.mark.parametrize("theta_deg, expected", [(55.0, 1.0131), (59.8, 1.2894), (60.0, 1.3028)])
def test_collagen_onset(theta_deg, expected):
    lam_star = collagen_onset_stretch(theta_deg)
    assert lam_star == pytest.approx(expected, abs=1e-4)
    # independent check: the helical stretch crosses 1 there
    assert helical_stretch(lam_star, theta_deg) == pytest.approx(1.0, abs=1e-12)
    # and the collagen carries no stress just below, some just above
    model = hbm.spyrou_model()
    theta = np.array([0.9, 0.2, 1e-4, 1.0, 10.0, theta_deg, 1e-4, 1e-4])
    only_collagen = model.stress([lam_star - 1 - 1e-6, lam_star - 1 + 1e-3], theta) - \
        model.stress([lam_star - 1 - 1e-6, lam_star - 1 + 1e-3], theta * np.r_[1, 1, 1, 0, 1, 1, 1, 1])
    assert only_collagen[0] == 0.0 and only_collagen[1] > 0.0


def test_volf_t1_invariance():
    """Equal G, c·P1 and (1−c)·T1 give identical stress whatever VOLF is (the VOLF–T1 manifold)."""
    eps = np.linspace(0, 0.45, 40)
    a = dict(VOLF=0.9, EOPT=0.184, P1=0.13, T1=1.5, T2=9.3, THETA=60.0, GF=0.012, GM=0.009)
    c2 = 0.6
    G = a["VOLF"] * a["GF"] + (1 - a["VOLF"]) * a["GM"]
    b = dict(a, VOLF=c2, P1=a["VOLF"] * a["P1"] / c2, T1=(1 - a["VOLF"]) * a["T1"] / (1 - c2),
             GF=G, GM=G)
    model = hbm.spyrou_model()
    sa = model.stress(eps, np.array([a[n] for n in NAMES]))
    sb = model.stress(eps, np.array([b[n] for n in NAMES]))
    np.testing.assert_allclose(sa, sb, rtol=1e-12)
    assert b["T1"] == pytest.approx(0.375)


def test_vectorised_shapes_and_no_sample_loop():
    model = hbm.spyrou_model()
    rng = np.random.default_rng(1)
    lo, hi = model.bounds.T
    theta = lo + (hi - lo) * rng.random((3, 5, 8))
    eps = np.linspace(0, 0.5, 7)
    s = model.stress(eps, theta)
    assert s.shape == (3, 5, 7)
    np.testing.assert_allclose(s[1, 2], model.stress(eps, theta[1, 2]), rtol=1e-14)


@settings(max_examples=60, deadline=None)
@given(u=st.lists(st.floats(0.0, 1.0), min_size=8, max_size=8))
def test_finite_everywhere_in_the_box(u):
    model = hbm.spyrou_model()
    lo, hi = model.bounds.T
    theta = lo + (hi - lo) * np.array(u)
    theta[4] = 200.0  # steepest collagen
    eps = np.linspace(-0.5, 1.0, 31)
    assert np.isfinite(model.stress(eps, theta)).all()
    assert np.isfinite(model.stress_jacobian(eps, theta)).all()


def test_jacobian_matches_finite_differences_away_from_kinks():
    model = hbm.spyrou_model()
    rng = np.random.default_rng(7)
    lo, hi = model.bounds.T
    theta = lo + (hi - lo) * rng.uniform(0.1, 0.9, (20, 8))
    theta[:, 4] = rng.uniform(1, 40, 20)  # keep the exponential moderate for FD accuracy
    eps = np.linspace(0.0, 0.5, 41)
    jac = model.stress_jacobian(eps, theta)
    assert jac.shape == (20, 41, 8)
    h = 1e-6 * (hi - lo)
    fd = np.empty_like(jac)
    for k in range(8):
        e = np.zeros(8)
        e[k] = h[k]
        fd[..., k] = (model.stress(eps, theta + e) - model.stress(eps, theta - e)) / (2 * h[k])
    # exclude points within one FD step of the two kinks (EOPT and the collagen onset)
    lam_star = collagen_onset_stretch(theta[:, 5])[:, None]
    near = (np.abs(eps[None, :] - theta[:, 1:2]) < 1e-3) | (np.abs(1 + eps[None, :] - lam_star) < 1e-3)
    scale = np.abs(fd).max(axis=1, keepdims=True) + 1e-12
    err = np.abs(jac - fd) / scale
    assert err[~near].max() < 1e-5


class Linear(hbm.Effect):
    """A user-defined elastic effect written in the test file (not in hbm)."""

    name = "linear_extra"
    stage = "elastic"
    parameters = (hbm.Parameter("EX", 0.0, 1.0, "MPa", "extra linear modulus", null=0.0),)

    def stress(self, state, p):
        return p["EX"] * state.eps


class Offset(hbm.Effect):
    name = "zero_offset"
    stage = "output"
    parameters = (hbm.Parameter("S0", -0.01, 0.01, "MPa", "load-cell zero", null=0.0),)

    def modify(self, state, p, stress):
        return stress + p["S0"]


def test_composition_adds_parameters_and_stress():
    base = hbm.spyrou_model()
    model = base + Linear()
    assert model.parameter_names == NAMES + ("EX",)
    assert model.bounds[-1].tolist() == [0.0, 1.0]
    model2 = base.with_effects(Linear(), Offset())
    assert model2.parameter_names == NAMES + ("EX", "S0")
    theta = np.array([0.9, 0.184, 0.13, 1.5, 9.3, 60.0, 0.012, 0.009])
    eps = np.linspace(0, 0.4, 9)
    s = model2.stress(eps, np.r_[theta, 0.25, 0.003])
    np.testing.assert_allclose(s, base.stress(eps, theta) + 0.25 * eps + 0.003, rtol=1e-13)
    # at the null values the extended model is the base model
    np.testing.assert_allclose(model2.stress(eps, model2.null_theta(theta)), base.stress(eps, theta))
    # analytic Jacobian of the base part survives composition with analytic effects only
    assert base.has_analytic_jacobian and not model2.has_analytic_jacobian
    jac = model2.stress_jacobian(eps, np.r_[theta, 0.25, 0.003])
    np.testing.assert_allclose(jac[:, -1], 1.0, rtol=1e-6)
    np.testing.assert_allclose(jac[:, -2], eps, rtol=1e-6, atol=1e-12)


def test_bad_effects_are_rejected():
    class NoHook(hbm.Effect):
        name = "nohook"
        stage = "history"

    with pytest.raises(TypeError, match="must implement modify"):
        hbm.spyrou_model() + NoHook()
    with pytest.raises(ValueError, match="duplicate effect"):
        hbm.spyrou_model().with_effects(Linear(), Linear())
    with pytest.raises(ValueError, match="columns"):
        hbm.spyrou_model().stress([0.1], np.ones(5))


def test_with_bounds_narrows_the_box():
    model = hbm.spyrou_model().with_bounds(VOLF=(0.5, 0.75))
    assert model.bounds[0].tolist() == [0.5, 0.75]
    assert (model + Linear()).bounds[0].tolist() == [0.5, 0.75]
    with pytest.raises(KeyError, match="unknown parameters"):
        hbm.spyrou_model().with_bounds(NOPE=(0, 1))


def test_loading_histories():
    # time restarts at the second test: two histories; continuing time: one history
    ld = hbm.Loading(np.zeros(6), time=np.array([0, 1, 2, 0, 1, 2.0]), test=np.array([0, 0, 0, 1, 1, 1]))
    assert ld.history.tolist() == [0, 0, 0, 1, 1, 1]
    ld2 = hbm.Loading(np.zeros(6), time=np.arange(6.0), test=np.array([0, 0, 0, 1, 1, 1]))
    assert ld2.history.tolist() == [0] * 6
