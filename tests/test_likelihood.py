"""Likelihood: values against scipy densities, gradient against finite differences, FIM
against the dense Gaussian Fisher-information formula, reduced runs, robustness."""

import numpy as np
import pytest
import xarray as xr
from scipy import stats

from hbm.errors import DataError, HbmError
from hbm.likelihood import make_likelihood
from hbm.model import spyrou_model

MODEL = spyrou_model()
TRUTH = np.array([0.9, 0.184, 0.13, 1.5, 9.3, 59.0, 0.012, 0.009])
# strain grid avoiding the kinks (EOPT = 0.184, collagen onset at 59° ≈ 0.21)
STRAIN = np.linspace(0.003, 0.4, 24)


def _dataset(noise_sd=0.003, seed=0, time=None):
    rng = np.random.default_rng(seed)
    s = MODEL.stress(STRAIN, TRUTH) + rng.normal(0, noise_sd, STRAIN.size)
    vars_ = {"strain": ("point", STRAIN), "stress": ("point", s)}
    if time is not None:
        vars_["time"] = ("point", time)
    return xr.Dataset(vars_)


NOISE_ROWS = {"iid": [0.004], "weighted": [0.3], "proportional": [0.003, 0.05], "ar1": [0.004, 0.6]}


def _row(noise):
    return np.r_[TRUTH, NOISE_ROWS[noise]]


@pytest.mark.parametrize("noise", ["iid", "weighted", "proportional"])
def test_loglik_matches_scipy(noise):
    ds = _dataset()
    lik = make_likelihood(MODEL, ds, noise=noise)
    row = _row(noise)
    m = MODEL.stress(STRAIN, TRUTH)
    y = ds.stress.values
    if noise == "iid":
        sd = np.full_like(y, row[-1])
    elif noise == "weighted":
        w = np.maximum(np.abs(y).max() / 10, np.abs(y))
        sd = row[-1] * w
    else:
        sd = np.sqrt(row[-2] ** 2 + (row[-1] * m) ** 2)
    expect = stats.norm.logpdf(y, m, sd).sum()
    assert lik(row[None])[0] == pytest.approx(expect, rel=1e-12, abs=1e-9)
    assert float(lik(row)) == pytest.approx(expect, rel=1e-12, abs=1e-9)  # 1-D row -> scalar


def test_ar1_matches_dense_multivariate_normal_with_history_restart():
    # two loading histories: time restarts at point 10
    time = np.r_[np.arange(10.0), np.arange(STRAIN.size - 10.0)]
    ds = _dataset(time=time)
    lik = make_likelihood(MODEL, ds, noise="ar1")
    sigma, rho = 0.004, 0.6
    idx = np.arange(STRAIN.size)
    hist = (idx >= 10).astype(int)
    cov = sigma**2 * rho ** np.abs(idx[:, None] - idx[None, :]) * (hist[:, None] == hist[None, :])
    m = MODEL.stress(STRAIN, TRUTH)
    expect = stats.multivariate_normal(m, cov).logpdf(ds.stress.values)
    got = lik(np.r_[TRUTH, sigma, rho][None])[0]
    assert got == pytest.approx(expect, rel=1e-10)
    # rho = 0 reduces to iid
    iid = make_likelihood(MODEL, ds)
    assert lik(np.r_[TRUTH, sigma, 0.0]) == pytest.approx(iid(np.r_[TRUTH, sigma]), rel=1e-12)


def test_out_of_box_and_nonfinite_give_minus_inf_never_nan():
    lik = make_likelihood(MODEL, _dataset())
    good = _row("iid")
    pop = np.tile(good, (6, 1))
    pop[1, 0] = 1.5            # VOLF out of box
    pop[2, 4] = np.nan         # NaN
    pop[3, -1] = np.inf        # inf sigma
    pop[4, -1] = 0.0           # sigma below box
    pop[5, 4] = 200.0          # T2 at the upper edge: huge but finite stress -> finite or -inf
    out = lik(pop)
    assert out.shape == (6,)
    assert not np.isnan(out).any()
    assert np.isfinite(out[0])
    assert np.all(out[1:5] == -np.inf)
    # a whole population of garbage
    garbage = np.random.default_rng(3).normal(0, 1e6, (50, lik.d))
    assert np.all(lik(garbage) == -np.inf)


