"""Noise models (hbm.likelihood.noise) against independent truths: dense Gaussian densities, the AR(1)
covariance σ²ρ^|i−j| per history, Monte-Carlo moments of the simulator and of the score, finite
differences, an lfilter implementation of the recursion, and a user noise model registered
without touching hbm."""

import math

import numpy as np
import pytest
import xarray as xr
from scipy import stats
from scipy.signal import lfilter

from hbm.errors import HbmError
from hbm.fit import pointwise_log_likelihood, posterior_predictive
from hbm.likelihood import make_likelihood
from hbm.model import spyrou_model
from hbm.likelihood.noise import (
    AR1Noise, NOISE_REGISTRY, NoiseModel, eq120_weights, get_noise, make_noise, noise_model_names, register_noise)

P = 25
STARTS = np.zeros(P, bool)
STARTS[[0, 9, 17]] = True                     # three loading histories
HIST = np.cumsum(STARTS)
X = np.column_stack([np.ones(P), np.linspace(0.0, 1.0, P)])   # linear mean model m = X·beta
BETA = np.array([0.05, 0.3])
ROWS = {"iid": [0.004], "weighted": [0.2], "proportional": [0.003, 0.08], "ar1": [0.004, 0.7]}


def ar1_cov(sd, rho):
    """Dense AR(1) covariance: sd_i sd_j rho^|i−j| within a history, 0 across histories."""
    i = np.arange(P)
    corr = rho ** np.abs(i[:, None] - i[None, :]) * (HIST[:, None] == HIST[None, :])
    sd = np.broadcast_to(np.asarray(sd, float), (P,))
    return corr * np.outer(sd, sd)


def observed(seed=0):
    return X @ BETA + np.random.default_rng(seed).normal(0.0, 0.004, P)


def noise_model(name, y=None):
    return make_noise(name, observed=observed() if y is None else y, history_starts=STARTS)


def dense_cov(name, nm, q, m):
    """Covariance of the residual from first principles (not from the noise classes)."""
    if name == "ar1":
        return ar1_cov(q[0], q[1])
    if name == "iid":
        sd = np.full(P, q[0])
    elif name == "weighted":
        y = nm.observed
        sd = q[0] * np.maximum(np.abs(y).max() / 10, np.abs(y))
    else:
        sd = np.sqrt(q[0] ** 2 + (q[1] * m) ** 2)
    return np.diag(sd ** 2)


# ------------------------------------------------------------------------------------- densities
@pytest.mark.parametrize("name", list(ROWS))
def test_loglik_and_pointwise_equal_dense_multivariate_normal(name):
    nm = noise_model(name)
    rng = np.random.default_rng(1)
    n = 6
    q = np.array(ROWS[name]) * rng.uniform(0.7, 1.3, (n, len(ROWS[name])))
    m = X @ BETA + rng.normal(0, 0.002, (n, P))
    expect = [stats.multivariate_normal(m[i], dense_cov(name, nm, q[i], m[i])).logpdf(nm.observed)
              for i in range(n)]
    np.testing.assert_allclose(nm.loglik(q, m.copy()), expect, rtol=1e-11)
    np.testing.assert_allclose(nm.pointwise(q, m).sum(axis=1), expect, rtol=1e-11)
    # overwrite=True may reuse the model stress as scratch: same value
    np.testing.assert_allclose(nm.loglik(q, m.copy(), overwrite=True), expect, rtol=1e-11)


def test_ar1_pointwise_terms_are_the_conditional_densities():
    nm = noise_model("ar1")
    s, rho = ROWS["ar1"]
    r = nm.observed - X @ BETA
    pw = nm.pointwise(np.array([[s, rho]]), (X @ BETA)[None])[0]
    for t in range(P):
        if STARTS[t]:
            expect = stats.norm.logpdf(r[t], 0.0, s)
        else:
            expect = stats.norm.logpdf(r[t], rho * r[t - 1], s * math.sqrt(1 - rho * rho))
        assert pw[t] == pytest.approx(expect, rel=1e-12)


