"""Issue 38: calibrated verdicts -- each statistic of the verdict against its own null on the file.

Independent truths: Šidák's critical value for independent statistics, scipy's bounded least
squares, the per-row model-free estimate, and the rejection rate of draws from a numpy-coded null.
"""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest
from scipy import optimize as sopt
from scipy import stats

from hbm.data import hold, protocol, ramp
from hbm.detective import diagnose
from hbm.detective.calibration import _bounded_gain, _pvalues, calibrate
from hbm.detective.inputs import as_data, resolve_candidates
from hbm.detective.noise_check import check_noise, model_free_noise
from hbm.errors import SettingError
from hbm.likelihood import make_likelihood
from hbm.model.spyrou import spyrou_model

TH = dict(VOLF=0.8, EOPT=0.1, P1=0.15, T1=0.8, T2=14.0, THETA=58.5, GF=0.015, GM=0.01)
SD = 0.0015


def test_family_wise_critical_value_is_sidak_for_independent_statistics():
    """m independent N(0, 1) statistics: the min-p critical value at 5 % is Φ⁻¹(0.95^(1/m))."""
    rng = np.random.default_rng(0)
    for m in (1, 6):
        table = rng.standard_normal((40001, m))
        res, p_star = _pvalues(table, 0.05)
        assert p_star == pytest.approx(1 - 0.95 ** (1 / m), rel=0.05)
        # each column's critical value scatters by ~0.04 at the 0.85 % tail of 40000 draws
        crit = np.array([r[2] for r in res])
        assert crit.mean() == pytest.approx(stats.norm.ppf(0.95 ** (1 / m)), abs=0.03)
        assert np.all(np.abs(crit - stats.norm.ppf(0.95 ** (1 / m))) < 0.1)


def test_bounded_gain_is_the_bounded_least_squares_optimum():
    rng = np.random.default_rng(1)
    A = rng.standard_normal((40, 3))
    lb, ub = np.array([0.0, -np.inf, -np.inf]), np.array([np.inf, np.inf, 0.0])
    R = rng.standard_normal((25, 40))
    got = _bounded_gain(A, lb, ub, R)
    for r, g in zip(R, got):
        sol = sopt.lsq_linear(A, r, bounds=(lb, ub), tol=1e-12)
        assert g == pytest.approx(0.5 * (r @ r - np.sum((r - A @ sol.x) ** 2)), abs=1e-9)


def test_model_free_noise_of_many_rows_is_each_row_alone():
    rng = np.random.default_rng(2)
    Y = np.cumsum(rng.standard_normal((6, 90)), axis=1) * 1e-3 + 2e-3 * rng.standard_normal((6, 90))
    seg = np.arange(90) // 45
    both = model_free_noise(Y, seg)
    for i in range(6):
        one = model_free_noise(Y[i], seg)
        assert both["rho"][i] == one["rho"]
        assert both["sigma"][i] == pytest.approx(one["sigma"], rel=1e-12)


def _design():
    ds = protocol([ramp(0.3, 2e-3, 40), hold(120.0, 40)])
    m = spyrou_model()
    th = np.array([TH[k] for k in m.parameter_names])
    s0 = np.asarray(m.stress(ds.strain, th, ds.time, ds.test))
    return ds, m, th, s0


def _null_fit(ds, m, th, stress):
    """The base 'fitted' at the truth (no optimiser: the calibration only needs an optimum)."""
    ds = ds.with_series("stress", stress)
    lik = make_likelihood(m, ds, noise="iid", sigma_bounds=(SD / 20, SD * 20))
    x = lik.from_natural(np.r_[th, SD][None, :])[0]
    return SimpleNamespace(likelihood=lik, model=m, theta_max=x, names=list(lik.names), noise="iid",
                           effects=[], noise_bic={}, noise_evidence={}), ds


def test_calibrated_false_alarms_and_a_ripple(tmp_path, monkeypatch):
    """Observed residuals drawn by numpy from the null: rejected in about 5 % of draws (family-wise);
    the same plus a 3 %-of-peak ripple: the periodic shape is significant."""
    monkeypatch.setenv("HBM_CACHE_DIR", "off")
    ds, m, th, s0 = _design()
    base, _ = _null_fit(ds, m, th, s0)
    cands = resolve_candidates(["offset", "viscoelastic"], m)
    rng = np.random.default_rng(11)

    def p_family(y):
        d = as_data(ds.with_series("stress", y))
        check = check_noise(base, model_free_noise(d.stress, d.segment), d, 0)
        return calibrate(base, check, cands, d, seed=3, replicates=200)

    n_draws = 40
    hits = sum(p_family(s0 + SD * rng.standard_normal(s0.size)).p_family <= 0.05 for _ in range(n_draws))
    # binomial(40, 0.05): P(X >= 7) = 0.004
    assert hits <= 6
    t = ds.time
    cal = p_family(s0 + SD * rng.standard_normal(s0.size) + 0.03 * s0.max() * np.sin(2 * np.pi * t / 11.0))
    assert cal.significant("periodic")
    assert cal.stats["periodic"]["p"] == pytest.approx(1 / 201)
    # located at its period (the verdict reports it when the refit of the shape did not find it)
    assert cal.stats["periodic"]["optimum"]["RIP_P"] == pytest.approx(11.0, rel=0.03)


