"""The exact fallback of the hierarchical layer (hbm.samplers.hierarchical.joint_gibbs) against independent truths.

Conjugate Gaussian toy: six specimens with Gaussian likelihoods N(y_i; θ_i, s_i²), a normal population
N(mu, sd²) (identity transform, truncated to a wide box) and the layer's hyperprior (mu uniform, log sd
uniform).  The marginal posterior of (mu, sd) is known in closed form up to a 2-D quadrature,
p(mu, sd | y) ∝ Π N(y_i; mu, sd² + s_i²) / Z(mu, sd)^n, and θ_1 | mu, sd, y is normal.
"""

import numpy as np
import pytest
from scipy.stats import norm

import hbm.cli as cli
import hbm.cli.run as cli_run
from hbm.errors import HbmError
from hbm.samplers.hierarchical import HierarchicalModel
from hbm.samplers.hierarchical import ExactSpecimen, ReuseSpecimen, joint_gibbs, rhat_ess

Y = np.array([-1.5, -0.3, 0.2, 0.9, 2.1, 3.0])
S = np.array([0.5, 1.0, 1.5, 0.7, 2.0, 1.0])
LO, HI = -20.0, 20.0


@pytest.fixture(scope="module")
def truth():
    """Quadrature of the toy's joint posterior: weights on a (mu, log sd) grid, θ_1's conditional."""
    mu = np.linspace(-8, 10, 361)
    lsd = np.linspace(np.log(0.2), np.log(10.0), 300)
    M, L = np.meshgrid(mu, lsd, indexing="ij")
    SD = np.exp(L)
    logz = np.log(norm.cdf((HI - M) / SD) - norm.cdf((LO - M) / SD))
    lp = sum(norm.logpdf(y, M, np.sqrt(SD**2 + s**2)) for y, s in zip(Y, S)) - len(Y) * logz
    w = np.exp(lp - lp.max())
    w /= w.sum()
    v = 1.0 / (1.0 / SD**2 + 1.0 / S[0] ** 2)
    m1 = v * (M / SD**2 + Y[0] / S[0] ** 2)
    return {"M": M, "SD": SD, "w": w, "m1": m1, "v1": v}


def _wq(vals, w, p):
    o = np.argsort(vals.ravel())
    return np.interp(p, np.cumsum(w.ravel()[o]), vals.ravel()[o])


def _model():
    return HierarchicalModel(["x"], [[LO, HI]], sd_range=(0.005, 0.25))  # sd in [0.2, 10]


def _exact(rows, init):
    return {f"s{i}": ExactSpecimen(log_likelihood=(lambda y, s: lambda t: norm.logpdf(y, t[:, 0], s))(y, s),
                                   columns=lambda t: (t, None), box=np.array([[LO, HI]]), init=init[i],
                                   scale_rows=rows[i], pooled_cols={0: 0})
            for i, (y, s) in enumerate(zip(Y, S))}


P = np.array([0.05, 0.5, 0.95])


def test_exact_specimens_match_the_conjugate_posterior(truth):
    rng = np.random.default_rng(1)
    nc = 128
    rows = [y + s * rng.standard_normal((2000, 1)) for y, s in zip(Y, S)]
    # crude starting points: the chains have to find the posterior of the population themselves
    init_raw = np.column_stack([rng.uniform(-2, 3, nc), np.log(rng.uniform(0.5, 3, nc))])
    r = joint_gibbs(_model(), init_raw, _exact(rows, [x[:nc] for x in rows]), n_keep=30, n_burn=80, thin=2,
                    seed=2, n_components=12)
    nat = _model().natural(r.flat_raw())
    tw = truth["w"]
    sd_mu = np.sqrt(np.sum(tw * truth["M"] ** 2) - np.sum(tw * truth["M"]) ** 2)
    sd_sd = np.sqrt(np.sum(tw * truth["SD"] ** 2) - np.sum(tw * truth["SD"]) ** 2)
    assert np.all(np.abs(np.quantile(nat[:, 0], P) - _wq(truth["M"], tw, P)) < 0.12 * sd_mu)
    assert np.all(np.abs(np.quantile(nat[:, 1], P) - _wq(truth["SD"], tw, P)) < 0.15 * sd_sd)
    grid = np.linspace(-5, 3, 81)
    cdf = np.array([(tw * norm.cdf((g - truth["m1"]) / np.sqrt(truth["v1"]))).sum() for g in grid])
    th1 = r.flat_state("s0")[:, 0]
    assert np.all(np.abs(np.quantile(th1, P) - np.interp(P, cdf, grid)) < 0.1 * th1.std())
    assert max(r.rhat.values()) < 1.1
    assert r.evaluations["s0"] > 128 * 140 * 3  # every move evaluates all chains in one batch
    assert 0.1 < r.acceptance["population"] < 0.5