def test_ar1_innovations_exist_once_and_are_white():
    nm = noise_model("ar1")
    q = np.array([ROWS["ar1"]])
    r = (nm.observed - X @ BETA)[None]
    u, v = nm.innovations(q, r)
    s, rho = ROWS["ar1"]
    # u = L⁻¹ r with the Cholesky-free AR(1) inverse: Cov(u) = diag(v) exactly
    a = np.eye(P) - rho * np.eye(P, k=-1) * (~STARTS)[:, None]
    np.testing.assert_allclose(u[0], a @ r[0], rtol=1e-13, atol=1e-17)
    np.testing.assert_allclose(a @ ar1_cov(s, rho) @ a.T, np.diag(v[0]), atol=1e-18)


# ------------------------------------------------------------------------------------- whitening
@pytest.mark.parametrize("name", list(ROWS))
def test_whitening_gives_identity_covariance(name):
    nm = noise_model(name)
    q = np.array(ROWS[name])
    m = X @ BETA
    w = nm.whiten(np.eye(P), q, model_stress=m)          # the matrix W of the linear map
    cov = dense_cov(name, nm, q, m)
    np.testing.assert_allclose(w @ cov @ w.T, np.eye(P), atol=1e-10)
    # columns are whitened one by one: W·J for a Jacobian, W·r for a residual
    np.testing.assert_allclose(nm.whiten(X, q, model_stress=m), w @ X, rtol=1e-12, atol=1e-12)
    r = nm.observed - m
    np.testing.assert_allclose(nm.whiten(r, q, model_stress=m), w @ r, rtol=1e-12, atol=1e-12)


def test_ar1_whitening_with_an_external_sd_and_rho_zero():
    nm = noise_model("ar1")
    sd = np.linspace(0.002, 0.006, P)                     # e.g. a model-free, per-point sd
    w = nm.whiten(np.eye(P), (np.nan, 0.55), sd=sd)
    np.testing.assert_allclose(w @ ar1_cov(sd, 0.55) @ w.T, np.eye(P), atol=1e-10)
    a = np.random.default_rng(2).normal(size=(P, 3))
    np.testing.assert_array_equal(nm.whiten(a, (np.nan, 0.0), sd=sd), a / sd[:, None])


# ------------------------------------------------------------------------------------- simulation
@pytest.mark.parametrize("name", list(ROWS))
def test_simulated_noise_has_the_model_covariance(name):
    nm = noise_model(name)
    q = np.array(ROWS[name])
    m = X @ BETA
    n = 40_000
    draws = nm.simulate(np.random.default_rng(3), np.tile(q, (n, 1)), np.tile(m, (n, 1)))
    cov = dense_cov(name, nm, q, m)
    sd = np.sqrt(np.diag(cov))
    emp = np.cov(draws, rowvar=False)
    # correlation-scale error: standard error ≈ 1/sqrt(n) = 0.005
    np.testing.assert_allclose(emp / np.outer(sd, sd), cov / np.outer(sd, sd), atol=0.03)
    assert np.abs(draws.mean(axis=0) / sd).max() < 0.03


def test_ar1_lag_correlations_and_moment_guess():
    long_starts = np.zeros(20_000, bool)
    long_starts[[0, 10_000]] = True
    nm = AR1Noise(history_starts=long_starts)
    q = np.array([0.01, 0.6])
    e = nm.simulate(np.random.default_rng(4), q)[0]
    for lag in (1, 2, 3):
        pairs = [(e[i: 10_000 - lag + i], e[i + lag: 10_000 + i]) for i in (0, 10_000)]
        corr = np.mean([np.corrcoef(a, b)[0, 1] for a, b in pairs])
        assert corr == pytest.approx(nm.autocorrelation(q, lag), abs=0.03)
    assert nm.autocorrelation(q, 2) == pytest.approx(0.36, rel=1e-12)
    guess = nm.moment_guess(e)
    assert guess["rho"] == pytest.approx(0.6, abs=0.03)
    assert guess["sigma"] == pytest.approx(0.01, rel=0.05)
    # independent noise: correlation 1 at lag 0, 0 elsewhere
    np.testing.assert_array_equal(noise_model("iid").autocorrelation([0.01], np.arange(3)), [1.0, 0.0, 0.0])


