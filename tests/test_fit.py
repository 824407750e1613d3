"""hbm.fit: one-specimen fits, pointwise log-likelihood, predictive, summaries, ``hbm fit``."""

from __future__ import annotations


import warnings

import numpy as np
import pytest
import xarray as xr
from conftest import cli_error

from hbm import io
from hbm.data import synthetic_specimen
from hbm.fit import specimen as fit_mod
from hbm.errors import HbmError, HbmWarning
from hbm.fit import fit_specimen, pointwise_log_likelihood, posterior_predictive, summarize
from hbm.runtime.seeds import child_ints
from hbm.likelihood import make_likelihood
from hbm.model import identifiable_combinations, spyrou_model

TRUTH = {"VOLF": 0.9, "EOPT": 0.15, "P1": 0.06, "T1": 1.0, "T2": 14.0, "THETA": 59.0, "GF": 0.03, "GM": 0.02}
FAST = {"max_steps": 8}


def _specimen(seed=1, n=30, noise="iid", rho=0.0, sid="syn"):
    m = spyrou_model()
    return synthetic_specimen(m, TRUTH, np.linspace(0, 0.42, n), 0.002, seed, noise=noise, rho=rho,
                              attrs={"id": sid})


def test_phase_seeds_deterministic_and_distinct():
    a, b = child_ints(5, 4), child_ints(5, 4)
    assert a == b and len(set(a)) == 4 and all(0 <= x < 2 ** 63 for x in a)
    assert child_ints(6, 4) != a


@pytest.mark.parametrize("noise", ["iid", "weighted", "proportional", "ar1"])
def test_pointwise_log_likelihood_sums_to_total(noise):
    data = _specimen(noise="ar1" if noise == "ar1" else "iid", rho=0.5)
    lik = make_likelihood(spyrou_model(), data, noise=noise)
    rng = np.random.default_rng(0)
    theta = lik.bounds[:, 0] + rng.random((50, lik.d)) * np.ptp(lik.bounds, axis=1)
    pw = pointwise_log_likelihood(lik, theta)
    assert pw.shape == (50, data.n_points)
    np.testing.assert_allclose(pw.sum(axis=1), lik(theta), rtol=1e-10, atol=1e-8)


def test_posterior_predictive_noise_level():
    data = _specimen()
    lik = make_likelihood(spyrou_model(), data)
    row = np.array([list(TRUTH.values()) + [0.01]])
    theta = np.repeat(row, 4000, axis=0)
    m, y = posterior_predictive(lik, theta, seed=3)
    resid = (y - m)[:, 5:]
    assert abs(resid.std() / 0.01 - 1) < 0.02  # noise sd equals sigma
    assert abs(np.corrcoef(resid[:, 0], resid[:, 1])[0, 1]) < 0.05  # iid: no lag correlation
    # AR(1): lag-one correlation equals rho, marginal sd equals sigma
    data = _specimen(noise="ar1", rho=0.6)
    lik = make_likelihood(spyrou_model(), data, noise="ar1")
    theta = np.repeat(np.array([list(TRUTH.values()) + [0.01, 0.6]]), 4000, axis=0)
    m, y = posterior_predictive(lik, theta, seed=4)
    r = y - m
    assert abs(r.std() / 0.01 - 1) < 0.03
    assert abs(np.corrcoef(r[:, 10], r[:, 11])[0, 1] - 0.6) < 0.05


