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


# two separated Gaussian lobes on the box: one t in the logit coordinates covers them poorly
LOBES = [(0.7, np.array([0.3, -1.0, 2.0]), np.array([0.03, 0.1, 0.1])),
         (0.3, np.array([0.6, -0.2, 3.0]), np.array([0.03, 0.1, 0.1]))]


def loglik_lobes(x):
    return np.logaddexp(*[np.log(w) + stats.norm.logpdf(x, m, s).sum(axis=1) for w, m, s in LOBES])


def _truth_lobes():
    # ∫ over the box of the normalised mixture (each lobe's box mass) / volume
    mass = sum(w * np.prod(stats.norm.cdf(BOUNDS[:, 1], m, s) - stats.norm.cdf(BOUNDS[:, 0], m, s)) for w, m, s in LOBES)
    return float(np.log(mass) - np.sum(np.log(BOUNDS[:, 1] - BOUNDS[:, 0])))


def _lobe_draws(n, rng):
    k = rng.random(n) < LOBES[0][0]
    return np.where(k[:, None], LOBES[0][1] + LOBES[0][2] * rng.standard_normal((n, 3)),
                    LOBES[1][1] + LOBES[1][2] * rng.standard_normal((n, 3)))


def test_mixture_refit_covers_two_lobes_better_than_one_t():
    """Known evidence of a two-lobed likelihood: the mixture refit is exact within its SE and has a
    several times larger ESS than the single refitted t from the same draws."""
    post = _lobe_draws(500, np.random.default_rng(3))
    errs, gain = [], []
    for seed in range(4):
        one = importance_evidence(loglik_lobes, BOUNDS, post, 6000, seed=seed, adapt=0.3)
        mix = importance_evidence(loglik_lobes, BOUNDS, post, 6000, seed=seed, adapt=0.3, mixture=3)
        assert mix.accepted
        errs.append((mix.log_evidence - _truth_lobes()) / mix.log_evidence_se)
        gain.append(mix.ess / one.ess)
    assert np.all(np.abs(errs) < 4)
    assert np.median(gain) > 2, gain


def test_reserve_is_spent_only_after_a_refusal_and_the_combined_estimate_is_unbiased():
    post = _lobe_draws(500, np.random.default_rng(4))
    kept = importance_evidence(loglik_lobes, BOUNDS, post, 5000, seed=1, adapt=0.3, mixture=3, reserve=0.2)
    assert kept.accepted and kept.n_evaluations == 4000 and kept.n_draws == 2500
    errs = []
    for seed in range(4):
        # an unreachable ESS forces the refusal of round 2: the reserve is drawn and rounds 2 and 3
        # are combined (balance heuristic); the estimate stays exact within its SE
        r = importance_evidence(loglik_lobes, BOUNDS, post, 5000, seed=seed, adapt=0.3, mixture=3, reserve=0.2,
                                min_ess=1e9)
        assert not r.accepted and "ESS" in r.reason
        assert r.n_evaluations == 5000 and r.n_draws == 3500 and r.samples.shape == (3500, 3)
        errs.append((r.log_evidence - _truth_lobes()) / r.log_evidence_se)
    assert np.all(np.abs(errs) < 4)
