"""Tests of the detective's noise check (hbm.detective.noise_check): the model-free noise
estimate, the AR(1) simulation and its whitening, and the misfit-window scan, each against a
known generator."""

from __future__ import annotations

import numpy as np
import pytest

from hbm.detective.noise_check import misfit_windows, model_free_noise, simulate_ar1, whitener


@pytest.mark.parametrize("rho", [0.0, 0.6])
def test_model_free_noise_recovers_sigma_and_rho(rho):
    """Smooth exponential curve + AR(1) noise: the difference estimator recovers (σ, ρ)."""
    rng = np.random.default_rng(3)
    n, sig = 2000, 0.01
    e = rng.standard_normal(n)
    x = np.empty(n)
    x[0] = e[0]
    for t in range(1, n):  # test-only generator loop (reference implementation)
        x[t] = rho * x[t - 1] + np.sqrt(1 - rho ** 2) * e[t]
    y = 0.05 * np.expm1(4 * np.linspace(0, 1, n)) + sig * x
    est = model_free_noise(y)
    assert est["sigma"] == pytest.approx(sig, rel=0.1)
    assert est["rho"] == pytest.approx(rho, abs=0.1)


@pytest.mark.parametrize("rho", [0.0, 0.7])
def test_misfit_windows_family_wise_rate_and_power(rho):
    """Pure AR(1) noise: the scan raises a window in ≈5 % of series (not the ~100 % a naive
    iid threshold gives at rho 0.7); a bump of 1.2 sd over 30 points is found with its sign
    and location."""
    rng = np.random.default_rng(11)
    n, reps = 150, 120
    strain = np.linspace(0, 0.3, n)
    seg = np.zeros(n, int)
    from scipy.signal import lfilter
    e = rng.standard_normal((reps, n))
    e[:, 1:] *= np.sqrt(1 - rho ** 2)
    z = lfilter([1.0], [1.0, -rho], e, axis=-1)
    alarms = sum(bool(misfit_windows(z[i], strain, seg, rho, seed=i)[0]) for i in range(reps))
    assert alarms / reps <= 0.12
    bump = np.where((strain > 0.1) & (strain < 0.16), 1.2 if rho == 0 else 2.5, 0.0)
    found = misfit_windows(z[0] + bump, strain, seg, rho, seed=0)[0]
    assert found and found[0]["sign"] == 1
    assert found[0]["eps_lo"] < 0.16 and found[0]["eps_hi"] > 0.1


@pytest.mark.parametrize("rho", [0.0, 0.6, -0.4])
def test_simulate_ar1_matches_the_recursion_and_whitener_inverts_it(rho):
    """simulate_ar1 is x_0 = e_0, x_t = ρ x_{t−1} + √(1−ρ²) e_t on the generator's normals
    (checked against the explicit recursion), and the whitener recovers those normals exactly,
    also across a restart of the process."""
    n, k = 120, 3
    e = np.random.default_rng(7).standard_normal((k, n))
    x = simulate_ar1(np.random.default_rng(7), (k, n), rho)
    ref = np.empty_like(e)
    ref[:, 0] = e[:, 0]
    for t in range(1, n):  # test-only reference loop
        ref[:, t] = rho * ref[:, t - 1] + np.sqrt(1 - rho ** 2) * e[:, t]
    np.testing.assert_allclose(x, ref, rtol=1e-12, atol=1e-12)
    first = np.zeros(n, bool)
    first[0] = True
    sd = np.linspace(0.5, 2.0, n)  # heteroscedastic marginal sd: whitening divides it out first
    w = whitener(sd, rho, first)
    np.testing.assert_allclose(w(sd[:, None] * x.T), e.T, rtol=1e-10, atol=1e-10)   # (n, k)
    np.testing.assert_allclose(w(sd * x[0]), e[0], rtol=1e-10, atol=1e-10)          # (n,)
    # two independent histories glued together: the second restarts at its own first point
    y = np.concatenate([x[1, :60], x[2, :60]])
    first2 = np.zeros(n, bool)
    first2[[0, 60]] = True
    u = whitener(np.ones(n), rho, first2)(y)
    np.testing.assert_allclose(u, np.concatenate([e[1, :60], e[2, :60]]), rtol=1e-10, atol=1e-10)


def test_simulate_ar1_is_stationary_with_unit_variance():
    rho = 0.7
    x = simulate_ar1(np.random.default_rng(1), (20000, 30), rho)
    assert x[:, 0].var() == pytest.approx(1.0, abs=0.04)
    assert x[:, -1].var() == pytest.approx(1.0, abs=0.04)
    assert np.corrcoef(x[:, 10], x[:, 11])[0, 1] == pytest.approx(rho, abs=0.03)
