"""The compiled diagonal path (hbm.model.energy3d.diagonal, hbm.model.loadcases.lateral_kernel) against the
numpy path it replaces, which stays the reference (an ``Energy3D`` whose ``kernel`` is ``None``).

Over the prior box (10 seeds x 20 draws) and strains -40..+44 %: principal stresses and tangents, every
diagonal mode's stresses, and uniaxial_c's lateral root, both readings."""

import numpy as np
import pytest

import independent3d as ind
from hbm.errors import HbmError
from hbm.model import spyrou_model
from hbm.model.energy3d import ConeCollagen, ConeFamilies, Energy3D, GstCollagen, diagonal
from hbm.model.loadcases import predict_observables
from hbm.model.loadcases import uniaxial_c as uc

MODEL = spyrou_model(form="energy")
STRAIN = np.linspace(-0.4, 0.44, 43)
DIAGONAL = ("uniaxial_f", "planar_f_hold_c", "planar_c_hold_f", "planar_c_hold_n", "biaxial_fc", "biaxial_cn")


class NumpyEnergy(Energy3D):
    """The numpy path: principal by :meth:`Energy3D.principal_numpy`, uniaxial_c by the numpy solver."""

    kernel = None


def box(n_per_seed=20, seeds=range(10)):
    """Parameter mapping (n, 1) of uniform prior-box draws, 10 seeds, plus the independent module's sets."""
    lo, hi = MODEL.bounds.T
    theta = np.vstack([lo + (hi - lo) * np.random.default_rng(s).random((n_per_seed, MODEL.n_params)) for s in seeds]
                      + [[[prm[k] for k in MODEL.parameter_names] for prm in (ind.CALVO, ind.HAWKINS)]])
    return MODEL._params(theta)


def scaled_error(a, b):
    """max |a − b| / max over the components of |b|, per element (tuples of arrays); where every component of b
    is 0 (the reference state) the difference itself."""
    scale = np.maximum.reduce([np.abs(v) for v in b])
    scale = np.where(scale > 0, scale, 1.0)
    return max(float(np.max(np.abs(x - y) / scale)) for x, y in zip(a, b))


@pytest.mark.parametrize("reading", ["cone", "gst"])
def test_principal_kernel_matches_numpy(reading):
    """τ and the tangent at the kinematics of every diagonal mode (uniaxial_c with the lateral split drawn at
    random): ≤ 1e-12 of the element's largest component (measured ≤ 4e-14)."""
    p = box()
    fast, ref = Energy3D(collagen3d=reading), NumpyEnergy(collagen3d=reading)
    assert fast.kernel is not None and ref.kernel is None
    e = np.log1p(STRAIN)
    split = np.random.default_rng(7).uniform(0.0, 1.0, (p["T2"].shape[0], STRAIN.size))
    kinematics = {"uniaxial_c": (-split * e, e + 0 * split, (split - 1.0) * e), "uniaxial_f": (e, -0.5 * e, -0.5 * e),
                  "planar": (e, 0 * e, -e), "biaxial_cn": (-1.5 * e, e, 0.5 * e)}
    for name, ek in kinematics.items():
        for tangent in (False, True):
            tau, c = fast.principal(p, ek, tangent)
            tau_ref, c_ref = ref.principal(p, ek, tangent)
            assert tau[0].shape == np.broadcast(*tau_ref).shape
            assert scaled_error(tau, tau_ref) <= 1e-12, (name, tangent)
            if tangent:
                flat = [c[i][j] for i in range(3) for j in range(3)]
                flat_ref = [c_ref[i][j] for i in range(3) for j in range(3)]
                assert scaled_error(flat, flat_ref) <= 1e-12, (name, "tangent")
                np.testing.assert_array_equal(c[0][2], c[2][0])


@pytest.mark.parametrize("reading", ["cone", "gst"])
def test_prescribed_modes_match_numpy(reading):
    """Every prescribed-F diagonal mode: the loaded stress ≤ 1e-12 relative to itself, stress_2 relative to the
    element's largest stress; lateral strains of uniaxial_f identical."""
    p = box()
    fast, ref = Energy3D(collagen3d=reading), NumpyEnergy(collagen3d=reading)
    for mode in DIAGONAL:
        s2 = 0.5 * STRAIN if mode.startswith("biaxial") else None
        got, want = predict_observables(fast, mode, p, STRAIN, s2), predict_observables(ref, mode, p, STRAIN, s2)
        nonzero = STRAIN != 0
        rel = np.abs(got["stress"] - want["stress"])[:, nonzero] / np.abs(want["stress"])[:, nonzero]
        assert rel.max() <= 1e-12, mode
        if "stress_2" in want:
            scale = np.maximum(np.abs(want["stress"]), np.abs(want["stress_2"]))[:, nonzero]
            assert (np.abs(got["stress_2"] - want["stress_2"])[:, nonzero] / scale).max() <= 1e-12, mode
        for k in set(want) - {"stress", "stress_2"}:
            np.testing.assert_array_equal(got[k], want[k])


