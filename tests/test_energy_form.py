"""The energy-consistent form of the Spyrou model against an independent 3-D equilibrium solve.

The reference is written here without hbm: the 3-D strain energy W(λ, μ1, μ2) of the
homogenised model (neo-Hookean matrix, fibers along axis 1, a collagen helix at θ to the axis
averaged around it), incompressibility by a Lagrange multiplier, the traction-free lateral
faces solved with scipy (brentq), every derivative by complex-step differentiation.
"""

import math

import numpy as np
import pytest
import scipy.optimize as so
from hypothesis import given, settings
from hypothesis import strategies as st

import hbm
from hbm.errors import HbmError
from hbm.model import (
    EnergyHelicalCollagen, HelicalCollagen, Loading, collagen_energy, collagen_onset_stretch, compression_check)

NAMES = ("VOLF", "EOPT", "P1", "T1", "T2", "THETA", "GF", "GM")
BOX = hbm.spyrou_model().bounds
ENERGY = hbm.spyrou_model(form="energy")
THESIS = hbm.spyrou_model()

# ---------------------------------------------------------------------------------------
# independent 3-D reference
# ---------------------------------------------------------------------------------------
PHI = 2.0 * np.pi * np.arange(16) / 16  # angle around the fiber axis: the helix's windings
H = 1e-40  # complex step: exact derivatives up to rounding, no step-size trade-off


def _collagen_w(lh, t1, t2):
    """W_c with dW_c/dλH = T1(exp(T2(λH−1)) − 1) for λH > 1 (complex-step safe)."""
    x = lh - 1.0
    if x.real <= 0.0:
        return 0.0 * x
    z = t2 * x
    if abs(z) < 1e-3:
        return t1 * x * (z / 2 + z * z / 6 + z ** 3 / 24 + z ** 4 / 120)
    return t1 * (np.exp(z) - 1.0 - z) / t2


def _energy_3d(lam, m1, m2, q, k):
    """W(F), F = diag(λ, μ1, μ2), fibers along e1, helix a(φ) = cosθ e1 + sinθ(−sinφ e2 + cosφ e3)."""
    c = q["VOLF"]
    g = c * q["GF"] + (1 - c) * q["GM"]
    w = k * g / 2 * (lam * lam + m1 * m1 + m2 * m2 - 3.0)
    f = lam - 1.0 - q["EOPT"]
    if f.real > 0:
        w = w + c * q["P1"] / 2 * f * f
    th = q["THETA"] * math.pi / 180.0
    lh2 = (math.cos(th) ** 2 * lam * lam
           + math.sin(th) ** 2 * (m1 * m1 * np.sin(PHI) ** 2 + m2 * m2 * np.cos(PHI) ** 2))
    return w + (1 - c) * sum(_collagen_w(np.sqrt(v), q["T1"], q["T2"]) for v in lh2) / PHI.size


def _grad(lam, m1, m2, q, k):
    x = [complex(lam), complex(m1), complex(m2)]
    out = []
    for i in range(3):
        y = list(x)
        y[i] += 1j * H
        out.append(_energy_3d(*y, q, k).imag / H)
    return out


def uniaxial_3d(eps, q, k=1.0):
    """σ11 with σ22 = σ33 = 0 and λ·μ1·μ2 = 1; returns (σ11, μ1, μ2, σ33)."""
    lam = 1.0 + eps

    def lateral(s):  # d/ds W(λ, e^s, e^−s/λ) = σ22 − σ33 (the incompressible lateral balance)
        m1, m2 = math.exp(s), math.exp(-s) / lam
        _, w1, w2 = _grad(lam, m1, m2, q, k)
        return m1 * w1 - m2 * w2

    # bracket in ln μ1 wide enough for every λ in [0.6, 2], not centred on the expected answer
    assert lateral(-1.0) < 0.0 < lateral(1.0)
    s = so.brentq(lateral, -1.0, 1.0, xtol=1e-15, rtol=4 * np.finfo(float).eps, maxiter=200)
    m1, m2 = math.exp(s), math.exp(-s) / lam
    w0, w1, w2 = _grad(lam, m1, m2, q, k)
    p = m1 * w1  # the pressure from σ22 = μ1·∂W/∂μ1 − p = 0
    return lam * w0 - p, m1, m2, m2 * w2 - p


def _draw(rng, n):
    return BOX[:, 0] + rng.random((n, len(NAMES))) * (BOX[:, 1] - BOX[:, 0])


