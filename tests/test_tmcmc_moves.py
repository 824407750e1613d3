"""The Move protocol from outside the package: a registered move and the benchmark's DE move.

Truths: a correlated 2-D Gaussian inside a box (closed-form evidence, mean and covariance); the
ordered pairs of the DE move are uniform (chi-square); a move registered by name runs exactly as
the same object passed directly.
"""

from __future__ import annotations

import math
import sys
from pathlib import Path

import numpy as np
import pytest

from hbm.errors import HbmError
from hbm.samplers import MOVES, RandomWalk, register_move
from hbm.samplers.tmcmc import tmcmc

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "workflows" / "benchmarks"))
from experimental_moves import DifferentialEvolution, pairs_excluding_self  # noqa: E402

MEAN = np.array([1.0, -1.0])
COV = np.array([[1.0, 0.95 * 2.0], [0.95 * 2.0, 4.0]])
PREC = np.linalg.inv(COV)
LOGDET = float(np.linalg.slogdet(COV)[1])
BOX = np.array([[-10.0, 12.0], [-20.0, 20.0]])
LOG_Z = -math.log(22.0 * 40.0)  # normalised density, all its mass inside the box


def corr_gauss(x):
    r = x - MEAN
    return -0.5 * np.einsum("ni,ij,nj->n", r, PREC, r) - 0.5 * LOGDET - math.log(2 * math.pi)


@pytest.mark.parametrize("transform", ["logit", "none"])
def test_differential_evolution_move_is_exact_on_a_correlated_gaussian(transform):
    move = DifferentialEvolution(fraction=1.0)
    res = tmcmc(corr_gauss, BOX, 2000, seed=31, progress=False, move=move, transform=transform)
    assert abs(res.log_evidence - LOG_Z) < max(4 * res.log_evidence_se, 0.1)
    x = res.samples
    sd = np.sqrt(np.diag(COV))
    assert np.all(np.abs(x.mean(axis=0) - MEAN) < 0.1 * sd)
    c = np.cov(x, rowvar=False)
    np.testing.assert_allclose(np.sqrt(np.diag(c)), sd, rtol=0.08)
    assert abs(c[0, 1] / np.sqrt(c[0, 0] * c[1, 1]) - 0.95) < 0.02
    # DE proposals were made and accepted at a useful rate
    acc = np.array(move.de_acceptance)
    assert len(acc) >= len(res.stages) and 0.15 < acc.mean() < 0.8


def test_de_fraction_zero_is_the_plain_random_walk():
    a = tmcmc(corr_gauss, BOX, 300, seed=3, progress=False)
    move = DifferentialEvolution(fraction=0.0, jump=0.5)
    c = tmcmc(corr_gauss, BOX, 300, seed=3, progress=False, move=move)
    assert np.array_equal(a.samples, c.samples)
    assert move.de_acceptance == []


def test_de_pairs_exclude_self_and_are_uniform():
    rng = np.random.default_rng(0)
    n, m = 5, 200_000
    rows = rng.integers(0, n, m)
    a, b = pairs_excluding_self(n, m, rng, rows)
    assert np.all((a != rows) & (b != rows) & (a != b))
    assert a.min() >= 0 and max(a.max(), b.max()) < n
    # for row 0 the 12 ordered pairs of {1..4} are equally likely (chi-square, 11 dof)
    sel = rows == 0
    counts = np.bincount(a[sel] * n + b[sel], minlength=n * n).reshape(n, n)[1:, 1:]
    obs = counts[~np.eye(4, dtype=bool)]
    exp = sel.sum() / 12
    assert np.sum((obs - exp) ** 2 / exp) < 35.0  # p ≈ 2e-4 under uniformity


def test_a_registered_move_is_selectable_by_name_and_checkpointed_apart(tmp_path):
    register_move("de_test", lambda: DifferentialEvolution(fraction=0.5))
    try:
        by_name = tmcmc(corr_gauss, BOX, 300, seed=4, progress=False, move="de_test")
        direct = tmcmc(corr_gauss, BOX, 300, seed=4, progress=False, move=DifferentialEvolution(fraction=0.5))
        plain = tmcmc(corr_gauss, BOX, 300, seed=4, progress=False, move=RandomWalk())
        assert np.array_equal(by_name.samples, direct.samples)
        assert not np.array_equal(by_name.samples, plain.samples)
        # a checkpoint of the random walk does not resume a run with the DE move
        ck = tmp_path / "c.npz"
        tmcmc(corr_gauss, BOX, 100, seed=4, progress=False, checkpoint=ck)
        with pytest.raises(HbmError, match="different settings"):
            tmcmc(corr_gauss, BOX, 100, seed=4, progress=False, checkpoint=ck, move="de_test")
    finally:
        MOVES.pop("de_test", None)
    with pytest.raises(HbmError, match="unknown move"):
        tmcmc(corr_gauss, BOX, 100, seed=4, progress=False, move="de_test")