def lateral(u, ec):
    """(strain_f, strain_n) and their per-element scale max(|strain_f|, |strain_n|)."""
    f, n = np.expm1(u), np.expm1(-u - ec)
    return f, n, np.maximum(np.abs(f), np.abs(n))


def residual(principal, p, u, ec):
    """(τ_ff − τ_nn, σ_cc, the round-off 8ε·(|τ_ff| + |τ_nn|)) at the lateral root ``u``, by ``principal``."""
    tau, _ = principal(p, (u, ec, -u - ec))
    return tau[0] - tau[2], tau[1] - 0.5 * (tau[0] + tau[2]), 8 * np.finfo(float).eps * (abs(tau[0]) + abs(tau[2]))


@pytest.mark.parametrize("reading", ["cone", "gst"])
def test_lateral_root_matches_the_numpy_solver(reading):
    """uniaxial_c over the box x -40..+44 %.  Isotropic start (the numpy solver's iterates): σ and the lateral
    strains ≤ 1e-12 of the numpy solver's (measured ≤ 1e-13).  Warm start (the default): the exact root to
    round-off -- residual |τ_ff − τ_nn| ≤ 1e-13·|σ| (the numpy solver stops at 1e-12), and the numpy solver's own
    stopping test holds at it, evaluated by numpy -- so it differs from the numpy solver's result by that
    solver's stopping error only (≤ 1e-11 here, measured ≤ 4.5e-12)."""
    p = box()
    fast, ref = Energy3D(collagen3d=reading), NumpyEnergy(collagen3d=reading)
    shape = (p["T2"].shape[0], STRAIN.size)
    ec = np.broadcast_to(np.log1p(STRAIN), shape)
    want = predict_observables(ref, "uniaxial_c", p, STRAIN)
    u_ref = np.log1p(want["strain_f"])
    f_ref, n_ref, scale = lateral(u_ref, ec)
    nonzero = STRAIN != 0
    for warm in (False, True):
        u, sigma, evaluations = uc._lateral_root_compiled(fast, p, STRAIN, shape, warm=warm)
        f, n, _ = lateral(u, ec)
        lat = max(np.max(np.abs(f - f_ref)[:, nonzero] / scale[:, nonzero]),
                  np.max(np.abs(n - n_ref)[:, nonzero] / scale[:, nonzero]))
        sig = np.max(np.abs(sigma - want["stress"])[:, nonzero] / np.abs(want["stress"][:, nonzero]))
        bound = 1e-11 if warm else 1e-12
        assert lat <= bound and sig <= bound, (warm, lat, sig)
        assert evaluations.shape == (shape[0], np.unique(STRAIN).size)
    got = predict_observables(fast, "uniaxial_c", p, STRAIN)
    u = np.log1p(got["strain_f"])
    g, sigma, floor = residual(fast.principal, p, u, ec)
    assert np.all(np.abs(g) <= 1e-13 * np.abs(sigma) + floor)
    assert np.all(np.abs(sigma - got["stress"]) <= 1e-12 * np.abs(sigma) + floor)
    g, sigma, floor = residual(ref.principal, p, u, ec)      # the numpy solver's stopping test, by numpy
    assert np.all(np.abs(g) <= uc.RTOL * np.abs(sigma) + floor)
    assert np.all(got["strain_f"][:, ~nonzero] == 0) and np.all(got["stress"][:, ~nonzero] == 0)