# ---------------------------------------------------------------------------------------
# the energy form against the 3-D solve
# ---------------------------------------------------------------------------------------
@pytest.mark.parametrize("k", [1.0, 2.0 / 3.0])
def test_energy_form_matches_3d_equilibrium(k):
    rng = np.random.default_rng(20240518 + int(3 * k))
    model = hbm.spyrou_model(iso_factor=k, form="energy")
    thetas = _draw(rng, 30)
    n_tension = n_compression = 0
    for theta in thetas:
        q = dict(zip(NAMES, theta))
        eps = rng.uniform(-0.4, 1.0, 8)
        got = model.stress(eps, theta)
        for e, s in zip(eps, got):
            want, m1, m2, s33 = uniaxial_3d(e, q, k)
            # the lateral faces are free and the equilibrium is transversely isotropic
            assert abs(s33) <= 1e-12 * (1.0 + abs(want))
            np.testing.assert_allclose([m1, m2], [(1 + e) ** -0.5] * 2, rtol=1e-12)
            np.testing.assert_allclose(s, want, rtol=1e-8, atol=1e-14)
            n_tension += e > 0
            n_compression += e < 0
    assert n_tension > 50 and n_compression > 50


def test_3d_solve_is_not_the_thesis_form_under_compression():
    """The reference distinguishes the forms: thesis tensile, 3-D compressive at ε = −0.3."""
    q = dict(VOLF=0.9, EOPT=0.1, P1=0.1, T1=5.0, T2=10.0, THETA=60.0, GF=0.01, GM=0.01)
    theta = np.array([q[n] for n in NAMES])
    thesis = THESIS.stress(np.array([-0.3]), theta)[0]
    want = uniaxial_3d(-0.3, q)[0]
    assert thesis == pytest.approx(0.5248, abs=1e-4)  # the thesis form's +0.53 MPa (collagen 0.534)
    assert want < -0.2
    assert ENERGY.stress(np.array([-0.3]), theta)[0] == pytest.approx(want, rel=1e-10)


def _closed_form(eps, VOLF, EOPT, P1, T1, T2, THETA, GF, GM):
    """Scalar σ = λ dW/dλ of the module docstring, math module only."""
    lam = 1.0 + eps
    th = math.radians(THETA)
    c2, s2 = math.cos(th) ** 2, math.sin(th) ** 2
    lh = math.sqrt(c2 * lam * lam + s2 / lam)
    col = T1 * math.expm1(T2 * (lh - 1.0)) * (c2 * lam - s2 / (2 * lam * lam)) / lh if lh > 1.0 else 0.0
    fib = P1 * (eps - EOPT) if eps > EOPT else 0.0
    return (VOLF * GF + (1 - VOLF) * GM) * (lam * lam - 1 / lam) + lam * (VOLF * fib + (1 - VOLF) * col)


def test_energy_form_closed_form_and_ratio_to_thesis():
    rng = np.random.default_rng(5)
    eps = np.array([-0.45, -0.3, -0.1, -0.01, 0.02, 0.1, 0.3, 0.31, 0.5, 1.0, 1.5])
    for theta in _draw(rng, 20):
        q = dict(zip(NAMES, theta))
        want = [_closed_form(e, **q) for e in eps]
        np.testing.assert_allclose(ENERGY.stress(eps, theta), want, rtol=1e-11, atol=1e-15)
    # collagen only, tension beyond the onset: energy / thesis = λH'(λ) in (0, cosθ)
    theta = np.array([0.7, 0.0, 1e-4, 3.0, 12.0, 57.0, 0.0, 0.0])
    lam = np.linspace(collagen_onset_stretch(57.0) + 1e-3, 3.0, 50)
    state = hbm.State(lam - 1.0, Loading(lam - 1.0))
    p = {n: np.array([v]) for n, v in zip(NAMES, theta)}
    ratio = EnergyHelicalCollagen().stress(state, p) / HelicalCollagen().stress(state, p)
    c2, s2 = math.cos(math.radians(57.0)) ** 2, math.sin(math.radians(57.0)) ** 2
    dlh = (c2 * lam - s2 / (2 * lam ** 2)) / np.sqrt(c2 * lam ** 2 + s2 / lam)
    np.testing.assert_allclose(ratio, dlh, rtol=1e-10)
    assert np.all(ratio > 0) and np.all(ratio < math.cos(math.radians(57.0)))


