"""TMCMC in caller-supplied sampling coordinates (``bijection=``): exact target, default unchanged.

Truths: a Gaussian likelihood truncated by the prior box has a closed-form evidence and moments
(products of 1-D truncated normals); a wrong log-Jacobian must visibly bias them (the check can
fail).  The muscle map of :mod:`hbm.identifiability.combinations` is checked against central differences.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.stats import norm, truncnorm

from hbm.identifiability.combinations import CombinationCoordinates, onset_strain
from hbm.errors import HbmError
from hbm.samplers.tmcmc import tmcmc
from hbm.samplers.coordinates import LogitCoordinates
from hbm.samplers.coordinates import to_logit as _to_logit

MU, S, HI = 1.0, 0.6, 5.0  # N(1, 0.6²) on [0, 5]^d: truncated at 1.67 sd on the left
D = 3


def _ll(x):
    return -0.5 * np.sum((x - MU) ** 2, axis=1) / S**2


BOUNDS = np.array([[0.0, HI]] * D)
# log Z = log ∫ L dθ / vol = d·log(√(2π)·S·(Φ((HI−μ)/S) − Φ(−μ/S))/HI)
LOG_Z = D * math.log(math.sqrt(2 * math.pi) * S * (norm.cdf((HI - MU) / S) - norm.cdf(-MU / S)) / HI)
TRUNC = truncnorm((0.0 - MU) / S, (HI - MU) / S, loc=MU, scale=S)


class LogCoordinates:
    """u = log θ on (0, HI]^d: support (−∞, log HI], log|dθ/du| = Σ u (nonlinear, non-constant)."""

    name = "log"
    support = np.array([[-np.inf, math.log(HI)]] * D)

    def __init__(self, jacobian: float = 1.0):
        self.jacobian = jacobian  # multiplies the log-Jacobian (1 = exact; a wrong value biases the target)

    def forward(self, theta):
        return np.log(theta)

    def inverse(self, u):
        return np.exp(u), self.jacobian * u.sum(axis=1)


def test_nonlinear_bijection_gives_exact_evidence_and_moments():
    errs = []
    for seed in range(3):
        r = tmcmc(_ll, BOUNDS, 1000, seed=seed, progress=False, bijection=LogCoordinates())
        errs.append(r.log_evidence - LOG_Z)
        assert abs(r.log_evidence - LOG_Z) <= 4 * r.log_evidence_se + 0.05, (r.log_evidence, r.log_evidence_se)
        assert np.all(r.samples > 0) and np.all(r.samples <= HI)
        # moments of the truncated normal (MC error of the mean ~0.02–0.03 with ~N/3 effective draws)
        np.testing.assert_allclose(r.samples.mean(axis=0), TRUNC.mean(), atol=0.08)
        np.testing.assert_allclose(r.samples.std(axis=0), TRUNC.std(), rtol=0.12)
        np.testing.assert_allclose(r.log_likelihood, _ll(r.samples))
    assert np.mean(np.abs(errs)) < 0.15


def test_a_wrong_jacobian_is_detected():
    # twice log|dθ/du| makes the walk sample L·θ instead of L: each mean moves up by
    # Var/E = 0.27 (size-biased truncated normal), far outside the tolerance of the test above
    r = tmcmc(_ll, BOUNDS, 1000, seed=0, progress=False, bijection=LogCoordinates(jacobian=2.0))
    shift = TRUNC.var() / TRUNC.mean()
    assert shift > 0.25
    assert np.all(np.abs(r.samples.mean(axis=0) - TRUNC.mean() - shift) < 0.08)


def test_logit_bijection_reproduces_the_default_bitwise():
    b = np.array([[-10.0, 10.0], [-3.0, 7.0], [0.0, 2.0]])
    r0 = tmcmc(_ll, b, 400, seed=7, progress=False)
    r1 = tmcmc(_ll, b, 400, seed=7, progress=False, bijection=LogitCoordinates(b))
    assert r0.log_evidence == r1.log_evidence and r0.n_evaluations == r1.n_evaluations
    assert np.array_equal(r0.samples, r1.samples)


def test_support_rejects_without_evaluating():
    rows = [0]

    def counted(x):
        rows[0] += len(x)
        assert np.all(x <= HI) and np.all(x > 0)  # never called outside the prior box
        return _ll(x)

    r = tmcmc(counted, BOUNDS, 300, seed=1, progress=False, bijection=LogCoordinates())
    assert rows[0] == r.n_evaluations


def test_bad_bijection_is_an_error():
    with pytest.raises(HbmError, match="move='rw'"):
        tmcmc(_ll, BOUNDS, 100, seed=0, progress=False, move="manifold",
              gradient_fim=lambda x: (x, np.ones((len(x), D, D))), bijection=LogCoordinates())
    bad = LogCoordinates()
    bad.support = np.zeros((D, 2))
    with pytest.raises(HbmError, match="support"):
        tmcmc(_ll, BOUNDS, 100, seed=0, progress=False, bijection=bad)
    with pytest.raises(HbmError, match="bijection needs"):
        tmcmc(_ll, BOUNDS, 100, seed=0, progress=False, bijection=object())
    with pytest.raises(HbmError, match="local"):
        tmcmc(_ll, BOUNDS, 100, seed=0, progress=False, move="local", bijection=LogCoordinates())


def test_checkpoint_of_other_coordinates_does_not_resume(tmp_path):
    ck = tmp_path / "run.npz"
    tmcmc(_ll, BOUNDS, 100, seed=0, progress=False, checkpoint=ck)
    with pytest.raises(HbmError):
        tmcmc(_ll, BOUNDS, 100, seed=0, progress=False, checkpoint=ck, bijection=LogCoordinates())


# ---------------------------------------------------------------------------- the muscle map
NAMES = ("VOLF", "EOPT", "P1", "T1", "T2", "THETA", "GF", "GM", "sigma")
MBOX = np.array([[0.5, 0.99], [0, 0.2], [1e-4, 0.5], [0, 20], [0, 200], [55, 60], [1e-4, 0.1], [1e-4, 0.1],
                 [1e-4, 0.05]])


@pytest.mark.parametrize("theta", ["onset", "linear", "logit"])
def test_combination_coordinates_roundtrip_and_jacobian(theta):
    m = CombinationCoordinates(NAMES, MBOX, theta=theta)
    rng = np.random.default_rng(0)
    x = MBOX[:, 0] + (0.02 + 0.96 * rng.random((40, 9))) * (MBOX[:, 1] - MBOX[:, 0])
    u = m.forward(x)
    back, log_j = m.inverse(u)
    np.testing.assert_allclose(back, x, rtol=1e-10, atol=1e-12)
    h = 1e-6
    jac = np.empty((40, 9, 9))
    for k in range(9):
        e = np.zeros(9)
        e[k] = h
        jac[:, :, k] = (m.inverse(u + e)[0] - m.inverse(u - e)[0]) / (2 * h)
    np.testing.assert_allclose(log_j, np.linalg.slogdet(jac)[1], atol=1e-5)
    # the shear straightens c·P1 = const: along it u_P1 moves only by the logit's curvature,
    # ≤ log((pb − p_lo)/(pb − p_hi)) over P1 ∈ [0.1, 0.2] (here 0.29), vs log(0.99/0.5) = 0.68 unsheared
    c = np.linspace(0.5, 0.99, 11)
    row = np.tile(x[0], (11, 1))
    row[:, 0], row[:, 2] = c, 0.099 / c
    j = NAMES.index("P1")
    assert np.ptp(m.forward(row)[:, j]) < 0.3 < np.ptp(_to_logit(row, MBOX)[:, j])
    if theta == "onset":
        np.testing.assert_allclose(m.support[5], np.log(onset_strain(MBOX[5])))
        assert abs(onset_strain(60.0) - 0.3028) < 1e-4  # DESIGN.md: λ* = 1.3028 at 60°


def test_combination_coordinates_bad_input():
    with pytest.raises(HbmError, match="magic angle|above"):
        CombinationCoordinates(NAMES, np.where(np.arange(9)[:, None] == 5, [[50.0, 60.0]], MBOX))
    with pytest.raises(HbmError, match="theta"):
        CombinationCoordinates(NAMES, MBOX, theta="cubic")
    with pytest.raises(HbmError, match="bounds"):
        CombinationCoordinates(NAMES, MBOX[:5])
