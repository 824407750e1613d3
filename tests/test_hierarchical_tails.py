"""Tails the reused stage-1 samples cannot see (issue 15): the reuse diagnostic against analytic
uncovered mass, and the defensive reference draws against an analytic p(d|ψ)."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.stats import norm

from hbm.errors import HbmError
from hbm.samplers.hierarchical import (HierarchicalModel, defensive_log_weights, reuse_diagnostics,
                                       reuse_unreliable)

BOX = np.array([[-10.0, 10.0]])


def _raw(model: HierarchicalModel, mu: float, sd: float) -> np.ndarray:
    return np.array([[mu, np.log(sd)]])


def test_uncovered_mass_matches_analytic_for_a_one_sided_likelihood():
    """Likelihood flat below 0 and zero above (a parameter bounded only from above); the stage-1
    samples stop at −4 (they never reached the tail).  Under the population N(−3, 1) the
    conditional posterior's mass below −4 is Φ(−1)/Φ(3) exactly; flat extrapolation is exact here."""
    model = HierarchicalModel(["x"], BOX)
    rng = np.random.default_rng(1)
    x = rng.uniform(-4.0, 0.0, (4000, 1))
    truth = norm.cdf(-1.0) / norm.cdf(3.0)
    r = reuse_diagnostics(model, x, _raw(model, -3.0, 1.0), log_likelihood=np.zeros(4000))
    assert r["uncovered"] == pytest.approx(truth, abs=0.03)
    assert r["likelihood_slope"]
    # a population centred well inside the samples: nothing uncovered
    r_in = reuse_diagnostics(model, x, _raw(model, -2.0, 0.3), log_likelihood=np.zeros(4000))
    assert r_in["uncovered"] < 1e-3


def test_uncovered_mass_uses_the_likelihood_slope_at_the_edge():
    """Gaussian likelihood N(0, 1) (samples reach about ±3.6) and the population N(2, 1): the
    conditional posterior is N(1, 1/2) and its mass beyond the samples is known exactly.  The
    extrapolation with the likelihood's log-slope at the edge is within a small factor of it (on
    the conservative side); flat extrapolation (no log-likelihoods) overstates it by ~100x and is
    therefore reported but not a trigger."""
    model = HierarchicalModel(["x"], BOX)
    rng = np.random.default_rng(2)
    x = rng.standard_normal((4000, 1))
    ll = norm.logpdf(x[:, 0])
    raw = _raw(model, 2.0, 1.0)
    s2 = np.sqrt(0.5)
    exact = norm.cdf((x.min() - 1.0) / s2) + norm.sf((x.max() - 1.0) / s2)
    sloped = reuse_diagnostics(model, x, raw, log_likelihood=ll)
    flat = reuse_diagnostics(model, x, raw)
    assert 0.5 * exact < sloped["uncovered"] < 10 * exact < flat["uncovered"]
    assert not flat["likelihood_slope"]
    flags = reuse_unreliable({"a": {**flat, "uncovered": 0.5}, "b": {**sloped, "uncovered": 0.5}})
    assert flags["a"] == (False, []) and flags["b"][0]


def test_psis_khat_flags_a_narrow_population_in_the_samples_tail():
    """Ratios N(x; mu, sd)/p0 on standard-normal samples: bounded and even for the population
    N(0, 1) (k̂ < 0.5), a handful of tail samples carry the weight for N(3, 0.3) (k̂ > 0.7)."""
    model = HierarchicalModel(["x"], BOX)
    x = np.random.default_rng(3).standard_normal((4000, 1))
    ok = reuse_diagnostics(model, x, _raw(model, 0.0, 1.0))
    bad = reuse_diagnostics(model, x, _raw(model, 3.0, 0.3))
    assert ok["khat_median"] < 0.5 and bad["khat_median"] > 0.7
    assert reuse_unreliable({"bad": bad})["bad"][0] and not reuse_unreliable({"ok": ok})["ok"][0]


def _log_pdh_one_sided(mu: float, sd: float, b: float = np.log(0.1)) -> float:
    """Exact log p(d|ψ)/Z for θ ~ U(0.001, 1), L = 1[θ ≤ 0.1], population z = log θ ~ N(mu, sd)
    truncated to [log 0.001, 0]: ∫_{z ≤ b} N_trunc / Z with Z = (0.1 − 0.001)/0.999."""
    lo, hi = np.log(1e-3), 0.0
    num = norm.cdf((b - mu) / sd) - norm.cdf((lo - mu) / sd)
    den = norm.cdf((hi - mu) / sd) - norm.cdf((lo - mu) / sd)
    return float(np.log(num / den) - np.log(0.099 / 0.999))


def test_defensive_reference_draws_recover_the_tail_of_a_one_sided_posterior():
    """The issue's failure in one dimension: c·P1 uniform a priori, the data bound it only from above
    (L = 1[θ ≤ 0.1]), so in z = log θ the stage-1 posterior falls off as e^z and 300 samples barely
    reach the small values a population at log 0.002 puts its mass on.  The plain reuse estimate of
    log p(d|ψ) is low and scattered over seeds; stage-1 samples plus reference draws flat in z,
    weighted as a deterministic mixture, match the closed form."""
    model = HierarchicalModel(["x"], np.array([[1e-3, 1.0]]), transforms={"x": "log"})
    mu, sd = np.log(0.002), 0.5
    raw = _raw(model, mu, sd)
    exact = _log_pdh_one_sided(mu, sd)
    log_z = np.log(0.099 / 0.999)
    plain, mixed = [], []
    for seed in range(20):
        rng = np.random.default_rng(seed)
        post = rng.uniform(1e-3, 0.1, 300)
        plain.append(model.log_mean_ratio(post[:, None], raw)[0][0])
        # reference: flat in z on [log 0.001, 0]: q(θ) = 1/(θ·log 1000), ρ = q/p0 with p0 = 1/0.999
        ref = np.exp(rng.uniform(np.log(1e-3), 0.0, 300))
        rows = np.concatenate([post, ref])
        ll = np.where(rows <= 0.1, 0.0, -np.inf)
        keep = np.isfinite(ll)  # draws with zero likelihood are dropped and counted
        log_rho = -np.log(rows * np.log(1e3)) + np.log(0.999)
        lw = defensive_log_weights(ll[keep], log_rho[keep], log_z, 300, 300)
        lp = np.full(keep.sum(), -np.log(0.999))
        lse = model.log_mean_ratio(rows[keep][:, None], raw, log_prior=lp - lw)[0][0]
        mixed.append(lse)
    plain, mixed = np.array(plain), np.array(mixed)
    assert abs(np.median(mixed) - exact) < 0.05 and np.std(mixed) < 0.12
    assert np.median(plain) < exact - 0.05 and np.std(plain) > 2 * np.std(mixed)


def test_defensive_log_weights_bad_input_and_bound():
    lw = defensive_log_weights(np.zeros(5), np.zeros(5), 0.0, 3, 4)
    # posterior rows: ω = post/q_mix ≤ 1/a, a = 3/7, times the kept/drawn factor 5/7
    assert np.all(lw <= np.log(7 / 3) + np.log(5 / 7) + 1e-12)
    with pytest.raises(HbmError):
        defensive_log_weights(np.zeros(5), np.zeros(4), 0.0, 3, 4)
    with pytest.raises(HbmError):
        defensive_log_weights(np.zeros(5), np.zeros(5), 0.0, 3, 1)