def test_stress_is_lambda_times_energy_derivative():
    """σ = λ·dW/dλ with W from :func:`collagen_energy` (central differences, 4th order)."""
    theta = np.array([0.8, 0.05, 0.2, 2.0, 30.0, 56.0, 0.02, 0.03])
    q = dict(zip(NAMES, theta))
    c2 = math.cos(math.radians(56.0)) ** 2

    def w(lam):
        lh = np.sqrt(c2 * lam * lam + (1 - c2) / lam)
        g = q["VOLF"] * q["GF"] + (1 - q["VOLF"]) * q["GM"]
        f = np.maximum(lam - 1 - q["EOPT"], 0.0)
        return (g / 2 * (lam * lam + 2 / lam - 3) + q["VOLF"] * q["P1"] / 2 * f * f
                + (1 - q["VOLF"]) * collagen_energy(lh, q["T1"], q["T2"]))

    lam = np.array([0.62, 0.8, 0.97, 1.03, 1.2, 1.5])
    h = 1e-4
    dw = (8 * (w(lam + h) - w(lam - h)) - (w(lam + 2 * h) - w(lam - 2 * h))) / (12 * h)
    np.testing.assert_allclose(ENERGY.stress(lam - 1.0, theta), lam * dw, rtol=1e-8)


def test_collagen_energy_guard_and_derivative():
    lh = np.array([0.9, 1.0, 1.001, 1.05, 1.2, 1.4])
    x = np.maximum(lh - 1, 0)
    assert np.array_equal(collagen_energy(lh, 3.0, 0.0), np.zeros(6))  # T2 = 0: no collagen stress
    # small T2: W_c = T1·T2·x²/2·(1 + T2·x/3 + ...)
    np.testing.assert_allclose(collagen_energy(lh, 3.0, 1e-7), 3.0 * 1e-7 * x ** 2 / 2, rtol=1e-6, atol=1e-300)
    # both sides of the series/quotient switch at T2·x = 1e-3 agree with the exact value,
    # T1·x·z·Σ z^k/(k+2)! (12 terms: exact to rounding at z ~ 1e-3)
    for t2 in (1e-3 / 0.05 * (1 - 1e-9), 1e-3 / 0.05 * (1 + 1e-9), 0.3, 5.0):
        z = t2 * 0.05
        exact = 3.0 * 0.05 * z * sum(z ** j / math.factorial(j + 2) for j in range(12))
        assert collagen_energy(1.05, 3.0, t2) == pytest.approx(exact, rel=1e-12)
    # dW_c/dλH = T1·(exp(T2·x) − 1)
    t1, t2, h = 2.0, 40.0, 1e-6
    lh = np.array([1.01, 1.1, 1.3])
    dw = (collagen_energy(lh + h, t1, t2) - collagen_energy(lh - h, t1, t2)) / (2 * h)
    np.testing.assert_allclose(dw, t1 * np.expm1(t2 * (lh - 1)), rtol=1e-7)


def test_energy_jacobian_matches_finite_differences():
    rng = np.random.default_rng(11)
    thetas = _draw(rng, 25)
    eps = np.array([-0.4, -0.2, -0.05, 0.05, 0.25, 0.35, 0.6, 0.9])
    assert ENERGY.has_analytic_jacobian
    jac = ENERGY.stress_jacobian(eps, thetas)
    width = BOX[:, 1] - BOX[:, 0]
    for j in range(len(NAMES)):
        h = 1e-6 * width[j]
        up, dn = thetas.copy(), thetas.copy()
        up[:, j] += h
        dn[:, j] -= h
        fd = (ENERGY.stress(eps, up) - ENERGY.stress(eps, dn)) / (2 * h)
        scale = np.abs(ENERGY.stress(eps, thetas)) / width[j] + 1e-12
        # kinks (EOPT, collagen onset) are avoided by the chosen strains / random draws
        np.testing.assert_array_less(np.abs(jac[..., j] - fd), 1e-5 * (np.abs(fd) + scale), err_msg=NAMES[j])


# ---------------------------------------------------------------------------------------
# properties over the prior box
# ---------------------------------------------------------------------------------------
unit = st.floats(0.0, 1.0)


@settings(max_examples=300, deadline=None)
@given(u=st.lists(unit, min_size=8, max_size=8), eps=st.floats(-0.5, -1e-9), zero_g=st.booleans(),
       k=st.sampled_from([1.0, 2.0 / 3.0]))
def test_energy_form_is_compressive_under_compression(u, eps, zero_g, k):
    theta = BOX[:, 0] + np.array(u) * (BOX[:, 1] - BOX[:, 0])
    if zero_g:
        theta[[6, 7]] = 0.0
    s = hbm.spyrou_model(iso_factor=k, form="energy").stress(np.array([eps, 0.0]), theta)
    assert s[1] == 0.0  # exactly, whatever the parameters
    if zero_g:
        assert s[0] <= 0.0
    else:
        assert s[0] < 0.0


