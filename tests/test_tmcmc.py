"""TMCMC against closed-form evidences and posteriors (fast selection + slow validations).

Analytic truths (uniform prior on the box, likelihood mass entirely inside the box):
- 9-D standard normal on U(−10, 10)⁹: log Z = −9·log 20 = −26.96159
- twisted banana x1 ~ N(0, 10²), x2 + 0.1·x1² − 10 ~ N(0, 1) on [−40, 40]×[−150, 20]:
  log Z = −log(80·170) = −9.51789 (the density is a normalised change of variables)
- 4-D mixture 0.1·N(−0.5·1, 0.1²I) + 0.9·N(+0.5·1, 0.1²I) on U(−2, 2)⁴: log Z = −4·log 4 = −5.54518
- 1-D exp(−x²/2) (unnormalised) on U(−20, 20): log Z = log(√(2π)/40) = −2.76994
"""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
from scipy.stats import norm

from hbm.errors import HbmError
from hbm.samplers import StageInfo, TMCMCConfig, checkpoint_progress, init, step
from hbm.samplers.moves import Manifold
from hbm.samplers.tmcmc import tmcmc

LOG2PI = math.log(2 * math.pi)


# ---------------------------------------------------------------------------- problems
def gauss9(x):
    return -0.5 * np.sum(x * x, axis=1) - 0.5 * x.shape[1] * LOG2PI


def gauss9_gf(x):
    return -x, np.broadcast_to(np.eye(x.shape[1]), (len(x), x.shape[1], x.shape[1])).copy()


GAUSS9 = (gauss9, np.array([[-10.0, 10.0]] * 9), -26.96159)


def banana(x):
    x1, x2 = x[:, 0], x[:, 1]
    return (-0.5 * (x1 / 10.0) ** 2 - math.log(10.0) - 0.5 * LOG2PI
            - 0.5 * (x2 + 0.1 * x1 ** 2 - 10.0) ** 2 - 0.5 * LOG2PI)


def banana_gf(x):
    x1, x2 = x[:, 0], x[:, 1]
    r = x2 + 0.1 * x1 ** 2 - 10.0
    g = np.stack([-x1 / 100.0 - r * 0.2 * x1, -r], axis=1)
    # Fisher information of the Gaussian change of variables: J^T diag(1/100, 1) J, J = d(z)/dx
    f = np.zeros((len(x), 2, 2))
    f[:, 0, 0] = 1 / 100.0 + (0.2 * x1) ** 2
    f[:, 0, 1] = f[:, 1, 0] = 0.2 * x1
    f[:, 1, 1] = 1.0
    return g, f


BANANA = (banana, np.array([[-40.0, 40.0], [-150.0, 20.0]]), -9.51789)


def mixture(x):
    d = x.shape[1]
    s = 0.1
    la = math.log(0.1) - 0.5 * np.sum((x + 0.5) ** 2, axis=1) / s ** 2
    lb = math.log(0.9) - 0.5 * np.sum((x - 0.5) ** 2, axis=1) / s ** 2
    return np.logaddexp(la, lb) - d * math.log(s) - 0.5 * d * LOG2PI


MIXTURE = (mixture, np.array([[-2.0, 2.0]] * 4), -5.54518)


def one_d(x):
    return -0.5 * x[:, 0] ** 2


def one_d_gf(x):
    return -x, np.ones((len(x), 1, 1))


ONE_D = (one_d, np.array([[-20.0, 20.0]]), -2.76994)


def check_evidence(res, truth, k=4.0, floor=0.05):
    err = abs(res.log_evidence - truth)
    assert np.isfinite(res.log_evidence_se) and res.log_evidence_se > 0
    assert err <= k * res.log_evidence_se + floor, (res.log_evidence, res.log_evidence_se, truth)


# ---------------------------------------------------------------------------- fast tests
def test_gaussian_9d_evidence_and_moments():
    f, b, truth = GAUSS9
    res = tmcmc(f, b, 1000, seed=1, progress=False)
    check_evidence(res, truth)
    assert res.samples.shape == (1000, 9) and res.log_likelihood.shape == (1000,)
    # posterior N(0, I): MC error of the mean with ~N/3 effective draws is ~0.05
    assert np.max(np.abs(res.samples.mean(axis=0))) < 0.2
    assert np.allclose(res.samples.std(axis=0), 1.0, atol=0.15)
    np.testing.assert_allclose(res.log_likelihood, f(res.samples))
    assert res.stages[-1].beta == 1.0
    assert np.all(np.diff([s.beta for s in res.stages]) > 0)
    assert res.n_evaluations == 1000 + sum(s.evaluations for s in res.stages)


