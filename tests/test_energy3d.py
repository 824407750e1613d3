"""The 3-D strain energy (hbm.model.energy3d) against an independent implementation (tests/independent3d.py)."""

import numpy as np
import pytest

import independent3d as ind
from hbm.errors import HbmError, SettingError
from hbm.model import spyrou_model
from hbm.model.energy3d import (COLLAGEN_READINGS, ConeCollagen, ConeFamilies, DirectionalCollagen, Energy3D, Sym,
                                energy_from_model, register_collagen_reading)
from hbm.model.loadcases import predict_observables

NAMES = ("VOLF", "EOPT", "P1", "T1", "T2", "THETA", "GF", "GM")
SETS = {"calvo": ind.CALVO, "hawkins": ind.HAWKINS, "box3": ind.random_box(3), "box4": ind.random_box(4)}


def as_params(prm):
    return {k: np.asarray(v, dtype=float) for k, v in prm.items()}


def deformations(seed=0):
    """F's that take each path of the cone: diagonal, shear in c-n (one harmonic in 2phi), shear in f-c
    (even in phi), and general."""
    rng = np.random.default_rng(seed)
    shear = lambda i, j, g: np.eye(3) + g * np.eye(3)[:, [i]] @ np.eye(3)[[j], :]   # noqa: E731
    out = {"diag_c": np.diag([0.9, 1.25, 1 / (0.9 * 1.25)]), "diag_f_compress": np.diag([0.8, 1.1, 1 / 0.88]),
           "shear_cn": shear(1, 2, 0.35), "shear_nc": shear(2, 1, -0.3), "shear_fc": shear(0, 1, 0.4),
           "shear_cf": shear(1, 0, -1.6), "general": np.eye(3) + 0.25 * rng.standard_normal((3, 3))}
    out["general_2"] = np.eye(3) + 0.15 * rng.standard_normal((3, 3))
    out["even_concave"] = np.array([[1.0, 0.3, 0.0], [0.0, 0.9, 0.0], [0.0, 0.0, 1.2]])   # D_cc < D_nn, D_fc != 0
    out["even_two_arcs"] = shear(0, 1, 1.5)          # f-c shear beyond 2·cot(theta): taut around phi = 0 and pi
    return out


def exponent(F, prm):
    """The largest collagen exponent T2·(l − 1) over the segments (what the cone's Gauss nodes must resolve)."""
    th = np.deg2rad(prm["THETA"])
    phi = np.linspace(0, 2 * np.pi, 4001)
    n = np.stack([np.full_like(phi, np.cos(th)), np.sin(th) * np.cos(phi), np.sin(th) * np.sin(phi)])
    return prm["T2"] * (np.linalg.norm(F @ n, axis=0).max() - 1)


@pytest.mark.parametrize("reading", ["cone", "gst"])
def test_energy_matches_independent_quadrature(reading):
    """<= 1e-10 relative while the largest collagen exponent is <= 100 (stresses up to ~1e40 MPa); the
    cone's 24 Gauss nodes per arc reach 1.5e-8 at exponent 161 (Hawkins-like, f-c shear 1.5: W = 8e63 MPa)."""
    energy = Energy3D(collagen3d=reading)
    for prm in SETS.values():
        for name, F in deformations().items():
            D = Sym.from_matrix(F.T @ F - np.eye(3))
            got = float(energy.energy(as_params(prm), D))
            ref = ind.energy(F, prm, reading)
            rel = 1e-10 if reading == "gst" or exponent(F, prm) <= 100 else 3e-8
            assert got == pytest.approx(ref, rel=rel, abs=1e-300), (name, prm)


@pytest.mark.parametrize("reading", ["cone", "gst"])
def test_kirchhoff_matches_finite_differences_of_w(reading):
    """τ = (∂W/∂F)·Fᵀ with ∂W/∂F by 5-point differences of the independent W (all 9 components)."""
    energy = Energy3D(collagen3d=reading)
    prm = ind.CALVO
    h = 1e-4
    for name, F in deformations(1).items():
        tau = energy.kirchhoff(as_params(prm), F)
        P = np.zeros((3, 3))
        for i in range(3):
            for j in range(3):
                def w(x, i=i, j=j):
                    G = F.copy()
                    G[i, j] = x
                    return ind.energy(G, prm, reading)
                x = F[i, j]
                P[i, j] = (-w(x + 2 * h) + 8 * w(x + h) - 8 * w(x - h) + w(x - 2 * h)) / (12 * h)
        ref = P @ F.T
        np.testing.assert_allclose(tau, ref, rtol=0, atol=1e-7 * np.abs(ref).max(), err_msg=name)


