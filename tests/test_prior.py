"""hbm.likelihood.prior: user-controlled priors (TOML, widened boxes, loguniform forms) through Likelihood and fit_specimen."""

from __future__ import annotations

import numpy as np
import pytest
import xarray as xr
from scipy import stats

from hbm import io
from hbm.errors import HbmError
from hbm.fit import fit_specimen
from hbm.likelihood import make_likelihood
from hbm.model import spyrou_model
from hbm.likelihood.prior import Prior, PriorError, load_prior, resolve_prior
from test_fit import _specimen

TRUTH = {"VOLF": 0.9, "EOPT": 0.15, "P1": 0.06, "T1": 1.0, "T2": 14.0, "THETA": 59.0, "GF": 0.03, "GM": 0.02}


def _write(tmp_path, text, name="prior.toml"):
    p = tmp_path / name
    p.write_text(text)
    return p


# ----------------------------------------------------------------------------- parsing and errors
def test_toml_prior_is_read_and_applied(tmp_path):
    p = _write(tmp_path, '[VOLF]\nlo = 0.3\nhi = 0.99\n[P1]\nlo = 1e-6\nhi = 1.0\nform = "loguniform"\n')
    pr = Prior.from_toml(p)
    assert pr["VOLF"].lo == 0.3 and pr["VOLF"].form == "uniform"
    assert pr["P1"].is_log and (pr["P1"].lo, pr["P1"].hi) == (1e-6, 1.0)
    lik = make_likelihood(spyrou_model(), _toy_curve(), prior=p)
    j = lik.index("P1")
    np.testing.assert_allclose(lik.bounds[j], np.log([1e-6, 1.0]), rtol=0, atol=0)
    np.testing.assert_array_equal(lik.natural_bounds[j], [1e-6, 1.0])
    np.testing.assert_array_equal(lik.bounds[lik.index("VOLF")], [0.3, 0.99])
    assert lik.forms[j] == "loguniform" and lik.forms[lik.index("VOLF")] == "uniform"
    # the thesis box elsewhere
    np.testing.assert_array_equal(lik.bounds[lik.index("THETA")], [55.0, 60.0])


@pytest.mark.parametrize("text, match", [
    ("[VOLF]\nlo = 0.9\nhi = 0.5\n", "VOLF.*lo < hi"),
    ("[VOLF]\nlo = 0.5\nhi = 0.5\n", "VOLF.*lo < hi"),
    ('[P1]\nlo = 0.0\nhi = 1.0\nform = "loguniform"\n', "P1.*loguniform.*lo > 0"),
    ('[P1]\nlo = 0.1\nhi = 1.0\nform = "normal"\n', "P1.*unknown form 'normal'"),
    ("[P1]\nlo = 0.1\nhi = 1.0\nmean = 3\n", "P1.*unknown key.*mean"),
    ("[P1]\nlo = 0.1\n", "P1.*missing hi"),
    ('[P1]\nlo = "a"\nhi = 1\n', "P1.*numbers"),
    ("P1 = 3\n", "P1.*expected a table"),
    ("[P1\nlo = 1\n", "not a valid TOML"),
    ("", "no parameter table"),
    ("# only a comment\n", "no parameter table"),
])
def test_bad_prior_files_raise_one_line_prior_errors(tmp_path, text, match):
    with pytest.raises(PriorError, match=match) as info:
        Prior.from_toml(_write(tmp_path, text))
    assert isinstance(info.value, HbmError) and "\n" not in str(info.value)
    assert "prior.toml" in str(info.value)


def test_unknown_parameter_and_missing_file(tmp_path):
    p = _write(tmp_path, "[FOO]\nlo = 0\nhi = 1\n")
    with pytest.raises(HbmError, match="unknown parameter.*FOO.*VOLF.*sigma"):
        make_likelihood(spyrou_model(), _toy_curve(), prior=p)
    with pytest.raises(PriorError, match="cannot read"):
        Prior.from_toml(tmp_path / "nope.toml")
    with pytest.raises(PriorError, match="unknown parameter.*BAR"):
        resolve_prior(spyrou_model(), bounds={"BAR": (0, 1)})


