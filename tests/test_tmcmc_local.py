"""Locally adapted random walk (``move="local"``, :class:`hbm.samplers.moves.LocalWalk`): exact MH kernel, neighbourhood covariances."""

from __future__ import annotations

import math

import numpy as np
import pytest

from hbm.errors import HbmError
from hbm.samplers.local_proposal import fit_local_metric, local_step, nearest_reference
from hbm.samplers.moves import LocalWalk
from hbm.samplers.resampling import islands, resample_islands
from hbm.samplers.tmcmc import tmcmc


def _curved(n, rng, sd=0.05):
    """Exact draws of a thin curved 2-D density: x1 ~ N(0, 1), x2 | x1 ~ N(x1², sd²)."""
    x1 = rng.standard_normal(n)
    return np.column_stack([x1, x1**2 + sd * rng.standard_normal(n)])


def _curved_logpdf(u):
    return -0.5 * u[:, 0] ** 2 - 0.5 * ((u[:, 1] - u[:, 0] ** 2) / 0.05) ** 2


def test_neighbourhood_covariance_is_local_and_nearest_is_exact():
    rng = np.random.default_rng(0)
    ref = _curved(2000, rng, sd=0.002)
    m = fit_local_metric(ref, np.cov(ref.T), k=20, ridge=1e-6)
    # the neighbourhood covariance at x1 = 1 follows the tangent (1, 2x1) = (1, 2): slope ≈ 2,
    # while the global covariance has slope ≈ 0 (x1 and x1² are uncorrelated)
    j = nearest_reference(m, np.array([[1.0, 1.0]]))[0]
    c = m.chols[j] @ m.chols[j].T
    assert abs(c[0, 1] / c[0, 0] - 2.0) < 0.5
    # nearest reference by brute force in the whitened metric
    q = rng.standard_normal((50, 2))
    w = np.linalg.inv(np.linalg.cholesky(np.cov(ref.T)))
    refs = m.refs_w @ np.linalg.inv(w).T
    brute = np.argmin((((q @ w.T)[:, None, :] - m.refs_w[None]) ** 2).sum(-1), axis=1)
    assert np.array_equal(nearest_reference(m, q), brute)
    assert np.allclose(refs[brute], np.unique(ref, axis=0)[brute])


def test_local_step_leaves_the_target_invariant():
    # a funnel (x1 ~ N(0, 1), x2 | x1 ~ N(0, e^{2·x1})): the neighbourhood covariances change
    # ~e² across the population, so a missing Hastings correction q(u|u')/q(u'|u) shifts the
    # x1 marginal visibly.  Start from exact draws; after many steps the moments must hold.
    rng = np.random.default_rng(1)

    def draws(n):
        x1 = rng.standard_normal(n)
        return np.column_stack([x1, np.exp(x1) * rng.standard_normal(n)])

    def evaluate(u):
        return -0.5 * u[:, 0] ** 2 - u[:, 0] - 0.5 * (u[:, 1] * np.exp(-u[:, 0])) ** 2, np.zeros(len(u))

    ref = draws(1000)
    m = fit_local_metric(ref, np.cov(ref.T), k=10, ridge=1e-3)
    x = draws(4000)
    ll, lp = evaluate(x)
    near = nearest_reference(m, x)
    acc = []
    for _ in range(40):
        x, ll, lp, near, a, _ = local_step(x, ll, lp, near, 1.0, 1.5, evaluate, rng, m)
        acc.append(a.mean())
    assert 0.05 < np.mean(acc) < 0.95
    se = 1.0 / math.sqrt(len(x))  # draws stay exact: E x1 = 0, E x1² = 1
    assert abs(x[:, 0].mean()) < 5 * se
    assert abs(np.mean(x[:, 0] ** 2) - 1.0) < 5 * math.sqrt(2) * se


def test_local_proposal_tmcmc_evidence_on_a_gaussian():
    # 3-D Gaussian likelihood on a box: Z = (√(2π)·0.3)³ / 10³ (mass inside the box)
    b = np.array([[-5.0, 5.0]] * 3)

    def ll(x):
        return -0.5 * np.sum((x - 1.0) ** 2, axis=1) / 0.09

    truth = 3 * (0.5 * math.log(2 * math.pi) + math.log(0.3)) - 3 * math.log(10.0)
    r = tmcmc(ll, b, 400, seed=3, progress=False, move=LocalWalk(neighbours=15, ridge=1e-3))
    assert abs(r.log_evidence - truth) <= 4 * r.log_evidence_se + 0.05
    assert np.allclose(r.samples.mean(axis=0), 1.0, atol=0.05)


def test_island_resampling_stays_in_its_island_with_systematic_counts():
    # every island draws its own size from its own particles, and systematic resampling gives each
    # particle floor or ceil of its expected count (size · normalised weight within the island)
    n, k = 100, 4
    starts, sizes, isl = islands(n, k)
    logw = np.log(np.random.default_rng(0).random(n))
    m_k = np.maximum.reduceat(logw, starts)
    idx = resample_islands(logw, m_k, starts, sizes, isl, np.random.default_rng(1), "systematic")
    assert np.array_equal(isl[idx], isl)
    w = np.exp(logw)
    expected = sizes[isl] * w / np.add.reduceat(w, starts)[isl]
    counts = np.bincount(idx, minlength=n)
    assert np.all((counts >= np.floor(expected)) & (counts <= np.ceil(expected)))


@pytest.mark.parametrize("kw, msg", [({"proposal": "local", "transform": "none"}, "needs transform='logit'"),
                                     ({"move": "local", "transform": "none"}, "needs transform='logit'"),
                                     ({"recycle": True}, "unknown options"),
                                     ({"proposal": "nope"}, "proposal must be")])
def test_bad_local_options(kw, msg):
    with pytest.raises(HbmError, match=msg):
        tmcmc(lambda x: -np.sum(x * x, axis=1), np.array([[-1.0, 1.0]] * 2), 50, seed=0, progress=False, **kw)


@pytest.mark.parametrize("kw, msg", [({"neighbours": 1}, "local_neighbours"), ({"ridge": 0.0}, "local_ridge")])
def test_bad_local_walk_settings(kw, msg):
    with pytest.raises(HbmError, match=msg):
        LocalWalk(**kw)
