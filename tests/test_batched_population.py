"""The population layer's joint sampler (hbm.samplers.hierarchical.batched) against independent truths.

Gaussian toys whose marginal posterior of the population (mu, sd) is known up to a 2-D quadrature:
six specimens with likelihoods N(y_i; θ_i, s_i²) (θ a nonlinear column: every move evaluates), or
N(y_i; e^{u_i}, s_i²) with u = log A an amplitude column (quadratic in A: the particle moves), a normal
population (identity transform, truncated to the box) and the layer's hyperprior (mu uniform, log sd
uniform).  Also: the compiled particle kernel against quadrature, the combinations' support constraints
against :func:`hbm.identifiability.combinations.in_support`, bitwise equality on dask, R-hat/ESS against ArviZ.
"""

import numpy as np
import pytest
from scipy.stats import norm

from hbm.identifiability.combinations import combination_box, in_support, support_constraints
from hbm.errors import HbmError
from hbm.model import spyrou_model
from hbm.population import JOINT_SD_RANGE
from hbm.samplers.hierarchical import HierarchicalModel, PooledFeatures, ShardSpec, batched_gibbs, rhat_ess, one_population
from hbm.samplers.hierarchical.amplitudes import amplitudes_valid, particles, quadratic_loglik

Y = np.array([-1.5, -0.3, 0.2, 0.9, 2.1, 3.0])
S = np.array([0.5, 1.0, 1.5, 0.7, 2.0, 1.0])
LO, HI = -20.0, 20.0
P = np.array([0.05, 0.5, 0.95])


class Toy:
    """Six (or fewer) specimens: y = (t, phi); ``amplitude``: t = u = log A with N(y_i; e^u, s_i²), else
    t = θ with N(y_i; θ, s_i²); phi ~ N(0, 1) by its own likelihood (unpooled, rides along)."""

    def __init__(self, idx, amplitude: bool, y=Y, s=S) -> None:
        self.y, self.s = y[idx] + (3.5 if amplitude else 0.0), s[idx] * (0.5 if amplitude else 1.0)
        self.n_specimens, self.dy = len(idx), 2
        self.amplitude_cols = np.array([0] if amplitude else [], int)
        self.nonlinear_cols = np.array([1] if amplitude else [0, 1], int)
        self.noise_cols = np.array([], int)
        self.box = np.array([[LO, HI] if not amplitude else [-6.0, 3.0], [-8.0, 8.0]])
        self.amplitude_constraints = None

    def prepare(self, y):
        return {"phi": y[..., 1].copy()}

    def quadratic(self, prep, y):
        s2 = self.s[:, None] ** 2 + 0.0 * y[..., 0]
        ll0 = -0.5 * (self.y[:, None] ** 2 / s2 + np.log(2 * np.pi * s2)) - 0.5 * (prep["phi"] ** 2 + np.log(2 * np.pi))
        return ll0, (1.0 / s2)[..., None, None], (self.y[:, None] / s2)[..., None]

    def loglik(self, prep, y):
        if self.amplitude_cols.size:
            return quadratic_loglik(y[..., :1], *self.quadratic(prep, y))
        return norm.logpdf(self.y[:, None], y[..., 0], self.s[:, None]) + norm.logpdf(prep["phi"])

    def select(self, prep, new, mask):
        return {k: np.where(mask, new[k], v) for k, v in prep.items()}

    def valid(self, y):
        return np.all((y >= self.box[:, 0]) & (y <= self.box[:, 1]), axis=-1)