def test_fit_specimen_writes_and_summarizes(tmp_path):
    data = _specimen()
    res = fit_specimen(data, samples=300, restarts=1, sweep="VOLF:0.25", optimize_options={"maxfevals": 300},
                       seed=11, progress=False, out=tmp_path / "syn.nc", checkpoint_dir=tmp_path / "ck",
                       tmcmc_options=FAST)
    assert io.is_complete(res.path) and not (tmp_path / "ck" / "syn.npz").exists()
    back = io.read_specimen_result(res.path)
    np.testing.assert_array_equal(back.samples, res.samples)
    assert back.names == list(res.likelihood.names)
    np.testing.assert_allclose(back.pointwise_log_likelihood.sum(1), back.log_likelihood, rtol=1e-9)
    kinds = {o["kind"] for o in back.optima}
    assert kinds == {"restart", "sweep"} and sum(o["kind"] == "sweep" for o in back.optima) == 2
    s = summarize(back)
    np.testing.assert_allclose(s["T2"]["mean"], back.column("T2").mean())
    combos = identifiable_combinations(list(back.names), back.samples)
    np.testing.assert_allclose(s["(1-VOLF)*T1"]["mean"], combos["(1-VOLF)*T1"].mean())
    lo, hi = np.quantile(combos["G"], [0.05, 0.95])
    assert s["G"]["lower"] == pytest.approx(lo) and s["G"]["upper"] == pytest.approx(hi)
    assert "log-evidence" in res.table() and np.isfinite(res.log_evidence)
    # same seed -> identical result (reproducible fits)
    again = fit_specimen(data, samples=300, restarts=1, sweep="VOLF:0.25", optimize_options={"maxfevals": 300},
                         seed=11, progress=False, tmcmc_options=FAST)
    np.testing.assert_array_equal(again.samples, res.samples)


def test_fit_specimen_fixed_parameter_and_errors():
    data = _specimen()
    res = fit_specimen(data, samples=100, restarts=0, fix={"EOPT": 0.15}, progress=False, tmcmc_options=FAST)
    assert "EOPT" not in res.names and res.result.fixed == {"EOPT": 0.15}
    assert summarize(res.result)["G"]["mean"] > 0
    with pytest.raises(HbmError):
        fit_specimen(data, samples=100, move="bogus", progress=False)
    with pytest.raises(HbmError):
        fit_specimen(data, samples=100, restarts=0, fix={"NOPE": 1.0}, progress=False)


def test_cli_fit(tmp_path, run_cli):
    from hbm.data import save_specimen

    csv = save_specimen(_specimen(sid="clirat"), tmp_path / "clirat.csv")
    out = tmp_path / "o.nc"
    rc, text, _ = run_cli(["fit", csv, "--samples", "100", "--restarts", "1", "--maxfevals", "200", "--out", out,
                           "--no-progress", "--fix", "EOPT=0.15"])
    assert rc == 0 and io.is_complete(out)
    assert "(1-VOLF)*T1" in text and "log-evidence" in text
    assert "sample size >= 20" in cli_error(run_cli, ["fit", csv, "--samples", "2"])
    assert "power of 2" in cli_error(run_cli, ["fit", csv, "--sobol", "100"])


def test_data_size_warnings(monkeypatch):
    """Few points for the free parameters, and a dense curve's measured cost, are said before
    the fit; a plain curve gets neither."""
    model = spyrou_model()
    theta = np.array([[0.9, 0.1, 0.1, 1.0, 12.0, 58.0, 0.01, 0.01]])

    def lik_of(n):
        eps = np.linspace(0, 0.3, n)
        ds = xr.Dataset({"strain": ("point", eps), "stress": ("point", model.stress(eps, theta)[0] + 1e-4)},
                        attrs={"id": "s"})
        return make_likelihood(model, ds)

    with pytest.warns(HbmWarning, match="6 points for 9 free parameters"):
        fit_mod.check_data_size("s", lik_of(6), 100)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        fit_mod.check_data_size("s", lik_of(40), 2000)  # neither warning
    monkeypatch.setattr(fit_mod, "LARGE_CURVE", 100)
    monkeypatch.setattr(fit_mod, "EVALUATIONS_PER_SAMPLE", 10 ** 9)
    with pytest.warns(HbmWarning, match=r"s: 400 points: one evaluation costs .* ms, the TMCMC fit about"):
        fit_mod.check_data_size("s", lik_of(400), 100)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        fit_mod.check_data_size("s", lik_of(400), 100, max_evaluations=10)  # capped: cheap
