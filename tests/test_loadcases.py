"""Load cases (hbm.model.loadcases): every mode against an independent implementation (tests/independent3d.py),
traction-free residuals, shapes, the registry and the refusal of the thesis form."""

import re
from pathlib import Path

import numpy as np
import pytest

import independent3d as ind
from hbm.errors import HbmError
from hbm.model import spyrou_model
from hbm.model.energy3d import Energy3D
from hbm.model.loadcases import (ALIASES, LOAD_CASES, THESIS_FORM_REASON, check_mode, get_load_case,
                                 predict_observables)

VOCABULARY = ("uniaxial_f", "uniaxial_c", "planar_f_hold_c", "planar_c_hold_f", "planar_c_hold_n", "biaxial_fc",
              "biaxial_cn", "shear_fc", "shear_cf", "shear_cn")
# box draws whose EOPT keeps the fibre kink >= 3e-3 away from every tested fibre strain (the independent
# finite differences must not straddle it)
SETS = {"calvo": ind.CALVO, "hawkins": ind.HAWKINS, "box10": ind.random_box(10), "box14": ind.random_box(14)}
ROOT = Path(__file__).resolve().parents[1]


def batch(*sets):
    """The parameter mapping of several sets, (n_sets, 1) each."""
    return {k: np.array([[s[k]] for s in sets]) for k in sets[0]}


def controls(mode):
    """(strain, strain_2): tension and compression (shear: both signs), a non-equal second biaxial axis."""
    strain = np.array([-0.3, 0.15, 0.4]) if mode.startswith("shear") else np.array([-0.2, 0.1, 0.3])
    return strain, (0.5 * strain if mode.startswith("biaxial") else None)


@pytest.mark.parametrize("reading", ["cone", "gst"])
@pytest.mark.parametrize("mode", VOCABULARY)
def test_mode_matches_independent_implementation(mode, reading):
    """<= 1e-6 relative on every observable (stresses and lateral strains), four parameter sets, tension and
    compression; the independent side solves the free faces by brentq on finite-difference stresses (for the
    cone's two uniaxial modes at the first two sets only: each of its points costs ~0.2 s)."""
    energy = Energy3D(collagen3d=reading)
    strain, strain_2 = controls(mode)
    names = list(SETS)
    if reading == "cone" and mode.startswith("uniaxial"):
        names = names[:2]
    got = predict_observables(energy, mode, batch(*(SETS[n] for n in names)), strain, strain_2)
    assert set(got) == set(LOAD_CASES[mode].observable_names)
    for i, name in enumerate(names):
        for j, s in enumerate(strain):
            ref = ind.predict(mode, s, SETS[name], reading, None if strain_2 is None else strain_2[j])
            for k, v in ref.items():
                assert abs(got[k][i, j] - v) <= 1e-6 * abs(v) + 1e-14, (name, s, k, got[k][i, j], v)


def test_traction_free_residuals_across_the_box():
    """uniaxial_c: |sigma_ff| = |sigma_nn| <= 1e-9 of sigma_cc at the returned stretches, 300 box draws x 25
    strains from -40 % to +60 % plus the shipped-like sets, both readings; uniaxial_f: the lateral strains
    are lambda^-1/2 - 1."""
    rng = np.random.default_rng(17)
    model = spyrou_model(form="energy")
    lo, hi = model.bounds.T
    theta = np.vstack([lo + (hi - lo) * rng.random((300, 8)), [[s[n] for n in model.parameter_names]
                                                             for s in SETS.values()]])
    p = model._params(theta)
    strain = np.linspace(-0.4, 0.6, 25)
    for reading in ("cone", "gst"):
        energy = Energy3D(collagen3d=reading)
        out = predict_observables(energy, "uniaxial_c", p, strain)
        e = (np.log1p(out["strain_f"]), np.log1p(strain) + 0 * out["strain_f"], np.log1p(out["strain_n"]))
        np.testing.assert_allclose(e[0] + e[1] + e[2], 0.0, atol=1e-14)          # J = 1
        tau, _ = energy.principal(p, e)
        sigma = tau[1] - tau[0]
        assert np.allclose(sigma, out["stress"], rtol=1e-9, atol=0)
        assert np.all(np.abs(tau[0] - tau[2]) <= 1e-9 * np.abs(sigma)), reading
        assert np.all(np.sign(out["stress"]) == np.sign(strain))
        uf = predict_observables(energy, "uniaxial_f", p, strain)
        np.testing.assert_allclose(uf["strain_c"], np.broadcast_to((1 + strain) ** -0.5 - 1, uf["strain_c"].shape),
                                   rtol=1e-13, atol=1e-16)
        np.testing.assert_array_equal(uf["strain_c"], uf["strain_n"])