def test_banana_evidence_and_moments():
    f, b, truth = BANANA
    res = tmcmc(f, b, 1000, seed=2, progress=False)
    check_evidence(res, truth)
    x1, x2 = res.samples.T
    assert abs(x1.mean()) < 1.5 and abs(x1.std() - 10.0) < 1.5
    # E[x2] = 10 − 0.1·E[x1²] = 0
    assert abs(x2.mean()) < 1.5


def test_mixture_evidence_and_weights():
    f, b, truth = MIXTURE
    res = tmcmc(f, b, 1000, seed=3, progress=False)
    check_evidence(res, truth)
    frac = np.mean(res.samples[:, 0] > 0)
    assert abs(frac - 0.9) < 0.06
    assert abs(res.samples[res.samples[:, 0] > 0].mean() - 0.5) < 0.03


def test_one_d_evidence():
    f, b, truth = ONE_D
    res = tmcmc(f, b, 500, seed=4, progress=False)
    check_evidence(res, truth)
    assert abs(res.samples.std() - 1.0) < 0.15


def test_transform_none_also_correct():
    f, b, truth = BANANA
    res = tmcmc(f, b, 1000, seed=5, progress=False, transform="none")
    check_evidence(res, truth)


def test_manifold_kernel_gaussian_and_banana():
    for (f, b, truth), gf in ((GAUSS9, gauss9_gf), (BANANA, banana_gf)):
        res = tmcmc(f, b, 1000, seed=6, move="manifold", gradient_fim=gf, progress=False)
        check_evidence(res, truth)
        assert all(s.metric_ok == 1.0 for s in res.stages)
        assert 0.2 < np.mean([s.acceptance_rate for s in res.stages]) < 0.95


def test_manifold_mh_uses_reverse_metric():
    """A strongly position-dependent metric keeps N(0, 1) exact only with the metric at θ'.

    Target exp(−x²/2) on (−20, 20); 'Fisher information' 1 + 4x² (any positive metric gives a
    valid kernel).  With the forward metric in both directions (Korali) the variance is biased.
    """
    def gf(x):
        return -x, (1.0 + 4.0 * x[:, :1] ** 2)[:, :, None]

    f, b, truth = ONE_D
    res = tmcmc(f, b, 2000, seed=7, move=Manifold(ridge=1e-3), gradient_fim=gf, progress=False, n_steps=30)
    check_evidence(res, truth)
    x = res.samples[:, 0]
    assert abs(x.mean()) < 0.08
    assert abs(x.var() - 1.0) < 0.1
    # kurtosis of N(0,1) is 3: a wrong reverse density distorts the tails
    assert abs(np.mean(x ** 4) / x.var() ** 2 - 3.0) < 0.5


def test_manifold_falls_back_where_metric_fails():
    def gf(x):
        g, f = -x, np.ones((len(x), 1, 1))
        bad = x[:, 0] > 0.5
        f[bad] = np.nan  # metric fails on part of the space: random walk there
        f[x[:, 0] < -1.0] = -1.0  # not positive definite
        return g, f

    f, b, truth = ONE_D
    res = tmcmc(f, b, 1000, seed=8, move=Manifold(ridge=1e-3), gradient_fim=gf, progress=False)
    check_evidence(res, truth)
    assert abs(res.samples.var() - 1.0) < 0.15
    assert all(s.metric_ok < 1.0 for s in res.stages[-3:])


def test_inf_and_nan_likelihood_do_not_break_the_run():
    """−inf for x0 > 1.5 and NaN for x1 < −2: the evidence is the truncated Gaussian mass."""
    def f(x):
        out = -0.5 * np.sum(x * x, axis=1) - LOG2PI
        out[x[:, 0] > 1.5] = -np.inf
        out[x[:, 1] < -2.0] = np.nan
        return out

    b = np.array([[-5.0, 5.0], [-5.0, 5.0]])
    truth = math.log(norm.cdf(1.5) * norm.sf(-2.0) / 100.0)
    res = tmcmc(f, b, 1000, seed=9, progress=False)
    assert np.isfinite(res.log_evidence) and np.all(np.isfinite(res.log_likelihood))
    check_evidence(res, truth)
    assert res.samples[:, 0].max() <= 1.5 and res.samples[:, 1].min() >= -2.0


