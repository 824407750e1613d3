"""The truncated normal's one home (hbm.samplers.truncnorm) against an independent implementation (the
C library's erfc, in the tail where it has no cancellation)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from hbm.samplers.truncnorm import log_mass, ppf


def _upper(z: float) -> float:
    """1 − Φ(z) without cancellation for z ≥ 0."""
    return 0.5 * math.erfc(z / math.sqrt(2.0)) if z != math.inf else 0.0


def _exact(z0: float, z1: float) -> tuple[float, float]:
    """log(Φ(z1) − Φ(z0)) and the truncated mean, by erfc on the side of the interval away from 0."""
    if z0 + z1 < 0:
        mean_neg = _exact(-z1, -z0)
        return mean_neg[0], -mean_neg[1]
    phi = lambda z: math.exp(-z * z / 2) / math.sqrt(2 * math.pi) if z != math.inf else 0.0  # noqa: E731
    if z0 >= 0:
        mass = _upper(z0) - _upper(z1)
    else:  # straddles 0: no cancellation either way
        mass = 0.5 * (math.erf(z1 / math.sqrt(2.0)) - math.erf(z0 / math.sqrt(2.0)))
    return math.log(mass), (phi(z0) - phi(z1)) / mass


@pytest.mark.parametrize("z0,z1", [(-1.0, 2.0), (-30.0, -28.0), (28.0, 30.0), (5.0, np.inf), (-np.inf, -25.0),
                                   (-0.5, 0.5), (1e-3, 2e-3)])
def test_log_mass_and_mean_deep_in_both_tails(z0, z1):
    want_l, want_m = _exact(z0, z1)
    got_l, got_m = log_mass(z0, z1, mean=True)
    assert float(got_l) == pytest.approx(want_l, rel=1e-10, abs=1e-12)
    assert float(got_m) == pytest.approx(want_m, rel=1e-8, abs=1e-12)
    assert float(log_mass(z0, z1)) == float(got_l)  # the same number without the mean


def test_log_mass_of_an_empty_interval_is_minus_inf():
    assert log_mass(1.0, 1.0) == -np.inf
    _, m = log_mass(1.0, 1.0, mean=True)
    assert m == 1.0


def test_ppf_inverts_the_truncated_cdf_in_the_upper_tail():
    mu, sd, lo, hi = 0.0, 1.0, 9.0, 12.0  # the mirror branch: Φ(9) rounds to 1
    u = np.array([0.1, 0.5, 0.9])
    x = ppf(u, mu, sd, lo, hi)
    for ui, xi in zip(u, x):
        assert (_upper(lo) - _upper(float(xi))) / (_upper(lo) - _upper(hi)) == pytest.approx(ui, rel=1e-8)