def test_warm_start_and_distinct_strains():
    """The warm start halves the energy evaluations on a loading ramp; repeated strains (a hold) are solved once
    and give the same numbers as the ramp alone; each particle's row is independent of the others (bitwise)."""
    p = box(n_per_seed=10, seeds=range(3))
    energy = Energy3D()
    ramp = np.linspace(-0.3, -0.01, 30)
    shape = (p["T2"].shape[0], ramp.size)
    cold = uc._lateral_root_compiled(energy, p, ramp, shape, warm=False)[2]
    warm = uc._lateral_root_compiled(energy, p, ramp, shape, warm=True)[2]
    assert warm.mean() <= 0.6 * cold.mean(), (warm.mean(), cold.mean())
    hold = np.concatenate([ramp, np.full(33, -0.3)])
    with_hold = predict_observables(energy, "uniaxial_c", p, hold)
    alone = predict_observables(energy, "uniaxial_c", p, ramp)
    for k in alone:
        np.testing.assert_array_equal(with_hold[k][:, :30], alone[k])
        np.testing.assert_array_equal(with_hold[k][:, 30:], np.repeat(alone[k][:, :1], 33, axis=1))
    one = predict_observables(energy, "uniaxial_c", {k: v[3, 0] for k, v in p.items()}, ramp)
    np.testing.assert_array_equal(one["stress"], alone["stress"][3])


def test_parameters_along_the_points_and_non_finite():
    """Parameters varying along the points (each element its own row) and non-finite parameters (NaN outputs,
    no refusal) behave as on the numpy path."""
    p = {k: np.broadcast_to(v[:4], (4, STRAIN.size)).copy() for k, v in box(n_per_seed=2, seeds=range(2)).items()}
    p["THETA"] = np.linspace(55.0, 60.0, STRAIN.size) + 0 * p["THETA"]
    p["T1"][1, 5] = np.nan
    got = predict_observables(Energy3D(), "uniaxial_c", p, STRAIN)
    want = predict_observables(NumpyEnergy(), "uniaxial_c", p, STRAIN)
    for k in want:
        np.testing.assert_array_equal(np.isnan(got[k]), np.isnan(want[k]))
    assert np.isnan(got["stress"][1, 5]) and np.isfinite(got["stress"]).sum() == got["stress"].size - 1
    ok = np.isfinite(want["stress"]) & (STRAIN != 0)
    assert np.max(np.abs(got["stress"] - want["stress"])[ok] / np.abs(want["stress"][ok])) <= 1e-11


@pytest.mark.parametrize("energy", [Energy3D(), NumpyEnergy()])
def test_refusal_without_a_unique_lateral_stretch(energy):
    """No shear modulus, no collagen: the lateral stretch is free; both paths refuse with the same message."""
    limp = {k: np.array([[v], [v]]) for k, v in ind.CALVO.items()}
    limp["GF"][1] = limp["GM"][1] = limp["T1"][1] = 0.0
    with pytest.raises(HbmError, match=r"no unique traction-free lateral stretch for 2 of 4 .*strain 0\.1 at "
                                       r"VOLF=0\.9.*GF=0.*where nothing resists"):
        predict_observables(energy, "uniaxial_c", limp, np.array([0.1, 0.2]))


def test_kernel_only_where_its_laws_hold():
    """The kernel runs for the cone (any node count) and gst readings of Energy3D and of a subclass that keeps the
    laws; a replaced fibre or segment law, another reading or the thesis form run the numpy path."""

    class Counting(Energy3D):
        def principal(self, p, e, tangent=False):
            return super().principal(p, e, tangent)

    class OtherFibres(Energy3D):
        @staticmethod
        def _fibre_force(p, lf_minus_1):
            return 2.0 * Energy3D._fibre_force(p, lf_minus_1)

    class OtherSegments(ConeCollagen):
        def segment_force(self, x, t1, t2):
            return 2.0 * super().segment_force(x, t1, t2)

    assert ConeCollagen.kernel_code == diagonal.CONE and GstCollagen.kernel_code == diagonal.GST
    assert Energy3D().kernel == diagonal.CONE and Energy3D(collagen3d="gst").kernel == diagonal.GST
    assert Counting().kernel == diagonal.CONE
    for energy in (OtherFibres(), Energy3D(collagen3d=OtherSegments()), Energy3D(collagen3d=ConeFamilies(24)),
                   Energy3D(form="thesis")):
        assert energy.kernel is None
    fine = Energy3D(collagen3d=ConeCollagen(32))
    assert fine.kernel == 0
    p = box(n_per_seed=5, seeds=range(2))
    e = np.log1p(STRAIN)
    ek = (-0.3 * e, e, -0.7 * e)
    assert scaled_error(fine.principal(p, ek, True)[0], fine.principal_numpy(p, ek, True)[0]) <= 1e-12
    # a replaced law changes the numbers: the dispatch matters
    doubled = OtherFibres().principal(p, (e, -0.5 * e, -0.5 * e))[0][0]
    assert np.any(doubled != Energy3D().principal(p, (e, -0.5 * e, -0.5 * e))[0][0])
