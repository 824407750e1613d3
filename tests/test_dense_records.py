"""Dense records at the cost of their information, heavy-tailed noise, further relaxation times and
progress lines in a log (issue 36).

Truths: scipy's Gaussian, multivariate Gaussian and Student-t densities; the variance of simulated
AR(1) means; the full record's own posterior (optimum and curvature); the Laplace-domain product of
two Prony relaxations; the arithmetic mean of a sample without its outlier.
"""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
from scipy import optimize, stats

from hbm.cli._common import NOISE_CHOICES
from hbm.data import hold, input_summary, protocol, ramp, specimen_loading, synthetic_specimen
from hbm.data.reduction import bin_counts, effective_count, reduce_record
from hbm.effects import applicable, make_effect
from hbm.errors import HbmError
from hbm.likelihood import make_likelihood
from hbm.likelihood.binned import BinnedNoise
from hbm.likelihood.noise import make_noise
from hbm.model.spyrou import spyrou_model
from hbm.runtime.progress import LineProgress
from hbm.samplers.tmcmc import tmcmc

THETA = dict(VOLF=0.8, EOPT=0.05, P1=0.15, T1=0.5, T2=12.0, THETA=57.0, GF=0.02, GM=0.01, G1=0.3, LOGTAU1=0.8)


def _record(n: int, seed: int = 0, rel: float = 0.01):
    model = spyrou_model() + make_effect("viscoelastic")
    prot = protocol([ramp(0.3, 0.01, n // 4), hold(120.0, n - n // 4)])
    return model, synthetic_specimen(model, THETA, prot, rel, seed=seed, relative=True)


# ------------------------------------------------------------------------------ binned noise
def test_binned_noise_is_the_density_of_bin_means():
    rng = np.random.default_rng(3)
    n = 12
    y, m = rng.normal(size=n), rng.normal(size=(2, n))
    c = rng.integers(1, 30, n).astype(float)
    starts = np.zeros(n, bool)
    starts[0] = True
    q_iid, q_prop, q_ar = np.array([[0.7], [1.3]]), np.array([[0.4, 0.2], [0.9, 0.5]]), np.array([[0.8, 0.6]])
    iid = BinnedNoise(make_noise("iid", observed=y, history_starts=starts), c)
    want = [stats.norm.logpdf(y, m[k], q_iid[k, 0] / np.sqrt(c)).sum() for k in range(2)]
    np.testing.assert_allclose(iid.loglik(q_iid, m.copy()), want, rtol=1e-12)
    prop = BinnedNoise(make_noise("proportional", observed=y, history_starts=starts), c)
    want = [stats.norm.logpdf(y, m[k], np.sqrt((q_prop[k, 0] ** 2 + (q_prop[k, 1] * m[k]) ** 2) / c)).sum()
            for k in range(2)]
    np.testing.assert_allclose(prop.loglik(q_prop, m.copy()), want, rtol=1e-12)
    ar = BinnedNoise(make_noise("ar1", observed=y, history_starts=starts), c)
    s, rho = q_ar[0]
    lag = np.abs(np.subtract.outer(np.arange(n), np.arange(n)))
    cov = s * s * rho ** lag / np.sqrt(np.outer(c, c))     # √c·r is AR(1) of the raw sd
    want = stats.multivariate_normal(m[0], cov).logpdf(y)
    np.testing.assert_allclose(ar.loglik(q_ar, m[:1].copy()), [want], rtol=1e-10)
    np.testing.assert_allclose(ar.pointwise(q_ar, m[:1]).sum(), want, rtol=1e-10)
    np.testing.assert_allclose(iid.sd(q_iid)[1], 1.3 / np.sqrt(c))


def test_effective_count_is_the_variance_of_simulated_ar1_means():
    rng = np.random.default_rng(0)
    rho, reps = 0.6, 40000
    for c in (1, 5, 20):
        z = make_noise("ar1", history_starts=np.r_[True, np.zeros(c - 1, bool)]).standard_draws(rng, (1.0, rho), reps)
        var = float(np.var(z.mean(axis=1)))
        want = 1.0 / float(effective_count(np.array([c]), rho)[0])
        assert abs(var / want - 1) < 0.03, (c, var, want)
    assert effective_count(np.array([7.0]), 0.0)[0] == 7.0


# ------------------------------------------------------------------------------ the reduction
def test_reduction_keeps_the_paths_corners_tests_and_rows():
    model, ds = _record(3000)
    r = reduce_record(ds)
    rows = np.array(json.loads(r.attrs["reduction"])["readings"])
    assert rows.sum() == 3000 and r.n_points < 400 and rows.max() == math.ceil(3000 / 250)
    np.testing.assert_allclose(bin_counts(r), rows)          # iid readings: every reading counts
    first = np.r_[0, np.cumsum(rows)[:-1]]
    # bins never cross a test; the first row, the ramp's last row and the hold's first row are bins of their own
    assert np.all(ds.test[first] == ds.test[first + rows - 1])
    end = int(np.flatnonzero(ds.test == ds.test[0])[-1])
    for i in (0, end, end + 1):
        j = int(np.searchsorted(first, i, side="right") - 1)
        assert first[j] == i and rows[j] == 1, i
    assert r.time[0] == 0.0 and specimen_loading(r).history_starts.sum() == 1
    assert "3000 rows reduced to" in input_summary(r)
    with pytest.raises(HbmError, match="reduced already"):
        reduce_record(r)


def _laplace(lik, x0):
    """Optimum of ``lik`` from ``x0`` and the sd of each parameter from its curvature there."""
    b = lik.bounds
    lo, w = b[:, 0], b[:, 1] - b[:, 0]
    fun = lambda u: -float(lik((lo + u * w)[None, :])[0])            # noqa: E731
    u = (x0 - lo) / w
    for _ in range(3):
        u = optimize.minimize(fun, u, method="L-BFGS-B", bounds=[(0, 1)] * u.size).x
    x = lo + u * w
    k = x.size
    h = 1e-4 * w
    E = np.eye(k) * h
    pts = [x] + [x + E[i] for i in range(k)] + [x - E[i] for i in range(k)]
    pairs = [(i, j) for i in range(k) for j in range(i + 1, k)]
    for i, j in pairs:
        pts += [x + E[i] + E[j], x + E[i] - E[j], x - E[i] + E[j], x - E[i] - E[j]]
    f = lik(np.array(pts))
    H = np.zeros((k, k))
    for i in range(k):
        H[i, i] = -(f[1 + i] - 2 * f[0] + f[1 + k + i]) / h[i] ** 2
    for m, (i, j) in enumerate(pairs):
        a = f[1 + 2 * k + 4 * m: 5 + 2 * k + 4 * m]
        H[i, j] = H[j, i] = -(a[0] - a[1] - a[2] + a[3]) / (4 * h[i] * h[j])
    return x, np.sqrt(np.diag(np.linalg.inv(H)))


def test_reduced_record_has_the_full_records_posterior():
    """3000 readings against their 300-odd bin means: the same optimum within 0.4 posterior
    sd and the same posterior sd within 20 % for every model parameter (the noise sd, a nuisance,
    is estimated from the means only: wider, not shifted)."""
    model, ds = _record(3000, seed=5)
    fix = {n: v for n, v in THETA.items() if n not in ("T1", "GM", "G1", "LOGTAU1")}
    full = make_likelihood(model, ds, fix=fix)
    red = make_likelihood(model, reduce_record(ds), fix=fix)
    x0 = np.array([THETA.get(n, float(ds.attrs["noise_sd"])) for n in full.names])
    xf, sf = _laplace(full, x0)
    xr, sr = _laplace(red, x0)
    k = full.n_model
    shift, ratio = (xr - xf)[:k] / sf[:k], sr[:k] / sf[:k]
    assert np.all(np.abs(shift) < 0.4), dict(zip(full.names, shift))
    assert np.all(np.abs(ratio - 1) < 0.2), dict(zip(full.names, ratio))
    assert abs(xr[k] / xf[k] - 1) < 0.15                              # sigma: one raw reading's sd


def test_a_reduced_records_null_replicates_are_means_of_raw_readings():
    """The calibrated detective's null draws from the likelihood's noise model: on a reduced record
    its replicates must have the spread of means of the bins' raw readings (independent truth: iid
    readings simulated and averaged bin by bin)."""
    model, ds = _record(3000)
    r = reduce_record(ds)
    lik = make_likelihood(model, r, noise="iid")
    assert isinstance(lik.noise_model, BinnedNoise)
    sigma, reps = 0.02, 4000
    draws = lik.noise_model.simulate(np.random.default_rng(5), np.full((reps, 1), sigma))
    rows = np.array(json.loads(r.attrs["reduction"])["readings"])
    raw = np.random.default_rng(6).normal(0.0, sigma, (reps, rows.sum()))
    means = np.add.reduceat(raw, np.r_[0, np.cumsum(rows)[:-1]], axis=1) / rows
    big = rows >= 8
    np.testing.assert_allclose(draws.std(axis=0)[big], means.std(axis=0)[big], rtol=0.08)
    assert abs(float(np.mean(draws.std(axis=0) / means.std(axis=0))) - 1.0) < 0.01


# ------------------------------------------------------------------------------ Student-t noise
def test_student_t_noise_is_the_t_density_and_robust():
    assert "student_t" in NOISE_CHOICES
    rng = np.random.default_rng(1)
    y = rng.normal(size=30)
    nm = make_noise("student_t", observed=y)
    q, m = np.array([[0.7, 2.5], [1.2, 30.0]]), np.full((2, 30), 0.1)
    want = [stats.t.logpdf(y - 0.1, df=q[k, 1], scale=q[k, 0]).sum() for k in range(2)]
    np.testing.assert_allclose(nm.loglik(q, m.copy()), want, rtol=1e-12)
    np.testing.assert_allclose(nm.pointwise(q, m).sum(axis=1), want, rtol=1e-12)
    r = y - 0.1
    w = (q[0, 1] + 1) / (q[0, 1] + (r / q[0, 0]) ** 2)                  # IRLS weight of a t residual
    np.testing.assert_allclose(nm.effective_sd(q[:1], r[None, :])[0], q[0, 0] / np.sqrt(w))
    big = make_noise("student_t", history_starts=np.r_[True, np.zeros(19999, bool)])
    draws = big.simulate(np.random.default_rng(2), np.array([[0.5, 4.0]]))[0]
    assert stats.kstest(draws, stats.t(df=4.0, scale=0.5).cdf).pvalue > 0.01
    # one reading at 50 sd: the Gaussian location moves towards it, the t location stays with the rest
    data = np.r_[rng.normal(size=60) * 0.1 + 1.0, 6.0]
    grid = np.linspace(0.8, 1.3, 2001)[:, None] * np.ones((1, data.size))
    t_mu = grid[np.argmax(make_noise("student_t", observed=data).loglik(np.tile([0.1, 3.0], (2001, 1)),
                                                                         grid.copy())), 0]
    g_mu = grid[np.argmax(make_noise("iid", observed=data).loglik(np.full((2001, 1), 0.1), grid.copy())), 0]
    assert abs(t_mu - data[:-1].mean()) < 0.02 and abs(g_mu - data.mean()) < 1e-3


# ------------------------------------------------------------------------------ relaxation spectra
def test_a_second_relaxation_time_is_the_two_term_prony_series():
    """Stacked QLV filters (viscoelastic + viscoelastic_2) equal one two-term Prony series whose
    weights are the partial fractions of the product of the two relaxations' Laplace transforms."""
    g1, t1, g2, t2 = 0.3, 2.0, 0.4, 40.0
    prot = protocol([ramp(0.3, 0.01, 6000), hold(200.0, 8000)])
    load = specimen_loading(prot)
    base = dict(THETA)
    stacked = spyrou_model() + make_effect("viscoelastic") + make_effect("viscoelastic_2")
    th = dict(base, G1=g1, LOGTAU1=math.log10(t1), G2=g2, LOGTAU2=math.log10(t2))
    s1 = stacked.stress(load, np.array([[th[n] for n in stacked.parameter_names]]))[0]
    a1, a2 = 1 / t1, 1 / t2
    b1, b2 = (1 - g1) * a1, (1 - g2) * a2
    d1, d2 = g1 * (a1 - b2) / (a1 - a2), g2 * (a2 - b1) / (a2 - a1)   # G(t) = (1-g1)(1-g2) + d1 e^-t/t1 + d2 e^-t/t2
    assert (1 - g1) * (1 - g2) + d1 + d2 == pytest.approx(1.0)
    prony = spyrou_model() + make_effect("viscoelastic", terms=2)
    th2 = dict(base, G1=d1, LOGTAU1=math.log10(t1), G2=d2, LOGTAU2=math.log10(t2))
    s2 = prony.stress(load, np.array([[th2[n] for n in prony.parameter_names]]))[0]
    assert np.max(np.abs(s1 - s2)) < 2e-3 * np.max(np.abs(s2))
    one = spyrou_model() + make_effect("viscoelastic")
    s0 = one.stress(load, np.array([[th[n] for n in one.parameter_names]]))[0]
    th["G2"] = 0.0
    np.testing.assert_array_equal(stacked.stress(load, np.array([[th[n] for n in stacked.parameter_names]]))[0], s0)


def test_further_relaxation_times_need_the_first():
    base = spyrou_model()
    v2, v3 = make_effect("viscoelastic_2"), make_effect("viscoelastic_3")
    assert not applicable(v2, base) and applicable(v2, base + make_effect("viscoelastic"))
    assert not applicable(v3, base + make_effect("viscoelastic")) and applicable(v3, base + make_effect("viscoelastic")
                                                                               + v2)
    assert not applicable(v2, base + make_effect("viscoelastic", terms=2))   # G2 is taken


# ------------------------------------------------------------------------------ progress in a log
def test_progress_in_a_log_is_one_line_per_step(capsys):
    f = lambda x: -25.0 * np.sum(x * x, axis=1)                         # noqa: E731
    res = tmcmc(f, np.array([[-1.0, 1.0], [-1.0, 1.0]]), 200, seed=1, progress=True)
    err = capsys.readouterr().err
    lines = err.splitlines()
    assert "\r" not in err and len(lines) == len(res.stages)
    assert all(ln.startswith("[tmcmc] (") and f"stage {k + 1} " in ln for k, ln in enumerate(lines))
    bar = LineProgress(3, "fit", unit="specimen")
    for k in range(3):
        bar.set_postfix_str(f"s{k}")
        bar.update(1)
    assert capsys.readouterr().err.splitlines()[-1].startswith("[fit] 3/3 specimen (100%")


def test_power_assesses_a_further_relaxation_time_beside_the_fitted_one():
    """--power: an effect that needs another first (viscoelastic_2) gets its limit at the final model
    that has it (its row says ``beside``), and none at a starting model without it."""
    from hbm.detective.inputs import as_data
    from hbm.detective.power import detection_power
    from hbm.detective.results import FitSummary
    prot = protocol([ramp(0.3, 0.01, 15), hold(120.0, 20)], [ramp(0.3, 0.001, 15), hold(120.0, 20)])
    base = spyrou_model()
    full = base + make_effect("viscoelastic")
    ds = synthetic_specimen(full, THETA, prot, 0.01, seed=2, relative=True)
    d = as_data(ds)

    def summary(model):
        lik = make_likelihood(model, ds)
        x = np.array([THETA.get(n, 0.01 * float(np.max(np.abs(ds.stress)))) for n in lik.names])
        return FitSummary(effects=[], noise="iid", names=list(lik.names), theta_max=x, max_log_likelihood=0.0,
                          bic=0.0, rmse=0.0, likelihood=lik, model=model)

    first, final = summary(base), summary(full)
    cands = [make_effect("offset"), make_effect("viscoelastic_2")]
    kw = dict(n_rep=20, n_levels=2, refine=0, with_controls=False)
    res = detection_power(first, d, cands, 0, noise_fit=final, **kw)
    rows = {r["effect"]: r for r in res["effects"]}
    assert set(rows) == {"offset", "viscoelastic_2"}
    assert "beside" not in rows["offset"] and rows["viscoelastic_2"]["beside"] == ["viscoelastic"]
    alone = detection_power(first, d, cands, 0, **kw)
    assert [r["effect"] for r in alone["effects"]] == ["offset"]
    assert "beside the fitted viscoelastic" in res["text"]