@pytest.mark.parametrize("form,reading", [("energy", "cone"), ("energy", "gst"), ("thesis", None)])
def test_principal_tangent_is_the_derivative_of_tau(form, reading):
    energy = Energy3D(1.0, form, reading)
    rng = np.random.default_rng(5)
    p = as_params({k: v[:, None] for k, v in zip(NAMES, np.array([list(s.values()) for s in SETS.values()]).T)})
    e = tuple(0.25 * rng.standard_normal((1, 7)) for _ in range(3))
    e = (e[0], e[1], e[2] if form == "energy" else -e[0] / 2)
    _, c = energy.principal(p, e, tangent=True)
    h = 1e-6
    for j in range(3):
        up = [x + h * (k == j) for k, x in enumerate(e)]
        dn = [x - h * (k == j) for k, x in enumerate(e)]
        tu, td = energy.principal(p, up)[0], energy.principal(p, dn)[0]
        for i in range(3):
            fd = (tu[i] - td[i]) / (2 * h)
            np.testing.assert_allclose(c[i][j], fd, rtol=2e-6, atol=1e-9 * np.abs(fd).max() + 1e-12)


@pytest.mark.parametrize("k_iso", [1.0, 2.0 / 3.0])
def test_along_fibre_tension_is_the_1d_model(k_iso):
    """uniaxial_f reproduces spyrou_model of the same form to <= 5e-14 of each curve's largest stress."""
    rng = np.random.default_rng(8)
    model = spyrou_model(iso_factor=k_iso, form="energy")
    lo, hi = model.bounds.T
    theta = np.vstack([lo + (hi - lo) * rng.random((400, 8)),
                       [[SETS[s][n] for n in NAMES] for s in SETS]])
    eps = np.concatenate([np.linspace(-0.5, 1.0, 76), [-1e-3, 1e-3, 0.0]])
    for form, readings in (("energy", ("cone", "gst")), ("thesis", (None,))):
        m = spyrou_model(iso_factor=k_iso, form=form)
        ref = m.stress(eps, theta)
        for reading in readings:
            got = predict_observables(Energy3D(k_iso, form, reading), "uniaxial_f", m._params(theta), eps)["stress"]
            err = np.abs(got - ref) / np.abs(ref).max(axis=1, keepdims=True)
            assert err.max() <= 5e-14, (form, reading, err.max())
            assert np.all(got[:, eps == 0.0] == 0.0)


def test_exact_cone_against_fibre_families():
    """N equally spaced families converge to the exact average only as O(N^-2) (the slack kink): the
    worst error over states just past the collagen onset (cross-fibre uniaxial and planar kinematics),
    times N^2, stays within a factor 3 from N = 32 to 512."""
    lc = np.linspace(1.02, 1.12, 11)
    e = (np.concatenate([-0.5 * np.log(lc), 0 * lc]), np.concatenate([np.log(lc)] * 2),
         np.concatenate([-0.5 * np.log(lc), -np.log(lc)]))
    Ns = np.array([32, 64, 128, 256, 512])
    for prm in (ind.CALVO, ind.HAWKINS):
        p = as_params(prm)
        exact = np.array(ConeCollagen().principal(p, e)[0])
        errs = np.array([(np.abs(np.array(ConeFamilies(n).principal(p, e)[0]) - exact).max(axis=0)
                          / np.abs(exact).max(axis=0)).max() for n in Ns])
        assert -2.3 < np.polyfit(np.log(Ns), np.log(errs), 1)[0] < -1.7, errs
        scaled = errs * Ns ** 2
        assert scaled.max() / scaled.min() < 3.0, errs
        assert errs[-1] > 1e-7                  # N = 512 is still far from the exact average
    # a discretised reading plugs into the energy and every mode (held axes are structural zeros)
    strain = np.array([-0.1, 0.1])
    for mode in ("planar_c_hold_f", "shear_cf"):
        exact = predict_observables(Energy3D(), mode, as_params(ind.CALVO), strain)["stress"]
        fam = predict_observables(Energy3D(collagen3d=ConeFamilies(512)), mode, as_params(ind.CALVO), strain)
        np.testing.assert_allclose(fam["stress"], exact, rtol=1e-4)


