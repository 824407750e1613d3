"""The amplitude block of the exact fallback (issue 27) against independent truths.

* Sampler level (:class:`hbm.samplers.hierarchical.ConditionalBlock` in ``joint_gibbs``): the conjugate
  Gaussian toy of ``test_joint_gibbs`` (posterior of (mu, sd) by 2-D quadrature) sampled by block moves
  and population moves *only* (no other specimen move): the block kernel alone reaches the posterior
  and leaves it invariant; a block whose proposal density is wrong is caught by the same check.
* Population level (:class:`hbm.population.blocks.AmplitudeBlock` on a synthetic base-model specimen):
  its cheap log-likelihood equals the full model's at moved amplitudes; the Jacobian of A = e^y
  against finite differences of the real map y -> θ (fibre point) -> amplitudes; its proposal density
  is the density of its draws (an independence MH step with it keeps a known target; without the
  Jacobian it does not).
"""

import numpy as np
import pytest
from scipy.stats import norm

from hbm.samplers.hierarchical import ExactSpecimen, joint_gibbs
from test_joint_gibbs import HI, LO, P, S, Y, _model, exact_joint_draws, truth  # noqa: F401 - the conjugate toy


class _ToyBlock:
    """Block of the toy's single column: likelihood N(Y; y, s²); proposal a mixture of N(Y, (k s)²) and the
    population N(mu, sd) (``wrong``: the density claims k = 1 while drawing with k = 2)."""

    columns = (0,)

    def __init__(self, y, s, wrong=False):
        self.y, self.s, self.wrong = y, s, wrong

    def prepare(self, y):
        return None

    def log_likelihood(self, prep, y, rows):
        return norm.logpdf(self.y, y[:, 0], self.s)

    def propose(self, prep, rng, population):
        n = len(population[0][0])
        own = self.y + 2.0 * self.s * rng.standard_normal(n)
        mu, sd = population[0]
        pop = mu + sd * rng.standard_normal(n)
        return np.where(rng.random(n) < 0.5, own, pop)[:, None]

    def log_q(self, prep, yb, population):
        mu, sd = population[0]
        k = 1.0 if self.wrong else 2.0
        return np.logaddexp(norm.logpdf(yb[:, 0], self.y, k * self.s), norm.logpdf(yb[:, 0], mu, sd)) + np.log(0.5)


class _ToyBlock2:
    """The toy with a second, non-block column ν: ℓ = log N(Y; θ, s²) + log N(ν; θ/2, 1), so θ's marginal
    is the toy's and ν | θ ~ N(θ/2, 1).  The block is θ given ν: proposal a mixture of its Gaussian
    conditional (precision 1/s² + 1/4) and the population."""

    columns = (0,)

    def __init__(self, y, s):
        self.y, self.s = y, s

    def prepare(self, y):
        prec = 1.0 / self.s**2 + 0.25
        return {"nu": y[:, 1].copy(), "m": (self.y / self.s**2 + 0.5 * y[:, 1]) / prec, "sd": np.full(len(y), prec**-0.5)}

    def log_likelihood(self, prep, y, rows):
        return norm.logpdf(self.y, y[:, 0], self.s) + norm.logpdf(prep["nu"][rows], 0.5 * y[:, 0], 1.0)

    def propose(self, prep, rng, population):
        n = len(prep["m"])
        mu, sd = population[0]
        own = prep["m"] + 1.2 * prep["sd"] * rng.standard_normal(n)
        return np.where(rng.random(n) < 0.5, own, mu + sd * rng.standard_normal(n))[:, None]

    def log_q(self, prep, yb, population):
        mu, sd = population[0]
        return np.logaddexp(norm.logpdf(yb[:, 0], prep["m"], 1.2 * prep["sd"]), norm.logpdf(yb[:, 0], mu, sd)) + np.log(0.5)

    def select(self, prep, other, mask):
        return {k: np.where(mask, other[k], v) for k, v in prep.items()}