def test_bounds_may_widen_with_a_notice():
    model = spyrou_model()
    pr = resolve_prior(model, {"P1": {"lo": 1e-6, "hi": 1.0, "form": "loguniform"}}, bounds={"THETA": (40, 70)})
    assert pr["THETA"].lo == 40 and pr["THETA"].hi == 70 and pr["P1"].is_log
    assert pr.notice(model) == ("prior departs from the thesis box: P1 [0.0001, 0.5] -> loguniform [1e-06, 1]; "
                                "THETA [55, 60] -> [40, 70]")
    assert resolve_prior(model).notice(model) is None
    # an override keeps the form; the likelihood accepts the widened box
    pr2 = pr.override({"P1": (1e-5, 2.0)})
    assert pr2["P1"].is_log and pr2["P1"].hi == 2.0
    lik = make_likelihood(model, _toy_curve(), prior=pr)
    np.testing.assert_array_equal(lik.natural_bounds[lik.index("THETA")], [40, 70])
    # make_likelihood(bounds=...) still only narrows inside the (user) prior box
    with pytest.raises(HbmError, match="outside the prior box"):
        make_likelihood(model, _toy_curve(), prior=pr, bounds={"THETA": (30, 50)})
    # with_bounds keeps the prior's forms and may leave the current box
    sub = lik.with_bounds(THETA=(35.0, 75.0), P1=(1e-3, 1e-2))
    np.testing.assert_allclose(sub.bounds[sub.index("P1")], np.log([1e-3, 1e-2]))
    np.testing.assert_array_equal(sub.natural_bounds[sub.index("THETA")], [35, 75])
    np.testing.assert_array_equal(sub.bounds[sub.n_model:], lik.bounds[lik.n_model:])
    assert load_prior(pr.to_dict()) == pr


# ----------------------------------------------------------------------------- the transform
def _toy_curve(n=12):
    m = spyrou_model()
    eps = np.linspace(0.0, 0.4, n)
    s = m.stress(eps, np.array([list(TRUTH.values())]))[0] + 0.002 * np.random.default_rng(3).standard_normal(n)
    return xr.Dataset({"strain": ("point", eps), "stress": ("point", s)}, attrs={"id": "toy"})


def test_loguniform_likelihood_equals_natural_one_and_gradient_is_chain_rule():
    model = spyrou_model()
    data = _toy_curve()
    prior = {"P1": (1e-6, 1.0, "loguniform"), "GF": (1e-5, 0.1, "loguniform"), "sigma": (1e-4, 0.1, "loguniform")}
    lg = make_likelihood(model, data, prior=prior, bounds={"P1": (1e-4, 0.5), "GF": (1e-4, 0.1)})
    nat = make_likelihood(model, data, sigma_bounds=(1e-4, 0.1))
    rng = np.random.default_rng(0)
    theta = nat.bounds[:, 0] + rng.random((40, nat.d)) * np.ptp(nat.bounds, axis=1)
    y = lg.from_natural(theta)
    assert lg.in_box(y).all()
    np.testing.assert_allclose(lg.to_natural(y), theta, rtol=1e-14)
    np.testing.assert_allclose(lg(y), nat(theta), rtol=1e-12)
    np.testing.assert_allclose(lg.predict(y), nat.predict(theta), rtol=1e-12)
    assert lg.as_dict(y[0]) == pytest.approx(nat.as_dict(theta[0]), rel=1e-12)
    # gradient in working coordinates against central differences of lg
    g, f = lg.gradient_fim(y[:3])
    h = 1e-6
    for k in range(lg.d):
        e = np.zeros(lg.d)
        e[k] = h
        fd = (lg(y[:3] + e) - lg(y[:3] - e)) / (2 * h)
        np.testing.assert_allclose(g[:, k], fd, rtol=2e-4, atol=1e-6)
    gn, fn = nat.gradient_fim(theta[:3])
    s = np.where(lg._log, theta[:3], 1.0)
    np.testing.assert_allclose(f, fn * s[:, :, None] * s[:, None, :], rtol=1e-12)