def test_thesis_collagen_is_tensile_under_compression_energy_collagen_is_not():
    """The defect the energy form repairs, over the whole box (T1, T2 > 0) and ε in [−0.5, 0)."""
    rng = np.random.default_rng(3)
    thetas = _draw(rng, 2000)
    thetas[:, 3:5] = np.maximum(thetas[:, 3:5], 1e-3)
    eps = -np.geomspace(1e-3, 0.5, 30)
    state = hbm.State(eps, Loading(eps))
    p = {n: thetas[:, i, None] for i, n in enumerate(NAMES)}
    assert np.all(HelicalCollagen().stress(state, p) > 0)  # THETA > 54.7°: the helix stretches
    assert np.all(EnergyHelicalCollagen().stress(state, p) < 0)


# ---------------------------------------------------------------------------------------
# the option itself
# ---------------------------------------------------------------------------------------
def test_form_option_and_thesis_default_unchanged():
    rng = np.random.default_rng(9)
    thetas = _draw(rng, 200)
    eps = np.linspace(-0.5, 2.0, 101)
    thesis = hbm.spyrou_model(form="thesis")
    assert thesis.name == THESIS.name == "spyrou"
    assert [type(e) for e in thesis.effects] == [type(e) for e in THESIS.effects]
    assert type(thesis.effects[-1]) is HelicalCollagen and type(ENERGY.effects[-1]) is EnergyHelicalCollagen
    assert np.array_equal(thesis.stress(eps, thetas), THESIS.stress(eps, thetas))
    assert ENERGY.name == "spyrou(form=energy)"
    assert hbm.spyrou_model(2 / 3, form="energy").name == "spyrou(k_iso=0.6667, form=energy)"
    assert ENERGY.effect_names == THESIS.effect_names == hbm.model.BASE_EFFECTS
    assert ENERGY.parameter_names == NAMES
    # matrix and fibers are the same; with T1 = 0 the forms agree bitwise
    thetas[:, 3] = 0.0
    assert np.array_equal(ENERGY.stress(eps, thetas), THESIS.stress(eps, thetas))
    with pytest.raises(HbmError, match="energy"):
        hbm.spyrou_model(form="hyperelastic")


# ---------------------------------------------------------------------------------------
# compression_check
# ---------------------------------------------------------------------------------------
def test_compression_check_tension_passes():
    assert compression_check(np.linspace(0.0, 0.45, 40)) is None
    # a tension test that starts slightly negative: exempt leading points / above −0.01
    assert compression_check(np.r_[-0.03, -0.02, -0.015, np.linspace(-0.005, 0.4, 37)]) is None
    assert compression_check(np.linspace(-0.009, 0.4, 40)) is None
    assert compression_check(np.r_[-0.01, -0.01, -0.01, -0.01, np.linspace(0, 0.4, 36)]) is None  # not below


def test_compression_check_flags_compression_and_names_energy_form():
    msg = compression_check(np.linspace(0.0, -0.3, 20), name="rat9")
    assert msg is not None and msg.startswith("rat9: 17 of 20 points are compressive")
    assert "form='energy'" in msg and "--form energy" in msg and "\n" not in msg
    assert compression_check(np.linspace(0.0, -0.3, 20), form="energy") is None
    with pytest.raises(HbmError):
        compression_check([0.0, -0.1], form="neo")


def test_compression_check_thresholds():
    base = np.linspace(0.0, 0.4, 40)
    three, four = base.copy(), base.copy()
    three[[10, 20, 30]] = -0.02  # 3 of 40 beyond the lead: ≤ 3 and ≤ 10 % -> passes
    four[[10, 20, 30, 35]] = -0.02  # 4 -> more than 3
    assert compression_check(three) is None
    assert compression_check(four) is not None
    short = np.linspace(0.0, 0.2, 9)
    short[5] = -0.05  # 1 of 9 > 10 %
    assert compression_check(short) is not None


def test_compression_check_exempts_the_start_of_each_history():
    one = np.r_[-0.03, -0.02, -0.015, np.linspace(0.0, 0.3, 10)]
    strain = np.r_[one, one]
    time = np.r_[np.arange(13.0), np.arange(13.0)]  # the time restarts: two histories
    assert compression_check(strain, time=time) is None
    assert compression_check(Loading(strain, time)) is None
    # one history (time continues): the second pre-load is 3 compressive points of 26 > 10 %
    assert compression_check(strain, time=np.arange(26.0)) is not None