def _truth(amplitude: bool, y=Y, s=S, sd_range=(0.005, 0.25), mu_grid=181):
    """Quadrature of p(mu, sd | y) on a (mu, log sd) grid; for the amplitude toy each specimen's
    likelihood of the population is a 1-D quadrature over u."""
    toy = Toy(np.arange(len(y)), amplitude, y, s)
    box = toy.box[0]
    mu = np.linspace(box[0], box[1], mu_grid)
    lsd = np.linspace(np.log(sd_range[0] * (box[1] - box[0])), np.log(sd_range[1] * (box[1] - box[0])), 150)
    M, L = np.meshgrid(mu, lsd, indexing="ij")
    SD = np.exp(L)
    logz = np.log(norm.cdf((box[1] - M) / SD) - norm.cdf((box[0] - M) / SD))
    if not amplitude:
        lp = sum(norm.logpdf(y, M, np.sqrt(SD**2 + s**2)) for y, s in zip(toy.y, toy.s))
    else:
        u = np.linspace(box[0], box[1], 600)
        du = u[1] - u[0]
        pu = norm.pdf(u[None, None, :], M[..., None], SD[..., None])
        lp = sum(np.log(np.sum(norm.pdf(y, np.exp(u), s) * pu, axis=-1) * du) for y, s in zip(toy.y, toy.s))
    lp = lp - len(toy.y) * logz
    w = np.exp(lp - lp.max())
    return M, SD, w / w.sum()


def _wq(vals, w, p):
    o = np.argsort(vals.ravel())
    return np.interp(p, np.cumsum(w.ravel()[o]), vals.ravel()[o])


def _run(amplitude: bool, parts=(np.arange(6),), seed=0, client=None, y=Y, s=S, sd_range=(0.005, 0.25), **kw):
    toy_box = Toy(np.arange(len(y)), amplitude, y, s).box
    model = HierarchicalModel(["t", "phi"], toy_box, pooled=["t"], sd_range=sd_range)
    features = PooledFeatures(model, [0], None)
    rng = np.random.default_rng(seed)
    C = 8
    shards = []
    for idx in parts:
        toy = Toy(idx, amplitude, y, s)
        rows = [np.column_stack([rng.normal(np.log(y) if amplitude else y, 0.3, 400), rng.normal(0, 1, 400)])
                for y in toy.y]
        shards.append(ShardSpec(batch=toy, rows=rows, init=rng.integers(0, 400, (len(idx), C)),
                                seeds=[np.random.SeedSequence(seed, spawn_key=(int(i),)) for i in idx], index=idx))
    x0 = np.column_stack([rng.normal(np.mean(y), 0.3, C), np.log(rng.uniform(1.0, 2.0, C))])
    if amplitude:
        x0[:, 0] = rng.normal(0.9, 0.3, C)
        x0[:, 1] = np.log(rng.uniform(0.5, 1.0, C))
    x0[:, 1] = np.maximum(x0[:, 1], np.log(1.1 * sd_range[0] * np.ptp(toy_box[0])))  # inside the hyperprior
    return batched_gibbs(one_population(model, len(y)), shards, x0, features=features,
                         valid=lambda y: np.all((y >= toy_box[:, 0]) & (y <= toy_box[:, 1]), axis=-1),
                         constraints=None, amp_cols=[0] if amplitude else [], amp_pool=[0] if amplitude else [],
                         box=toy_box, seed=np.random.SeedSequence(seed, spawn_key=(99,)), client=client, **kw), model


@pytest.mark.parametrize("amplitude", [False, True])
def test_population_matches_the_quadrature(amplitude):
    """Both kinds of specimen column (evaluated, and amplitude by importance particles) give the marginal
    posterior of (mu, sd) of the quadrature: 5/50/95 % quantiles within Monte Carlo error."""
    res, model = _run(amplitude, n_burn=300, n_keep=600, thin=2)
    M, SD, w = _truth(amplitude)
    nat = model.natural(model.expand(res.x.reshape(-1, 2)))
    for col, grid in ((0, M), (1, SD)):
        got, want = np.quantile(nat[:, col], P), _wq(grid, w, P)
        spread = _wq(grid, w, 0.84) - _wq(grid, w, 0.16)
        assert np.all(np.abs(got - want) < 0.15 * spread), (col, got, want)
    assert max(v for k, v in res.rhat.items() if k.startswith("hyper")) < 1.1
    assert res.evaluations.sum() > 0