def exact_joint_draws(truth, rng, nc):
    """``nc`` exact draws of the toy's joint posterior: (mu, sd) from the quadrature grid, each θ_i from its
    normal conditional."""
    flat = truth["w"].ravel()
    j = rng.choice(flat.size, nc, p=flat)
    mu, sd = truth["M"].ravel()[j], truth["SD"].ravel()[j]
    th = []
    for y, s in zip(Y, S):
        v = 1.0 / (1.0 / sd**2 + 1.0 / s**2)
        th.append((v * (mu / sd**2 + y / s**2) + np.sqrt(v) * rng.standard_normal(nc))[:, None])
    return mu, sd, th


def test_exact_target_is_left_invariant(truth):
    """Chains started from exact draws of the joint posterior stay distributed as it (no burn-in, no adaptation)."""
    rng = np.random.default_rng(3)
    mu, sd, th = exact_joint_draws(truth, rng, 400)
    rows = [y + s * rng.standard_normal((2000, 1)) for y, s in zip(Y, S)]
    r = joint_gibbs(_model(), np.column_stack([mu, np.log(sd)]), _exact(rows, th), n_keep=8, n_burn=0, thin=3,
                    seed=4, n_components=12)
    nat = _model().natural(r.flat_raw())
    exact_mu = _wq(truth["M"], truth["w"], P)
    start_mu = np.quantile(mu, P)
    # the kept draws are as close to the truth as the exact starting sample is (Monte Carlo error only)
    assert np.all(np.abs(np.quantile(nat[:, 0], P) - exact_mu) < 0.25 + 1.5 * np.abs(start_mu - exact_mu))
    cdf_mu = np.interp(np.sort(nat[:, 0]), np.sort(truth["M"].ravel()),
                       np.cumsum(truth["w"].ravel()[np.argsort(truth["M"].ravel())]))
    ks = np.max(np.abs(cdf_mu - (np.arange(cdf_mu.size) + 0.5) / cdf_mu.size))
    assert ks < 0.06  # 3200 draws, correlated within chains: an invariant kernel stays well inside this


def test_reuse_specimens_follow_the_empirical_posterior(truth):
    rng = np.random.default_rng(5)
    nc = 128
    specs = {f"s{i}": ReuseSpecimen(rows=y + s * rng.standard_normal((4000, 1)), log_prior=None,
                                    init=np.arange(nc)) for i, (y, s) in enumerate(zip(Y, S))}
    init_raw = np.column_stack([rng.uniform(-2, 3, nc), np.log(rng.uniform(0.5, 3, nc))])
    r = joint_gibbs(_model(), init_raw, specs, n_keep=40, n_burn=100, thin=2, seed=6)
    nat = _model().natural(r.flat_raw())
    assert np.all(np.abs(np.quantile(nat[:, 0], P) - _wq(truth["M"], truth["w"], P)) < 0.2)
    assert r.evaluations == {}  # no likelihood calls for reused specimens
    assert r.flat_state("s0").dtype.kind == "i"


def test_rhat_ess_on_known_chains():
    rng = np.random.default_rng(7)
    iid = rng.standard_normal((64, 400))
    rh, ess = rhat_ess(iid)
    assert abs(rh - 1.0) < 0.01 and 0.8 * iid.size < ess < 1.2 * iid.size
    rho = 0.8  # AR(1): integrated autocorrelation time (1 + rho) / (1 - rho) = 9
    x = np.empty((64, 2000))
    x[:, 0] = rng.standard_normal(64)
    e = rng.standard_normal((64, 2000)) * np.sqrt(1 - rho**2)
    for t in range(1, 2000):
        x[:, t] = rho * x[:, t - 1] + e[:, t]
    rh, ess = rhat_ess(x)
    assert abs(rh - 1.0) < 0.02 and 0.8 * x.size / 9 < ess < 1.2 * x.size / 9
    shifted = iid + np.arange(64)[:, None] * 0.5  # chains that disagree
    assert rhat_ess(shifted)[0] > 2


def test_rhat_ess_agree_with_arviz():
    """An independent implementation (ArviZ, a test extra): rank-normalised split R-hat (bulk)
    equal, bulk ESS within 5 % (the autocorrelation truncation differs in detail)."""
    az = pytest.importorskip("arviz")
    rng = np.random.default_rng(3)
    x = np.cumsum(rng.standard_normal((8, 500)), axis=1) * 0.05 + rng.standard_normal((8, 500))
    x += np.arange(8)[:, None] * 0.1  # chains that disagree a little
    rh, ess = rhat_ess(x)
    assert rh == pytest.approx(float(az.rhat(x, method="z_scale")), abs=1e-10)
    assert ess == pytest.approx(float(az.ess(x, method="bulk")), rel=0.05)


