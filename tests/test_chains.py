"""Posterior chains for R-hat (issue 29): TMCMC islands, importance batches, the pooling fallback, storage.

Truths: analytic Gaussian posteriors (mean and sd known), constructed populations whose islands sit
in known modes, iid importance weights of known structure, and files laid out as the code before
chains wrote them.
"""

from __future__ import annotations

import math
import warnings

import numpy as np
import pytest

from hbm.data import Series, Specimen
from hbm import io
from hbm.samplers.chains import MAX_SPREAD, POOLED, Chains, importance_batches
from hbm.samplers.tmcmc import step, tmcmc
from hbm.samplers.types import TMCMCConfig, TMCMCState

az = pytest.importorskip("arviz")


def _rhat(x: np.ndarray, k: int) -> float:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return float(az.rhat(np.asarray(x).reshape(k, -1)))


def _gauss(d=3, s=0.3, mu=1.0, half=5.0):
    b = np.array([[-half, half]] * d)
    return (lambda x: -0.5 * np.sum((x - mu) ** 2, axis=1) / s ** 2), b


def test_islands_are_chains_with_rhat_near_one_and_correct_means():
    ll, b = _gauss()
    res = tmcmc(ll, b, 1000, seed=3, progress=False)
    ch = res.chains
    assert ch.n_chains == 4 and ch.method == "tmcmc_islands" and "adaptation" in ch.note
    assert ch.spread <= ch.tolerance
    x = res.samples.reshape(4, 250, 3)
    for j in range(3):
        assert _rhat(res.samples[:, j], 4) < 1.02
    # every island alone is a posterior sample of N(1, 0.3²): its mean within 4 MC sd, with the
    # ESS taken as a third of its 250 draws (as for the whole population in test_tmcmc)
    tol = 4 * 0.3 / math.sqrt(250 / 3)
    assert np.all(np.abs(x.mean(axis=1) - 1.0) <= tol), x.mean(axis=1)
    assert np.all(np.abs(x.std(axis=1) - 0.3) <= 0.3 * 0.25)


def test_pooled_setting_and_evidence_unchanged():
    ll, b = _gauss()
    a = tmcmc(ll, b, 1000, seed=3, progress=False)
    p = tmcmc(ll, b, 1000, seed=3, progress=False, final_resampling="pooled")
    assert a.log_evidence == p.log_evidence and a.log_evidence_se == p.log_evidence_se
    assert p.chains.n_chains == 1 and "final_resampling='pooled'" in p.chains.note
    assert abs(p.samples.mean() - 1.0) < 0.05