def test_the_default_hyperprior_admits_a_narrow_population():
    """40 specimens from a population of spread 0.02 × the box (0.8 on [-20, 20], noise sd 0.3, values at the
    generator's quantiles: its sample mean and sd are the generator's): with the joint layer's default sd range the
    sampler's 5/50/95 % of (mu, sd) match the quadrature, and both 90 % intervals hold the generating mu and
    sd.  The former floor, 0.05 × the range (2.0 here), kept sd above the truth: the layer's intervals missed
    the generating spread at every population size (results/benchmarks/population_layer.md)."""
    n, mu0, sd0 = 40, 1.0, 0.02 * (HI - LO)
    y = mu0 + sd0 * norm.ppf((np.arange(n) + 0.5) / n) / np.std(norm.ppf((np.arange(n) + 0.5) / n), ddof=1)
    s = np.full(n, 0.3)
    res, model = _run(False, parts=(np.arange(n),), y=y, s=s, sd_range=JOINT_SD_RANGE, n_burn=300, n_keep=400,
                      thin=2)
    M, SD, w = _truth(False, y, s, JOINT_SD_RANGE, mu_grid=1601)
    nat = model.natural(model.expand(res.x.reshape(-1, 2)))
    for col, grid, truth in ((0, M, mu0), (1, SD, sd0)):
        got, want = np.quantile(nat[:, col], P), _wq(grid, w, P)
        spread = _wq(grid, w, 0.84) - _wq(grid, w, 0.16)
        assert np.all(np.abs(got - want) < 0.15 * spread), (col, got, want)
        assert want[0] < truth < want[2] and got[0] < truth < got[2], (col, got, want, truth)


def test_draws_do_not_depend_on_where_the_shards_run():
    """The same partition in this process and as dask actors on two workers: bitwise the same draws."""
    distributed = pytest.importorskip("distributed")
    parts = (np.arange(3), np.arange(3, 6))
    local, _ = _run(True, parts, n_burn=20, n_keep=8, thin=2)
    with distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=False, dashboard_address=None) as lc, \
            distributed.Client(lc) as client:
        remote, _ = _run(True, parts, client=client, n_burn=20, n_keep=8, thin=2)
    assert np.array_equal(local.x, remote.x) and np.array_equal(local.y, remote.y)
    assert np.array_equal(local.evaluations, remote.evaluations)


def test_chains_extend_until_converged_and_stop_at_the_cap():
    """Chains not converged at the planned length go on half of it at a time: the extended run is bitwise the
    run planned at that length from the start (the same rounds), the checks are recorded, and the cap holds."""
    planned, _ = _run(True, n_burn=20, n_keep=16, thin=2)
    extended_to = []

    def conv(rhat, ess):
        extended_to.append(1)
        return len(extended_to) >= 3   # the third check (8 -> 12 -> 16 draws) says converged

    ext, _ = _run(True, n_burn=20, n_keep=8, thin=2, converged=conv, max_keep=40)
    assert ext.x.shape == planned.x.shape and np.array_equal(ext.x, planned.x) and np.array_equal(ext.y, planned.y)
    assert np.array_equal(ext.evaluations, planned.evaluations)
    assert [c[0] for c in ext.options["convergence_checks"]] == [8, 12, 16]
    assert ext.options["n_keep"] == 16 and ext.options["n_keep_planned"] == 8
    capped, _ = _run(True, n_burn=20, n_keep=8, thin=2, converged=lambda r, e: False, max_keep=14)
    assert capped.x.shape[1] == 14 and [c[0] for c in capped.options["convergence_checks"]] == [8, 12, 14]
    once, _ = _run(True, n_burn=20, n_keep=8, thin=2, converged=lambda r, e: True, max_keep=40)
    short, _ = _run(True, n_burn=20, n_keep=8, thin=2)
    assert np.array_equal(once.x, short.x) and len(once.options["convergence_checks"]) == 1
    assert once.rhat == short.rhat   # the check's diagnostics are the result's