def test_bad_input():
    m = _model()
    with pytest.raises(HbmError, match="init_raw"):
        joint_gibbs(m, np.zeros((2, 2)), {})
    rows = np.zeros((10, 1))
    spec = ExactSpecimen(log_likelihood=lambda t: np.zeros(len(t)), columns=lambda t: (t, None),
                         box=np.array([[LO, HI]]), init=np.full((8, 1), 50.0), scale_rows=rows + np.arange(10)[:, None])
    with pytest.raises(HbmError, match="no finite target"):
        joint_gibbs(m, np.tile([0.0, 0.0], (8, 1)), {"a": spec})


def test_population_exact_settings_and_combination_coordinates():
    from hbm.identifiability.combinations import log_density, support_hull, to_features
    from hbm.model import spyrou_model
    from hbm.population import PopulationConfig
    from hbm.population.fallbacks import exact_applies
    from hbm.population.pooling import PhiCoordinates

    with pytest.raises(HbmError, match="gibbs"):  # a record refuses a bad setting when it is built
        PopulationConfig(exact="nuts")
    with pytest.raises(HbmError, match="exact_chains"):
        PopulationConfig(exact_chains=2)
    assert PopulationConfig().exact == "gibbs"  # on by default (README, results/benchmarks/hierarchical_gold.md)
    data = {"a": None, "b": None}
    assert not exact_applies(PopulationConfig(groups={"a": "x"}), ["a"], data, "ab")  # grouped: refinements
    assert not exact_applies(PopulationConfig(), [], data, "ab")  # nothing flagged: plain reuse
    assert not exact_applies(PopulationConfig(), ["a"], None, "ab")  # no data: reuse (flag warned)
    assert exact_applies(PopulationConfig(), ["a"], data, "abc") == ["a", "b"]  # all with data
    assert exact_applies(PopulationConfig(exact_all=False), ["a"], data, "ab") == ["a"]
    # the fibre map: a θ with the given combinations exactly where p0(φ) > 0 (its support)
    m = spyrou_model()
    names, b = list(m.parameter_names), np.asarray(m.bounds)
    hull = np.log(support_hull(b, names))
    co = PhiCoordinates(names, b, hull, 0.0)
    rng = np.random.default_rng(0)
    phi = rng.uniform(hull[:, 0], hull[:, 1], (3000, 3))
    rest = b[co.other, 0] + rng.random((3000, len(co.other))) * np.ptp(b[co.other], axis=1)
    th, ok = co.theta_of(np.column_stack([phi, rest]))
    assert np.array_equal(ok, np.isfinite(log_density(phi, b, names)))
    assert 0.5 < ok.mean() < 1.0
    assert np.allclose(np.log(to_features(names, th[ok])), phi[ok], atol=1e-12)
    assert np.all((th >= b[:, 0]) & (th <= b[:, 1]))


def test_report_says_what_the_exact_fallback_did(tmp_path):
    from types import SimpleNamespace

    from hbm.workflow.report import _reuse

    reuse = {"a": {"unreliable": True, "reasons": ["population mass beyond the samples"], "ess_q10": 300.0},
             "b": {"unreliable": False, "reasons": [], "ess_q10": 900.0}}
    exact = {"exact": ["a"], "n_chains": 128, "n_keep": 60, "n_burn": 600, "evaluations": {"a": 12345},
             "wall_s": 9.0, "rhat_max": 1.2, "ess_min": 400.0}
    h = SimpleNamespace(reuse=reuse, attrs={"refined": [], "exact": exact})
    txt = _reuse(SimpleNamespace(hierarchical=h), tmp_path)
    assert "joint Gibbs, real likelihood" in txt and "joint Gibbs, reweighted samples" in txt
    assert "12345 likelihood evaluations" in txt and "max R-hat 1.2" in txt
    h.attrs = {"refined": ["a"]}
    txt = _reuse(SimpleNamespace(hierarchical=h), tmp_path)
    assert "fresh TMCMC" in txt and "did not run" in txt


def test_run_option_hier_exact_reaches_the_population_layer(monkeypatch, tmp_path):
    """``--hier-exact none`` switches the fallback off; the default is gibbs; --quick shortens it."""
    class Captured(Exception):
        pass

    def capture(cfg, **kw):
        raise Captured(cfg.population_settings())

    monkeypatch.setenv("HBM_DEBUG", "1")
    monkeypatch.setattr(cli_run, "run_workflow", capture)
    got = {}
    for label, extra in (("default", []), ("none", ["--hier-exact", "none"]), ("quick", ["--quick"])):
        with pytest.raises(Captured) as exc:
            cli.main(["run", "--out", str(tmp_path / "r"), "--no-progress", *extra])
        got[label] = exc.value.args[0]
    assert got["default"].exact == "gibbs" and got["none"].exact is None
    assert (got["quick"].exact_burn, got["quick"].exact_keep) == (200, 12)
    assert (got["default"].exact_burn, got["default"].exact_keep) == (400, 120)
