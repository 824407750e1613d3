"""Tests of the slender-body organ model (hbm.organ) against closed forms and independent solvers."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
from scipy.optimize import brentq

from hbm.errors import HbmError
from hbm.model import Effect, Model, Parameter, spyrou_model
from hbm.model.spyrou import identifiable_combinations
from hbm.organ import (
    FusiformGeometry, extrapolation_mask, force_levels, load_geometry, nominal_stress, organ_response,
    tendon_strain, theta_from_samples)

ROOT = Path(__file__).resolve().parents[1]
GEOMETRY_FILE = ROOT / "data" / "geometry" / "fusiform.toml"

NAMES = ("VOLF", "EOPT", "P1", "T1", "T2", "THETA", "GF", "GM")
CALVO1 = dict(VOLF=0.9, EOPT=0.184, P1=0.13, T1=1.5, T2=9.3, THETA=60.0, GF=0.012, GM=0.009)
HAWKINS = dict(VOLF=0.97, EOPT=0.192, P1=0.005, T1=0.127, T2=162.0, THETA=59.8, GF=0.006, GM=0.006)
CALVO2 = dict(VOLF=0.8, EOPT=0.0, P1=1e-4, T1=0.5, T2=16.0, THETA=60.0, GF=0.035, GM=0.03)


def theta_of(*sets):
    return np.array([[s[n] for n in NAMES] for s in sets], dtype=float)


class LinearBar(Effect):
    """σ = E·(λ − 1)·λ, i.e. nominal stress P = E·(λ − 1): a linear-elastic bar."""

    name = "linear_bar"
    stage = "elastic"
    parameters = (Parameter("E", 0.01, 100.0, "MPa", "Young's modulus"),)

    def stress(self, state, p):
        return p["E"] * state.eps * state.lam


class Softening(Effect):
    """P = E·(λ − 1)·exp(−(λ − 1)/0.3): nominal stress peaks at λ = 1.3, then decreases."""

    name = "softening"
    stage = "elastic"
    parameters = (Parameter("E", 0.01, 100.0, "MPa", "modulus"),)

    def stress(self, state, p):
        return p["E"] * state.eps * np.exp(-state.eps / 0.3) * state.lam


class Offset(Effect):
    name = "offset_test"
    stage = "output"
    parameters = (Parameter("S0", -1.0, 1.0, "MPa", "offset", null=0.0),)

    def modify(self, state, p, stress):
        return stress + p["S0"]


def stress_at(model, theta_row, lam):
    """Model.stress (the public API, one sample) at an array of stretches of any shape."""
    lam = np.asarray(lam, dtype=float)
    return model.stress((lam - 1.0).ravel(), theta_row).reshape(lam.shape)


# ------------------------------------------------------------------------------------------
def test_uniform_cylinder_reproduces_material_curve():
    model = spyrou_model()
    theta = theta_of(CALVO1, HAWKINS, CALVO2)
    L, R = 20.0, 2.0
    A0 = math.pi * R * R
    geom = FusiformGeometry.uniform_cylinder(L, R, n_sections=8)
    forces = np.linspace(0.0, 3.0, 41)
    res = organ_response(model, theta, geom, forces, max_stretch=3.0)
    assert not res.unreachable.any()
    assert res.extra["distinct_sections"] == 1  # all sections share one area
    lam = res.elongation / L + 1.0
    assert np.all(np.diff(lam, axis=1) > 0)  # monotone force–elongation
    assert np.allclose(res.max_strain, lam - 1.0, rtol=0, atol=1e-13)
    for i in range(theta.shape[0]):
        F = stress_at(model, theta[i], lam[i]) * A0 / lam[i]
        np.testing.assert_allclose(F[1:], forces[1:], rtol=1e-9)
    assert np.all(lam[:, 0] == 1.0)


def test_linear_material_tapered_bar_closed_form():
    E = 2.5
    model = Model([LinearBar()])
    Rend, Rmid, L = 1.0, 2.0, 30.0
    geom = FusiformGeometry(length=L, radius_mid=Rmid, radius_end=Rend, profile="linear", n_sections=256)
    forces = np.array([0.0, 0.5, 1.0, 4.0])
    res = organ_response(model, np.array([[E]]), geom, forces, max_stretch=4.0)
    # ∫ F/(E·π·R(z)²) dz over the double cone = F·L/(E·π·R_end·R_mid)
    exact = forces * L / (E * math.pi * Rend * Rmid)
    np.testing.assert_allclose(res.elongation[0, 1:], exact[1:], rtol=1e-6)
    # the trapezoid rule is less accurate but converges to the same value
    res_t = organ_response(model, np.array([[E]]), geom, forces, max_stretch=4.0, quadrature="trapezoid")
    np.testing.assert_allclose(res_t.elongation[0, 1:], exact[1:], rtol=1e-4)
    # the strain in the end sections is F/(E·A_end) exactly
    np.testing.assert_allclose(res.max_strain[0], forces / (E * math.pi * Rend ** 2), rtol=1e-9)
    np.testing.assert_allclose(res.mid_strain[0], forces / (E * math.pi * Rmid ** 2), rtol=1e-9)


@pytest.mark.parametrize("n_anchors, n_grid", [(512, 129), (16, 9), (2, 3)])
def test_equilibrium_in_every_section(n_anchors, n_grid):
    # coarse anchors/tables force most unknowns through the bracketed polishing path
    model = spyrou_model()
    theta = theta_of(CALVO1, HAWKINS, CALVO2)
    geom = FusiformGeometry(length=32.0, radius_mid=3.5, radius_end=1.2, n_sections=32)
    forces = np.linspace(0.0, 4.0, 17)
    tol = 1e-10
    res = organ_response(model, theta, geom, forces, return_stretch=True, tol=tol, n_anchors=n_anchors,
                         n_grid=n_grid)
    assert res.stretch.shape == (3, 33, 17)
    assert np.isfinite(res.stretch).mean() > 0.9
    A0 = geom.area(geom.nodes)[:, None]
    FF = np.broadcast_to(forces, (33, 17))
    for i in range(theta.shape[0]):
        lam = res.stretch[i]
        ok = np.isfinite(lam)
        lam = np.where(ok, lam, 1.0)
        F = stress_at(model, theta[i], lam) * A0 / lam
        # floating-point floor: the force change over 4 ulps of λ (steep exponential branch)
        ulp = np.abs(stress_at(model, theta[i], lam * (1 + 4 * np.finfo(float).eps)) * A0 / lam - F)
        err = np.abs(F - FF)
        assert np.all((err <= 1.01 * tol * FF + ulp)[ok])
    # the belly elongation is the Simpson integral of the stretch field
    w = np.full(33, 2.0)
    w[1::2] = 4.0
    w[[0, -1]] = 1.0
    w *= geom.length / 32 / 3
    np.testing.assert_allclose(np.einsum("k,nkf->nf", w, res.stretch - 1.0), res.belly_elongation, rtol=1e-12)


def test_stretch_matches_independent_brent_solver():
    model = spyrou_model()
    theta = theta_of(HAWKINS, CALVO1)
    geom = FusiformGeometry(length=25.0, radius_mid=3.0, radius_end=1.0, profile="parabolic", n_sections=10,
                            exponent=2.0)
    forces = np.array([0.01, 0.3, 1.0, 2.5])
    res = organ_response(model, theta, geom, forces, return_stretch=True)
    A0 = geom.area(geom.nodes)
    for i in range(2):
        for k in (0, 3, 5):
            for j, F in enumerate(forces):
                f = lambda lam: stress_at(model, theta[i], np.array([lam]))[0] / lam - F / A0[k]
                root = brentq(f, 1.0, 3.0, xtol=1e-14, rtol=1e-15)
                assert res.stretch[i, k, j] == pytest.approx(root, rel=1e-9)


def test_identifiable_manifold_gives_same_organ_curve():
    model = spyrou_model()
    th1 = theta_of(CALVO1)[0]
    c1, c2 = th1[0], 0.62
    G = c1 * th1[6] + (1 - c1) * th1[7]
    th2 = th1.copy()
    th2[0] = c2
    th2[2] = c1 * th1[2] / c2                # same VOLF·P1
    th2[3] = (1 - c1) * th1[3] / (1 - c2)    # same (1−VOLF)·T1
    th2[6] = 0.02
    th2[7] = (G - c2 * th2[6]) / (1 - c2)   # same G
    comb1 = identifiable_combinations(NAMES, th1)
    comb2 = identifiable_combinations(NAMES, th2)
    for key in comb1:
        assert comb1[key] == pytest.approx(comb2[key], rel=1e-14)
    # a set off the manifold (same VOLF change, T1 unchanged) must give a different curve
    th3 = th2.copy()
    th3[3] = th1[3]
    geom = load_geometry(GEOMETRY_FILE)
    forces = force_levels(model, th1[None], geom, 0.4, n_forces=50)
    res = organ_response(model, np.stack([th1, th2, th3]), geom, forces)
    e = res.elongation
    np.testing.assert_allclose(e[1, 1:], e[0, 1:], rtol=1e-6)
    assert np.max(np.abs(e[2, 1:] / e[0, 1:] - 1)) > 1e-3


def test_tendon_contribution_closed_forms():
    model = Model([LinearBar()])
    forces = np.linspace(0.0, 5.0, 26)
    base = FusiformGeometry.uniform_cylinder(10.0, 1.5, tendon_length=8.0, tendon_area=0.5, tendon_modulus=800.0)
    res = organ_response(model, np.array([[3.0]]), base, forces)
    np.testing.assert_allclose(res.tendon_elongation, 8.0 * forces / (800.0 * 0.5), rtol=1e-14)
    np.testing.assert_allclose(res.elongation - res.belly_elongation, res.tendon_elongation[None], rtol=1e-12,
                               atol=1e-15)
    # belly of a uniform linear bar: L·F/(E·A0)
    np.testing.assert_allclose(res.belly_elongation[0], 10.0 * forces / (3.0 * math.pi * 1.5 ** 2), rtol=1e-9)
    # toe + linear law against a numerical inversion of its forward law S(ε)
    toe = base.replace(tendon_law="toe_linear", tendon_toe_strain=0.03)
    E, et = 800.0, 0.03

    def forward(eps):
        return E * eps * eps / (2 * et) if eps <= et else E * (eps - et / 2)

    eps = tendon_strain(forces, toe)
    for F, e in zip(forces[1:], eps[1:]):
        ref = brentq(lambda x: forward(x) - F / 0.5, 0.0, 1.0, xtol=1e-15)
        assert e == pytest.approx(ref, rel=1e-10)
    # continuity at the end of the toe region
    s_toe = 0.5 * E * et
    assert tendon_strain(np.array([s_toe * 0.5]), toe)[0] == pytest.approx(et, rel=1e-12)
    # rigid tendons (modulus inf) contribute nothing
    rigid = base.replace(tendon_modulus=math.inf)
    assert np.all(tendon_strain(forces, rigid) == 0)


def test_unreachable_and_strict():
    model = Model([LinearBar()])
    geom = FusiformGeometry.uniform_cylinder(10.0, 1.0)
    A = math.pi
    forces = np.array([0.0, 1.0 * A, 2.5 * A])  # E = 1: needs λ = 1, 2, 3.5
    res = organ_response(model, np.array([[1.0]]), geom, forces, max_stretch=3.0)
    assert res.unreachable.tolist() == [[False, False, True]]
    assert np.isnan(res.elongation[0, 2]) and res.elongation[0, 1] == pytest.approx(10.0, rel=1e-9)
    with pytest.raises(HbmError, match="max_stretch"):
        organ_response(model, np.array([[1.0]]), geom, forces, max_stretch=3.0, strict=True)
    with pytest.raises(HbmError, match="tension-only"):
        organ_response(model, np.array([[1.0]]), geom, np.array([-1.0]))


def test_non_monotone_nominal_stress_is_flagged():
    model = Model([Softening()])
    geom = FusiformGeometry.uniform_cylinder(10.0, 1.0)
    peak = 0.3 * math.exp(-1.0)  # max of P/E
    forces = np.array([0.5, 0.9]) * peak * math.pi
    res = organ_response(model, np.array([[1.0], [1.0]]), geom, forces, max_stretch=2.0)
    assert res.non_monotone.all()
    # the root returned is a root (the solver still brackets one)
    lam = res.elongation / 10.0 + 1.0
    np.testing.assert_allclose((lam - 1) * np.exp(-(lam - 1) / 0.3) * math.pi, forces[None].repeat(2, 0),
                               rtol=1e-9)
    with pytest.raises(HbmError, match="not unique"):
        organ_response(model, np.array([[1.0]]), geom, forces, max_stretch=2.0, strict=True)
    # below the peak only (max_stretch 1.25) the curve is monotone: no flag
    res2 = organ_response(model, np.array([[1.0]]), geom, forces[:1], max_stretch=1.25)
    assert not res2.non_monotone.any()


def test_force_levels_and_extrapolation_mask():
    model = spyrou_model()
    theta = theta_of(CALVO1)
    geom = load_geometry(GEOMETRY_FILE)
    F = force_levels(model, theta, geom, 0.4, factor=1.5, n_forces=30)
    assert F[0] == 0 and F.size == 30 and np.all(np.diff(F) > 0)
    res = organ_response(model, theta, geom, F)
    assert res.mid_strain[0, -1] == pytest.approx(0.6, rel=1e-9)
    Fmax = force_levels(model, theta, geom, 0.4, factor=1.5, n_forces=30, where="max")
    res2 = organ_response(model, theta, geom, Fmax)
    assert res2.max_strain[0, -1] == pytest.approx(0.6, rel=1e-9)
    mask = extrapolation_mask(res, 0.4)
    assert mask.shape == (1, 30)
    np.testing.assert_array_equal(mask, res.max_strain > 0.4)
    assert mask[0, -1] and not mask[0, 1]
    # per-sample tested strains
    two = organ_response(model, np.repeat(theta, 2, 0), geom, F)
    m2 = extrapolation_mask(two, np.array([0.4, 10.0]))
    assert m2[0].any() and not m2[1].any()
    with pytest.raises(HbmError):
        extrapolation_mask(two, np.array([0.4, 0.4, 0.4]))
    # quantile across samples: 0 = softest sample, 1 = stiffest
    thetas = theta_of(CALVO1, CALVO2)
    f_lo = force_levels(model, thetas, geom, 0.4, quantile=0.0)[-1]
    f_hi = force_levels(model, thetas, geom, 0.4, quantile=1.0)[-1]
    per = nominal_stress(model, thetas, np.array([1.6]))[:, 0] * geom.area(np.array([geom.length / 2]))[0]
    assert f_lo == pytest.approx(per.min(), rel=1e-12) and f_hi == pytest.approx(per.max(), rel=1e-12)


def test_chunking_and_population_consistency():
    model = spyrou_model()
    rng = np.random.default_rng(7)
    base = theta_of(CALVO1)[0]
    theta = base * np.exp(0.05 * rng.standard_normal((40, 8)))
    theta[:, 5] = np.clip(theta[:, 5], 55, 60)
    geom = load_geometry(GEOMETRY_FILE)
    F = force_levels(model, theta, geom, 0.4, n_forces=20)
    big = organ_response(model, theta, geom, F)
    small = organ_response(model, theta, geom, F, chunk_elements=500)  # one sample per chunk
    single = organ_response(model, theta[7:8], geom, F)
    np.testing.assert_allclose(small.elongation, big.elongation, rtol=1e-9, equal_nan=True)
    np.testing.assert_allclose(single.elongation[0], big.elongation[7], rtol=1e-9, equal_nan=True)
    band = big.band((0.05, 0.5, 0.95))
    assert band.shape == (3, 20) and np.all(band[0] <= band[1]) and np.all(band[1] <= band[2])
    ds = big.to_dataset(tested_max_strain=0.4)
    assert ds["elongation"].dims == ("sample", "force") and "extrapolated" in ds


def test_excluded_effects_are_reported():
    model = spyrou_model() + Offset()
    theta = model.null_theta(theta_of(CALVO1))
    theta[0, -1] = 0.05  # the offset must not change the organ
    geom = FusiformGeometry.uniform_cylinder(10.0, 1.0)
    r1 = organ_response(model, theta, geom, np.array([0.1, 0.2]))
    r0 = organ_response(spyrou_model(), theta_of(CALVO1), geom, np.array([0.1, 0.2]))
    assert r1.excluded_effects == ("offset_test",)
    np.testing.assert_allclose(r1.elongation, r0.elongation, rtol=1e-12)


# ------------------------------------------------------------------------------------------
def test_geometry_file_and_profiles():
    g = load_geometry(GEOMETRY_FILE)
    assert g.profile == "sine" and g.exponent == 1.0 and g.tendon_law == "toe_linear"
    L, Re, Rm = g.length, g.radius_end, g.radius_mid
    z = g.nodes
    np.testing.assert_array_equal(g.radius(z), g.radius(z[::-1]))  # exactly symmetric
    assert g.radius(np.array([0.0]))[0] == pytest.approx(Re) and g.radius(np.array([L / 2]))[0] == pytest.approx(Rm)
    # sine profile p = 1: volume = π·L·(R_e² + 4·R_e·ΔR/π + ΔR²/2)
    d = Rm - Re
    vol = math.pi * L * (Re ** 2 + 4 * Re * d / math.pi + d * d / 2)
    assert g.volume == pytest.approx(vol, rel=1e-6)
    assert g.max_slope == pytest.approx(math.pi * d / L, rel=1e-4)
    assert g.max_slope < 0.3  # the example respects the slender-body assumption
    for prof in ("parabolic", "linear", "uniform"):
        gp = g.replace(profile=prof)
        assert gp.radius(np.array([L / 2]))[0] == pytest.approx(Rm)
    assert g.replace(profile="parabolic").max_slope == pytest.approx(4 * d / L)


@pytest.mark.parametrize("text, needle", [
    ("[belly]\nlength = 10.0\nradius_mid = 2.0\n", "radius_end is missing"),
    ("[belly]\nlength = -1.0\nradius_mid = 2.0\nradius_end = 1.0\n", "length must be > 0"),
    ("[belly]\nlength = 'ten'\nradius_mid = 2.0\nradius_end = 1.0\n", "length must be a number"),
    ("[belly]\nlength = 10.0\nradius_mid = 2.0\nradius_end = 1.0\nn_sections = 3.5\n", "n_sections must be an integer"),
    ("[belly]\nlength = 10.0\nradius_mid = 2.0\nradius_end = 1.0\nprofile = 'egg'\n", "profile must be one of"),
    ("[belly]\nlength = 10.0\nradius_mid = 2.0\nradius_end = 1.0\nlenght = 3\n", "unknown key"),
    ("[belly]\nlength = 10.0\nradius_mid = 2.0\nradius_end = 1.0\n[tendon]\nlength_distal = -2.0\n",
     "length_distal must be >= 0"),
    ("[belly]\nlength = 10.0\nradius_mid = 2.0\nradius_end = 1.0\n[tendon]\nmodulus = 0\n", "modulus must be > 0"),
    ("[belly\nlength = 10.0\n", "invalid TOML"),
])
def test_geometry_errors_are_one_line_and_name_the_key(tmp_path, text, needle):
    path = tmp_path / "g.toml"
    path.write_text(text)
    with pytest.raises(HbmError) as info:
        load_geometry(path)
    msg = str(info.value)
    assert needle in msg and str(path) in msg and "\n" not in msg


def test_geometry_missing_file(tmp_path):
    with pytest.raises(HbmError, match="not found"):
        load_geometry(tmp_path / "nope.toml")


def test_input_validation():
    model = spyrou_model()
    geom = FusiformGeometry.uniform_cylinder(10.0, 1.0)
    with pytest.raises(HbmError, match="theta must have shape"):
        organ_response(model, np.ones((2, 3)), geom, np.array([1.0]))
    with pytest.raises(HbmError, match="max_stretch"):
        organ_response(model, theta_of(CALVO1), geom, np.array([1.0]), max_stretch=1.0)
    with pytest.raises(HbmError, match="radius_end must be a positive"):
        FusiformGeometry(length=10.0, radius_mid=1.0, radius_end=-1.0)


def test_theta_from_samples():
    model = spyrou_model()
    names = ["VOLF", "P1", "T1", "T2", "THETA", "GF", "GM", "sigma"]
    samples = np.arange(16.0).reshape(2, 8)
    th = theta_from_samples(model, names, samples, fixed={"EOPT": 0.19})
    assert th.shape == (2, 8)
    np.testing.assert_array_equal(th[:, model.index("EOPT")], 0.19)
    np.testing.assert_array_equal(th[:, model.index("GM")], samples[:, 6])
    with pytest.raises(HbmError, match="EOPT"):
        theta_from_samples(model, names, samples)