class ToyModel:
    """stress = log(P) at every point: a Gaussian likelihood in log P with closed-form answers."""

    name = "toy"
    effect_names = ()
    parameter_names = ("P",)
    n_params = 1

    def __init__(self, lo=1e-3, hi=10.0):
        self.bounds = np.array([[lo, hi]])

    def index(self, name):
        return self.parameter_names.index(name)

    def stress(self, loading, theta):
        npt = loading.n_points if hasattr(loading, "n_points") else len(loading)
        with np.errstate(all="ignore"):
            return np.log(np.asarray(theta, float)[..., :1]) * np.ones(npt)


def _toy_fit(mu, form, lo=1e-3, hi=10.0, n=4, sigma=0.4, samples=3000, seed=5, out=None):
    data = xr.Dataset({"strain": ("point", np.linspace(0.0, 0.3, n)), "stress": ("point", np.full(n, mu))},
                      attrs={"id": "toy"})
    # sigma held (to 1e-9 relative) at its value by a vanishing box
    prior = {"P": (lo, hi, form), "sigma": (sigma, sigma * (1 + 1e-9))}
    return fit_specimen(data, model=ToyModel(lo, hi), samples=samples, restarts=0, seed=seed, progress=False,
                        prior=prior, out=out)


def test_loguniform_posterior_and_evidence_match_closed_form(tmp_path):
    lo, hi, n, sigma = 1e-3, 10.0, 4, 0.4
    la, lb = np.log(lo), np.log(hi)
    mu = la + 0.05  # piled against the lower edge: the truncation matters
    s = sigma / np.sqrt(n)
    res = _toy_fit(mu, "loguniform", lo, hi, n, sigma, out=tmp_path / "toy.nc")
    r = res.result
    p = r.samples[:, 0]
    assert p.min() >= lo and p.max() <= hi  # natural units, not log
    tn = stats.truncnorm((la - mu) / s, (lb - mu) / s, loc=mu, scale=s)
    logp = np.log(p)
    assert abs(logp.mean() - tn.mean()) < 0.02 and abs(logp.std() / tn.std() - 1) < 0.08
    # Z = (1/W) ∫ L(y) dy, L(y) = (2πσ²)^(-n/2) exp(-n (μ - y)² / 2σ²)
    log_z = (-0.5 * n * np.log(2 * np.pi * sigma ** 2) + np.log(s * np.sqrt(2 * np.pi))
             + np.log(stats.norm.cdf((lb - mu) / s) - stats.norm.cdf((la - mu) / s))
             - np.log(lb - la))
    assert abs(r.log_evidence - log_z) < max(0.1, 3 * r.log_evidence_se)
    # mass within 2 % of the log width of the lower edge: the truncated normal's
    w = 0.02 * (lb - la)
    frac = tn.cdf(la + w)
    edge = [a for a in r.at_bounds if a["parameter"] == "P"]
    assert len(edge) == 1 and edge[0]["side"] == "lower" and edge[0]["edge"] == lo
    assert abs(edge[0]["fraction"] - frac) < 0.05 and edge[0]["map_at_edge"]
    # stored prior and warnings survive the file
    back = io.read_specimen_result(res.path)
    assert back.prior["P"] == {"lo": lo, "hi": hi, "form": "loguniform"}
    assert back.at_bounds == r.at_bounds
    np.testing.assert_array_equal(back.bounds[0], [lo, hi])
    assert "P logU[0.001, 10]" in res.table() and "P at its lower bound 0.001" in res.table()


def test_uniform_and_loguniform_forms_give_their_own_posteriors():
    """Away from the edges: log-uniform -> log P ~ N(μ, s²); uniform in P -> N(μ + s², s²)."""
    n, sigma = 4, 0.4
    s = sigma / np.sqrt(n)
    mu = np.log(0.1)
    lg = np.log(_toy_fit(mu, "loguniform", n=n, sigma=sigma).result.samples[:, 0])
    un = np.log(_toy_fit(mu, "uniform", n=n, sigma=sigma).result.samples[:, 0])
    assert abs(lg.mean() - mu) < 0.015 and abs(un.mean() - (mu + s * s)) < 0.015
    assert abs(lg.std() / s - 1) < 0.08 and abs(un.std() / s - 1) < 0.08