def test_the_layer_convergence_rule():
    from hbm.population.layer import ESS_TARGET, RHAT_SPECIMEN, RHAT_TARGET, converged
    ok = {"hyper:a": 1.0, "0:1": 1.0}, {"hyper:a": ESS_TARGET, "0:1": 10.0}
    assert converged(*ok)
    assert not converged({**ok[0], "hyper:a": RHAT_TARGET + 1e-3}, ok[1])
    assert not converged(ok[0], {**ok[1], "hyper:a": ESS_TARGET - 1})
    assert not converged({**ok[0], "0:1": RHAT_SPECIMEN + 1e-3}, ok[1])
    assert converged({**ok[0], "0:1": float("nan")}, ok[1])    # a constant column


def test_bad_input():
    with pytest.raises(HbmError, match="n_keep"):
        _run(False, n_burn=0, n_keep=2, thin=1)


def test_particle_weights_integrate_to_the_quadrature():
    """E_q[π/q] over the kernel's particles is ∫π (a 2-D grid): the proposal's density is the density of
    its draws, for rows with and without a population on each column."""
    rng = np.random.default_rng(1)
    n, k = 3, 2
    X = rng.standard_normal((n, 15, k))
    G, b = np.einsum("nik,nil->nkl", X, X) * 4, rng.standard_normal((n, k)) * 3
    mu, sd = rng.normal(-1, 0.5, (n, k)), np.exp(rng.normal(0, 0.3, (n, k)))
    lo, hi = np.full(k, -9.0), np.full(k, 4.0)
    M = 100_000
    _, lw = particles(G, b, np.zeros(n), mu, sd, np.ones(k, bool), lo, hi, None, rng.random((n, M)),
                      rng.standard_normal((n, M, k + 4)))
    g = np.linspace(-9, 4, 801)
    uu = np.stack(np.meshgrid(g, g, indexing="ij"), -1).reshape(-1, 2)
    for r in range(n):
        lp = quadratic_loglik(uu, 0.0, G[r], b[r]) - 0.5 * np.sum(((uu - mu[r]) / sd[r]) ** 2, -1)
        grid = np.exp(lp).sum() * (g[1] - g[0]) ** 2
        assert np.mean(np.exp(lw[r])) == pytest.approx(grid, rel=0.03)


def test_support_constraints_are_the_combinations_support():
    model = spyrou_model()
    box = combination_box(model.bounds, model.parameter_names)
    rng = np.random.default_rng(2)
    phi = np.column_stack([rng.uniform(-10, -1, 20000), rng.uniform(-12, 0, 20000), rng.uniform(-12, 3, 20000)])
    got = amplitudes_valid(phi, np.full(3, -50.0), np.full(3, 50.0), support_constraints(box))
    assert np.array_equal(got, in_support(phi, box)) and 0.2 < got.mean() < 0.8


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
    """An independent implementation (ArviZ): rank-normalised split R-hat (bulk) equal, bulk ESS within 5 %."""
    az = pytest.importorskip("arviz")
    rng = np.random.default_rng(3)
    x = np.cumsum(rng.standard_normal((8, 500)), axis=1) * 0.05 + rng.standard_normal((8, 500))
    x += np.arange(8)[:, None] * 0.1  # chains that disagree a little
    rh, ess = rhat_ess(x)
    assert rh == pytest.approx(float(az.rhat(x, method="z_scale")), abs=1e-10)
    assert ess == pytest.approx(float(az.ess(x, method="bulk")), rel=0.05)


def test_average_ranks_equal_scipys_rankdata_with_ties():
    """R-hat's ranks (numpy only, so `hbm summary` skips scipy.stats) against scipy.stats.rankdata: equal,
    bit for bit, with and without ties and for a 2-D input ranked as one sample."""
    from scipy.stats import rankdata

    from hbm.samplers.convergence import average_ranks

    rng = np.random.default_rng(11)
    for x in (rng.standard_normal((4, 50)), rng.integers(0, 6, size=(3, 40)).astype(float),
              np.round(rng.standard_normal(200), 1), np.zeros(5), np.array([2.0]),
              np.array([1.0, np.inf, -np.inf, 1.0]), np.array([0.5, np.nan, 0.2])):
        assert np.array_equal(average_ranks(x), rankdata(x, axis=None), equal_nan=True)