def test_ar1_draws_equal_an_lfilter_recursion_bitwise():
    """The random stream of AR(1) noise is that of the stationary recursion per history."""
    rho, n = 0.73, 5
    got = AR1Noise(history_starts=STARTS).standard_draws(np.random.default_rng(5), (1.0, rho), n=n)
    z = np.random.default_rng(5).standard_normal((n, P))
    expect = np.empty_like(z)
    edges = list(np.flatnonzero(STARTS)) + [P]
    for a, b in zip(edges[:-1], edges[1:]):
        seg = z[:, a:b].copy()
        seg[:, 1:] *= math.sqrt(1 - rho * rho)
        expect[:, a:b] = lfilter([1.0], [1.0, -rho], seg, axis=-1)
    np.testing.assert_array_equal(got, expect)
    # rho = 0: exactly the independent stream
    np.testing.assert_array_equal(
        AR1Noise(history_starts=STARTS).standard_draws(np.random.default_rng(5), (1.0, 0.0), n=n),
        np.random.default_rng(5).standard_normal((n, P)))


# ------------------------------------------------------------------------- gradient and Fisher
def _loglik_at(name, nm, x):
    """Log-likelihood as a function of (beta, noise parameters) for the linear mean model."""
    return nm.loglik(x[None, 2:], (X @ x[:2])[None])[0]


@pytest.mark.parametrize("name", list(ROWS))
def test_gradient_matches_finite_differences(name):
    nm = noise_model(name)
    x = np.r_[BETA * 1.05, ROWS[name]]                   # off the truth: mean part non-zero
    jac = np.broadcast_to(X, (1, P, 2))
    g, f = nm.grad_fim(x[None, 2:], (X @ x[:2])[None], jac)
    h = 1e-6 * np.maximum(np.abs(x), 1e-3)
    fd = [(_loglik_at(name, nm, x + h[i] * e) - _loglik_at(name, nm, x - h[i] * e)) / (2 * h[i])
          for i, e in enumerate(np.eye(x.size))]
    np.testing.assert_allclose(g[0], fd, rtol=1e-5, atol=1e-6 * np.abs(fd).max())
    np.testing.assert_allclose(f[0], f[0].T, rtol=1e-13)


@pytest.mark.parametrize("name", list(ROWS))
def test_fisher_information_equals_monte_carlo_score_covariance(name):
    """F = E[∇ℓ ∇ℓᵀ] over data simulated from the model itself."""
    q = np.array(ROWS[name])
    m = X @ BETA
    jac = np.broadcast_to(X, (1, P, 2))
    base = noise_model(name)
    rng = np.random.default_rng(6)
    n = 8000
    ys = m + base.simulate(rng, np.tile(q, (n, 1)), np.tile(m, (n, 1)))
    scores = []
    for y in ys:
        # weighted: the weights are fixed by the first curve (they are data, not parameters)
        nm = base if name == "weighted" else noise_model(name, y)
        if name == "weighted":
            nm.observed = y
        scores.append(nm.grad_fim(q[None], m[None], jac)[0][0])
    scores = np.array(scores)
    mc = scores.T @ scores / n
    _, fim = base.grad_fim(q[None], m[None], jac)
    scale = np.sqrt(np.outer(np.diag(fim[0]), np.diag(fim[0])))
    # correlation-scale Monte-Carlo error ≈ sqrt(2/n) = 0.016
    np.testing.assert_allclose(mc / scale, fim[0] / scale, atol=0.08)
    assert np.abs(scores.mean(axis=0) / np.sqrt(np.diag(fim[0]))).max() < 0.08   # E[score] = 0