def test_all_inf_is_a_clear_error():
    with pytest.raises(HbmError, match="-inf"):
        tmcmc(lambda x: np.full(len(x), -np.inf), [[0, 1]], 100, seed=0, progress=False)


def test_seed_determinism():
    f, b, _ = BANANA
    a = tmcmc(f, b, 300, seed=11, progress=False)
    c = tmcmc(f, b, 300, seed=11, progress=False)
    d = tmcmc(f, b, 300, seed=12, progress=False)
    assert np.array_equal(a.samples, c.samples) and a.log_evidence == c.log_evidence
    assert not np.array_equal(a.samples, d.samples)


class Boom(RuntimeError):
    pass


def test_resume_is_bitwise_identical(tmp_path):
    f, b, _ = MIXTURE
    ref = tmcmc(f, b, 400, seed=21, progress=False)
    calls = {"n": 0}

    def flaky(x):
        calls["n"] += 1
        if calls["n"] == 250:  # in the middle of a stage
            raise Boom("interrupted")
        return f(x)

    ck = tmp_path / "run.npz"
    with pytest.raises(Boom):
        tmcmc(flaky, b, 400, seed=21, progress=False, checkpoint=ck)
    assert ck.exists()
    res = tmcmc(flaky, b, 400, seed=21, progress=False, checkpoint=ck)
    assert 0 < res.resumed_from_stage < len(ref.stages)
    assert np.array_equal(res.samples, ref.samples)
    assert np.array_equal(res.log_likelihood, ref.log_likelihood)
    assert res.log_evidence == ref.log_evidence and res.log_evidence_se == ref.log_evidence_se
    # the stage records of the finished stages travel through the checkpoint with their types
    np.testing.assert_array_equal(np.array(res.stages, float), np.array(ref.stages, float))
    assert all(type(s) is StageInfo and type(s.n_steps) is int and type(s.capped) is bool for s in res.stages)
    # a finished checkpoint returns the same result without new evaluations
    again = tmcmc(f, b, 400, seed=21, progress=False, checkpoint=ck)
    assert np.array_equal(again.samples, ref.samples)
    # different settings are rejected
    with pytest.raises(HbmError, match="different settings"):
        tmcmc(f, b, 400, seed=22, progress=False, checkpoint=ck)
    with pytest.raises(HbmError, match="different settings"):
        tmcmc(f, b, 400, seed=21, progress=False, checkpoint=ck, cov_target=0.5)
    bad = tmp_path / "bad.npz"
    bad.write_text("not a checkpoint")
    with pytest.raises(HbmError, match="cannot read checkpoint"):
        tmcmc(f, b, 400, seed=21, progress=False, checkpoint=bad)


def test_pure_core_matches_driver():
    f, b, _ = ONE_D
    cfg = TMCMCConfig(n_samples=200)
    st = init(f, b, cfg, 5)
    infos = []
    while st.beta < 1.0:
        st, info = step(st, f, b, cfg)
        infos.append(info)
    res = tmcmc(f, b, 200, seed=5, progress=False)
    assert np.array_equal(st.samples, res.samples)
    assert st.log_evidence == res.log_evidence
    assert abs(sum(i.log_evidence_increment for i in infos) - st.log_evidence) < 1e-9
    # the recorded proposal scale is the adapted scale the state carries into the next stage
    assert all(type(i) is StageInfo for i in infos) and infos[-1].proposal_scale == st.scale
    assert [i.proposal_scale for i in infos] == [s.proposal_scale for s in res.stages]