def _specs(init, wrong=False):
    rows = [np.linspace(-3, 3, 50)[:, None] for _ in Y]
    return {f"s{i}": ExactSpecimen(log_likelihood=(lambda y, s: lambda t: norm.logpdf(y, t[:, 0], s))(y, s),
                                   columns=lambda t: (t, None), box=np.array([[LO, HI]]), init=init[i],
                                   scale_rows=rows[i], pooled_cols={0: 0}, block=_ToyBlock(y, s, wrong))
            for i, (y, s) in enumerate(zip(Y, S))}


def _block_only(init_raw, init, seed, wrong=False, **kw):
    # spec_steps=0, nc_steps=0: the specimens move only through their blocks
    return joint_gibbs(_model(), init_raw, _specs(init, wrong), spec_steps=0, nc_steps=0, n_components=4,
                       seed=seed, **kw)


def test_refresh_move_of_the_other_columns_keeps_the_posterior(truth):
    """Block moves plus the refresh move (ν random walk with θ redrawn from the block's proposal) only:
    mu, θ_i and ν_i | θ_i ~ N(θ_i/2, 1) come out as the quadrature says."""
    rng = np.random.default_rng(21)
    nc = 128
    init_raw = np.column_stack([rng.uniform(-2, 3, nc), np.log(rng.uniform(0.5, 3, nc))])
    specs = {f"s{i}": ExactSpecimen(
        log_likelihood=(lambda y, s: lambda t: norm.logpdf(y, t[:, 0], s) + norm.logpdf(t[:, 1], 0.5 * t[:, 0], 1.0))(y, s),
        columns=lambda t: (t[:, :1], None), box=np.array([[LO, HI], [LO, HI]]),
        init=np.column_stack([rng.uniform(-3, 3, nc), rng.uniform(-3, 3, nc)]),
        scale_rows=rng.normal(0, 1, (50, 2)), pooled_cols={0: 0}, block=_ToyBlock2(y, s)) for i, (y, s) in enumerate(zip(Y, S))}
    r = joint_gibbs(_model(), init_raw, specs, spec_steps=0, nc_steps=0, n_components=4, seed=22, n_keep=30,
                    n_burn=40, thin=2, block_rounds=4, block_refresh=2)
    assert _ks_mu(r, truth)[0] < 0.05
    assert max(_ks_theta(r, truth, i) for i in range(len(Y))) < 0.05
    for i in range(len(Y)):
        th, nu = r.flat_state(f"s{i}").T
        resid = nu - 0.5 * th  # N(0, 1) independent of θ
        assert abs(resid.mean()) < 0.1 and abs(resid.std() - 1.0) < 0.06
        assert abs(np.corrcoef(resid, th)[0, 1]) < 0.08
    assert 0.1 < r.acceptance["s0"]["block_refresh"] < 0.9
    # the start, then per sweep the prepare and the two refresh moves' prepares
    assert r.evaluations["s0"] == 128 * (1 + 3 * (40 + 30 * 2))


def _ks_mu(r, truth):
    nat = _model().natural(r.flat_raw())
    o = np.argsort(truth["M"].ravel())
    cdf = np.interp(np.sort(nat[:, 0]), truth["M"].ravel()[o], np.cumsum(truth["w"].ravel()[o]))
    return float(np.max(np.abs(cdf - (np.arange(cdf.size) + 0.5) / cdf.size))), nat


