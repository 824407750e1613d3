"""PSIS k-hat against arviz.psislw (independent implementation) and the reuse diagnostic's flags."""

from __future__ import annotations

import numpy as np
import pytest

from hbm.errors import HbmError
from hbm.samplers.hierarchical import pareto_khat

az = pytest.importorskip("arviz")


@pytest.mark.parametrize("k_true", [0.2, 0.5, 0.9, 1.5])
def test_khat_matches_arviz(k_true):
    rng = np.random.default_rng(int(10 * k_true))
    lw = np.log1p(rng.pareto(1.0 / k_true, 2000))  # ratios with a Pareto tail of shape k_true
    _, k_ref = az.psislw(lw.copy())
    assert pareto_khat(lw) == pytest.approx(float(k_ref), abs=1e-10)


def test_khat_rows_match_arviz_and_bad_input():
    rng = np.random.default_rng(3)
    lw = rng.normal(0.0, 2.0, (6, 1000))
    _, k_ref = az.psislw(lw.copy())
    np.testing.assert_allclose(pareto_khat(lw), k_ref, atol=1e-10)
    with pytest.raises(HbmError):
        pareto_khat(np.full(5, 0.0))