def test_checkpoint_progress_mid_run(tmp_path):
    """Interrupt a run inside stage k + 1; the checkpoint reports k stages and the β of stage k.

    With fixed ``n_steps`` and the logit walk (no box rejections) the likelihood is called once
    by :func:`init` and once per MH step, so call 1 + n_steps·k + 2 lies inside stage k + 1.
    """
    f, b, _ = MIXTURE
    n_steps, k = 3, 4
    counted = {"n": 0}

    def counting(x):
        counted["n"] += 1
        return f(x)

    ref = tmcmc(counting, b, 300, seed=4, progress=False, n_steps=n_steps)
    assert counted["n"] == 1 + n_steps * len(ref.stages) and len(ref.stages) > k + 1
    calls = {"n": 0}

    def flaky(x):
        calls["n"] += 1
        if calls["n"] == 1 + n_steps * k + 2:
            raise Boom("interrupted")
        return f(x)

    ck = tmp_path / "run.npz"
    assert checkpoint_progress(ck) is None
    with pytest.raises(Boom):
        tmcmc(flaky, b, 300, seed=4, progress=False, n_steps=n_steps, checkpoint=ck)
    assert checkpoint_progress(ck) == (k, ref.stages[k - 1].beta)
    from hbm.runtime.parallel import checkpoint_status
    assert checkpoint_status(ck) == f"stage {k} β={ref.stages[k - 1].beta:.3g}"
    # a checkpoint from before StageInfo (keys "cov", "scale", "stage") still resumes
    with np.load(ck) as z:
        arrays = {name: z[name] for name in z.files}
    meta = json.loads(str(arrays["meta"]))
    legacy = {"cov_weights": "cov", "proposal_scale": "scale"}
    meta["stages"] = [{"stage": i + 1, **{legacy.get(key, key): v for key, v in rec.items()}}
                      for i, rec in enumerate(meta["stages"])]
    arrays["meta"] = np.array(json.dumps(meta))
    with open(ck, "wb") as fh:
        np.savez(fh, **arrays)
    res = tmcmc(f, b, 300, seed=4, progress=False, n_steps=n_steps, checkpoint=ck)
    assert res.resumed_from_stage == k and np.array_equal(res.samples, ref.samples)
    np.testing.assert_array_equal(np.array(res.stages, float), np.array(ref.stages, float))
    assert checkpoint_progress(ck) == (len(ref.stages), 1.0)
    bad = tmp_path / "bad.npz"
    bad.write_text("not a checkpoint")
    assert checkpoint_progress(bad) is None and checkpoint_status(bad) is None


def test_beta_schedule_min_step_and_cap():
    # an enormous likelihood range: must neither hang nor exceed the stage cap
    f = lambda x: -1e12 * np.sum(x * x, axis=1)  # noqa: E731
    res = tmcmc(f, [[-1, 1], [-1, 1]], 200, seed=0, progress=False, max_stages=6, n_steps=2)
    assert len(res.stages) == 6 and res.stages[-1].capped and res.stages[-1].beta == 1.0
    # a flat likelihood jumps to beta = 1 in one stage with evidence exactly 0 (+const)
    flat = tmcmc(lambda x: np.full(len(x), 3.0), [[0, 1]], 100, seed=0, progress=False)
    assert len(flat.stages) == 1 and abs(flat.log_evidence - 3.0) < 1e-12
    # the CoV of each regular stage hits the target
    g, b, _ = GAUSS9
    res = tmcmc(g, b, 500, seed=1, progress=False, cov_target=0.5, n_steps=3)
    assert all(abs(s.cov_weights - 0.5) < 1e-6 for s in res.stages[:-1])


def test_progress_bar_on_stderr(capsys):
    tmcmc(one_d, [[-20, 20]], 100, seed=0, progress=True)
    cap = capsys.readouterr()
    assert cap.out == ""
    assert "tmcmc" in cap.err


def corr_gauss(x):
    """N(m, C) with correlation 0.95 and sds (1, 2), normalised (log Z = −log of the box area)."""
    r = x - CG_MEAN
    q = np.einsum("ni,ij,nj->n", r, CG_PREC, r)
    return -0.5 * q - 0.5 * CG_LOGDET - LOG2PI


CG_MEAN = np.array([1.0, -1.0])
CG_COV = np.array([[1.0, 0.95 * 2.0], [0.95 * 2.0, 4.0]])
CG_PREC = np.linalg.inv(CG_COV)
CG_LOGDET = float(np.linalg.slogdet(CG_COV)[1])
CORR_GAUSS = (corr_gauss, np.array([[-10.0, 12.0], [-20.0, 20.0]]), -math.log(22.0 * 40.0))