def test_block_moves_alone_reach_the_conjugate_posterior(truth):
    rng = np.random.default_rng(11)
    nc = 128
    init_raw = np.column_stack([rng.uniform(-2, 3, nc), np.log(rng.uniform(0.5, 3, nc))])
    init = [rng.uniform(-3, 3, (nc, 1)) for _ in Y]
    r = _block_only(init_raw, init, 12, n_keep=40, n_burn=60, thin=2, block_rounds=4)
    ks, nat = _ks_mu(r, truth)
    tw = truth["w"]
    sd_mu = np.sqrt(np.sum(tw * truth["M"] ** 2) - np.sum(tw * truth["M"]) ** 2)
    M = truth["M"].ravel()
    o = np.argsort(M)
    exact = np.interp(P, np.cumsum(tw.ravel()[o]), M[o])
    assert np.all(np.abs(np.quantile(nat[:, 0], P) - exact) < 0.12 * sd_mu)
    assert ks < 0.05
    assert max(r.rhat.values()) < 1.05
    # the start, then one evaluation per chain and sweep (the block's prepare), none in the cheap rounds
    assert r.evaluations["s0"] == 128 * (1 + 60 + 40 * 2)
    assert r.options["blocks"] == [f"s{i}" for i in range(6)]
    assert 0.2 < r.acceptance["s0"]["block_independence"] < 1.0


def test_block_kernel_leaves_the_target_invariant_and_a_wrong_density_is_caught(truth):
    """Chains started from exact joint draws stay distributed as the posterior (no burn-in); the same
    run with a proposal density that does not match the draws drifts away (the check can fail)."""
    mu, sd, th = exact_joint_draws(truth, np.random.default_rng(13), 400)
    raw = np.column_stack([mu, np.log(sd)])
    good = _block_only(raw, th, 14, n_keep=10, n_burn=0, thin=3, block_rounds=4)
    bad = _block_only(raw, th, 14, n_keep=10, n_burn=0, thin=3, block_rounds=4, wrong=True)
    assert _ks_mu(good, truth)[0] < 0.05
    ks_good = [_ks_theta(good, truth, i) for i in range(len(Y))]
    ks_bad = [_ks_theta(bad, truth, i) for i in range(len(Y))]
    assert max(ks_good) < 0.035  # 4000 draws per specimen, correlated within chains
    assert max(ks_bad) > 0.055


def _ks_theta(r, truth, i):
    """KS distance of specimen i's draws from its exact marginal (normal given (mu, sd), mixed over the grid)."""
    M, SD, w = truth["M"], truth["SD"], truth["w"]
    v = 1.0 / (1.0 / SD**2 + 1.0 / S[i] ** 2)
    m = v * (M / SD**2 + Y[i] / S[i] ** 2)
    x = np.sort(r.flat_state(f"s{i}")[:, 0])[::40]
    cdf = np.array([(w * norm.cdf((g - m) / np.sqrt(v))).sum() for g in x])
    return float(np.max(np.abs(cdf - (np.arange(x.size) * 40 + 0.5) / (40 * x.size))))


# -- the population side: the amplitude block of a base-model specimen ---------------------------------
@pytest.fixture(scope="module")
def specimen():
    from hbm.identifiability.combinations import support_hull
    from hbm.data import synthetic_specimen
    from hbm.likelihood import make_likelihood
    from hbm.model import spyrou_model
    from hbm.population.pooling import PhiCoordinates

    m = spyrou_model()
    th = dict(VOLF=0.6, EOPT=0.1, P1=0.006, T1=0.3, T2=12.0, THETA=58.0, GF=0.01, GM=0.008)
    ds = synthetic_specimen(m, th, np.round(np.arange(45) * 0.01, 10), 0.015, 3, relative=True)
    lik = make_likelihood(m, ds)
    names, b = list(lik.names), np.asarray(lik.bounds)  # the stage-1 columns: model parameters, sigma
    co = PhiCoordinates(names, b, np.log(support_hull(b, names)), 0.0)
    rng = np.random.default_rng(5)
    th["sigma"] = 0.002
    theta = np.array([th[n] for n in names]) * np.exp(0.05 * rng.standard_normal((64, len(names))))
    theta = np.clip(theta, b[:, 0], b[:, 1])
    return lik, co, co.y_of(theta)


