"""Importance-sampling evidence: a Gaussian likelihood on a box with a known evidence, refusal."""

import numpy as np
import pytest
from scipy import stats

from hbm.samplers.importance import importance_evidence

MEAN = np.array([0.3, -1.0, 2.0])
SD = np.array([0.05, 0.2, 0.1])
BOUNDS = np.array([[0.0, 1.0], [-3.0, 1.0], [0.0, 5.0]])


def loglik(x):
    return stats.norm.logpdf(x, MEAN, SD).sum(axis=1)


def _truth():
    # Z = Π (Φ(hi) − Φ(lo)) / Π width: the box cuts nothing visible here
    mass = stats.norm.cdf(BOUNDS[:, 1], MEAN, SD) - stats.norm.cdf(BOUNDS[:, 0], MEAN, SD)
    return float(np.sum(np.log(mass)) - np.sum(np.log(BOUNDS[:, 1] - BOUNDS[:, 0])))


@pytest.mark.parametrize("adapt", [0.0, 0.3])
def test_evidence_within_its_standard_error_and_accepted(adapt):
    rng = np.random.default_rng(0)
    post = MEAN + SD * rng.standard_normal((500, 3))
    errs = []
    for seed in range(5):
        r = importance_evidence(loglik, BOUNDS, post, 4000, seed=seed, adapt=adapt)
        assert r.n_evaluations == 4000 and r.n_draws == 4000 - int(round(adapt * 4000))
        assert r.accepted and r.reason is None
        assert r.khat < 0.7 and r.ess > 0.3 * r.n_draws
        errs.append((r.log_evidence - _truth()) / r.log_evidence_se)
    assert np.all(np.abs(errs) < 4)


def test_bad_proposal_is_refused_with_the_reason():
    rng = np.random.default_rng(1)
    # posterior draws from the wrong place, too narrow: the proposal misses the mass
    post = MEAN + np.array([0.3, 0.0, 0.0]) + 0.1 * SD * rng.standard_normal((500, 3))
    r = importance_evidence(loglik, BOUNDS, post, 4000, seed=0)
    assert not r.accepted
    assert "k̂" in r.reason or "ESS" in r.reason


def test_adaptive_round_repairs_a_poor_first_proposal():
    """A proposal fitted to too-narrow, shifted draws is refused in one round; the refit recovers."""
    rng = np.random.default_rng(2)
    post = MEAN + np.array([0.05, 0.0, 0.0]) + 0.3 * SD * rng.standard_normal((500, 3))
    one = importance_evidence(loglik, BOUNDS, post, 6000, seed=1)
    two = importance_evidence(loglik, BOUNDS, post, 6000, seed=1, adapt=0.3)
    assert not one.accepted
    assert two.accepted and abs(two.log_evidence - _truth()) < 4 * two.log_evidence_se


def test_needs_enough_samples():
    from hbm.errors import HbmError
    with pytest.raises(HbmError, match="posterior samples"):
        importance_evidence(loglik, BOUNDS, np.zeros((3, 3)), 100, seed=0)