def _fd_grad(lik, row, rel=1e-6):
    width = lik.bounds[:, 1] - lik.bounds[:, 0]
    h = rel * width
    pts = np.concatenate([row + np.diag(h), row - np.diag(h)])
    f = lik(pts)
    d = lik.d
    return (f[:d] - f[d:]) / (2 * h)


@pytest.mark.parametrize("noise", ["iid", "weighted", "proportional", "ar1"])
def test_gradient_matches_finite_differences(noise):
    time = np.r_[np.arange(12.0), np.arange(STRAIN.size - 12.0)]
    lik = make_likelihood(MODEL, _dataset(time=time), noise=noise)
    row = _row(noise)
    row = row.copy()
    row[0] = 0.8  # off the truth so that the mean part of the gradient is not ~0
    g, fim = lik.gradient_fim(row[None])
    fd = _fd_grad(lik, row)
    np.testing.assert_allclose(g[0], fd, rtol=2e-4, atol=1e-6 * np.abs(fd).max())
    assert fim.shape == (1, lik.d, lik.d)
    np.testing.assert_allclose(fim[0], fim[0].T, rtol=1e-12)


@pytest.mark.parametrize("noise", ["iid", "weighted", "proportional", "ar1"])
def test_fim_matches_dense_gaussian_formula(noise):
    """F_ab = J_aᵀ Σ⁻¹ J_b + ½ tr(Σ⁻¹ ∂_aΣ Σ⁻¹ ∂_bΣ), with ∂ by finite differences."""
    time = np.r_[np.arange(12.0), np.arange(STRAIN.size - 12.0)]
    lik = make_likelihood(MODEL, _dataset(time=time), noise=noise)
    row = _row(noise)
    n = STRAIN.size
    idx = np.arange(n)
    hist = (idx >= 12).astype(int)

    def mean_cov(th):
        m = lik.predict(th[None])[0]
        if noise == "ar1":
            s, r = th[-2], th[-1]
            cov = s**2 * r ** np.abs(idx[:, None] - idx[None, :]) * (hist[:, None] == hist[None, :])
        else:
            cov = np.diag(lik.noise_sd(th[None])[0] ** 2)
        return m, cov

    h = 1e-6 * (lik.bounds[:, 1] - lik.bounds[:, 0])
    dm, dc = [], []
    for a in range(lik.d):
        e = np.zeros(lik.d)
        e[a] = h[a]
        mp, cp = mean_cov(row + e)
        mq, cq = mean_cov(row - e)
        dm.append((mp - mq) / (2 * h[a]))
        dc.append((cp - cq) / (2 * h[a]))
    _, cov = mean_cov(row)
    ci = np.linalg.inv(cov)
    dm = np.array(dm)
    expect = dm @ ci @ dm.T + 0.5 * np.array([[np.trace(ci @ dc[a] @ ci @ dc[b]) for b in range(lik.d)]
                                             for a in range(lik.d)])
    _, fim = lik.gradient_fim(row[None])
    scale = np.sqrt(np.outer(np.diag(expect), np.diag(expect)))
    np.testing.assert_allclose(fim[0] / scale, expect / scale, atol=2e-5)


def test_gradient_fim_population_and_out_of_box_rows():
    lik = make_likelihood(MODEL, _dataset())
    rng = np.random.default_rng(0)
    pop = lik.from_unit(rng.uniform(0.2, 0.8, (5, lik.d)))
    pop[2, 0] = 7.0
    g, f = lik.gradient_fim(pop)
    assert g.shape == (5, lik.d) and f.shape == (5, lik.d, lik.d)
    assert np.isnan(g[2]).all()
    ok = [0, 1, 3, 4]
    assert np.isfinite(g[ok]).all() and np.isfinite(f[ok]).all()
    # FIM is positive semi-definite
    assert (np.linalg.eigvalsh(f[ok]) > -1e-8 * np.abs(f[ok]).max()).all()