def _two_mode_state(minor_weight: float, n=800, beta=0.5, seed=0):
    """Islands 0–2 in the mode at +2, island 3 in the mode at −2 (tempered to ``beta``), and the
    log-likelihood of the mixture w·N(−2, 0.1²) + (1 − w)·N(2, 0.1²) in 1-D."""
    s = 0.1

    def ll(x):
        return np.logaddexp(math.log(minor_weight) - 0.5 * ((x[:, 0] + 2) / s) ** 2,
                            math.log(1 - minor_weight) - 0.5 * ((x[:, 0] - 2) / s) ** 2)

    rng = np.random.default_rng(seed)
    centre = np.where(np.arange(n) < 3 * n // 4, 2.0, -2.0)
    x = (centre + rng.normal(0, s / math.sqrt(beta), n))[:, None]
    state = TMCMCState(x, ll(x), np.zeros(4), beta, 0.0, 0.0, 5, 0.2, 1.0, n,
                       np.random.Generator(np.random.PCG64(seed)).bit_generator.state)
    return ll, state


def _finish(ll, state, b):
    cfg = TMCMCConfig(n_samples=len(state.samples), max_steps=20)
    while state.beta < 1.0:
        state, _ = step(state, ll, b, cfg)
    return state


def test_an_island_stuck_in_another_mode_is_flagged_by_rhat():
    # equal-mass modes: the stuck island's evidence agrees with the others', so the islands stay
    # chains -- and R-hat shows that one of them sits elsewhere
    ll, st = _two_mode_state(0.5)
    b = np.array([[-5.0, 5.0]])
    fin = _finish(ll, st, b)
    assert fin.n_chains == 4
    x = fin.samples[:, 0]
    assert np.all(x[600:] < 0) and np.all(x[:600] > 0)  # the islands kept their modes
    assert _rhat(x, 4) > 1.05


def test_a_dead_island_is_pooled_by_evidence_and_says_why(tmp_path):
    # the stuck island's mode has 1e-4 of the mass: its evidence is ~4.6 nats lower, beyond the
    # tolerance; pooled by evidence the minor mode keeps ~0 mass (equal-weight chains would give it 1/4)
    ll, st = _two_mode_state(1e-4)
    b = np.array([[-5.0, 5.0]])
    cfg = TMCMCConfig(n_samples=800, max_steps=20)
    fin = _finish(ll, st, b)
    assert fin.n_chains == 1
    assert fin.island_log_evidence.max() - fin.island_log_evidence.min() > MAX_SPREAD
    assert np.mean(fin.samples[:, 0] < 0) < 0.01
    from hbm.samplers.tmcmc import _result_chains
    ch = _result_chains(fin, cfg)
    assert ch.n_chains == 1 and "differ by" in ch.note and "no R-hat" in ch.note
    # stored: one chain, the reason in the posterior's attributes, R-hat NaN (the truthful outcome)
    r = io.SpecimenResult(specimen_id="s", names=["x"], samples=fin.samples, log_likelihood=fin.log_likelihood,
                          log_evidence=0.0, log_evidence_se=0.1, bounds=b, chains=ch)
    path = io.write_specimen_result(r, tmp_path / "s.nc")
    idata = az.from_netcdf(str(path))
    assert idata.posterior.sizes["chain"] == 1 and idata.posterior.attrs["chains"] == "pooled"
    assert "differ by" in idata.posterior.attrs["chains_note"]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        assert np.isnan(az.summary(idata)["r_hat"]).all()


def test_importance_batches_resample_within_their_batch():
    rng = np.random.default_rng(0)
    m = 4000
    x = rng.normal(size=m)
    lw = -0.5 * x ** 2 / 0.8  # target N(0, 1) from proposal N(0, 1)·... : weights exp(-x²/1.6)
    idx, ch = importance_batches(lw, 800, 4, np.random.default_rng(1))
    assert ch.n_chains == 4 and ch.method == "importance_batches"
    batch = idx % 4  # interleaved batches: row i belongs to batch i mod 4
    assert np.array_equal(batch, np.repeat(np.arange(4), 200))
    # weighted target: N(0, 1)·exp(−x²/1.6) ∝ N(0, 1/(1 + 1/0.8)) -> sd 0.667
    y = x[idx]
    assert abs(y.mean()) < 4 * 0.667 / math.sqrt(800 / 2) and abs(y.std() - 0.667) < 0.07
    assert _rhat(y, 4) < 1.05


def test_importance_batch_dominated_by_one_weight_is_pooled():
    rng = np.random.default_rng(0)
    lw = rng.normal(size=4000) * 0.3
    lw[3100] = 12.0  # one draw of one batch (row 3100: batch 0) carries almost all the weight
    idx, ch = importance_batches(lw, 800, 4, np.random.default_rng(1))
    assert idx is None and ch.n_chains == 1 and "differ by" in ch.note


def _specimen(chains: Chains, n=400, p=6, seed=0):
    rng = np.random.default_rng(seed)
    samples = np.column_stack([rng.normal(1, 0.3, n), rng.normal(-2, 0.5, n)])
    return io.SpecimenResult(
        specimen_id="rat", names=["T1", "sigma"], samples=samples, log_likelihood=rng.normal(size=n),
        log_evidence=3.0, log_evidence_se=0.1, bounds=np.array([[-5.0, 5.0], [-5.0, 5.0]]),
        stages=[{"beta": 0.3, "acceptance_rate": 0.4}, {"beta": 1.0, "acceptance_rate": 0.3}],
        data=Specimen("s", np.linspace(0, 0.3, p), observed={"stress": Series.known("stress", np.linspace(0, 1, p))}),
        pointwise_log_likelihood=rng.normal(size=(n, p)),
        predictive=rng.normal(size=(n, p)), predictive_model=rng.normal(size=(n, p)), chains=chains)


def test_file_with_chains_round_trips_and_gives_finite_rhat(tmp_path):
    ch = Chains(4, "tmcmc_islands", "four islands", 0.3, 1.0)
    r = _specimen(ch)
    path = io.write_specimen_result(r, tmp_path / "rat.nc")
    idata = az.from_netcdf(str(path))
    assert dict(idata.posterior.sizes) == {"chain": 4, "draw": 100}
    assert idata.log_likelihood.sizes["chain"] == 4 and idata.posterior_predictive.sizes["draw"] == 100
    np.testing.assert_array_equal(idata.posterior["T1"].values.reshape(-1), r.samples[:, 0])
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        s = az.summary(idata)
    assert np.isfinite(s["r_hat"]).all() and (s["r_hat"] < 1.05).all()
    back = io.read_specimen_result(path)
    np.testing.assert_array_equal(back.samples, r.samples)
    np.testing.assert_array_equal(back.pointwise_log_likelihood, r.pointwise_log_likelihood)
    np.testing.assert_array_equal(back.predictive, r.predictive)
    np.testing.assert_array_equal(back.log_likelihood, r.log_likelihood)
    assert back.chains == ch and back.log_evidence == 3.0 and [s.beta for s in back.stages] == [0.3, 1.0]


def test_file_of_the_code_before_chains_still_loads(tmp_path):
    # the layout the previous writer produced: chain = [0], no chains attributes
    r = _specimen(POOLED)
    path = io.write_specimen_result(r, tmp_path / "old.nc")
    import xarray as xr
    tree = xr.open_datatree(path, engine="netcdf4")
    tree = tree.copy()
    for key in ("chains", "chains_note", "chains_spread_log_evidence", "chains_tolerance_log_evidence"):
        del tree["posterior"].attrs[key]
    old = tmp_path / "old2.nc"
    tree.to_netcdf(old, engine="netcdf4")
    back = io.read_specimen_result(old)
    assert back.chains.n_chains == 1 and back.chains.method == "pooled" and "pooled" in back.chains.note
    np.testing.assert_array_equal(back.samples, r.samples)
    np.testing.assert_array_equal(back.pointwise_log_likelihood, r.pointwise_log_likelihood)


def test_rows_that_no_longer_split_into_chains_are_stored_as_one(tmp_path):
    r = _specimen(Chains(4, "tmcmc_islands", "x"), n=402)
    back = io.read_specimen_result(io.write_specimen_result(r, tmp_path / "r.nc"))
    assert back.chains.n_chains == 1 and "do not split" in back.chains.note


def test_default_fit_file_gives_finite_rhat_for_every_parameter(tmp_path):
    from hbm.data import synthetic_specimen
    from hbm.fit import fit_specimen
    from hbm.model import spyrou_model

    truth = {"VOLF": 0.9, "EOPT": 0.15, "P1": 0.06, "T1": 1.0, "T2": 14.0, "THETA": 59.0, "GF": 0.03, "GM": 0.02}
    data = synthetic_specimen(spyrou_model(), truth, np.linspace(0, 0.42, 30), 0.002, 1, attrs={"id": "syn"})
    res = fit_specimen(data, samples=400, restarts=0, seed=11, progress=False, out=tmp_path / "syn.nc")
    assert res.result.chains.n_chains == 4  # the default (collapsed) fit: importance batches as chains
    idata = az.from_netcdf(str(res.path))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        s = az.summary(idata)
    assert set(s.index) == set(res.result.names)
    assert np.isfinite(s["r_hat"]).all() and (s["r_hat"] < 1.05).all(), s["r_hat"]
    assert idata.posterior.attrs["chains"] in ("importance_batches", "tmcmc_islands")
    js = res.to_json()["chains"]
    assert js["n_chains"] == 4 and js["max_rhat"] == pytest.approx(
        max(float(az.rhat(idata, method="z_scale")[n]) for n in res.result.names), abs=1e-4)
    assert "chains: 4" in res.report()


def test_summary_rhat_column_matches_arviz(tmp_path):
    from hbm.cli.summary import rows
    from hbm.fit import chains_line

    r = _specimen(Chains(4, "tmcmc_islands", "four islands"), n=800)
    r.samples[600:, 0] += 0.3  # the last chain sits elsewhere in T1
    path = io.write_specimen_result(r, tmp_path / "rat.nc")
    table = {row[0]: row for row in rows(path)[1:]}
    idata = az.from_netcdf(str(path))
    for name in ("T1", "sigma"):
        # ArviZ's bulk (rank-normalised split) R-hat: the same definition, an independent implementation
        ref = float(az.rhat(idata, method="z_scale")[name])
        assert float(table[name][-1]) == pytest.approx(ref, abs=1e-4)
    assert float(table["T1"][-1]) > 1.05 and float(table["sigma"][-1]) < 1.01
    line = chains_line(io.read_specimen_result(path))
    assert "4 TMCMC islands" in line and "disagree" in line
    one = io.read_specimen_result(io.write_specimen_result(_specimen(POOLED), tmp_path / "one.nc"))
    assert "no R-hat" in chains_line(one)


def test_importance_batch_resting_on_few_draws_is_flagged_by_rhat():
    # the last batch has the others' total weight but carries it on three draws: its evidence agrees (the
    # batches stay chains) and its chain repeats three points, which R-hat flags
    rng = np.random.default_rng(2)
    m = 4000
    x = rng.normal(size=m)
    lw = np.zeros(m)
    lw[3::4] = -30.0  # batch 3 (interleaved: rows 3, 7, 11, ...)
    lw[[3103, 3403, 3703]] = math.log(1000 / 3)
    idx, ch = importance_batches(lw, 800, 4, np.random.default_rng(1))
    assert ch.n_chains == 4 and abs(ch.spread) < 0.1
    y = x[idx]
    assert len(np.unique(y[600:])) == 3
    assert _rhat(y, 4) > 1.05