def test_amplitude_block_likelihood_is_the_models(specimen):
    from hbm.population.blocks import amplitude_block
    from hbm.population.fallbacks import _OnFibre

    lik, co, y = specimen
    block, why = amplitude_block(lik, co, co.names_y, y[:16], np.random.default_rng(0))
    assert block is not None and why == "" and block.columns == (0, 1, 2)
    prep = block.prepare(y)
    full = _OnFibre(lik, co)
    assert np.allclose(block.log_likelihood(prep, y, np.arange(64)), full(y), rtol=1e-10)
    moved = y.copy()
    moved[:, :3] += np.random.default_rng(1).normal(0, 0.3, (64, 3))
    ref = full(moved)
    got = block.log_likelihood(prep, moved, np.arange(64))
    assert np.isfinite(ref).sum() > 40
    assert np.array_equal(np.isfinite(got), np.isfinite(ref))
    fin = np.isfinite(ref)
    assert np.allclose(got[fin], ref[fin], rtol=1e-9, atol=1e-8)


def test_amplitude_jacobian_by_finite_differences(specimen):
    """log|det ∂A/∂y| of the real map y -> fibre point -> amplitudes is Σ y (the term in log_q)."""
    from hbm.model.linear import structure_of

    lik, co, y = specimen
    st = structure_of(lik.model)

    def amps(yy):
        theta, ok = co.theta_of(yy)
        assert ok.all()
        return st.amplitudes(lik.model_theta(theta))

    h = 1e-6
    for row in y[:5]:
        J = np.empty((3, 3))
        for j in range(3):
            up, dn = row.copy(), row.copy()
            up[j] += h
            dn[j] -= h
            J[:, j] = (amps(up[None])[0] - amps(dn[None])[0]) / (2 * h)
        assert np.linalg.slogdet(J)[1] == pytest.approx(row[:3].sum(), abs=1e-6)


def test_amplitude_proposal_density_is_the_draws_density(specimen):
    """Independence MH with the block's proposal and a known target π (a Gaussian in y on the draws'
    ridge) started from exact π draws stays at π: log_q is the density of the draws, mixture weights
    and Jacobian included; dropping the Jacobian from log_q moves the means by many standard errors."""
    from scipy.stats import multivariate_normal

    from hbm.population.blocks import amplitude_block

    lik, co, y = specimen
    block, _ = amplitude_block(lik, co, co.names_y, y[:16], np.random.default_rng(0))
    n = 40_000
    prep = block.prepare(np.repeat(y[:1], n, axis=0))
    pop = {1: (np.full(n, y[0, 1] - 0.5), np.full(n, 1.0))}  # population of log c·P1 at one ψ
    yb = block.propose(prep, np.random.default_rng(2), pop)
    ok = np.all(np.isfinite(yb), axis=1)
    assert ok.mean() > 0.9  # A <= 0 is proposed rarely (NaN: rejected)
    centre, cov = np.median(yb[ok], axis=0), 0.25 * np.cov(yb[ok].T)
    target = multivariate_normal(centre, cov)
    z = {}
    for jacobian in (True, False):
        rng = np.random.default_rng(3)
        x = target.rvs(n, random_state=rng)

        def lq(v):
            out = block.log_q(prep, v, pop)
            return out if jacobian else out - v.sum(axis=1)

        for _ in range(5):
            prop = block.propose(prep, rng, pop)
            fin = np.all(np.isfinite(prop), axis=1)
            with np.errstate(invalid="ignore"):
                a = fin & (np.log(rng.random(n)) < target.logpdf(np.where(fin[:, None], prop, centre))
                           - target.logpdf(x) + lq(x) - lq(prop))
            x[a] = prop[a]
        z[jacobian] = (x.mean(axis=0) - centre) / np.sqrt(np.diag(cov) / n)
    assert np.all(np.abs(z[True]) < 4)
    assert np.max(np.abs(z[False])) > 6