def test_fix_and_bounds_reduce_the_free_set():
    ds = _dataset()
    full = make_likelihood(MODEL, ds)
    red = make_likelihood(MODEL, ds, fix={"EOPT": 0.184, "GM": 0.009}, bounds={"VOLF": (0.8, 0.95)})
    assert red.names == ("VOLF", "P1", "T1", "T2", "THETA", "GF", "sigma")
    assert red.bounds[0].tolist() == [0.8, 0.95]
    row = np.r_[TRUTH, 0.004]
    rrow = np.delete(row, [1, 7])
    np.testing.assert_allclose(red.model_theta(rrow[None])[0], TRUTH)
    assert red(rrow[None])[0] == pytest.approx(full(row[None])[0], rel=1e-13)
    rrow2 = rrow.copy()
    rrow2[0] = 0.97  # inside the prior box but outside the narrowed box
    assert red(rrow2[None])[0] == -np.inf
    assert set(red.as_dict(rrow)) == set(MODEL.parameter_names) | {"sigma"}


@pytest.mark.parametrize("kw, match", [
    ({"fix": {"FOO": 1.0}}, "unknown parameter.*FOO"),
    ({"fix": {"VOLF": 2.0}}, "VOLF.*outside"),
    ({"bounds": {"T2": (10, 5)}}, "T2"),
    ({"bounds": {"T2": (-5, 5)}}, "outside the prior box"),
    ({"noise": "laplace"}, "noise model"),
    ({"sigma_bounds": (0.0, 1.0)}, "sigma_bounds"),
])
def test_bad_options_raise_one_line_hbm_errors(kw, match):
    with pytest.raises(HbmError, match=match) as info:
        make_likelihood(MODEL, _dataset(), **kw)
    assert "\n" not in str(info.value)


def test_bad_data_raise_data_error():
    ds = xr.Dataset({"strain": ("point", STRAIN)})
    with pytest.raises(DataError, match="stress"):
        make_likelihood(MODEL, ds)
    ds = _dataset()
    ds["stress"][3] = np.nan
    with pytest.raises(DataError, match="finite"):
        make_likelihood(MODEL, ds)


def test_default_sigma_box_and_wls_objective():
    ds = _dataset()
    lik = make_likelihood(MODEL, ds)
    smax = np.abs(ds.stress.values).max()
    assert lik.bounds[-1].tolist() == [1e-4, max(0.05, 0.5 * smax)]
    y = ds.stress.values
    w = np.maximum(smax / 10, np.abs(y))
    er = (((MODEL.stress(STRAIN, TRUTH) - y) / w) ** 2).sum()
    assert lik.wls(TRUTH[None])[0] == pytest.approx(er, rel=1e-12)
    # the weighted noise model's log-likelihood is a decreasing function of Er at fixed scale
    wl = make_likelihood(MODEL, ds, noise="weighted")
    a = wl(np.r_[TRUTH, 0.3][None])[0]
    other = TRUTH.copy()
    other[3] = 1.6
    b = wl(np.r_[other, 0.3][None])[0]
    assert (a - b) == pytest.approx(-(lik.wls(TRUTH[None])[0] - lik.wls(other[None])[0]) / (2 * 0.09), rel=1e-10)