# ------------------------------------------------------------------------------------- registry
def test_registry_lookup_and_errors():
    assert noise_model_names()[:4] == ("iid", "weighted", "proportional", "ar1")
    assert get_noise("ar1") is AR1Noise
    with pytest.raises(HbmError, match="noise model must be one of iid, weighted"):
        get_noise("laplace")
    with pytest.raises(HbmError, match="not a subclass"):
        register_noise(dict)

    class NoNames(NoiseModel):
        name = "nonames"

    with pytest.raises(HbmError, match="names"):
        register_noise(NoNames)

    class Clash(AR1Noise):
        pass

    with pytest.raises(HbmError, match="already registered"):
        register_noise(Clash)
    assert get_noise("ar1") is AR1Noise
    with pytest.raises(HbmError, match="first point"):
        AR1Noise(history_starts=[False, True])
    with pytest.raises(HbmError, match="sigma_bounds"):
        noise_model("iid").box((0.0, 1.0))
    np.testing.assert_array_equal(eq120_weights([0.0, -2.0, 0.1, 1.0]), [0.2, 2.0, 0.2, 1.0])


class LaplaceNoise(NoiseModel):
    """r_i ~ Laplace(0, b) independent: a user noise model, not part of hbm."""

    name = "test_laplace"
    names = ("b",)

    def default_box(self):
        return {"b": (1e-4, self.sigma_upper())}

    def sd(self, q, model_stress=None):
        return np.broadcast_to(math.sqrt(2.0) * q[:, :1], (q.shape[0], self.n_points))

    def pointwise(self, q, model_stress):
        b = q[:, :1]
        return -np.log(2.0 * b) - np.abs(self.observed - model_stress) / b

    def standard_draws(self, rng, q, n=None):
        return rng.laplace(0.0, 1.0 / math.sqrt(2.0), (np.atleast_2d(q).shape[0], self.n_points))


@pytest.fixture
def laplace():
    register_noise(LaplaceNoise)
    yield LaplaceNoise
    NOISE_REGISTRY.pop(LaplaceNoise.name)


def test_user_noise_model_works_end_to_end(laplace):
    from hbm.likelihood import NOISE_MODELS

    assert "test_laplace" in NOISE_MODELS                 # the tuple follows the registry
    model = spyrou_model()
    truth = np.array([0.9, 0.184, 0.13, 1.5, 9.3, 59.0, 0.012, 0.009])
    strain = np.linspace(0.003, 0.4, 30)
    clean = model.stress(strain, truth)
    y = clean + np.random.default_rng(7).laplace(0.0, 0.003, strain.size)
    ds = xr.Dataset({"strain": ("point", strain), "stress": ("point", y)})
    lik = make_likelihood(model, ds, noise="test_laplace")
    assert lik.noise == "test_laplace" and isinstance(lik.noise_model, LaplaceNoise)
    assert lik.names[-1] == "b" and lik.bounds[-1].tolist() == [1e-4, max(0.05, 0.5 * np.abs(y).max())]
    theta = np.array([np.r_[truth, 0.003], np.r_[truth * 1.01, 0.004]])
    m = lik.predict(theta)
    expect = stats.laplace.logpdf(y, m, theta[:, -1:]).sum(axis=1)
    np.testing.assert_allclose(lik(theta), expect, rtol=1e-12)
    np.testing.assert_allclose(pointwise_log_likelihood(lik, theta).sum(axis=1), expect, rtol=1e-12)
    np.testing.assert_allclose(lik.noise_sd(theta), np.sqrt(2.0) * theta[:, -1:] * np.ones(strain.size))
    big = np.tile(theta[:1], (4000, 1))
    pm, pp = posterior_predictive(lik, big, seed=8)
    r = (pp - pm).ravel()
    assert r.std() == pytest.approx(math.sqrt(2.0) * 0.003, rel=0.02)
    assert stats.kurtosis(r) == pytest.approx(3.0, abs=1.0)   # Laplace (3), not Gaussian (0); SE ≈ 0.15
    with pytest.raises(HbmError, match="variance_jacobian"):
        lik.gradient_fim(theta)
    # the narrowed copy keeps the user noise model
    assert lik.with_bounds(VOLF=(0.8, 0.95)).noise == "test_laplace"