def test_gauss_nodes_converged_at_high_t2():
    """24 nodes per interval agree with 64 (and the independent quadrature) to << 1e-6 at T2 = 160-200."""
    for t2, theta in ((162.0, 59.8), (200.0, 55.0), (200.0, 60.0)):
        prm = dict(ind.HAWKINS, T2=t2, THETA=theta)
        p = as_params(prm)
        for F in (np.diag([1 / 1.3, 1.3, 1.0]), np.diag([0.75, 1 / 0.75, 1.0]), np.eye(3) + 0.3 * np.eye(3)[:, [0]]
                  @ np.eye(3)[[1], :], np.eye(3) + 0.3 * np.eye(3)[:, [1]] @ np.eye(3)[[2], :]):
            D = Sym.from_matrix(F.T @ F - np.eye(3))
            a, b = ConeCollagen(24).pk2(p, D), ConeCollagen(64).pk2(p, D)
            scale = max(abs(float(v)) for v in b if np.ndim(v) or v)
            assert max(abs(float(x) - float(y)) for x, y in zip(a, b)) <= 1e-9 * scale
            w = float(Energy3D(collagen3d="cone").energy(p, D))
            assert w == pytest.approx(ind.energy(F, prm, "cone"), rel=1e-10)


def test_readings_registry_and_options():
    assert {"cone", "gst"} <= set(COLLAGEN_READINGS)
    with pytest.raises(SettingError, match="collagen3d"):
        Energy3D(collagen3d="helix")
    with pytest.raises(SettingError, match="energy form"):
        Energy3D(form="thesis", collagen3d="gst")
    with pytest.raises(HbmError, match="energy form"):
        Energy3D(form="thesis").energy(as_params(ind.CALVO), Sym(0.1, -0.05, -0.05))
    e = energy_from_model(spyrou_model(iso_factor=2 / 3, form="energy"), "gst")
    assert (e.iso_factor, e.form, e.collagen3d) == (2 / 3, "energy", "gst") and "collagen3d=gst" in e.label
    assert energy_from_model(spyrou_model()).collagen3d == "axial"
    assert energy_from_model(spyrou_model(form="energy")).collagen3d == "cone"


def test_a_new_reading_is_one_class():
    """A reading that only supplies its quadrature rule works in every mode by itself."""
    @register_collagen_reading
    class Along(DirectionalCollagen):
        name = "test-along"
        description = "all collagen along the fibre (a test reading)"

        def rule(self, D, theta_deg, need="tangent"):
            N = Sym(np.ones((1, 1)), 0.0, 0.0)
            l2m1 = np.asarray(D.ff + 0 * theta_deg, dtype=float)[..., None]
            return N, np.ones_like(l2m1), l2m1
    try:
        energy = Energy3D(collagen3d="test-along")
        p = as_params({k: np.array([v]) for k, v in ind.CALVO.items()})
        s = predict_observables(energy, "shear_cf", p, np.array([0.3]))["stress"]
        # the fibre and the collagen both along e1, stretched to sqrt(1 + g^2) by F = I + g e_c(x)e_f
        lf = np.sqrt(1.09)
        c = ind.CALVO["VOLF"]
        fibre = c * ind.CALVO["P1"] * max(lf - 1 - ind.CALVO["EOPT"], 0) / lf
        coll = (1 - c) * ind.CALVO["T1"] * np.expm1(ind.CALVO["T2"] * (lf - 1)) / lf
        mu = c * ind.CALVO["GF"] + (1 - c) * ind.CALVO["GM"]
        assert s[0] == pytest.approx(0.3 * (mu + fibre + coll), rel=1e-12)   # σ_cf = S_cf + γ·S_ff
    finally:
        COLLAGEN_READINGS.pop("test-along")