def test_likelihood_cost_close_to_model_cost():
    """The iid log-likelihood adds little to the model call (10,000 × 9 on 40 points)."""
    import time as _t
    e = np.linspace(0, 0.4, 40)
    ds = xr.Dataset({"strain": ("point", e), "stress": ("point", MODEL.stress(e, TRUTH))})
    lik = make_likelihood(MODEL, ds)
    pop = lik.from_unit(np.random.default_rng(0).random((10_000, lik.d)))
    full = lik.model_theta(pop)
    tl, tm = [], []
    for _ in range(7):
        t0 = _t.perf_counter()
        lik(pop)
        t1 = _t.perf_counter()
        with np.errstate(all="ignore"):
            MODEL.stress(lik.loading, full)
        tm.append(_t.perf_counter() - t1)
        tl.append(t1 - t0)
    assert np.median(tl) < 2.0 * np.median(tm)  # measured ≈ 1.2× on the dev machine


def test_history_effects_see_the_loading_path_and_fd_jacobian_fallback():
    """The likelihood passes time/test to the model (viscoelastic memory) and its gradient is
    right with the model's finite-difference Jacobian (non-analytic effect)."""
    effects = pytest.importorskip("hbm.effects")
    model = MODEL + effects.make_effect("viscoelastic")
    theta = np.r_[TRUTH, 0.4, 1.0]
    # two ramps at different rates, each starting from rest (time restarts)
    e = np.r_[np.linspace(0.01, 0.35, 12), np.linspace(0.01, 0.35, 12)]
    t = np.r_[np.linspace(0, 10, 12), np.linspace(0, 1000, 12)]
    test = np.r_[np.ones(12, int), 2 * np.ones(12, int)]
    s = model.stress(e, theta, time=t, test=test)
    assert not np.allclose(s[:12], s[12:], rtol=1e-3)  # rate matters: the history is used
    ds = xr.Dataset({"strain": ("point", e), "stress": ("point", s + 0.001),
                     "time": ("point", t), "test": ("point", test)})
    lik = make_likelihood(model, ds, fix={"EOPT": 0.184})
    row = np.r_[np.delete(theta, 1), 0.003]
    np.testing.assert_allclose(lik.predict(row[None])[0], s, rtol=1e-12)
    assert lik(row[None])[0] == pytest.approx(stats.norm.logpdf(s + 0.001, s, 0.003).sum(), rel=1e-10)
    g, _ = lik.gradient_fim(row[None])
    fd = _fd_grad(lik, row, rel=1e-5)
    np.testing.assert_allclose(g[0], fd, rtol=2e-3, atol=1e-4 * np.abs(fd).max())


def test_noise_model_object_names_and_sd():
    from hbm.likelihood import NOISE_MODELS
    from hbm.likelihood.noise import AR1Noise

    assert NOISE_MODELS[:4] == ("iid", "weighted", "proportional", "ar1")
    ds = _dataset()
    lik = make_likelihood(MODEL, ds, noise="ar1")
    assert lik.noise == "ar1" and isinstance(lik.noise_model, AR1Noise)
    assert lik.noise_names == ("sigma", "rho") and lik.names[-2:] == ("sigma", "rho")
    # the proportional sd needs the model stress: computed when not given
    prop = make_likelihood(MODEL, ds, noise="proportional")
    row = _row("proportional")
    m = MODEL.stress(STRAIN, TRUTH)
    expect = np.sqrt(0.003 ** 2 + (0.05 * m) ** 2)
    np.testing.assert_allclose(prop.noise_sd(row[None])[0], expect, rtol=1e-13)
    np.testing.assert_allclose(prop.noise_sd(row[None], m[None])[0], expect, rtol=1e-13)


def test_noise_parameter_names_must_not_clash_with_model_parameters():
    from hbm.likelihood.noise import NOISE_REGISTRY, IidNoise, register_noise

    class Clash(IidNoise):
        name = "test_clash"
        names = ("VOLF",)

        def default_box(self):
            return {"VOLF": (1e-4, 1.0)}

    register_noise(Clash)
    try:
        with pytest.raises(HbmError, match="VOLF.*clash"):
            make_likelihood(MODEL, _dataset(), noise="test_clash")
    finally:
        NOISE_REGISTRY.pop("test_clash")
