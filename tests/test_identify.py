"""Identifiable combinations and VOLF–T1 manifolds on samples with a known structure."""

from __future__ import annotations

import numpy as np
import pytest

from hbm.errors import HbmError
from hbm.identify import (
    VolfT1Manifold,
    compare_manifolds,
    identifiable_directions,
    volf_t1_manifold,
)

NAMES = ["VOLF", "EOPT", "P1", "T1", "T2", "THETA", "GF", "GM"]
BOUNDS = np.array([[0.5, 0.99], [0, 0.2], [1e-4, 0.5], [0, 20], [0, 200], [55, 60], [1e-4, 0.1], [1e-4, 0.1]])


def structured_samples(n, seed, k=3.81e-3, af=0.01, g=0.02):
    """VOLF spread over its box; (1−VOLF)·T1 = k, VOLF·P1 = af, G = g fixed up to 1 % noise;
    EOPT, T2, THETA individually pinned; nothing else informative."""
    rng = np.random.default_rng(seed)
    x = rng.uniform(BOUNDS[:, 0], BOUNDS[:, 1], (n, 8))
    c = rng.uniform(0.5, 0.99, n)
    x[:, 0] = c
    x[:, 3] = k / (1 - c) * np.exp(0.01 * rng.standard_normal(n))
    x[:, 2] = af / c * np.exp(0.01 * rng.standard_normal(n))
    x[:, 1] = 0.15 + 0.002 * rng.standard_normal(n)
    x[:, 4] = 100 + 1.0 * rng.standard_normal(n)
    x[:, 5] = 59.0 + 0.03 * rng.standard_normal(n)
    # G = c·GF + (1−c)·GM fixed: GF free in a range that keeps GM positive
    gf = rng.uniform(0.005, 0.035, n)
    x[:, 6] = gf
    x[:, 7] = (g * np.exp(0.01 * rng.standard_normal(n)) - c * gf) / (1 - c)
    keep = (x[:, 7] > 1e-4) & (x[:, 7] < 0.1)
    return x[keep]


def test_directions_discover_one_minus_volf_times_t1():
    x = structured_samples(6000, seed=1)
    rep = identifiable_directions(x, NAMES, bounds=BOUNDS, threshold=0.1)
    labels = [d["label"] for d in rep.directions]
    assert "(1-VOLF)·T1" in labels, labels
    assert "VOLF·P1" in labels, labels
    d = rep.directions[labels.index("(1-VOLF)·T1")]
    assert d["exponents"] == {"(1-VOLF)": 1.0, "T1": 1.0}
    assert d["lo"] < 3.81e-3 < d["hi"] and abs(d["median"] / 3.81e-3 - 1) < 0.01
    assert d["sd_ratio_rounded"] < 0.02
    # VOLF and T1 themselves are NOT identified: no direction is VOLF or T1 alone
    assert "VOLF" not in labels and "T1" not in labels
    # the candidates: CV of the combination shrinks by a large factor vs VOLF and T1
    cand = rep.candidates
    assert cand["(1-VOLF)*T1"]["identified"] and cand["(1-VOLF)*T1"]["shrink"] < 0.1
    assert cand["VOLF*P1"]["identified"]
    assert cand["VOLF*GF+(1-VOLF)*GM"]["identified"]
    assert abs(cand["VOLF*GF+(1-VOLF)*GM"]["median"] / 0.02 - 1) < 0.01
    assert "(1-VOLF)·T1" in rep.table()


def test_directions_do_not_invent_a_product_when_volf_and_t1_are_separately_known():
    rng = np.random.default_rng(3)
    x = rng.uniform(BOUNDS[:, 0], BOUNDS[:, 1], (4000, 8))
    x[:, 0] = 0.9 + 0.002 * rng.standard_normal(4000)
    x[:, 3] = 2.0 * np.exp(0.01 * rng.standard_normal(4000))
    rep = identifiable_directions(x, NAMES, bounds=BOUNDS)
    labels = [d["label"] for d in rep.directions]
    assert "T1" in labels and any(lb in ("VOLF", "(1-VOLF)") for lb in labels)
    assert "(1-VOLF)·T1" not in labels
    assert not rep.candidates["VOLF*P1"]["identified"]


def test_spline_through_points_on_the_structural_manifold_returns_k():
    k = 3.81e-3
    volf = np.linspace(0.51, 0.985, 25)  # like the thesis's CMA-ES sweep optima
    t1 = k / (1 - volf)
    man = volf_t1_manifold(volf[::-1], t1[::-1], source="points")
    g = np.linspace(0.51, 0.985, 301)
    np.testing.assert_allclose(man.product(g), k, rtol=2e-3)
    np.testing.assert_allclose(man(volf), t1, rtol=1e-9)  # interpolating
    assert man.flatness < 5e-3
    assert np.isnan(man(0.995)) and np.isnan(man(0.3))
    # serialisation round trip
    back = VolfT1Manifold.from_arrays(man.to_arrays())
    np.testing.assert_allclose(back(g), man(g), rtol=1e-12)


def test_manifold_from_posterior_samples_and_comparison():
    x1 = structured_samples(5000, seed=4, k=3.81e-3)
    x2 = structured_samples(5000, seed=5, k=3.81e-3)
    x3 = structured_samples(5000, seed=6, k=6.0e-3)
    mans = {name: volf_t1_manifold(x[:, 0], x[:, 3]) for name, x in (("a", x1), ("b", x2), ("c", x3))}
    for m in mans.values():
        assert m.source == "samples"
        assert m.flatness < 0.05
    assert abs(mans["c"].level[0] / 6.0e-3 - 1) < 0.01
    cmp_ = compare_manifolds(mans)
    assert set(cmp_.differ) == {("a", "c"), ("b", "c")}
    assert cmp_.overlap[0, 1] and not cmp_.overlap[0, 2]
    assert cmp_.grid_t1.shape == (3, cmp_.grid_volf.size) and cmp_.grid_volf.size > 0
    # on a common VOLF, T1 curves scale like the levels
    np.testing.assert_allclose(cmp_.grid_t1[2] / cmp_.grid_t1[0], 6.0 / 3.81, rtol=0.05)
    assert abs(cmp_.spread - 6.0 / 3.81) < 0.05
    assert "c" in cmp_.table()


def test_bad_inputs():
    with pytest.raises(HbmError):
        volf_t1_manifold([0.5, 0.6], [1.0, 2.0, 3.0])
    with pytest.raises(HbmError):
        volf_t1_manifold([0.5, 0.6, 0.7], [1.0, 2.0, 3.0], source="points")
    with pytest.raises(HbmError):
        identifiable_directions(np.zeros((3, 8)), NAMES)