def test_calibration_cache_is_keyed_by_the_inputs(tmp_path, monkeypatch):
    monkeypatch.setenv("HBM_CACHE_DIR", str(tmp_path))
    ds, m, th, s0 = _design()
    base, ds1 = _null_fit(ds, m, th, s0 + SD * np.random.default_rng(4).standard_normal(s0.size))
    d = as_data(ds1)
    cands = resolve_candidates(["offset"], m)
    check = check_noise(base, model_free_noise(d.stress, d.segment), d, 0)
    first = calibrate(base, check, cands, d, seed=5, replicates=50)
    again = calibrate(base, check, cands, d, seed=5, replicates=50)
    assert not first.cached and again.cached and again.stats == first.stats
    # other data (one point), another seed: computed anew
    ds2 = ds1.with_series("stress", ds1.stress + np.r_[1e-4, np.zeros(s0.size - 1)])
    assert not calibrate(base, check, cands, as_data(ds2), seed=5, replicates=50).cached
    assert not calibrate(base, check, cands, d, seed=6, replicates=50).cached


def test_calibration_setting_is_checked_before_any_fit():
    ds, *_ = _design()
    with pytest.raises(SettingError, match="calibration"):
        diagnose(ds.with_series("stress", np.linspace(0.0, 0.05, ds.n_points)), calibration="maybe")
    with pytest.raises(SettingError, match="replicates"):
        diagnose(ds.with_series("stress", np.linspace(0.0, 0.05, ds.n_points)), replicates=3)


def test_the_report_gives_each_statistic_with_its_calibrated_p_value(monkeypatch):
    """A clean curve: adequate, and the text and JSON say it was calibrated, with p-values and the
    number of replicates; switched off, the record says "fixed"."""
    from hbm.detective.calibration import calibration_record
    monkeypatch.setenv("HBM_CACHE_DIR", "off")
    ds = protocol(ramp(0.3, 2e-3, 30))
    m = spyrou_model()
    s0 = np.asarray(m.stress(ds.strain, np.array([TH[k] for k in m.parameter_names]), ds.time))
    y = s0 + SD * np.random.default_rng(8).standard_normal(s0.size)
    dg = diagnose(ds.with_series("stress", y), seed=2, n_samples=250, candidates=["offset"], removal=False,
                  replicates=100, workers=1, noise="iid")
    js = dg.to_dict()["calibration"]
    assert js["method"] == "calibrated" and js["rounds"][0]["replicates"] == 100
    st = js["rounds"][0]["statistics"]
    assert {"windows", "noise", "offset", "local_misfit", "periodic"} <= set(st)
    for v in st.values():
        assert 1 / 101 <= v["p"] <= 1 and v["p"] <= v["p_family"] <= 1
    assert "calibration: 100 null replicates" in dg.summary()
    if dg.verdict == "adequate":
        assert "family-wise" in dg.message and "replicates" in dg.message
    assert calibration_record([(dg.base, None)], on=False)["method"] == "fixed"


def test_calibration_in_worker_processes_is_the_serial_one(monkeypatch):
    """The candidate and shape statistics computed in forked workers: bitwise the serial table."""
    import multiprocessing as mp
    from concurrent.futures import ProcessPoolExecutor
    monkeypatch.setenv("HBM_CACHE_DIR", "off")
    ds, m, th, s0 = _design()
    base, ds1 = _null_fit(ds, m, th, s0 + SD * np.random.default_rng(9).standard_normal(s0.size))
    d = as_data(ds1)
    cands = resolve_candidates(["offset", "viscoelastic"], m)
    check = check_noise(base, model_free_noise(d.stress, d.segment), d, 0)
    serial = calibrate(base, check, cands, d, seed=5, replicates=60)
    with ProcessPoolExecutor(2, mp_context=mp.get_context("fork")) as pool:
        par = calibrate(base, check, cands, d, seed=5, replicates=60,
                        run_tasks=lambda task, calls: [f.result() for f in [pool.submit(task, *c) for c in calls]])
    assert par.stats == serial.stats