def test_thesis_prior_passed_explicitly_is_bitwise_the_default():
    data = _specimen(n=16)
    kw = dict(samples=120, restarts=1, optimize_options={"maxfevals": 150}, seed=3, progress=False,
              tmcmc_options={"max_steps": 4})
    a = fit_specimen(data, **kw).result
    b = fit_specimen(data, prior=resolve_prior(spyrou_model()), **kw).result
    for key in ("samples", "log_likelihood", "predictive", "predictive_model", "pointwise_log_likelihood", "bounds"):
        np.testing.assert_array_equal(getattr(a, key), getattr(b, key))
    assert a.log_evidence == b.log_evidence and a.optima == b.optima
    assert a.prior == b.prior and a.prior["THETA"] == {"lo": 55.0, "hi": 60.0, "form": "uniform"}


def test_spyrou_fit_with_loguniform_prior_reports_natural_units():
    data = _specimen(n=16)
    prior = {"P1": (1e-5, 1.0, "loguniform"), "GF": (1e-5, 0.1, "loguniform")}
    res = fit_specimen(data, samples=150, restarts=1, optimize_options={"maxfevals": 200}, seed=2,
                       progress=False, tmcmc_options={"max_steps": 4}, prior=prior)
    r, lik = res.result, res.likelihood
    for nm in ("P1", "GF"):
        col = r.column(nm)
        assert col.min() >= prior[nm][0] and col.max() <= prior[nm][1]
        assert all(prior[nm][0] <= o["params"][nm] <= prior[nm][1] for o in r.optima)
    np.testing.assert_allclose(r.samples, lik.to_natural(res.tmcmc.samples))
    np.testing.assert_allclose(r.predictive_model, lik.predict(lik.from_natural(r.samples)), rtol=1e-10)
    with pytest.raises(PriorError, match="sweep.*loguniform"):
        fit_specimen(data, samples=20, restarts=1, sweep="P1:0.1", prior=prior, progress=False)


def test_population_refuses_non_uniform_stage1_priors():
    from types import SimpleNamespace

    from hbm.population import run_population

    model = spyrou_model()
    rng = np.random.default_rng(0)
    prior = {n: {"lo": float(a), "hi": float(b), "form": "uniform"}
             for n, (a, b) in zip(model.parameter_names, model.bounds)}
    prior["P1"]["form"] = "loguniform"
    res = {f"s{k}": SimpleNamespace(names=list(model.parameter_names), bounds=model.bounds.copy(),
                                    samples=rng.uniform(model.bounds[:, 0], model.bounds[:, 1], (50, 8)),
                                    log_evidence=0.0, log_evidence_se=0.01, specimen_id=f"s{k}", prior=prior)
           for k in range(2)}
    with pytest.raises(HbmError, match="non-uniform prior on P1"):
        run_population(res, None, model, pooled=["T2"], samples=50, progress=False)


def test_wls_optimum_reports_natural_noise_under_a_loguniform_sigma_prior():
    from hbm.fit.optimization import optimize

    data = _specimen(n=16)
    kw = dict(restarts=1, seed=4, objective="wls", maxfevals=300)
    plain = optimize(make_likelihood(spyrou_model(), data, sigma_bounds=(1e-4, 0.1)), **kw).best
    lg = optimize(make_likelihood(spyrou_model(), data, prior={"sigma": (1e-4, 0.1, "loguniform")}), **kw).best
    # the model parameters are optimised identically (wls ignores sigma); sigma is the same RMS residual
    assert lg["params"]["VOLF"] == plain["params"]["VOLF"]
    assert lg["params"]["sigma"] == pytest.approx(plain["params"]["sigma"], rel=1e-12)
