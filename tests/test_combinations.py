"""Exact stage-1 prior density of the identifiable combinations and the prior conditional."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.integrate import quad
from scipy.stats import kstest, qmc, uniform

from hbm.identifiability.combinations import (
    COMBINATION_PARAMS, combination_box, combination_features, fibre_point, log_density, sample_conditional,
    support_hull, to_features)
from hbm.identifiability.combinations import _integrand
from hbm.errors import HbmError
from hbm.model import spyrou_model

# a narrowed box with all lower ends > 0 and different GF/GM boxes (every trapezoid kink active)
BOX = {"VOLF": (0.55, 0.9), "P1": (0.01, 0.5), "T1": (0.5, 20.0), "GF": (0.001, 0.1), "GM": (0.002, 0.05)}


def prior_draws(box, n, seed):
    rng = np.random.default_rng(seed)
    return np.column_stack([rng.uniform(*box[p], n) for p in COMBINATION_PARAMS])


def test_quadrature_matches_adaptive_quad_on_the_default_box():
    m = spyrou_model()
    box = {p: tuple(m.bounds[m.index(p)]) for p in COMBINATION_PARAMS}
    th = prior_draws(box, 12, seed=1)
    phi, lp = combination_features(list(COMBINATION_PARAMS), th, box)
    B = combination_box(box)
    for i in range(len(th)):
        # independent reference: adaptive quadrature over c on many equal pieces (kinks are handled
        # by the adaptivity, not by our breakpoints)
        e = np.linspace(B[0, 0], B[0, 1], 201)
        ref = sum(quad(lambda c: _integrand(phi[i:i + 1], np.array([[c]]), B)[0, 0], a, b,
                       epsabs=0, epsrel=1e-10, limit=200)[0] for a, b in zip(e[:-1], e[1:]))
        assert abs(lp[i] - np.log(ref)) < 1e-5, (i, lp[i], np.log(ref))


@pytest.fixture(scope="module")
def prior_bins():
    n = 400_000
    th = prior_draws(BOX, n, seed=2)
    phi = np.log(to_features(list(COMBINATION_PARAMS), th))
    H, edges = np.histogramdd(phi, bins=8)
    order = np.argsort(H.ravel())[::-1]
    bins = []
    for flat in order[::7][:8]:  # bins of various densities, each with >= 1000 prior draws
        idx = np.unravel_index(flat, H.shape)
        if H[idx] >= 1000:
            bins.append((np.array([edges[k][idx[k]] for k in range(3)]),
                         np.array([edges[k][idx[k] + 1] for k in range(3)]), H[idx] / n))
    assert len(bins) >= 5
    return n, bins


def _bin_z(n, bins, logdens):
    """Per bin: |∫_bin p dφ − p̂| / (4 SE + 3 % QMC allowance); all < 1 means the density fits."""
    u = qmc.Sobol(3, seed=3).random(4096)
    out = []
    for lo, hi, p_hat in bins:
        mass = np.exp(logdens(lo + (hi - lo) * u)).mean() * np.prod(hi - lo)
        out.append(abs(mass - p_hat) / (4 * np.sqrt(p_hat / n) + 0.03 * p_hat))
    return np.array(out)


def test_density_matches_prior_histogram_and_is_normalised(prior_bins):
    n, bins = prior_bins
    z = _bin_z(n, bins, lambda x: log_density(x, BOX))
    assert np.all(z < 1), z
    # normalisation over the log support hull (all lower ends > 0 here)
    hull = np.log(support_hull(BOX))
    v = qmc.Sobol(3, seed=4).random(2**16)
    total = np.exp(log_density(hull[:, 0] + (hull[:, 1] - hull[:, 0]) * v, BOX)).mean() * np.prod(np.ptp(hull, axis=1))
    assert abs(total - 1.0) < 0.02, total


@pytest.mark.parametrize("k", [0, 1, 2])
def test_missing_jacobian_fails_the_histogram_check(prior_bins, k):
    """The check is sharp: the density without the e^{y_k} factor of one component (with the
    normalisation it then lacks restored on average) misses the bin masses."""
    n, bins = prior_bins
    z = _bin_z(n, bins, lambda x: log_density(x, BOX) - x[:, k] + np.mean([0.5 * (lo[k] + hi[k]) for lo, hi, _ in bins]))
    assert np.max(z) > 1, z


def test_sample_conditional_reproduces_phi_and_the_uniform_prior():
    n = 20_000
    th = prior_draws(BOX, n, seed=6)
    phi = np.log(to_features(list(COMBINATION_PARAMS), th))
    draws = sample_conditional(phi, BOX, np.random.default_rng(7))
    assert draws.shape == (n, 5)
    back = np.log(to_features(list(COMBINATION_PARAMS), draws))
    assert np.max(np.abs(back - phi)) < 1e-10
    for j, p in enumerate(COMBINATION_PARAMS):
        lo, hi = BOX[p]
        assert np.all((draws[:, j] >= lo) & (draws[:, j] <= hi))
        assert kstest(draws[:, j], uniform(lo, hi - lo).cdf).pvalue > 1e-3, p
    # the conditional is not the identity map: fresh draws differ from the originals
    assert np.mean(np.abs(draws[:, 0] - th[:, 0])) > 0.02


def test_fibre_point_reproduces_phi_inside_the_support_only():
    """Prior draws (inside the support by construction) give back a box point with the same φ;
    φ pushed off the box is flagged exactly where log p0 is -inf."""
    th = prior_draws(BOX, 5000, seed=8)
    phi = np.log(to_features(list(COMBINATION_PARAMS), th))
    parts, ok = fibre_point(phi, BOX)
    assert ok.all()
    np.testing.assert_allclose(np.log(to_features(list(COMBINATION_PARAMS), parts)), phi, atol=1e-10)
    lo, hi = np.array([BOX[p] for p in COMBINATION_PARAMS]).T
    assert np.all((parts >= lo) & (parts <= hi))
    shifted = phi + np.random.default_rng(9).normal(0.0, 2.0, phi.shape)
    _, ok = fibre_point(shifted, BOX)
    assert 0.05 < ok.mean() < 0.95
    np.testing.assert_array_equal(ok, np.isfinite(log_density(shifted, BOX)))


def test_bad_inputs():
    with pytest.raises(HbmError, match="VOLF"):
        combination_features(["P1", "T1", "GF", "GM"], np.ones((3, 4)), np.ones((4, 2)) * [0, 1])
    with pytest.raises(HbmError, match="inside"):
        combination_box({**BOX, "VOLF": (0.5, 1.0)})
    with pytest.raises(HbmError, match="support"):
        sample_conditional(np.array([[10.0, 0.0, 0.0]]), BOX, 0)
    assert np.isneginf(log_density(np.array([[10.0, 0.0, 0.0]]), BOX))[0]


# ----------------------------------------------------------------------------------------
# workflow: --pool combinations on synthetic stage-1 posteriors
# ----------------------------------------------------------------------------------------
def _sir_specimen(model, centre, seed, n_prior=200_000, n=1500):
    """Stage-1 posterior under the uniform box prior for a likelihood N(φ; centre, 0.3²) ×
    N(T2; 40, 15²) × N(THETA; 58, 0.7²), by importance resampling of prior draws; log Z from the
    same weights."""
    from types import SimpleNamespace

    rng = np.random.default_rng(seed)
    names = list(model.parameter_names)
    th = rng.uniform(model.bounds[:, 0], model.bounds[:, 1], (n_prior, len(names)))
    phi = np.log(to_features(names, th))
    ll = (-0.5 * np.sum(((phi - centre) / 0.3) ** 2, axis=1) - 3 * np.log(0.3 * np.sqrt(2 * np.pi))
          - 0.5 * ((th[:, names.index("T2")] - 40) / 15) ** 2 - np.log(15 * np.sqrt(2 * np.pi))
          - 0.5 * ((th[:, names.index("THETA")] - 58) / 0.7) ** 2 - np.log(0.7 * np.sqrt(2 * np.pi)))
    w = np.exp(ll - ll.max())
    logz = float(np.log(w.mean()) + ll.max())
    idx = rng.choice(n_prior, n, p=w / w.sum())
    return SimpleNamespace(names=names, bounds=model.bounds.copy(), samples=th[idx], log_evidence=logz,
                           log_evidence_se=0.01, specimen_id=f"s{seed}")


def test_workflow_pool_combinations(tmp_path):
    from hbm.organ import theta_from_samples
    from hbm.population import COMBINATION_COLUMNS, run_population
    from hbm.identifiability.views import population_table

    model = spyrou_model()
    centres = [np.array([-3.8, -3.0, -2.0]), np.array([-3.5, -2.7, -2.3]), np.array([-4.0, -3.2, -1.8]),
               np.array([-3.7, -2.9, -2.1])]
    results = {f"s{k}": _sir_specimen(model, c, seed=k) for k, c in enumerate(centres)}
    # pooled as the CLI passes it; no datasets, no dask
    hf, path = run_population(results, None, model, out=tmp_path, pooled=["combinations"], samples=400,
                              progress=False)
    from hbm import io

    h = io.read_hierarchical(path)
    assert h.pooled_names[:5] == list(COMBINATION_COLUMNS) + ["T2", "THETA"]
    assert sorted(h.attrs["derived"]) == sorted(["VOLF", "EOPT", "P1", "T1", "GF", "GM"])
    # the new specimen's parameters reproduce its pooled combinations exactly
    back = np.log(to_features(h.pooled_names, h.new_specimen))
    assert np.max(np.abs(back - h.new_specimen[:, :3])) < 1e-9
    th = theta_from_samples(model, h.pooled_names, h.new_specimen)
    assert np.all((th >= model.bounds[:, 0]) & (th <= model.bounds[:, 1]))
    pt = population_table(h)  # natural units, keyed by quantity
    assert list(pt) == ["G", "VOLF*P1", "(1-VOLF)*T1", "T2", "THETA"]
    assert [pt[c]["transform"] for c in ("G", "VOLF*P1", "(1-VOLF)*T1")] == ["log"] * 3
    mean_centre = np.exp(np.mean(centres, axis=0))  # geometric mean of the specimens' centres
    for k, c in enumerate(("G", "VOLF*P1", "(1-VOLF)*T1")):  # the population centre is near it
        assert pt[c]["median_lower"] < mean_centre[k] < pt[c]["median_upper"], (c, pt[c], mean_centre[k])
    assert h.updated.shape[1:] == (4, len(model.parameter_names))
    assert np.isfinite(h.log_evidence)


def test_importance_ratio_with_combination_prior_matches_population_integral():
    """log p(d|ψ) from reused stage-1 samples + log_prior equals ∫ L(φ) p(φ|ψ) dφ computed by direct
    Monte Carlo over the population (exact check of the whole φ pipeline, Jacobian included)."""
    from scipy.stats import norm, truncnorm

    from hbm.samplers.hierarchical import HierarchicalModel

    model = spyrou_model()
    centre = np.array([-3.7, -2.9, -2.1])
    r = _sir_specimen(model, centre, seed=11, n=20_000)
    names = list(r.names)
    phi, lp = combination_features(names, r.samples, r.bounds)
    hull = np.log(support_hull(r.bounds, names))
    hull[:, 0] = np.minimum(hull[:, 0], phi.min(0) - 1e-9)
    cols = ["log_G", "log_VOLF*P1", "log_(1-VOLF)*T1"]
    hm = HierarchicalModel(names + cols, np.vstack([r.bounds, hull]), pooled=cols)
    mu, sd = np.array([-3.5, -3.0, -2.5]), np.array([0.5, 0.4, 0.6])
    raw = np.concatenate([mu, np.log(sd)])[None, :]
    lm, ess = hm.log_mean_ratio(np.hstack([r.samples, phi]), raw, log_prior=lp)
    est = r.log_evidence + lm[0]
    # direct: E_{φ ~ population}[N(φ; centre, 0.3²) 1_S(φ)] × the T2 and THETA factors under their priors
    rng = np.random.default_rng(12)
    a, b = (hull[:, 0] - mu) / sd, (hull[:, 1] - mu) / sd
    draws = np.column_stack([truncnorm.rvs(a[k], b[k], loc=mu[k], scale=sd[k], size=60_000, random_state=rng)
                             for k in range(3)])
    inside = np.isfinite(log_density(draws, r.bounds, names))
    lik = np.exp(np.sum(norm.logpdf(draws, centre, 0.3), axis=1)) * inside
    f_t2 = (norm.cdf((200 - 40) / 15) - norm.cdf(-40 / 15)) / 200
    f_th = (norm.cdf((60 - 58) / 0.7) - norm.cdf((55 - 58) / 0.7)) / 5
    exact = np.log(lik.mean() * f_t2 * f_th)
    se = lik.std() / lik.mean() / np.sqrt(lik.size)
    assert abs(est - exact) < 4 * np.sqrt(se**2 + 1.0 / ess[0]) + 0.02, (est, exact, se, ess)
    # the density of the natural-unit combinations (Jacobian e^{-Σφ} missing) is far off
    wrong = r.log_evidence + hm.log_mean_ratio(np.hstack([r.samples, phi]), raw, log_prior=lp - phi.sum(1))[0][0]
    assert abs(wrong - exact) > 1.0
