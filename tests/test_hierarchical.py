"""Hierarchical layer against closed forms (Gaussian toy) and synthetic population recovery."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.special import logsumexp
from scipy.stats import multivariate_normal, norm, truncnorm

from hbm.errors import HbmError
from hbm.samplers.hierarchical import HierarchicalModel, hierarchical, refine_individual

L = 20.0  # stage-1 box [-L, L]
Y = np.array([-1.0, 0.5, 1.2, 2.0, 0.3, -0.4])
S = np.array([0.5, 0.8, 0.4, 1.0, 0.6, 0.7])
# A fixed number of MH steps per TMCMC stage keeps the default suite fast; the hyper-posteriors
# here are smooth and low-dimensional (the adaptive default runs up to 100 steps per stage).
FAST = {"n_steps": 12}


def gaussian_stage1(y, s, n, seed, lo=-L, hi=L):
    """Exact stage-1 posteriors for data y_i ~ N(θ_i, s_i²) under a uniform prior on [lo, hi].

    Posterior: N(y_i, s_i²) truncated to the box; evidence Z_i = P(box)/(hi − lo).
    """
    rng = np.random.default_rng(seed)
    out = {}
    for i, (yi, si) in enumerate(zip(y, s)):
        a, b = (lo - yi) / si, (hi - yi) / si
        x = truncnorm.rvs(a, b, loc=yi, scale=si, size=n, random_state=rng)
        logz = np.log(norm.cdf(b) - norm.cdf(a)) - np.log(hi - lo)
        out[f"s{i}"] = (x[:, None], logz)
    return out


def exact_log_marginal(mu, sd, y=Y, s=S):
    """log Π_i p(y_i | mu, sd) with the population N(mu, sd²) truncated to [-L, L] (exact)."""
    mu, sd = np.asarray(mu, float)[..., None], np.asarray(sd, float)[..., None]
    v = 1.0 / (1.0 / s**2 + 1.0 / sd**2)
    m = v * (y / s**2 + mu / sd**2)
    mass = norm.cdf((L - m) / np.sqrt(v)) - norm.cdf((-L - m) / np.sqrt(v))
    trunc = norm.cdf((L - mu) / sd) - norm.cdf((-L - mu) / sd)
    return np.sum(norm.logpdf(y, mu, np.sqrt(sd**2 + s**2)) + np.log(mass) - np.log(trunc), axis=-1)


# ----------------------------------------------------------------------------------------
# density algebra against scipy
# ----------------------------------------------------------------------------------------
def test_population_density_matches_scipy_with_transforms():
    names = ["a", "b", "c"]
    bounds = np.array([[0.5, 0.99], [1e-3, 2.0], [-1.0, 3.0]])
    hm = HierarchicalModel(names, bounds, transforms={"a": "logit", "b": "log"})
    rng = np.random.default_rng(0)
    theta = rng.uniform(bounds[:, 0], bounds[:, 1], (50, 3))
    raw = np.array([[0.7, -1.0, 0.5, np.log(0.8), np.log(0.6), np.log(1.3)]])
    got = hm.log_density(theta, raw)
    # independent: product of the three θ-space densities
    mu, sd = raw[0, :3], np.exp(raw[0, 3:])
    u = (theta[:, 0] - 0.5) / 0.49
    za = np.log(u / (1 - u))
    pa = norm.logpdf(za, mu[0], sd[0]) - np.log(u * (1 - u) * 0.49)
    lb = np.log(theta[:, 1])
    tb = truncnorm((np.log(1e-3) - mu[1]) / sd[1], (np.log(2.0) - mu[1]) / sd[1], loc=mu[1], scale=sd[1])
    pb = tb.logpdf(lb) - lb
    tc = truncnorm((-1 - mu[2]) / sd[2], (3 - mu[2]) / sd[2], loc=mu[2], scale=sd[2])
    pc = tc.logpdf(theta[:, 2])
    np.testing.assert_allclose(got, pa + pb + pc, rtol=0, atol=1e-9)


def test_full_covariance_density_matches_scipy():
    names = ["a", "b", "c"]
    bounds = np.array([[0.0, 1.0], [2.0, 5.0], [-1.0, 1.0]])
    hm = HierarchicalModel(names, bounds, full_cov=["a", "b", "c"])
    assert hm.transforms == {"a": "logit", "b": "logit", "c": "logit"}
    rng = np.random.default_rng(1)
    theta = rng.uniform(bounds[:, 0], bounds[:, 1], (40, 3))
    cpc = np.array([0.6, -0.3, 0.4])
    raw = np.concatenate([[0.2, -0.5, 1.0], np.log([0.9, 1.5, 0.7]), cpc])[None, :]
    got = hm.log_density(theta, raw)
    nat = hm.natural(raw)[0]
    sd = nat[3:6]
    R = np.eye(3)
    for (i, j), r in zip([(1, 0), (2, 0), (2, 1)], nat[6:]):
        R[i, j] = R[j, i] = r
    # CPC construction: R_10 = z_10, R_20 = z_20, R_21 = z_20 z_10 + z_21 sqrt((1-z_10²)(1-z_20²))
    assert np.isclose(R[1, 0], 0.6) and np.isclose(R[2, 0], -0.3)
    assert np.isclose(R[2, 1], -0.3 * 0.6 + 0.4 * np.sqrt((1 - 0.36) * (1 - 0.09)))
    cov = R * np.outer(sd, sd)
    u = (theta - bounds[:, 0]) / (bounds[:, 1] - bounds[:, 0])
    z = np.log(u / (1 - u))
    jac = -np.sum(np.log(u * (1 - u) * (bounds[:, 1] - bounds[:, 0])), axis=1)
    want = multivariate_normal(raw[0, :3], cov).logpdf(z) + jac
    np.testing.assert_allclose(got, want, rtol=0, atol=1e-9)


def test_predictive_draws_match_truncated_normal():
    hm = HierarchicalModel(["x"], [[0.0, 1.0]])
    from hbm.samplers.hierarchical import draw_population

    raw = np.array([[0.9, np.log(0.3)]])
    x = draw_population(hm, raw, 200_000, np.random.default_rng(2))[:, 0]
    tn = truncnorm((0 - 0.9) / 0.3, (1 - 0.9) / 0.3, loc=0.9, scale=0.3)
    assert abs(x.mean() - tn.mean()) < 4 * tn.std() / np.sqrt(x.size)
    assert abs(x.std() - tn.std()) < 0.005
    assert x.min() >= 0 and x.max() <= 1


# ----------------------------------------------------------------------------------------
# Gaussian toy: exact marginal likelihood, hyper-posterior and hyper-evidence
# ----------------------------------------------------------------------------------------
def test_importance_estimate_of_log_marginal_matches_exact():
    n = 20_000
    st1 = gaussian_stage1(Y, S, n, seed=11)
    hm = HierarchicalModel(["x"], [[-L, L]])
    mus = np.array([0.5, 0.0, 1.0, -3.0, 0.3])
    sds = np.array([1.0, 0.3, 2.0, 5.0, 0.2])
    raw = np.column_stack([mus, np.log(sds)])
    coef, cconst = hm.coefficients(raw)
    est = np.zeros(len(mus))
    var = np.zeros(len(mus))
    for x, logz in st1.values():
        F, c = hm.features(x)
        lse, ess = hm.log_ratio_stats(F, c, coef, cconst)
        est += logz + lse - np.log(n)
        var += 1.0 / ess - 1.0 / n
    exact = exact_log_marginal(mus, sds)
    err = np.abs(est - exact)
    assert np.all(err < 4 * np.sqrt(var) + 1e-3), (est, exact, np.sqrt(var))
    assert np.all(err < 0.03)


@pytest.fixture(scope="module")
def toy_run():
    st1 = gaussian_stage1(Y, S, 2500, seed=5)
    return hierarchical(st1, ["x"], [[-L, L]], n_samples=1000, seed=7, progress=False, tmcmc_options=FAST)


def _grid_posterior():
    """Hyper-posterior on a (mu, log sd) grid with the exact marginal likelihood."""
    mus = np.linspace(-L, L, 1601)
    lsd = np.linspace(np.log(1e-3 * 2 * L), np.log(2 * L), 351)
    MU, LS = np.meshgrid(mus, lsd, indexing="ij")
    ll = exact_log_marginal(MU, np.exp(LS))
    logprior = -np.log(2 * L) - np.log(lsd[-1] - lsd[0])  # uniform mu, log-uniform sd
    # trapezoid weights
    w_mu = np.full(mus.size, mus[1] - mus[0]); w_mu[[0, -1]] /= 2
    w_ls = np.full(lsd.size, lsd[1] - lsd[0]); w_ls[[0, -1]] /= 2
    logw = ll + logprior + np.log(w_mu)[:, None] + np.log(w_ls)[None, :]
    logev = logsumexp(logw)
    p = np.exp(logw - logev)
    return logev, p, MU, np.exp(LS)


def test_hyper_posterior_and_evidence_match_grid(toy_run):
    res = toy_run
    assert res.hyper_names == ["mu_x", "sd_x"]
    logev, p, MU, SD = _grid_posterior()
    m_mu = np.sum(p * MU)
    s_mu = np.sqrt(np.sum(p * MU**2) - m_mu**2)
    m_sd = np.sum(p * SD)
    mu_draws, sd_draws = res.hyper("mu_x"), res.hyper("sd_x")
    n = mu_draws.size
    # posterior mean of mu within 4 Monte Carlo SE (TMCMC draws are correlated: use n/3)
    assert abs(mu_draws.mean() - m_mu) < 4 * s_mu / np.sqrt(n / 3), (mu_draws.mean(), m_mu)
    assert abs(mu_draws.std() - s_mu) < 0.15 * s_mu
    assert abs(sd_draws.mean() - m_sd) < 0.15 * m_sd
    # hyper-evidence against numerical integration, tolerance from the reported SE
    assert res.log_evidence_se > 0
    assert abs(res.log_evidence - logev) < 4 * res.log_evidence_se + 0.05, (res.log_evidence, logev, res.log_evidence_se)
    assert not res.collapsed


def test_hyper_posterior_with_known_sd_is_the_gaussian_closed_form():
    sd = 0.8
    st1 = gaussian_stage1(Y, S, 2500, seed=9)
    res = hierarchical(st1, ["x"], [[-L, L]], n_samples=800, seed=3, fix={"sd_x": sd}, progress=False,
                       n_updated=4000, tmcmc_options=FAST)
    # mu | y ~ N(m, V), V = 1/Σ 1/(sd²+s²), m = V Σ y/(sd²+s²)  (box truncation negligible here)
    prec = 1.0 / (sd**2 + S**2)
    V = 1.0 / prec.sum()
    m = V * np.sum(prec * Y)
    mu = res.hyper("mu_x")
    assert np.allclose(res.hyper("sd_x"), sd)
    assert abs(mu.mean() - m) < 4 * np.sqrt(V / (mu.size / 3))
    assert abs(mu.std() - np.sqrt(V)) < 0.12 * np.sqrt(V)
    # evidence: ∫ Π N(y_i; mu, sd²+s_i²) dmu / (2L) in closed form
    # completing the square: Σ log N(y_i; mu, τ_i²) = Σ log N(y_i; 0, τ_i²) + m·mu/V − mu²/(2V)
    logev = (np.sum(norm.logpdf(Y, 0, np.sqrt(sd**2 + S**2))) + 0.5 * m**2 / V
             + 0.5 * np.log(2 * np.pi * V) - np.log(2 * L))
    assert abs(res.log_evidence - logev) < 4 * res.log_evidence_se + 0.05
    # updated individuals: θ_i | D ~ N(v_i (y_i/s_i² + m/sd²), v_i + (v_i/sd²)² V), v_i = 1/(1/s_i²+1/sd²)
    for i, key in enumerate(res.specimens):
        v = 1.0 / (1.0 / S[i] ** 2 + 1.0 / sd**2)
        mean = v * (Y[i] / S[i] ** 2 + m / sd**2)
        var = v + (v / sd**2) ** 2 * V
        th = res.updated[key][:, 0]
        assert abs(th.mean() - mean) < 0.06, (key, th.mean(), mean)
        assert abs(th.std() - np.sqrt(var)) < 0.08 * np.sqrt(var)


def test_collapse_is_flagged_and_refine_individual_recovers_the_closed_form():
    sd = 0.05
    y = np.array([0.0, 0.1, -0.1, 0.05, -0.05, 0.3])
    s = np.array([0.05, 0.05, 0.05, 0.05, 0.05, 5.0])  # last specimen: almost no information
    st1 = gaussian_stage1(y, s, 2000, seed=4)
    with pytest.warns(RuntimeWarning, match="collapsed"):
        res = hierarchical(st1, ["x"], [[-L, L]], n_samples=600, seed=1, fix={"sd_x": sd}, progress=False,
                           tmcmc_options=FAST)
    assert res.ess_collapsed["s5"] and res.collapsed
    assert not res.ess_collapsed["s0"]
    assert any("s5" in w for w in res.warnings)
    assert res.ess_summary["s5"]["median"] < 50

    def loglik(theta):
        return norm.logpdf(y[5], theta[:, 0], s[5])

    prec = 1.0 / (sd**2 + s**2)
    V = 1.0 / prec.sum()
    m = V * np.sum(prec * y)
    v = 1.0 / (1.0 / s[5] ** 2 + 1.0 / sd**2)
    mean = v * (y[5] / s[5] ** 2 + m / sd**2)
    sdev = np.sqrt(v + (v / sd**2) ** 2 * V)
    out = refine_individual(res, "s5", loglik, n_samples=1500, seed=2, progress=False, **FAST)
    th = out.samples[:, 0]
    assert abs(th.mean() - mean) < 0.1 * sdev + 4 * sdev / np.sqrt(th.size / 3)
    assert abs(th.std() - sdev) < 0.1 * sdev


# ----------------------------------------------------------------------------------------
# synthetic multi-specimen recovery (Gaussian surrogates of stage-1 posteriors)
# ----------------------------------------------------------------------------------------
@pytest.mark.filterwarnings("ignore:hierarchical. importance ESS")
def test_population_recovery_and_shrinkage():
    rng = np.random.default_rng(123)
    names = ["VOLF", "P1", "E"]
    bounds = np.array([[0.5, 0.99], [1e-3, 1.0], [-1.0, 1.0]])
    transforms = {"VOLF": "logit", "P1": "log"}
    mu_true = np.array([1.0, np.log(0.05), 0.2])  # transformed units
    sd_true = np.array([0.4, 0.5, 0.15])
    hm = HierarchicalModel(names, bounds, transforms=transforms)
    n_spec = 8
    theta_true = hm.from_z(mu_true + sd_true * rng.standard_normal((n_spec, 3)))
    noise = np.array([0.03, 0.02, 0.15])  # stage-1 posterior sd in θ units
    st1 = {}
    for i in range(n_spec):
        y = theta_true[i] + noise * rng.standard_normal(3)
        a, b = (bounds[:, 0] - y) / noise, (bounds[:, 1] - y) / noise
        x = truncnorm.rvs(a, b, loc=y, scale=noise, size=(1500, 3), random_state=rng)
        logz = np.sum(np.log(norm.cdf(b) - norm.cdf(a)) - np.log(bounds[:, 1] - bounds[:, 0]))
        st1[f"r{i}"] = (x, logz)
    res = hierarchical(st1, names, bounds, transforms=transforms, n_samples=800, seed=8, progress=False,
                       tmcmc_options=FAST)
    summ = res.summary(q=(0.025, 0.975))
    for k, p in enumerate(names):
        s = summ[f"mu_{p}"]
        assert s["lo"] < mu_true[k] < s["hi"], (p, s, mu_true[k])
    assert res.predictive.shape == (800, 3)
    assert np.all((res.predictive >= bounds[:, 0]) & (res.predictive <= bounds[:, 1]))
    # shrinkage: updated individuals move toward the population centre of E (wide stage-1)
    centre = np.median(res.predictive[:, 2])
    d1 = np.array([abs(st1[k][0][:, 2].mean() - centre) for k in res.specimens])
    d2 = np.array([abs(res.updated[k][:, 2].mean() - centre) for k in res.specimens])
    far = d1 > 0.1  # specimens clearly off-centre must move toward the population
    assert far.sum() >= 2 and np.all(d2[far] < d1[far])
    assert d2.sum() < 0.8 * d1.sum()
    assert np.mean([res.updated[k][:, 2].std() for k in res.specimens]) < np.mean(
        [st1[k][0][:, 2].std() for k in res.specimens])


def test_bad_inputs_raise_hbm_error():
    st1 = gaussian_stage1(Y[:2], S[:2], 100, seed=0)
    with pytest.raises(HbmError, match="bounds"):
        hierarchical(st1, ["x"], [[1.0, 0.0]], progress=False)
    with pytest.raises(HbmError, match="log"):
        HierarchicalModel(["x"], [[-1.0, 1.0]], transforms={"x": "log"})
    with pytest.raises(HbmError, match="logit"):
        HierarchicalModel(["x", "y"], [[0, 1], [0, 1]], transforms={"x": "identity"}, full_cov=["x", "y"])
    with pytest.raises(HbmError, match="outside"):
        hierarchical({"a": (np.full((10, 1), 30.0), 0.0)}, ["x"], [[-L, L]], progress=False)
    with pytest.raises(HbmError, match="samples must be"):
        hierarchical({"a": (np.zeros((10, 2)), 0.0)}, ["x"], [[-L, L]], progress=False)


def test_halfnormal_hyperprior_correction_is_a_normalised_density():
    hm = HierarchicalModel(["x", "y"], [[0.0, 1.0], [0.0, 2.0]], sd_prior="halfnormal")
    rng = np.random.default_rng(0)
    raw = rng.uniform(hm.box[:, 0], hm.box[:, 1], (400_000, hm.box.shape[0]))
    # E_uniform[exp(correction)] = ∫ prior = 1
    m = np.exp(hm.log_hyperprior_correction(raw)).mean()
    assert abs(m - 1.0) < 0.01


@pytest.mark.slow
def test_full_covariance_recovers_a_strong_correlation():
    rng = np.random.default_rng(5)
    names = ["a", "b"]
    bounds = np.array([[0.0, 1.0], [0.0, 1.0]])
    hm = HierarchicalModel(names, bounds, full_cov=names)
    n_spec = 12
    cov = np.array([[0.5**2, 0.9 * 0.25], [0.9 * 0.25, 0.5**2]])
    z = rng.multivariate_normal([0.0, 0.5], cov, n_spec)
    theta = hm.from_z(z)
    st1 = {}
    for i in range(n_spec):
        y = theta[i] + 0.01 * rng.standard_normal(2)
        a, b = (bounds[:, 0] - y) / 0.01, (bounds[:, 1] - y) / 0.01
        x = truncnorm.rvs(a, b, loc=y, scale=0.01, size=(3000, 2), random_state=rng)
        st1[f"r{i}"] = (x, float(np.sum(np.log(norm.cdf(b) - norm.cdf(a)))))
    res = hierarchical(st1, names, bounds, full_cov=names, n_samples=1000, seed=2, progress=False,
                       tmcmc_options=FAST)
    r = res.hyper("corr_b_a")
    # 12 specimens with sample correlation 0.73 (true 0.9): Fisher-z 90 % interval ≈ [0.36, 0.90]
    assert np.mean(r > 0) > 0.9 and r.mean() > 0.3
    diag = hierarchical(st1, names, bounds, transforms={"a": "logit", "b": "logit"}, n_samples=1000, seed=2,
                        progress=False, tmcmc_options=FAST)
    # the correlated family explains the data better (≈ +4 nats of likelihood at the truth minus
    # the Occam factor of one correlation): higher hyper-evidence
    assert res.log_evidence > diag.log_evidence


@pytest.mark.slow
def test_toy_with_adaptive_tmcmc_defaults_matches_grid():
    st1 = gaussian_stage1(Y, S, 5000, seed=21)
    res = hierarchical(st1, ["x"], [[-L, L]], n_samples=2000, seed=4, progress=False)
    logev, p, MU, SD = _grid_posterior()
    assert abs(res.log_evidence - logev) < 4 * res.log_evidence_se + 0.03
    assert abs(res.hyper("mu_x").mean() - np.sum(p * MU)) < 0.05


# ----------------------------------------------------------------------------------------
# kernel-smoothed estimator, against closed forms in the log-transformed space
# ----------------------------------------------------------------------------------------
# Stage-1 toy in log space: data y_i ~ N(log θ_i, s_i²), θ uniform on [e^A, e^B].  In z = log θ
# the posterior is N(y_i + s_i², s_i²) truncated to [A, B] (the uniform prior's Jacobian e^z
# tilts it) and Z_i = e^(y_i + s_i²/2) P([A, B]) / (e^B − e^A).  With the population
# z ~ N(mu, sd²) truncated to [A, B], p(y_i|ψ) = ∫_A^B N(y_i; z, s_i²) N(z; mu, sd²) dz / mass.
A_LOG, B_LOG = -6.0, 4.0


def exact_log_marginal_box(mu, sd, y, s, lo, hi):
    """Σ_i log p(y_i | mu, sd) for the population N(mu, sd²) truncated to [lo, hi] (exact).

    ``sd`` may carry a trailing specimen axis (a per-specimen population width)."""
    mu = np.asarray(mu, float)[..., None]
    sd = np.asarray(sd, float)
    sd = sd if sd.ndim and sd.shape[-1] == len(y) else sd[..., None]
    v = 1.0 / (1.0 / s**2 + 1.0 / sd**2)
    m = v * (y / s**2 + mu / sd**2)
    mass = norm.cdf((hi - m) / np.sqrt(v)) - norm.cdf((lo - m) / np.sqrt(v))
    trunc = norm.cdf((hi - mu) / sd) - norm.cdf((lo - mu) / sd)
    return np.sum(norm.logpdf(y, mu, np.sqrt(sd**2 + s**2)) + np.log(mass) - np.log(trunc), axis=-1)


def log_stage1(y, s, n, seed, lo=A_LOG, hi=B_LOG):
    rng = np.random.default_rng(seed)
    out = {}
    for i, (yi, si) in enumerate(zip(y, s)):
        m = yi + si**2
        a, b = (lo - m) / si, (hi - m) / si
        z = truncnorm.rvs(a, b, loc=m, scale=si, size=n, random_state=rng)
        logz = yi + 0.5 * si**2 + np.log(norm.cdf(b) - norm.cdf(a)) - np.log(np.exp(hi) - np.exp(lo))
        out[f"s{i}"] = (np.exp(z)[:, None], logz)
    return out


def test_kernel_bandwidth_rules():
    from hbm.samplers.hierarchical import kernel_bandwidth

    assert np.isclose(kernel_bandwidth(1000, 1), (4 / 3) ** 0.2 * 1000 ** -0.2)  # 1.06 n^-1/5
    assert np.isclose(kernel_bandwidth(2000, 2, "scott"), 2000 ** (-1 / 6))
    assert kernel_bandwidth(10, 3, 0.7) == 0.7
    with pytest.raises(HbmError, match="bandwidth"):
        kernel_bandwidth(10, 3, "wide")


def test_raw_and_kernel_estimators_match_closed_forms_in_log_space():
    """Raw ratios are unbiased for p(y|ψ) (tests the log Jacobian); the kernel estimator is
    unbiased for the marginal of the population widened by h²Σ_i — a missing or misplaced
    h²Σ term, or a kernel in θ instead of z, fails the second check."""
    n = 20_000
    st1 = log_stage1(Y, S, n, seed=3)
    hm = HierarchicalModel(["x"], [[np.exp(A_LOG), np.exp(B_LOG)]], transforms={"x": "log"})
    mus = np.array([0.5, 0.0, 1.0, -2.0, 0.3])
    sds = np.array([1.0, 0.3, 2.0, 3.0, 0.15])
    raw = np.column_stack([mus, np.log(sds)])
    h = 0.6  # large on purpose: the smoothing term must be visible above the Monte Carlo noise
    est = {"raw": 0.0, "kernel": 0.0}
    var = {"raw": 0.0, "kernel": 0.0}
    sig = []
    for x, logz in st1.values():
        hk, kv = hm.kernel_variance(x, h)
        assert hk == h
        sig.append(np.sqrt(kv[0]) / h)
        for kind, k in (("raw", None), ("kernel", kv)):
            lm, ess = hm.log_mean_ratio(x, raw, k)
            est[kind] = est[kind] + logz + lm
            var[kind] = var[kind] + 1.0 / ess - 1.0 / n
    sig = np.array(sig)
    exact = exact_log_marginal_box(mus, sds, Y, S, A_LOG, B_LOG)
    smoothed = exact_log_marginal_box(mus, np.sqrt(sds[:, None] ** 2 + (h * sig) ** 2), Y, S, A_LOG, B_LOG)
    tol = {k: 4 * np.sqrt(v) + 2e-3 for k, v in var.items()}
    assert np.all(np.abs(est["raw"] - exact) < tol["raw"]), (est["raw"], exact)
    assert np.all(np.abs(est["kernel"] - smoothed) < tol["kernel"]), (est["kernel"], smoothed)
    # the check discriminates: the O(h²) smoothing bias exceeds the tolerance at narrow ψ
    assert np.max(np.abs(smoothed - exact) - tol["kernel"]) > 0.1
    # the default (Silverman) bandwidth keeps the bias small: within 0.1 nat over six specimens
    # at every ψ here, and it shrinks with N as h² ∝ N^(-2/5)
    est_def = sum(logz + hm.log_mean_ratio(x, raw, hm.kernel_variance(x)[1])[0] for x, logz in st1.values())
    assert np.all(np.abs(est_def - exact) < 0.1), est_def - exact


def _grid_posterior_box(y, s, lo, hi, n_mu=801, n_sd=301):
    mus = np.linspace(lo, hi, n_mu)
    w = hi - lo
    lsd = np.linspace(np.log(1e-3 * w), np.log(w), n_sd)
    MU, LS = np.meshgrid(mus, lsd, indexing="ij")
    ll = exact_log_marginal_box(MU, np.exp(LS), y, s, lo, hi)
    w_mu = np.full(mus.size, mus[1] - mus[0]); w_mu[[0, -1]] /= 2
    w_ls = np.full(lsd.size, lsd[1] - lsd[0]); w_ls[[0, -1]] /= 2
    logw = ll - np.log(w) - np.log(lsd[-1] - lsd[0]) + np.log(w_mu)[:, None] + np.log(w_ls)[None, :]
    logev = logsumexp(logw)
    p = np.exp(logw - logev)
    return logev, p, MU, np.exp(LS)


@pytest.mark.filterwarnings("ignore:hierarchical. importance ESS")
def test_kernel_hierarchical_matches_grid_in_log_space():
    st1 = log_stage1(Y, S, 2500, seed=17)
    res = hierarchical(st1, ["x"], [[np.exp(A_LOG), np.exp(B_LOG)]], transforms={"x": "log"}, n_samples=1000,
                       seed=5, progress=False, tmcmc_options=FAST, estimator="kernel")
    assert res.options["estimator"] == "kernel" and 0 < res.options["kernel_h"]["s0"] < 0.3
    assert res.ess_raw.shape == res.ess.shape and "raw_q10" in res.ess_summary["s0"]
    logev, p, MU, SD = _grid_posterior_box(Y, S, A_LOG, B_LOG)
    m_mu = np.sum(p * MU)
    s_mu = np.sqrt(np.sum(p * MU**2) - m_mu**2)
    m_sd = np.sum(p * SD)
    # total Σ log p̂ bias of the Silverman kernel here is ≈ +0.07 nat (measured over seeds); the
    # hyper-evidence must lie within 4 SE + 0.15, the posterior mean of mu within 4 MC SE + 0.03
    # (a wrong log Jacobian moves both by several units)
    assert abs(res.log_evidence - logev) < 4 * res.log_evidence_se + 0.15, (res.log_evidence, logev)
    mu = res.hyper("mu_x")
    assert abs(mu.mean() - m_mu) < 4 * s_mu / np.sqrt(mu.size / 3) + 0.03, (mu.mean(), m_mu)
    # the kernel widens the population, so sd comes out a little low (−4 % on average over seeds)
    assert abs(res.hyper("sd_x").mean() - m_sd) < 0.2 * m_sd


def test_kernel_estimator_keeps_ess_where_raw_ratios_collapse():
    """A population much narrower than a specimen's posterior: raw ratios rest on a handful of
    samples, the kernel-smoothed ratios on hundreds, and the smoothed estimate stays within its
    closed-form O(h²) bias of the exact marginal."""
    y = np.array([0.0, 0.1, -0.1, 0.05, -0.05, 0.3])
    s = np.array([0.05, 0.05, 0.05, 0.05, 0.05, 5.0])  # last specimen: almost no information
    st1 = gaussian_stage1(y, s, 2000, seed=4)
    hm = HierarchicalModel(["x"], [[-L, L]])
    x5, _ = st1["s5"]
    raw = np.column_stack([np.linspace(-0.05, 0.1, 5), np.log(np.full(5, 0.05))])
    lm_r, ess_r = hm.log_mean_ratio(x5, raw)
    h, kv = hm.kernel_variance(x5)
    lm_k, ess_k = hm.log_mean_ratio(x5, raw, kv)
    assert np.all(ess_r < 40) and np.all(ess_k > 8 * ess_r) and np.all(ess_k > 250), (ess_r, ess_k)
    # exact: N(y5; mu, sd² + s5²) (box truncation negligible); Z_5 = 1/(2L) up to e^-16
    exact = norm.logpdf(y[5], raw[:, 0], np.sqrt(0.05**2 + s[5] ** 2)) + np.log(2 * L)
    smoothed = norm.logpdf(y[5], raw[:, 0], np.sqrt(0.05**2 + kv[0] + s[5] ** 2)) + np.log(2 * L)
    assert np.all(np.abs(lm_k - smoothed) < 4 / np.sqrt(ess_k))
    assert np.all(np.abs(smoothed - exact) < h**2)  # ½ log(1 + relative variance change ≤ h²σ̂²/s²)
    # through hierarchical(): the hyper-posterior is no longer flagged, the updated individual is
    with pytest.warns(RuntimeWarning, match="updated posterior"):
        res = hierarchical(st1, ["x"], [[-L, L]], n_samples=300, seed=1, fix={"sd_x": 0.05}, progress=False,
                           tmcmc_options={"n_steps": 6}, estimator="kernel")
    assert not res.hyper_ess_collapsed["s5"] and res.ess_collapsed["s5"]
    assert res.ess_summary["s5"]["q10"] > 8 * res.ess_summary["s5"]["raw_q10"]


# ----------------------------------------------------------------------------------------
# automatic choice of the pooled parameters
# ----------------------------------------------------------------------------------------
def test_prior_sd_in_transformed_space():
    from hbm.samplers.hierarchical import prior_sd_transformed

    rng = np.random.default_rng(0)
    u = rng.uniform(1e-4, 0.5, 400_000)
    assert abs(prior_sd_transformed("log", 1e-4, 0.5) - np.log(u).std()) < 0.01
    assert np.isclose(prior_sd_transformed("log", 2.0, 2.2), np.log(rng.uniform(2.0, 2.2, 400_000)).std(), rtol=0.01)
    v = rng.uniform(0, 1, 400_000)
    assert abs(prior_sd_transformed("logit", 3.0, 7.0) - np.log(v / (1 - v)).std()) < 0.01
    assert np.isclose(prior_sd_transformed("identity", -1.0, 3.0), 4 / np.sqrt(12))


def test_auto_pool_picks_the_informative_parameters():
    from hbm.samplers.hierarchical import auto_pool

    rng = np.random.default_rng(9)
    names = ["a", "b", "c", "d", "sigma"]
    bounds = np.array([[0.0, 1.0], [0.0, 1.0], [1e-3, 1.0], [-5.0, 5.0], [1e-3, 1.0]])
    transforms = {"a": "logit", "b": "logit", "c": "log", "d": "identity"}
    n, samples = 3000, {}
    for i in range(6):
        x = rng.uniform(bounds[:, 0], bounds[:, 1], (n, 5))  # prior-like unless set below
        x[:, 0] = 1 / (1 + np.exp(-rng.normal(rng.normal(0, 1), 0.3, n)))  # a: sd 0.3 in logit, every rat
        if i < 4:  # c: log-normal posterior (sd 0.4 in log space) in four of six rats
            x[:, 2] = np.clip(np.exp(rng.normal(-3.0, 0.4, n)), 1e-3, 1.0)
        if i < 2:  # d: informed in two of six only
            x[:, 3] = rng.normal(1.0, 0.2, n)
        x[:, 4] = rng.uniform(0.01, 0.02, n)  # sigma: informative, but not a candidate
        samples[f"r{i}"] = x
    choice = auto_pool(samples, names, bounds, transforms, candidates=names[:4])
    pooled, reasons = choice
    assert pooled == ["a", "c"]
    assert reasons["a"]["n_informative"] == 6 and reasons["c"]["n_informative"] == 4
    assert reasons["d"]["n_informative"] == 2 and not reasons["d"]["pooled"]
    # prior-like samples have sd ratio ≈ 1 in every transformed space
    assert np.allclose(reasons["b"]["sd_ratio"], 1.0, atol=0.06)
    assert np.allclose(reasons["d"]["sd_ratio"][2:], 1.0, atol=0.06)
    assert "sigma" not in reasons
    # a stricter rule (all specimens informed) drops c
    assert auto_pool(samples, names, bounds, transforms, candidates=names[:4], min_fraction=1.0).pooled == ["a"]
    # nothing informative: the best-informed candidate is pooled (min_pooled=1), or none with 0
    few = auto_pool(samples, names, bounds, transforms, candidates=["b", "d"])
    assert few.pooled == ["d"] and "pooled anyway" in few.reasons["d"]["reason"]
    assert auto_pool(samples, names, bounds, transforms, candidates=["b", "d"], min_pooled=0).pooled == []
    # a cap on the informed specimens needed (the joint sampler's rule): d, informed in two of six, is pooled
    # when two suffice, and the reason says how many were needed
    capped = auto_pool(samples, names, bounds, transforms, candidates=names[:4], max_needed=2)
    assert capped.pooled == ["a", "c", "d"] and "(need 2)" in capped.reasons["d"]["reason"]
    assert auto_pool(samples, names, bounds, transforms, candidates=names[:4], max_needed=10).pooled == ["a", "c"]


def test_the_joint_sampler_pools_what_ten_specimens_inform():
    """The layout of a layer (``--pool combinations``, the default): the joint sampler pools a shape parameter
    that JOINT_POOL_INFORMED specimens inform, the reuse layer one that half of them inform.  24 specimens with
    EOPT informed in 11 (fewer than 12): pooled for the joint sampler only; informed in 9: by neither."""
    from types import SimpleNamespace

    from hbm.model import spyrou_model
    from hbm.population import PopulationConfig
    from hbm.population.pooling import JOINT_POOL_INFORMED, CombinationPooling, joint_needed, pack_results

    model = spyrou_model()
    names = list(model.parameter_names)
    lo, hi = model.bounds[names.index("EOPT")]

    def specimens(n_informed: int) -> dict:
        out = {}
        for k in range(24):
            rng = np.random.default_rng(100 + k)
            th = rng.uniform(model.bounds[:, 0], model.bounds[:, 1], (600, len(names)))
            t2lo, t2hi = model.bounds[names.index("T2")]   # T2 informed everywhere (auto-pool's min_pooled met)
            th[:, names.index("T2")] = rng.normal(t2lo + 0.3 * (t2hi - t2lo), 0.01 * (t2hi - t2lo), 600)
            if k < n_informed:
                th[:, names.index("EOPT")] = rng.normal(lo + 0.4 * (hi - lo), 0.01 * (hi - lo), 600)
            out[f"s{k:02d}"] = SimpleNamespace(names=names, bounds=model.bounds.copy(), samples=th, log_evidence=0.0,
                                               log_evidence_se=0.01, specimen_id=f"s{k:02d}")
        return out

    assert JOINT_POOL_INFORMED == 10 and joint_needed(True) == 10 and joint_needed(False) is None
    cfg = PopulationConfig(progress=False)
    for n_informed, joint_pools in ((11, True), (9, False)):
        data = pack_results(specimens(n_informed), model, cfg)
        for joint in (False, True):
            layout = CombinationPooling().layout(data, cfg, joint=joint)
            assert ("EOPT" in layout.pooled) == (joint and joint_pools), (n_informed, joint, layout.pooled)
            need = 10 if joint else 12
            assert f"in {n_informed}/24 specimens (need {need})" in layout.attrs["pool_reasons"]["EOPT"]


def test_kernel_widened_ratios_match_scipy_for_mixed_covariance():
    """log mean_j N(z_j; mu, Σ + diag(e)) |g'(θ_j)| / p_prior(θ_j) with a full-covariance block
    (logit) and a truncated log-normal column, against scipy."""
    names = ["a", "b", "c"]
    bounds = np.array([[0.0, 1.0], [2.0, 5.0], [0.1, 3.0]])
    hm = HierarchicalModel(names, bounds, full_cov=["a", "b"], transforms={"c": "log"})
    rng = np.random.default_rng(4)
    theta = rng.uniform(bounds[:, 0], bounds[:, 1], (30, 3))
    raw = np.concatenate([[0.3, -0.4, 0.2], np.log([0.8, 1.2, 0.5]), [0.7]])[None, :]
    e = np.array([0.3, 0.1, 0.05])
    lm, _ = hm.log_mean_ratio(theta, raw, e)
    nat = hm.natural(raw)[0]
    sd = nat[3:6]
    cov = np.array([[sd[0] ** 2, nat[6] * sd[0] * sd[1]], [nat[6] * sd[0] * sd[1], sd[1] ** 2]]) + np.diag(e[:2])
    u = (theta[:, :2] - bounds[:2, 0]) / (bounds[:2, 1] - bounds[:2, 0])
    z = np.log(u / (1 - u))
    lab = multivariate_normal(raw[0, :2], cov).logpdf(z) - np.sum(np.log(u * (1 - u) * (bounds[:2, 1] - bounds[:2, 0])), axis=1)
    sc = np.sqrt(sd[2] ** 2 + e[2])  # widened, then truncated to the log box
    tc = truncnorm((np.log(0.1) - raw[0, 2]) / sc, (np.log(3.0) - raw[0, 2]) / sc, loc=raw[0, 2], scale=sc)
    lc = tc.logpdf(np.log(theta[:, 2])) - np.log(theta[:, 2])
    want = logsumexp(lab + lc + np.sum(np.log(bounds[:, 1] - bounds[:, 0]))) - np.log(theta.shape[0])
    np.testing.assert_allclose(lm, [want], rtol=0, atol=1e-9)


# ----------------------------------------------------------------------------------------
# non-uniform stage-1 prior of the pooled columns (log_prior)
# ----------------------------------------------------------------------------------------
TAU = 2.5  # stage-1 prior N(0, TAU²) truncated to [-L, L] instead of the uniform box


def gaussian_stage1_normal_prior(y, s, n, seed, tau=TAU):
    """Exact stage-1 posteriors and evidences under the prior N(0, τ²) truncated to [-L, L],
    with the per-sample log prior density."""
    rng = np.random.default_rng(seed)
    p0_mass = norm.cdf(L / tau) - norm.cdf(-L / tau)
    st1, lp = {}, {}
    for i, (yi, si) in enumerate(zip(y, s)):
        v = 1.0 / (1.0 / si**2 + 1.0 / tau**2)
        m = v * yi / si**2
        a, b = (-L - m) / np.sqrt(v), (L - m) / np.sqrt(v)
        x = truncnorm.rvs(a, b, loc=m, scale=np.sqrt(v), size=n, random_state=rng)
        logz = norm.logpdf(yi, 0.0, np.sqrt(si**2 + tau**2)) + np.log(norm.cdf(b) - norm.cdf(a)) - np.log(p0_mass)
        st1[f"s{i}"] = (x[:, None], logz)
        lp[f"s{i}"] = norm.logpdf(x, 0.0, tau) - np.log(p0_mass)
    return st1, lp


def test_log_prior_importance_estimate_matches_exact_and_uniform_default_does_not():
    n = 20_000
    st1, lp = gaussian_stage1_normal_prior(Y, S, n, seed=21)
    hm = HierarchicalModel(["x"], [[-L, L]])
    mus = np.array([0.5, 0.0, 1.0, -3.0])
    sds = np.array([1.0, 0.3, 2.0, 5.0])
    raw = np.column_stack([mus, np.log(sds)])
    est = np.zeros(len(mus))
    var = np.zeros(len(mus))
    wrong = np.zeros(len(mus))
    for key, (x, logz) in st1.items():
        lm, ess = hm.log_mean_ratio(x, raw, log_prior=lp[key])
        est += logz + lm
        var += 1.0 / ess - 1.0 / n
        wrong += logz + hm.log_mean_ratio(x, raw)[0]
    exact = exact_log_marginal(mus, sds)  # p(y|ψ) does not depend on the stage-1 prior
    err = np.abs(est - exact)
    assert np.all(err < 4 * np.sqrt(var) + 1e-3), (est, exact, np.sqrt(var))
    assert np.all(err < 0.06)
    assert np.all(np.abs(wrong - exact) > 1.0)


def test_log_prior_hyper_posterior_and_evidence_match_grid():
    st1, lp = gaussian_stage1_normal_prior(Y, S, 2500, seed=23)
    res = hierarchical(st1, ["x"], [[-L, L]], n_samples=1000, seed=8, progress=False, tmcmc_options=FAST,
                       log_prior=lp, thin=2000)
    logev, p, MU, SD = _grid_posterior()
    m_mu = np.sum(p * MU)
    s_mu = np.sqrt(np.sum(p * MU**2) - m_mu**2)
    m_sd = np.sum(p * SD)
    mu_draws, sd_draws = res.hyper("mu_x"), res.hyper("sd_x")
    assert abs(mu_draws.mean() - m_mu) < 4 * s_mu / np.sqrt(mu_draws.size / 3), (mu_draws.mean(), m_mu)
    assert abs(mu_draws.std() - s_mu) < 0.15 * s_mu
    assert abs(sd_draws.mean() - m_sd) < 0.15 * m_sd
    assert abs(res.log_evidence - logev) < 4 * res.log_evidence_se + 0.05, (res.log_evidence, logev)
    assert res.options["log_prior"] is True
    with pytest.raises(HbmError, match="log_prior"):
        refine_individual(res, "s0", lambda t: np.zeros(len(t)))
    with pytest.raises(HbmError, match="log_prior"):
        hierarchical(st1, ["x"], [[-L, L]], log_prior={"s0": lp["s0"]}, progress=False)


def test_refine_individual_with_augment_divides_by_the_feature_prior():
    """Pooled feature x = a + b of stage-1 parameters (a, b) ~ U(−1, 1)², triangular p0(x) = (2 − |x|)/4.

    The likelihood depends on θ only through x, so p(x_i | all data) is the Gaussian closed form of
    the population N(mu, sd²) (sd fixed, flat mu) whatever p0 is; the fresh TMCMC over (a, b) must
    divide by p0(x), or the triangle would narrow x's posterior visibly (sd ratio ≈ 0.85 here).
    """
    sd = 0.5
    y = np.array([0.2, -0.3, 0.5, 0.0, 0.4, 0.0])
    s = np.array([0.1, 0.1, 0.1, 0.1, 0.1, 5.0])  # last specimen: almost no information
    rng = np.random.default_rng(3)

    def log_p0(x):
        with np.errstate(divide="ignore"):
            return np.log(np.maximum(2.0 - np.abs(x), 0.0) / 4.0)

    st1, lp = {}, {}
    for i, (yi, si) in enumerate(zip(y, s)):
        # exact stage-1 posterior of x ∝ N(y; x, s²)·p0(x) by rejection, then (a, b) | x uniform
        x = np.empty(0)
        while x.size < 3000:
            c = rng.normal(yi, si, 20000) if si < 1 else rng.uniform(-2, 2, 20000)
            acc = rng.random(c.size) < (np.exp(log_p0(c)) * 2.0 if si < 1 else
                                        np.exp(norm.logpdf(yi, c, si) - norm.logpdf(0, 0, si)))
            x = np.concatenate([x, c[acc & (np.abs(c) < 2)]])
        x = x[:3000]
        a = rng.uniform(np.maximum(-1.0, x - 1.0), np.minimum(1.0, x + 1.0))
        st1[f"s{i}"] = (np.column_stack([a, x - a, x]), 0.0)  # evidences do not matter at fixed sd
        lp[f"s{i}"] = log_p0(x)
    bounds = [[-1.0, 1.0], [-1.0, 1.0], [-2.0, 2.0]]
    res = hierarchical(st1, ["a", "b", "x"], bounds, pooled=["x"], transforms={"x": "identity"},
                       fix={"sd_x": sd}, log_prior=lp, n_samples=600, seed=1, progress=False, tmcmc_options=FAST)

    def augment(theta):
        xx = theta[:, 0] + theta[:, 1]
        return np.column_stack([theta, xx]), log_p0(xx)

    def loglik(theta):
        return norm.logpdf(y[5], theta[:, 0] + theta[:, 1], s[5])

    prec = 1.0 / (sd**2 + s[:5] ** 2)  # mu | other specimens (leave-one-out weighting), flat prior
    V = 1.0 / prec.sum()
    m = V * np.sum(prec * y[:5])
    v = 1.0 / (1.0 / s[5] ** 2 + 1.0 / sd**2)
    mean = v * (y[5] / s[5] ** 2 + m / sd**2)
    sdev = np.sqrt(v + (v / sd**2) ** 2 * V)
    with pytest.raises(HbmError, match="bounds"):
        refine_individual(res, "s5", loglik, augment=augment)
    out = refine_individual(res, "s5", loglik, augment=augment, bounds=bounds[:2], n_samples=2000, seed=2,
                            progress=False, **FAST)
    assert out.samples.shape == (2000, 2)
    xs = out.samples.sum(axis=1)
    assert abs(xs.mean() - mean) < 4 * sdev / np.sqrt(xs.size / 3)
    assert abs(xs.std() - sdev) < 0.06 * sdev, (xs.std(), sdev)
    # (a, b) | x stays uniform on its segment: a − x/2 is symmetric with the segment's spread
    assert abs(np.mean(out.samples[:, 0] - xs / 2)) < 0.05
