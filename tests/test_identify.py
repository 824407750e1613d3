"""Identifiable combinations and VOLF–T1 manifolds on samples with a known structure."""

from __future__ import annotations

import numpy as np
import pytest

from hbm.errors import HbmError
from hbm.identifiability.identify import (
    VolfT1Manifold, candidate_combinations, compare_manifolds, identifiable_directions, volf_t1_manifold)

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
    # VOLF pinned makes both log VOLF and log(1-VOLF) identified (k = 3): counted, listed once
    assert rep.n_identified == rep.n_resolved == 3
    assert len(labels) == 2


def _labels(rep):
    return {d["label"] for d in rep.directions}


def _direction(rep, label):
    return next(d for d in rep.directions if d["label"] == label)


def correlated_log_errors(rng, n, sds, rho=0.9):
    """Errors e_i = sd_i·(ρ·z + √(1−ρ²)·w_i) with a common factor z: the identified
    combinations are correlated in the posterior, as on real fits (THETA with the collagen
    stiffness), so the eigenvectors of the identified subspace are mixtures of them."""
    z = rng.standard_normal(n)
    w = rng.standard_normal((len(sds), n))
    return [s * (rho * z + np.sqrt(1 - rho ** 2) * wi) for s, wi in zip(sds, w)]


def test_sparse_basis_recovers_the_generating_combinations():
    """(1−VOLF)·T1 = a, VOLF·P1 = b, THETA pinned; VOLF, GF, T2 (and the rest) uniform.

    Posterior/prior sd ratios ≈ 0.04 (THETA), 0.05, 0.06 with correlated errors: the
    identified subspace is 3-D and its eigenvectors are mixtures (the old per-eigenvector
    pruning collapsed them all onto THETA) — the basis must be exactly the three generators."""
    rng = np.random.default_rng(11)
    n, a, b = 4000, 0.05, 0.05
    x = rng.uniform(BOUNDS[:, 0], BOUNDS[:, 1], (n, 8))
    c = x[:, 0]
    e_t1, e_p1, e_th = correlated_log_errors(rng, n, (0.065, 0.06, 0.04 * 0.025))
    x[:, 3] = a / (1 - c) * np.exp(e_t1)
    x[:, 2] = b / c * np.exp(e_p1)
    x[:, 5] = 58.0 * np.exp(e_th)
    rep = identifiable_directions(x, NAMES, bounds=BOUNDS)
    assert rep.n_identified == 3 and rep.n_resolved == 3
    assert _labels(rep) == {"(1-VOLF)·T1", "VOLF·P1", "THETA"}
    assert _direction(rep, "(1-VOLF)·T1")["exponents"] == {"(1-VOLF)": 1.0, "T1": 1.0}
    assert _direction(rep, "VOLF·P1")["exponents"] == {"VOLF": 1.0, "P1": 1.0}
    for label, true in (("(1-VOLF)·T1", a), ("VOLF·P1", b), ("THETA", 58.0)):
        d = _direction(rep, label)
        assert abs(d["median"] / true - 1) < 0.01, (label, d["median"])
        assert d["lo"] < true < d["hi"]
        assert d["sd_ratio_rounded"] < 0.1
    assert rep.candidates["(1-VOLF)*T1"]["identified"] and rep.candidates["VOLF*P1"]["identified"]
    assert not rep.candidates["(1-VOLF)*T1*T2"]["identified"]  # T2 is free


def test_linear_collagen_regime_identifies_only_the_product_with_t2():
    """(1−VOLF)·T1·T2 = a with T1 and T2 trading off: the product is found, (1−VOLF)·T1 is not."""
    rng = np.random.default_rng(12)
    n, a = 8000, 0.5
    x = rng.uniform(BOUNDS[:, 0], BOUNDS[:, 1], (n, 8))
    c = x[:, 0]
    x[:, 4] = np.exp(rng.uniform(np.log(5.0), np.log(200.0), n))
    e_k, e_th = correlated_log_errors(rng, n, (0.08, 0.04 * 0.025))
    x[:, 3] = a / ((1 - c) * x[:, 4]) * np.exp(e_k)
    x[:, 5] = 56.0 * np.exp(e_th)
    x = x[(x[:, 3] > 0) & (x[:, 3] < 20)]
    rep = identifiable_directions(x, NAMES, bounds=BOUNDS)
    assert _labels(rep) == {"(1-VOLF)·T1·T2", "THETA"}
    assert "(1-VOLF)·T1" not in _labels(rep)
    d = _direction(rep, "(1-VOLF)·T1·T2")
    assert abs(d["median"] / a - 1) < 0.01
    assert rep.candidates["(1-VOLF)*T1*T2"]["identified"]
    assert not rep.candidates["(1-VOLF)*T1"]["identified"]