def test_cov_target_default_per_kernel():
    from hbm.samplers.tmcmc import DEFAULT_COV_TARGET
    assert TMCMCConfig(100).cov_target == DEFAULT_COV_TARGET == 1.0
    assert TMCMCConfig(100, move="manifold").cov_target == DEFAULT_COV_TARGET == 1.0
    f, b, _ = GAUSS9
    res = tmcmc(f, b, 300, seed=2, progress=False, n_steps=2, cov_target=1.5)
    assert res.config.cov_target == 1.5
    assert all(abs(s.cov_weights - 1.5) < 1e-6 for s in res.stages[:-1])
    old = tmcmc(f, b, 300, seed=2, progress=False, n_steps=2)
    assert old.config.cov_target == 1.0 and all(abs(s.cov_weights - 1.0) < 1e-6 for s in old.stages[:-1])
    assert len(old.stages) > len(res.stages)  # smaller CoV target: more, gentler stages


def test_adaptive_step_count_gives_correct_evidence():
    f, b, truth = BANANA
    res = tmcmc(f, b, 1000, seed=13, progress=False)
    check_evidence(res, truth)
    assert all(s.n_steps >= 2 for s in res.stages)
    assert all(s.mixing <= 0.1 or s.n_steps == 100 for s in res.stages)


def test_logit_prior_density_matches_jacobian():
    """log p(u) of the logit coordinates = log |dx/du| / width, by central differences."""
    from hbm.samplers.coordinates import from_logit as _from_logit
    from hbm.samplers.coordinates import to_logit as _to_logit
    b = np.array([[0.5, 0.99], [-3.0, 7.0], [1e-4, 0.05]])
    rng = np.random.default_rng(1)
    u = rng.normal(0.0, 6.0, (50, 3))
    u[0] = [40.0, -40.0, 0.0]  # far tails stay finite
    x, lp = _from_logit(u, b, True)
    assert np.all(np.isfinite(lp)) and np.all((x >= b[:, 0]) & (x <= b[:, 1]))
    h = 1e-5
    jac = (_from_logit(u + h, b) - _from_logit(u - h, b)) / (2 * h)
    fd = np.sum(np.log(jac[1:] / (b[:, 1] - b[:, 0])), axis=1)
    np.testing.assert_allclose(lp[1:], fd, rtol=1e-6, atol=1e-8)
    np.testing.assert_allclose(_from_logit(_to_logit(x[1:], b), b), x[1:], rtol=1e-12, atol=1e-15)


@pytest.mark.parametrize("kw, msg", [
    ({"kernel": "hmc"}, "kernel"),
    ({"move": "hmc"}, "unknown move"),
    ({"move": object()}, "registered name"),
    ({"move": "local", "kernel": "manifold"}, "not both"),
    ({"proposal": "mixture"}, "proposal"),
    ({"proposal": "local", "transform": "none"}, "transform='logit'"),
    ({"kernel": "manifold"}, "gradient_fim"),
    ({"cov_target": -1.0}, "cov_target"),
    ({"n_steps": 0}, "n_steps"),
    ({"bogus": 1}, "unknown options"),
])
def test_bad_options(kw, msg):
    with pytest.raises(HbmError, match=msg):
        tmcmc(one_d, [[-1, 1]], 100, seed=0, progress=False, **kw)


def test_bad_bounds_and_seed():
    with pytest.raises(HbmError, match="bounds"):
        tmcmc(one_d, [[1, -1]], 100, seed=0, progress=False)
    with pytest.raises(HbmError, match="seed"):
        tmcmc(one_d, [[-1, 1]], 100, seed=None, progress=False)
    with pytest.raises(HbmError, match="shape"):
        tmcmc(lambda x: np.zeros((len(x), 2)), [[-1, 1]], 100, seed=0, progress=False)


# ---------------------------------------------------------------------------- slow validation
SEEDS = range(20)


def _runs(problem, n=10_000, **kw):
    f, b, truth = problem
    return [tmcmc(f, b, n, seed=s, progress=False, **kw) for s in SEEDS], truth


def _check_accuracy_and_se(runs, truth):
    z = np.array([r.log_evidence for r in runs])
    se = np.array([r.log_evidence_se for r in runs])
    assert np.mean(np.abs(z - truth)) <= 0.1, (z.mean(), truth)
    spread = z.std(ddof=1)
    assert 0.5 <= spread / se.mean() <= 2.0, (spread, se.mean())
    return float(np.mean(np.abs(z - truth)))