@pytest.mark.parametrize("mode", VOCABULARY)
def test_shapes_and_broadcast(mode):
    """(particles, points), (a, b, points) and scalar parameters give the same numbers as one particle at a
    time (bitwise: the solvers are element-wise)."""
    energy = Energy3D(collagen3d="cone")
    strain, strain_2 = controls(mode)
    sets = [SETS[n] for n in SETS]
    two_d = predict_observables(energy, mode, batch(*sets), strain, strain_2)
    grid = {k: v.reshape(2, 2, 1) for k, v in batch(*sets).items()}
    three_d = predict_observables(energy, mode, grid, strain, strain_2)
    for i, s in enumerate(sets):
        one = predict_observables(energy, mode, s, strain, strain_2)
        for k in LOAD_CASES[mode].observable_names:
            assert two_d[k].shape == (4, strain.size) and three_d[k].shape == (2, 2, strain.size)
            assert one[k].shape == strain.shape
            np.testing.assert_array_equal(two_d[k][i], one[k])
            np.testing.assert_array_equal(three_d[k][i // 2, i % 2], one[k])


def test_vocabulary_registry_and_aliases():
    assert tuple(LOAD_CASES) == VOCABULARY
    for case in LOAD_CASES.values():
        assert case.control in ("stretch", "shear") and case.description and case.observables[0].name == "stress"
        assert all(o.unit in ("MPa", "1") and o.long_name for o in case.observables)
        assert case.inputs == (("strain", "strain_2") if case.name.startswith("biaxial") else ("strain",))
    assert get_load_case("uniaxial") is LOAD_CASES["uniaxial_f"]
    assert get_load_case("transverse") is LOAD_CASES["uniaxial_c"]
    assert all(get_load_case(a).name == n for a, n in ALIASES.items())
    with pytest.raises(HbmError, match="unknown mode 'torsion'.*uniaxial_f"):
        get_load_case("torsion")


def test_biaxial_second_strain_defaults_to_the_first():
    energy = Energy3D()
    p = batch(ind.CALVO)
    s = np.array([0.05, 0.1, 0.2])
    equi = predict_observables(energy, "biaxial_fc", p, s)
    same = predict_observables(energy, "biaxial_fc", p, s, s)
    gaps = predict_observables(energy, "biaxial_fc", p, s, np.array([0.05, np.nan, 0.2]))
    for k in equi:
        np.testing.assert_array_equal(equi[k], same[k])
        np.testing.assert_array_equal(equi[k], gaps[k])
    # equibiaxial across the fibres: transverse isotropy makes both stresses equal
    cn = predict_observables(energy, "biaxial_cn", p, s)
    np.testing.assert_allclose(cn["stress"], cn["stress_2"], rtol=1e-13)


def test_nominal_stress_stretches():
    s = np.array([-0.2, 0.1, 0.3])
    np.testing.assert_allclose(get_load_case("uniaxial_c").load_stretch("stress", s), 1 + s, rtol=1e-15)
    np.testing.assert_allclose(get_load_case("planar_f_hold_c").load_stretch("stress_2", s), 1.0)
    np.testing.assert_allclose(get_load_case("biaxial_cn").load_stretch("stress_2", s, 0.5 * s), 1 + 0.5 * s,
                               rtol=1e-15)
    np.testing.assert_array_equal(get_load_case("shear_cf").load_stretch("stress", s), 1.0)
    with pytest.raises(HbmError, match="strain"):
        get_load_case("uniaxial_f").load_stretch("strain_c", s)


def test_bad_kinematics_and_undetermined_lateral_problem():
    energy = Energy3D()
    p = ind.CALVO
    with pytest.raises(HbmError, match=r"uniaxial_c: strain must be > -1 \(a stretch > 0\), got -1"):
        predict_observables(energy, "uniaxial_c", p, np.array([0.1, -1.0]))
    with pytest.raises(HbmError, match="strain_2 must be > -1"):
        predict_observables(energy, "biaxial_fc", p, np.array([0.1]), np.array([-1.5]))
    with pytest.raises(HbmError, match="finite"):
        predict_observables(energy, "shear_fc", p, np.array([np.inf]))
    with pytest.raises(HbmError, match="one control"):
        predict_observables(energy, "planar_c_hold_n", p, np.array([0.1]), np.array([0.1]))
    assert predict_observables(energy, "shear_cn", p, np.array([-3.0]))["stress"][0] < 0   # any gamma
    limp = dict(ind.CALVO, GF=0.0, GM=0.0, T1=0.0)      # no shear modulus, no collagen: lateral stretch free
    with pytest.raises(HbmError, match="no unique traction-free lateral stretch"):
        predict_observables(energy, "uniaxial_c", limp, np.array([0.1]))


def shipped_parameters():
    out = {}
    for f in sorted((ROOT / "data" / "specimens").glob("*.csv")):
        line = next(x for x in f.read_text().splitlines() if x.startswith("# parameters:"))
        out[f.stem] = {k: float(v) for k, v in re.findall(r'"(\w+)": ([-\d.e]+)', line)}
    return out


def test_thesis_form_refused_with_its_reason():
    thesis = Energy3D(form="thesis")
    for mode in VOCABULARY[1:]:
        with pytest.raises(HbmError, match=f"mode {mode} needs the energy form .--form energy.: .*not convex"):
            check_mode(spyrou_model(), mode)
        with pytest.raises(HbmError, match="compressive tangent"):
            predict_observables(thesis, mode, ind.CALVO, np.array([0.1]))
    check_mode(spyrou_model(), "uniaxial")
    check_mode("energy", "shear_cf")
    eps = np.linspace(-0.3, 0.45, 16)
    m = spyrou_model()
    theta = np.array([[ind.CALVO[n] for n in m.parameter_names]])
    np.testing.assert_allclose(predict_observables(thesis, "uniaxial_f", m._params(theta), eps)["stress"],
                               m.stress(eps, theta), rtol=5e-14, atol=1e-17)
    # the reason, checked: the compressive tangent dσ/dε at λ -> 1- is 3μ + (1-c)·T1·T2·(3cos²θ - 1)/2 < 0 ...
    specimens = shipped_parameters()
    assert len(specimens) == 6
    for name, prm in specimens.items():
        c, th = prm["VOLF"], np.deg2rad(prm["THETA"])
        mu = c * prm["GF"] + (1 - c) * prm["GM"]
        formula = 3 * mu + (1 - c) * prm["T1"] * prm["T2"] * (3 * np.cos(th) ** 2 - 1) / 2
        h = 1e-7
        s = predict_observables(thesis, "uniaxial_f", prm, np.array([-2 * h, -h]))["stress"]
        assert formula < 0 and (s[1] - s[0]) / h == pytest.approx(formula, rel=1e-5), name
    # ... and cross-fibre tension has no traction-free state: τ_ff - τ_nn > 0 at every fibre stretch
    u = np.linspace(-3, 3, 6001)
    for prm in specimens.values():
        tau, _ = thesis.principal(prm, (u, np.log(1.2), -u - np.log(1.2)))
        assert np.all(tau[0] - tau[2] > 0)
    assert "energy form" in THESIS_FORM_REASON or "along-fibre" in THESIS_FORM_REASON