def test_narrow_box_parameter_keeps_its_exponent():
    """T2 ∝ THETA^6: log THETA has a prior sd of only 0.025 on [55, 60], so normalising the
    largest exponent to 1 would read THETA·T2^-0.17 and round to THETA; the label must be
    T2·THETA^-6 (neither T2 nor THETA is identified on its own)."""
    rng = np.random.default_rng(13)
    n = 4000
    x = rng.uniform(BOUNDS[:, 0], BOUNDS[:, 1], (n, 8))
    x[:, 4] = 100.0 * (x[:, 5] / 57.5) ** 6 * np.exp(0.002 * rng.standard_normal(n))
    rep = identifiable_directions(x, NAMES, bounds=BOUNDS)
    assert _labels(rep) == {"T2·THETA^-6"}
    d = _direction(rep, "T2·THETA^-6")
    assert d["exponents"] == {"T2": 1.0, "THETA": -6.0}
    assert abs(d["median"] / (100.0 * 57.5 ** -6) - 1) < 2e-3


def test_combination_longer_than_max_terms_is_counted_but_not_invented():
    """(1−VOLF)·T1·T2·GF fixed: a 4-term direction; max_terms=3 must report nothing
    (and say one direction is unresolved), max_terms=4 must report exactly it."""
    rng = np.random.default_rng(14)
    n, a = 6000, 1e-3
    x = rng.uniform(BOUNDS[:, 0], BOUNDS[:, 1], (n, 8))
    x[:, 4] = rng.uniform(20.0, 200.0, n)
    x[:, 6] = rng.uniform(0.01, 0.1, n)
    x[:, 3] = a / ((1 - x[:, 0]) * x[:, 4] * x[:, 6]) * np.exp(0.005 * rng.standard_normal(n))
    x = x[x[:, 3] < 20]
    rep3 = identifiable_directions(x, NAMES, bounds=BOUNDS, max_terms=3)
    assert rep3.n_identified == 1 and rep3.n_resolved == 0 and rep3.directions == []
    assert "without a sparse representation" in rep3.table()
    rep4 = identifiable_directions(x, NAMES, bounds=BOUNDS, max_terms=4)
    assert _labels(rep4) == {"(1-VOLF)·T1·T2·GF"}
    assert abs(_direction(rep4, "(1-VOLF)·T1·T2·GF")["median"] / a - 1) < 2e-3


def test_prior_draws_identify_nothing():
    rng = np.random.default_rng(15)
    x = rng.uniform(BOUNDS[:, 0], BOUNDS[:, 1], (3000, 8))
    rep = identifiable_directions(x, NAMES, bounds=BOUNDS)
    assert rep.n_identified == 0 and rep.directions == []
    assert rep.spectrum.min() > 0.5
    assert not any(c["identified"] for c in rep.candidates.values())
    for c in rep.candidates.values():
        assert 0.8 < c["sd_ratio"] < 1.2


def test_candidate_flag_follows_the_sd_ratio_not_the_cv_shrink():
    """VOLF on a narrow range (CV ≈ 0.03) and VOLF·P1 known to CV 0.07: the old CV-shrink
    criterion said "not identified", but the prior sd of log(VOLF·P1) on the box is ≈ 1, so
    the posterior/prior sd ratio is ≈ 0.07 < 0.1."""
    rng = np.random.default_rng(16)
    n = 5000
    x = rng.uniform(BOUNDS[:, 0], BOUNDS[:, 1], (n, 8))
    x[:, 0] = rng.uniform(0.85, 0.95, n)
    x[:, 2] = 0.1 / x[:, 0] * np.exp(0.07 * rng.standard_normal(n))
    # prior sd of log(VOLF·P1) from the generator's box: log U(a, b) moments in closed form
    def log_uniform_var(a, b):
        m1 = (b * np.log(b) - b - a * np.log(a) + a) / (b - a)
        m2 = (b * (np.log(b) ** 2 - 2 * np.log(b) + 2) - a * (np.log(a) ** 2 - 2 * np.log(a) + 2)) / (b - a)
        return m2 - m1 ** 2
    prior_sd = np.sqrt(log_uniform_var(0.5, 0.99) + log_uniform_var(1e-4, 0.5))
    assert 0.9 < prior_sd < 1.1
    cand = candidate_combinations(x, NAMES, bounds=BOUNDS)
    c = cand["VOLF*P1"]
    assert abs(c["cv"] - 0.07) < 0.005
    assert c["shrink"] > 0.5  # the old criterion would have said no
    assert abs(c["sd_ratio"] - 0.07 / prior_sd) < 0.01
    assert c["identified"]
    assert not cand["(1-VOLF)*T1"]["identified"] and cand["(1-VOLF)*T1"]["sd_ratio"] > 0.5
    # without bounds or prior draws: the old CV-shrink criterion, no ratio
    old = candidate_combinations(x, NAMES)["VOLF*P1"]
    assert np.isnan(old["sd_ratio"]) and not old["identified"]
    # identifiable_directions threads its prior draws through
    rep = identifiable_directions(x, NAMES, bounds=BOUNDS)
    assert rep.candidates["VOLF*P1"]["identified"]
    assert abs(rep.candidates["VOLF*P1"]["sd_ratio"] - c["sd_ratio"]) < 0.01


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