@pytest.mark.slow
@pytest.mark.parametrize("problem, gf", [(GAUSS9, gauss9_gf), (BANANA, banana_gf), (ONE_D, one_d_gf)],
                         ids=["gauss9", "banana", "one_d"])
def test_slow_accuracy_rw_and_manifold(problem, gf):
    runs, truth = _runs(problem)
    err_rw = _check_accuracy_and_se(runs, truth)
    pooled = np.concatenate([r.samples for r in runs])
    means = np.array([r.samples.mean(axis=0) for r in runs])
    sd = pooled.std(axis=0)
    if problem is BANANA:
        exact_mean, exact_sd = np.array([0.0, 0.0]), np.array([10.0, math.sqrt(1 + 0.01 * 2 * 100 ** 2)])
    else:
        exact_mean, exact_sd = np.zeros(pooled.shape[1]), np.ones(pooled.shape[1])
    assert np.all(np.abs(means.mean(axis=0) - exact_mean) <= 0.05 * exact_sd)
    assert np.all(np.abs(sd - exact_sd) <= 0.05 * exact_sd)
    mruns, _ = _runs(problem, move="manifold", gradient_fim=gf)
    err_m = _check_accuracy_and_se(mruns, truth)
    assert err_m <= max(err_rw * 1.25, 0.05)


@pytest.mark.slow
def test_slow_mixture():
    runs, truth = _runs(MIXTURE)
    _check_accuracy_and_se(runs, truth)
    frac = np.array([np.mean(r.samples[:, 0] > 0) for r in runs])
    assert np.all(np.abs(frac - 0.9) <= 0.03), frac
    # component means within 0.05 sd (sd = 0.1)
    hi = np.array([r.samples[r.samples[:, 0] > 0].mean(axis=0) for r in runs])
    assert np.all(np.abs(hi.mean(axis=0) - 0.5) <= 0.005)


# ----------------------------------------------------------------------------------------
# issue 16: evaluation budget, presets
# ----------------------------------------------------------------------------------------
def _gauss_problem(d=3, s=0.3, mu=1.0, half=5.0):
    """Gaussian likelihood exp(−|x−μ|²/2s²) (unnormalised) on a box: Z = (√(2π)s)^d/(2·half)^d."""
    b = np.array([[-half, half]] * d)

    def ll(x):
        return -0.5 * np.sum((x - mu) ** 2, axis=1) / s**2

    log_z = d * (0.5 * np.log(2 * np.pi) + np.log(s)) - d * np.log(2 * half)
    return ll, b, log_z


@pytest.mark.parametrize("kw", [{}, {"move": "local"}, {"transform": "none"}, {"preset": "lean"}])
def test_max_evaluations_is_respected_exactly(kw):
    ll, b, _ = _gauss_problem()
    rows = [0]

    def counted(x):
        rows[0] += len(x)
        return ll(x)

    budget = 7 * 400 + 123
    r = tmcmc(counted, b, 400, seed=1, progress=False, max_evaluations=budget, **kw)
    assert rows[0] == r.n_evaluations <= budget
    assert r.budget_exhausted
    assert r.beta[-1] == 1.0 and np.isfinite(r.log_evidence) and r.log_evidence_se > 0
    free = tmcmc(ll, b, 400, seed=1, progress=False, **kw)
    assert not free.budget_exhausted and free.n_evaluations > budget


def test_max_evaluations_below_population_is_an_error():
    ll, b, _ = _gauss_problem()
    with pytest.raises(HbmError, match="max_evaluations"):
        tmcmc(ll, b, 400, seed=1, progress=False, max_evaluations=399)
    with pytest.raises(HbmError, match="preset"):
        tmcmc(ll, b, seed=1, progress=False, preset="nope")


@pytest.mark.slow
@pytest.mark.parametrize("problem", [GAUSS9, BANANA], ids=["gauss9", "banana"])
def test_slow_accuracy_lean(problem):
    # the "lean" preset (N = 1500, CoV target 1.5) keeps the analytic checks' accuracy bound
    f, b, truth = problem
    runs = [tmcmc(f, b, seed=s, progress=False, preset="lean") for s in SEEDS]
    assert all(r.config.n_samples == 1500 and r.config.cov_target == 1.5 for r in runs)
    _check_accuracy_and_se(runs, truth)
