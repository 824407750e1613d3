"""The collapsed likelihood: the identity ∫ p(A|φ) L(φ, A) dA against independent computations.

* induced column priors against histograms of the original parameters (every derived form);
* the box-truncated Gaussian integral against scipy's adaptive quadrature and against the
  closed form of a flat prior on a wide box (no truncation);
* the collapsed likelihood of the base model against plain Monte Carlo over the original
  amplitude parameters with the full likelihood, and the evidence over a small box against
  brute-force integration of the full likelihood;
* a deliberately wrong induced prior (flat G) is detected;
* the tier is refused, with the reason, where it does not apply.

The base model's basis is written here from the README formulas (an independent
implementation of the linear structure, used until the model declares its own).
"""

import numpy as np
import pytest
import xarray as xr
from scipy import integrate
from scipy.special import ndtr

from hbm.likelihood.collapsed import BoxGaussianIntegral, CollapseError, ColumnPrior, Term, box_qp
from hbm.likelihood.collapsed.likelihood import CollapsedLikelihood, collapse_reason
from hbm.likelihood import make_likelihood
from hbm.model import spyrou_model

MODEL = spyrou_model()


class BaseStructure:
    """Linear structure of the base model from the README formulas (test-only)."""

    columns = ("G", "AF", "AM")
    amplitude_parameters = ("GF", "GM", "P1", "T1")
    column_of = {"GF": "G", "GM": "G", "P1": "AF", "T1": "AM"}
    nonlinear_parameters = ("VOLF", "EOPT", "T2", "THETA")

    def __init__(self, model):
        self.model = model
        self.i = {n: model.index(n) for n in model.parameter_names}

    def coefficients(self, theta):
        c = np.asarray(theta)[..., self.i["VOLF"]]
        return np.stack([c, 1 - c, c, 1 - c], axis=-1)

    def basis(self, loading, theta):
        theta = np.asarray(theta)
        eps = loading.strain
        lam = 1 + eps
        g = lambda n: theta[..., self.i[n], None]  # noqa: E731
        th = np.deg2rad(g("THETA"))
        lh = np.sqrt(np.cos(th) ** 2 * lam ** 2 + np.sin(th) ** 2 / lam)
        mat = np.broadcast_to(lam ** 2 - 1 / lam, lh.shape)
        fib = lam * np.maximum(eps - g("EOPT"), 0.0)
        col = np.where(lh > 1, lam * (np.exp(g("T2") * (lh - 1)) - 1), 0.0)
        return np.stack([mat, fib, col], axis=-1)


STRAIN = np.linspace(0.01, 0.42, 30)
TRUTH = {"VOLF": 0.9, "EOPT": 0.15, "P1": 0.13, "T1": 1.5, "T2": 9.3, "THETA": 59.0, "GF": 0.012, "GM": 0.009}


def _data(sd=0.004, seed=0, **truth):
    rng = np.random.default_rng(seed)
    row = np.array([{**TRUTH, **truth}[n] for n in MODEL.parameter_names])
    s = MODEL.stress(STRAIN, row) + rng.normal(0, sd, STRAIN.size)
    return xr.Dataset({"strain": ("point", STRAIN), "stress": ("point", s)}, attrs={"id": "t"})


# ------------------------------------------------------------------------------ induced priors
def _hist_check(prior, draws, row=0, bins=60):
    h, e = np.histogram(draws, bins=bins, range=(prior.lo[row], prior.hi[row]), density=True)
    mid = 0.5 * (e[1:] + e[:-1])
    # exact bin averages of the derived density (fine Simpson grid inside each bin)
    sub = np.linspace(e[:-1], e[1:], 41).T
    pdf = prior.pdf(np.broadcast_to(sub.ravel(), (prior.n, sub.size)))[row].reshape(sub.shape)
    avg = integrate.simpson(pdf, x=sub, axis=1) / (e[1:] - e[:-1])
    se = np.sqrt(np.maximum(avg, 1e-12) / (draws.size * (e[1] - e[0])))
    assert np.all(np.abs(h - avg) < 5 * se + 1e-3 * avg.max()), (mid, h, avg)
    # and it integrates to one
    x = np.linspace(prior.lo[row], prior.hi[row], 20001)
    assert integrate.trapezoid(prior.pdf(np.broadcast_to(x, (prior.n, x.size)))[row], x) == pytest.approx(1, abs=2e-3)


@pytest.mark.parametrize("forms", [("uniform", "uniform"), ("loguniform", "loguniform"),
                                   ("uniform", "loguniform"), ("loguniform", "uniform")])
def test_two_term_induced_prior_matches_histogram(forms):
    rng = np.random.default_rng(1)
    t1, t2 = Term.of("GF", 1e-3, 0.1, forms[0]), Term.of("GM", 2e-3, 0.05, forms[1])
    c = np.array([0.7, 0.95])
    prior = ColumnPrior("G", [t1, t2], np.column_stack([c, 1 - c]))
    draw = lambda t, m: (np.exp(rng.uniform(np.log(t.lo), np.log(t.hi), m)) if t.is_log  # noqa: E731
                         else rng.uniform(t.lo, t.hi, m))
    m = 400_000
    for row in range(2):
        g = c[row] * draw(t1, m) + (1 - c[row]) * draw(t2, m)
        _hist_check(prior, g, row)


@pytest.mark.parametrize("form", ["uniform", "loguniform"])
def test_one_term_induced_prior_matches_histogram(form):
    rng = np.random.default_rng(2)
    t = Term.of("P1", 1e-4, 0.5, form)
    prior = ColumnPrior("AF", [t], np.array([[0.8]]))
    a = np.exp(rng.uniform(np.log(t.lo), np.log(t.hi), 400_000)) if t.is_log else rng.uniform(t.lo, t.hi, 400_000)
    _hist_check(prior, 0.8 * a, bins=50 if form == "uniform" else 200)


@pytest.mark.parametrize("forms", [("uniform", "uniform"), ("loguniform", "loguniform"), ("uniform", "loguniform")])
def test_split_returns_the_prior_of_the_original_parameters(forms):
    """A ~ induced prior, then (a1, a2) | A: the pair must be the independent prior draws again."""
    rng = np.random.default_rng(3)
    t1, t2 = Term.of("GF", 1e-3, 0.1, forms[0]), Term.of("GM", 2e-3, 0.05, forms[1])
    m, c = 200_000, 0.6
    draw = lambda t: (np.exp(rng.uniform(np.log(t.lo), np.log(t.hi), m)) if t.is_log  # noqa: E731
                      else rng.uniform(t.lo, t.hi, m))
    a1, a2 = draw(t1), draw(t2)
    prior = ColumnPrior("G", [t1, t2], np.tile([c, 1 - c], (m, 1)))
    out = prior.split(c * a1 + (1 - c) * a2, rng)
    np.testing.assert_allclose(c * out["GF"] + (1 - c) * out["GM"], c * a1 + (1 - c) * a2, rtol=1e-9)
    from scipy import stats
    for t, x in ((t1, out["GF"]), (t2, out["GM"])):
        ref = np.log(x) if t.is_log else x
        lo, hi = (np.log(t.lo), np.log(t.hi)) if t.is_log else (t.lo, t.hi)
        assert stats.kstest(ref, stats.uniform(lo, hi - lo).cdf).pvalue > 1e-3


def test_three_terms_are_refused():
    with pytest.raises(CollapseError, match="3 free parameters"):
        ColumnPrior("S", [Term.of("a", 0, 1), Term.of("b", 0, 1), Term.of("c", 0, 1)], np.ones((1, 3)))


# ------------------------------------------------------------------------------ the integral
def _problem(seed, n=3, P=20, scale=(30.0, 10.0)):
    rng = np.random.default_rng(seed)
    X = rng.normal(size=(n, P, 2)) * np.array(scale)
    y = X @ np.array([0.05, 0.2]) + rng.normal(size=(n, P))
    return X, y


def _hby(X, y):
    return np.einsum("npi,npj->nij", X, X), np.einsum("npi,np->ni", X, y), (y * y).sum(1)


def test_box_integral_matches_adaptive_quadrature_and_draws_match_moments():
    X, y = _problem(0)
    c = np.array([0.6, 0.8, 0.95])
    pG = ColumnPrior("G", [Term.of("GF", 1e-4, 0.1), Term.of("GM", 1e-4, 0.1)], np.column_stack([c, 1 - c]))
    pP = ColumnPrior("AF", [Term.of("P1", 1e-4, 0.5)], c[:, None])
    v, err = BoxGaussianIntegral(*_hby(X, y), [pG, pP]).log_integral(refine=True)
    H, b, yy = _hby(X, y)
    for r in range(3):  # independent: Simpson on a 2001² grid (≥ 100 points per posterior sd)
        g1, g2 = np.linspace(pG.lo[r], pG.hi[r], 2001), np.linspace(pP.lo[r], pP.hi[r], 2001)
        A1, A2 = np.meshgrid(g1, g2, indexing="ij")
        Q = yy[r] - 2 * (b[r, 0] * A1 + b[r, 1] * A2) + H[r, 0, 0] * A1 ** 2 + 2 * H[r, 0, 1] * A1 * A2 + H[r, 1, 1] * A2 ** 2
        f = pG.pdf(np.broadcast_to(g1, (3, g1.size)))[r][:, None] * pP.pdf(np.full((3, 1), 0.2))[r] * np.exp(-0.5 * (Q - Q.min()))
        ref = integrate.simpson(integrate.simpson(f, x=g2, axis=1), x=g1)
        assert v[r] == pytest.approx(np.log(ref) - 0.5 * Q.min(), abs=1e-4)
        assert err[r] < 1e-4
    # draws of A | y: moments against a fine grid
    m = 6000
    Xr, yr = np.repeat(X[:1], m, 0), np.repeat(y[:1], m, 0)
    pri = [ColumnPrior("G", pG.terms, np.tile([c[0], 1 - c[0]], (m, 1))), ColumnPrior("AF", pP.terms, np.full((m, 1), c[0]))]
    A = BoxGaussianIntegral(*_hby(Xr, yr), pri).draw(np.random.default_rng(4))
    g1, g2 = np.linspace(pG.lo[0], pG.hi[0], 601), np.linspace(pP.lo[0], pP.hi[0], 601)
    G1, G2 = np.meshgrid(g1, g2, indexing="ij")
    Q = ((y[0] - G1[..., None] * X[0][:, 0] - G2[..., None] * X[0][:, 1]) ** 2).sum(-1)
    w = pG.pdf(np.broadcast_to(g1, (3, g1.size)))[0][:, None] * np.exp(-0.5 * (Q - Q.min()))
    w /= w.sum()
    for j, G in enumerate((G1, G2)):
        mean = (w * G).sum()
        sd = np.sqrt((w * (G - mean) ** 2).sum())
        assert abs(A[:, j].mean() - mean) < 4 * sd / np.sqrt(m)
        assert A[:, j].std() == pytest.approx(sd, rel=0.05)


def test_wide_flat_box_gives_the_gaussian_closed_form():
    """Uniform priors far wider than the likelihood: (2π)^{k/2} det H^{-1/2} e^{−RSS/2} / Π width."""
    rng = np.random.default_rng(5)
    n, P, k = 4, 25, 3
    X = rng.normal(size=(n, P, k)) * np.array([5.0, 20.0, 1.0])
    X[:, :, 2] += 0.9 * X[:, :, 0] / 5.0  # correlated columns
    y = X @ np.array([1.0, -0.3, 2.0]) + rng.normal(size=(n, P))
    H, b, yy = _hby(X, y)
    width = 400.0
    pri = [ColumnPrior(f"c{j}", [Term.of(f"a{j}", -200.0, 200.0)], np.ones((n, 1))) for j in range(k)]
    v, _ = BoxGaussianIntegral(H, b, yy, pri).log_integral()
    mhat = np.linalg.solve(H, b[..., None])[..., 0]
    rss = yy - np.einsum("ni,ni->n", b, mhat)
    expect = 0.5 * k * np.log(2 * np.pi) - 0.5 * np.linalg.slogdet(H)[1] - 0.5 * rss - k * np.log(width)
    v2, err = BoxGaussianIntegral(H, b, yy, pri).log_integral(refine=True)
    assert np.all(np.abs(v - expect) < 5e-5)
    assert np.all(np.abs(v - expect) <= 3 * err + 1e-8)  # the error estimate covers the error


def test_zero_column_integrates_its_prior_to_one():
    X, y = _problem(6)
    X[:, :, 1] = 0.0  # e.g. the fibre column when EOPT exceeds the largest strain
    pri = [ColumnPrior("G", [Term.of("GF", 1e-4, 0.1), Term.of("GM", 1e-4, 0.1)], np.tile([0.7, 0.3], (3, 1))),
           ColumnPrior("AF", [Term.of("P1", 1e-4, 0.5)], np.full((3, 1), 0.7))]
    both, _ = BoxGaussianIntegral(*_hby(X, y), pri).log_integral()
    one, _ = BoxGaussianIntegral(*_hby(X[:, :, :1], y), pri[:1]).log_integral()
    np.testing.assert_allclose(both, one, atol=1e-10)


def test_box_qp_matches_brute_force_grid():
    rng = np.random.default_rng(7)
    for _ in range(20):
        L = rng.normal(size=(3, 3))
        P = L @ L.T
        q = rng.normal(size=3) * 3
        x = box_qp(P, q, np.zeros(3), np.ones(3))
        g = np.stack(np.meshgrid(*[np.linspace(0, 1, 41)] * 3, indexing="ij"), -1).reshape(-1, 3)
        f = 0.5 * np.einsum("ni,ij,nj->n", g, P, g) - g @ q
        assert 0.5 * x @ P @ x - q @ x <= f.min() + 1e-12


# ------------------------------------------------------------------------------ the base model
def _small_box_lik(sd=0.02, sigma=(0.015, 0.03), **truth):
    """Base model, narrow amplitude boxes: brute force over them is feasible."""
    prior = {"P1": (0.08, 0.2), "T1": (0.5, 3.0), "GF": (0.005, 0.02), "GM": (0.004, 0.015)}
    return make_likelihood(MODEL, _data(sd=sd, **truth), fix={"EOPT": 0.15, "T2": 9.3, "THETA": 59.0}, prior=prior,
                           sigma_bounds=sigma)


def test_collapsed_likelihood_equals_monte_carlo_over_the_original_amplitudes():
    lik = _small_box_lik()
    cl = CollapsedLikelihood(lik, BaseStructure(MODEL))
    assert cl.names == ("VOLF", "sigma")
    phis = np.array([[0.6, 0.02], [0.9, 0.018], [0.97, 0.025]])
    v, err = cl.log_likelihood(phis, refine=True)
    assert np.all(err < 1e-4)
    rng = np.random.default_rng(8)
    m = 400_000
    for r, phi in enumerate(phis):
        rows = np.empty((m, lik.d))
        rows[:, lik.index("VOLF")], rows[:, lik.index("sigma")] = phi
        for p in ("P1", "T1", "GF", "GM"):
            lo, hi = lik.bounds[lik.index(p)]
            rows[:, lik.index(p)] = rng.uniform(lo, hi, m)
        ll = lik(rows)
        mx = ll.max()
        w = np.exp(ll - mx)
        mc, se = np.log(w.mean()) + mx, w.std() / w.mean() / np.sqrt(m)
        assert abs(v[r] - mc) < 4 * se + 1e-4, (r, v[r], mc, se)


def test_collapsed_evidence_equals_brute_force_and_flat_G_prior_is_caught():
    """log Z over (VOLF, sigma) with the amplitudes integrated exactly, against quasi-Monte Carlo
    over all six free parameters of the full likelihood; a flat prior on G (the wrong induced
    prior) moves log Z by more than the brute force's error.  G = 0.006 lies on the trapezoid's
    lower ramp, where the two priors differ."""
    lik = _small_box_lik(sd=0.003, sigma=(0.002, 0.005), GF=0.006, GM=0.006)
    cl = CollapsedLikelihood(lik, BaseStructure(MODEL))
    (v0, v1), (s0, s1) = cl.bounds[0], cl.bounds[1]
    xg, wg = np.polynomial.legendre.leggauss(24)
    V, S = np.meshgrid(v0 + (xg + 1) / 2 * (v1 - v0), s0 + (xg + 1) / 2 * (s1 - s0), indexing="ij")
    W = np.outer(wg, wg) / 4.0  # prior density × area cancel: weights of the unit square
    ll = cl(np.column_stack([V.ravel(), S.ravel()]))
    logz_c = np.log(np.sum(W.ravel() * np.exp(ll - ll.max()))) + ll.max()
    # brute force: scrambled Sobol over the 6-D box of the full likelihood
    from scipy.stats import qmc
    est = []
    for s in range(8):
        u = qmc.Sobol(lik.d, scramble=True, seed=s).random(2 ** 17)
        full = lik(lik.bounds[:, 0] + u * (lik.bounds[:, 1] - lik.bounds[:, 0]))
        est.append(np.log(np.mean(np.exp(full - full.max()))) + full.max())
    brute, se = np.mean(est), np.std(est, ddof=1) / np.sqrt(len(est))
    assert abs(logz_c - brute) < max(4 * se, 2e-3), (logz_c, brute, se)

    # wrong: G uniform on the trapezoid's support instead of the trapezoid
    class FlatG(BaseStructure):
        pass

    wrong = CollapsedLikelihood(lik, FlatG(MODEL))
    orig = ColumnPrior.__init__

    def flat_init(self, name, terms, weights, offset=None):
        if name == "G":
            w = np.asarray(weights)
            lo = w[:, 0] * terms[0].lo + w[:, 1] * terms[1].lo
            hi = w[:, 0] * terms[0].hi + w[:, 1] * terms[1].hi
            orig(self, name, [Term.of("G", 0.0, 1.0)], (hi - lo)[:, None], lo)
        else:
            orig(self, name, terms, weights, offset)

    ColumnPrior.__init__ = flat_init
    try:
        llw = wrong(np.column_stack([V.ravel(), S.ravel()]))
    finally:
        ColumnPrior.__init__ = orig
    logz_w = np.log(np.sum(W.ravel() * np.exp(llw - llw.max()))) + llw.max()
    assert abs(logz_w - brute) > 6 * se + 0.1, (logz_w, brute, se)


@pytest.mark.parametrize("noise", ["iid", "weighted", "ar1"])
def test_collapsed_matches_monte_carlo_for_each_gaussian_noise(noise):
    ds = _data(sd=0.02)
    lik = make_likelihood(MODEL, ds, noise=noise, fix={"EOPT": 0.15, "T2": 9.3, "THETA": 59.0, "GM": 0.009},
                          prior={"P1": (0.08, 0.2), "T1": (0.5, 3.0), "GF": (0.005, 0.02)})
    cl = CollapsedLikelihood(lik, BaseStructure(MODEL))
    noise_row = {"iid": [0.02], "weighted": [0.4], "ar1": [0.02, 0.5]}[noise]
    phi = np.array([[0.85] + noise_row])
    v, _ = cl.log_likelihood(phi)
    rng = np.random.default_rng(9)
    m = 300_000
    rows = np.empty((m, lik.d))
    for j, n in enumerate(cl.names):
        rows[:, lik.index(n)] = phi[0, j]
    for p in ("P1", "T1", "GF"):
        lo, hi = lik.bounds[lik.index(p)]
        rows[:, lik.index(p)] = rng.uniform(lo, hi, m)
    ll = lik(rows)
    w = np.exp(ll - ll.max())
    mc, se = np.log(w.mean()) + ll.max(), w.std() / w.mean() / np.sqrt(m)
    assert abs(v[0] - mc) < 4 * se + 1e-4


def test_completion_draws_full_rows_consistent_with_the_likelihood():
    lik = _small_box_lik()
    cl = CollapsedLikelihood(lik, BaseStructure(MODEL))
    phi = np.tile([0.9, 0.02], (3000, 1))
    full = cl.complete(phi, np.random.default_rng(10))
    assert full.shape == (3000, lik.d)
    assert np.all(lik.in_box(full))
    np.testing.assert_allclose(full[:, lik.index("VOLF")], 0.9)
    # the mean of the identified amplitude G against the full likelihood's importance average
    rng = np.random.default_rng(11)
    m = 200_000
    rows = np.tile(full[0], (m, 1))
    for p in ("P1", "T1", "GF", "GM"):
        lo, hi = lik.bounds[lik.index(p)]
        rows[:, lik.index(p)] = rng.uniform(lo, hi, m)
    w = np.exp(lik(rows) - lik(rows).max())
    G = lambda r: 0.9 * r[:, lik.index("GF")] + 0.1 * r[:, lik.index("GM")]  # noqa: E731
    ref = np.sum(w * G(rows)) / w.sum()
    sd = np.sqrt(np.sum(w * (G(rows) - ref) ** 2) / w.sum())
    assert abs(G(full).mean() - ref) < 4 * sd / np.sqrt(3000) + 4 * sd / np.sqrt(w.sum() ** 2 / (w * w).sum())


def test_tier_is_refused_with_the_reason():
    ds = _data()
    lik = make_likelihood(MODEL, ds, noise="proportional")
    assert "not Gaussian" in collapse_reason(lik, BaseStructure(MODEL))
    with pytest.raises(CollapseError, match="proportional"):
        CollapsedLikelihood(lik, BaseStructure(MODEL))
    assert "no linear structure" in collapse_reason(make_likelihood(MODEL, ds), None)
    # VOLF allowed to reach 1: the ECM phase's weight vanishes, the induced prior is not derived
    lik1 = make_likelihood(MODEL, ds, prior={"VOLF": (0.5, 1.0)})
    with pytest.raises(CollapseError, match="must stay > 0"):
        CollapsedLikelihood(lik1, BaseStructure(MODEL))


def test_sampling_phi_only_reaches_the_brute_force_evidence():
    """TMCMC over (VOLF, sigma) on the collapsed likelihood + importance finish: log Z against
    the quadrature over φ of the test above's validated collapsed likelihood, and the completed
    posterior has every original parameter inside its box."""
    from hbm.likelihood.collapsed.sampling import sample_collapsed
    lik = _small_box_lik()
    cl = CollapsedLikelihood(lik, BaseStructure(MODEL))
    (v0, v1), (s0, s1) = cl.bounds
    xg, wg = np.polynomial.legendre.leggauss(24)
    V, S = np.meshgrid(v0 + (xg + 1) / 2 * (v1 - v0), s0 + (xg + 1) / 2 * (s1 - s0), indexing="ij")
    ll = cl(np.column_stack([V.ravel(), S.ravel()]))
    truth = np.log(np.sum(np.outer(wg, wg).ravel() / 4 * np.exp(ll - ll.max()))) + ll.max()
    fit = sample_collapsed(cl, 400, seed=3, importance_draws=2000, max_steps=10)
    assert fit.evidence_source == "importance" and fit.importance.accepted
    assert abs(fit.log_evidence - truth) < 4 * fit.log_evidence_se + 0.02
    assert abs(fit.tmcmc.log_evidence - truth) < 4 * fit.tmcmc.log_evidence_se + 0.05
    assert fit.samples.shape == (400, lik.d) and np.all(lik.in_box(fit.samples))
    np.testing.assert_allclose(fit.log_likelihood, lik(fit.samples))
    assert fit.n_evaluations > fit.tmcmc.n_evaluations + 2000
    assert fit.quadrature_error < 1e-2


def test_model_structure_agrees_with_the_readme_basis_and_is_used_by_default():
    from hbm.model.core import Loading
    from hbm.model.linear import structure_of
    s = structure_of(MODEL)
    ref = BaseStructure(MODEL)
    rng = np.random.default_rng(12)
    b = MODEL.bounds
    theta = b[:, 0] + rng.random((5, MODEL.n_params)) * (b[:, 1] - b[:, 0])
    load = Loading(STRAIN)
    order = [s.columns.index(c) for c in s.columns]  # model's columns: G, fibres, collagen
    np.testing.assert_allclose(s.basis(load, theta)[..., order], ref.basis(load, theta), rtol=1e-12, atol=1e-15)
    lik = _small_box_lik()
    phi = np.array([[0.7, 0.02], [0.95, 0.022]])
    np.testing.assert_allclose(CollapsedLikelihood(lik)(phi), CollapsedLikelihood(lik, ref)(phi), rtol=0, atol=1e-9)


def test_tier_choice_auto_full_and_refusals():
    from hbm.likelihood.collapsed import choose_tier
    from hbm.effects import make_effect
    from hbm.errors import SettingError
    ds = _data()
    cl, note = choose_tier(make_likelihood(MODEL, ds), "auto")
    assert cl is not None and note.startswith("collapsed likelihood")
    cl, note = choose_tier(make_likelihood(MODEL, ds), "full")
    assert cl is None and "requested" in note
    damage = MODEL + make_effect("damage")
    cl, note = choose_tier(make_likelihood(damage, ds), "auto")
    assert cl is None and "damage" in note
    with pytest.raises(SettingError, match="not available.*damage"):
        choose_tier(make_likelihood(damage, ds), "collapsed")
    import hbm

    class BlackBox(hbm.Effect):  # a user's effect that declares nothing
        name, stage = "black_box", "elastic"
        parameters = (hbm.Parameter("BB", 0.0, 1.0, "MPa", "a black box", null=0.0),)

        def stress(self, state, p):
            return p["BB"] * state.eps ** 2

    cl, note = choose_tier(make_likelihood(MODEL + BlackBox(), ds), "auto")
    assert cl is None and "black_box" in note and "does not declare" in note
    cl, note = choose_tier(make_likelihood(MODEL, ds, noise="proportional"), "auto")
    assert cl is None and "not Gaussian" in note
    cl, note = choose_tier(make_likelihood(MODEL, ds), "auto", move="manifold")
    assert cl is None and "gradient" in note
    with pytest.raises(SettingError, match="tier must be one of"):
        choose_tier(make_likelihood(MODEL, ds), "fast")


@pytest.mark.parametrize("case", ["loguniform", "fixed_P1"])
def test_loguniform_amplitudes_and_a_fixed_column_match_monte_carlo(case):
    """Log-uniform amplitude priors (outer columns integrated in log A, G a sum of two log-uniform
    terms) and a column whose only parameter is held fixed (moved into the data)."""
    ds = _data(sd=0.01)
    if case == "loguniform":
        prior = {"P1": (0.01, 1.0, "loguniform"), "T1": (0.5, 3.0), "GF": (1e-3, 0.05, "loguniform"),
                 "GM": (1e-3, 0.05, "loguniform")}
        fix = {"EOPT": 0.15, "T2": 9.3, "THETA": 59.0}
    else:
        prior = {"T1": (0.5, 3.0), "GF": (0.005, 0.02), "GM": (0.004, 0.015)}
        fix = {"EOPT": 0.15, "T2": 9.3, "THETA": 59.0, "P1": 0.13}
    lik = make_likelihood(MODEL, ds, fix=fix, prior=prior)
    cl = CollapsedLikelihood(lik)
    phi = np.array([[0.8, 0.01], [0.93, 0.012]])
    v, err = cl.log_likelihood(phi, refine=True)
    assert np.all(err < 2e-2)
    rng = np.random.default_rng(13)
    m = 400_000
    for r in range(2):
        rows = np.empty((m, lik.d))
        rows[:, lik.index("VOLF")], rows[:, lik.index("sigma")] = phi[r]
        for p in cl.amplitude_parameters:
            if p in lik.names:  # working coordinates: uniform in log for loguniform parameters
                lo, hi = lik.bounds[lik.index(p)]
                rows[:, lik.index(p)] = rng.uniform(lo, hi, m)
        ll = lik(rows)
        w = np.exp(ll - ll.max())
        mc, se = np.log(w.mean()) + ll.max(), w.std() / w.mean() / np.sqrt(m)
        assert abs(v[r] - mc) < 4 * se + 3 * err[r] + 1e-3, (r, v[r], mc, se, err[r])
    full = cl.complete(np.tile(phi[0], (200, 1)), np.random.default_rng(14))
    assert np.all(lik.in_box(full))


def _fit(**kw):
    from hbm.fit import fit_specimen
    return fit_specimen(_data(sd=0.004), restarts=0, seed=1, progress=False, fix={"EOPT": 0.15, "THETA": 59.0}, **kw)


def test_fit_specimen_collapsed_default_route(tmp_path):
    """fit_specimen: the default tier is collapsed (pilot + importance), stores every original
    parameter and the tier (config, text, JSON, netCDF attribute)."""
    from hbm.io import read_attrs
    res = _fit(samples=300, out=tmp_path / "c.nc")
    cfg = res.result.config
    assert cfg["likelihood_tier"] == "collapsed" and "integrated exactly" in cfg["likelihood_note"]
    assert cfg["collapsed"]["route"] == "pilot TMCMC + importance finish"
    assert res.result.samples.shape == (300, 7) and res.result.names == list(res.likelihood.names)
    assert np.all(res.likelihood.in_box(res.likelihood.from_natural(res.result.samples)))
    assert read_attrs(tmp_path / "c.nc")["likelihood_tier"] == "collapsed"
    assert "likelihood: collapsed" in res.report() and res.to_json()["likelihood_tier"] == "collapsed"


@pytest.mark.slow
def test_fit_specimen_collapsed_evidence_agrees_with_the_full_tier():
    res, full = _fit(samples=600), _fit(samples=1500, tier="full")
    assert full.result.config["likelihood_tier"] == "full"
    se = np.hypot(res.log_evidence_se, full.log_evidence_se)
    assert abs(res.log_evidence - full.log_evidence) < 4 * se + 0.15
    assert res.result.config["n_evaluations"] < full.result.config["n_evaluations"] / 5


@pytest.mark.parametrize("argv, needle", [
    (["--tier", "collapsed", "--noise", "proportional"], "not Gaussian"),
    (["--tier", "collapsed", "--move", "manifold"], "gradient"),
    (["--tier", "fast"], "--tier"),
    (["--likelihood", "fast"], "--likelihood"),   # the older flag: the same rule
])
def test_cli_refuses_the_collapsed_tier_where_it_does_not_apply(argv, needle, tmp_path, capsys):
    from hbm.cli import main
    out = tmp_path / "x.nc"
    try:
        rc = main(["fit", "data/specimens/calvo2010_rat1.csv", "--no-plot", "--out", str(out), *argv])
    except SystemExit as exc:  # argparse refuses a bad choice itself
        rc = exc.code
    assert rc == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("hbm: error:") and needle in err[0]
    assert not out.exists()


def test_qlv_model_collapsed_matches_monte_carlo():
    """Quasi-linear viscoelasticity filters every amplitude column (G1, LOGTAU1 join φ): the
    collapsed likelihood of the shipped QLV benchmark curve against Monte Carlo at fixed φ."""
    from pathlib import Path

    from hbm.data import load_specimen
    from hbm.effects import make_effect
    curve = Path(__file__).resolve().parents[1] / "results" / "benchmarks" / "qlv_benchmark.csv"
    if not curve.exists():
        pytest.skip("qlv benchmark curve not in this tree")
    model = MODEL + make_effect("viscoelastic")
    ds = load_specimen(curve)
    prior = {"P1": (0.08, 0.2), "T1": (0.5, 3.0), "GF": (0.005, 0.02), "GM": (0.004, 0.015)}
    lik = make_likelihood(model, ds, prior=prior, fix={"EOPT": 0.184, "T2": 9.3, "THETA": 60.0},
                          sigma_bounds=(0.01, 0.05))
    cl = CollapsedLikelihood(lik)
    assert set(cl.names) == {"VOLF", "G1", "LOGTAU1", "sigma"}
    row = {"VOLF": 0.85, "G1": 0.35, "LOGTAU1": 1.3, "sigma": 0.02}
    phi = np.array([[row[n] for n in cl.names]])
    v, err = cl.log_likelihood(phi, refine=True)
    rng = np.random.default_rng(15)
    m = 200_000
    rows = np.empty((m, lik.d))
    for n, x in row.items():
        rows[:, lik.index(n)] = x
    for p in ("P1", "T1", "GF", "GM"):
        lo, hi = lik.bounds[lik.index(p)]
        rows[:, lik.index(p)] = rng.uniform(lo, hi, m)
    ll = lik(rows)
    w = np.exp(ll - ll.max())
    mc, se = np.log(w.mean()) + ll.max(), w.std() / w.mean() / np.sqrt(m)
    assert abs(v[0] - mc) < 4 * se + 3 * err[0] + 1e-3, (v[0], mc, se, err[0])


def _interior_problem(n=5, seed=11):
    """Two trapezoid columns with their Gaussians on the rising ramps (both sloped) and one uniform."""
    rng = np.random.default_rng(seed)
    c = rng.uniform(0.6, 0.8, n)
    pri = [ColumnPrior("G", [Term.of("GF", 1e-4, 0.1), Term.of("GM", 1e-4, 0.1)], np.column_stack([c, 1 - c])),
           ColumnPrior("G2", [Term.of("GF2", 1e-4, 0.1), Term.of("GM2", 1e-4, 0.1)], np.column_stack([1 - c, c])),
           ColumnPrior("AF", [Term.of("P1", 1e-4, 0.5)], c[:, None])]
    mode = np.column_stack([np.full(n, 0.012), np.full(n, 0.013), np.full(n, 0.2)])
    sd = np.array([0.001, 0.0012, 0.01])
    corr = np.array([[1.0, 0.6, -0.3], [0.6, 1.0, 0.2], [-0.3, 0.2, 1.0]])
    cov = corr * np.outer(sd, sd)
    H = np.broadcast_to(np.linalg.inv(cov), (n, 3, 3)).copy()
    b = np.einsum("nij,nj->ni", H, mode)
    yy = np.einsum("ni,ni->n", b, mode) + rng.uniform(10.0, 50.0, n)
    return H, b, yy, pri


def test_interior_rows_are_exact_and_agree_with_the_quadrature():
    """Deep inside one linear piece of every column the integral is E[Π p_j] of a Gaussian (Isserlis'
    pair term for two sloped columns); the quadrature is the independent check."""
    H, b, yy, pri = _interior_problem()
    box = BoxGaussianIntegral(H, b, yy, pri)
    inside, exact = box.interior()
    assert inside.all()
    quad = box._value(12)  # the quadrature alone, finer than the default
    np.testing.assert_allclose(exact, quad, atol=2e-6)
    # without the pair term the two sloped columns would be off by the covariance term
    dens = np.column_stack([p.pdf(np.full((len(yy), 1), m))[:, 0] for p, m in zip(box.priors, (0.012, 0.013, 0.2))])
    assert np.all(np.abs(np.log(np.prod(dens, axis=1)) - (exact + 0.5 * box.const - 1.5 * np.log(2 * np.pi)
                                                          + 0.5 * np.log(box.h).sum(axis=1))) > 1e-4)
    # a row pushed against its box edge is left to the quadrature
    b2 = b.copy()
    b2[0] = np.einsum("ij,j->i", H[0], [0.012, 0.013, 0.0005])
    inside2, _ = BoxGaussianIntegral(H, b2, yy, pri).interior()
    assert not inside2[0] and inside2[1:].all()


def _numpy_closed_form(self, mu):
    """The innermost closed form written with numpy arrays (the compiled kernel's independent check;
    ``self`` is the BoxGaussianIntegral)."""
    pr = self.priors[0]
    h = self.h[:, 0][:, None]
    flat = (h == 0.0)[..., None]
    s = (1.0 / np.sqrt(np.where(h == 0.0, 1.0, h)))[..., None]
    kn = pr.knots[:, None, :]
    pv = pr.knot_values[:, None, :]
    z = (kn - mu[..., None]) / s  # (n, M, K)
    u = ndtr(-np.abs(z))  # tail probability beyond |z|
    e = np.exp(-0.5 * z * z)
    z0, z1, u0, u1, e0, e1 = z[..., :-1], z[..., 1:], u[..., :-1], u[..., 1:], e[..., :-1], e[..., 1:]
    dphi = np.where(z0 >= 0, u0 - u1, np.where(z1 <= 0, u1 - u0, 1.0 - u0 - u1))
    width = kn[..., 1:] - kn[..., :-1]
    slope = np.where(width > 0, (pv[..., 1:] - pv[..., :-1]) / np.where(width > 0, width, 1.0), 0.0)
    with np.errstate(divide="ignore", invalid="ignore"):
        mz = (e0 - e1) / (np.sqrt(2.0 * np.pi) * dphi)
    mz = np.where(dphi > 0, np.clip(mz, z0, z1), 0.5 * (z0 + z1))
    pm = pv[..., :-1] + slope * s * (mz - z0)  # density at the truncated mean (linear piece)
    total = (np.sqrt(2.0 * np.pi) * s[..., 0] * np.sum(np.maximum(dphi, 0.0) * np.maximum(pm, 0.0), axis=-1))
    flat_total = np.sum(width * 0.5 * (pv[..., 1:] + pv[..., :-1]), axis=-1) + 0.0 * mu
    total = np.where(flat[..., 0], flat_total, total)
    with np.errstate(divide="ignore"):
        out = np.log(total)
    bad = ~(total > 1e-250)
    if bad.any():
        rows, cols = np.nonzero(bad)
        sub = self._take(rows)
        out[rows, cols] = sub._closed_form_log(mu[rows, cols][:, None])[:, 0]
    return out


def test_compiled_closed_form_equals_the_numpy_form():
    """The numba kernel of the innermost column against its numpy form, including far tails (log path)."""
    X, y = _problem(0)
    c = np.array([0.6, 0.8, 0.95])
    pG = ColumnPrior("G", [Term.of("GF", 1e-4, 0.1), Term.of("GM", 1e-4, 0.1)], np.column_stack([c, 1 - c]))
    pP = ColumnPrior("AF", [Term.of("P1", 1e-4, 0.5)], c[:, None])
    box = BoxGaussianIntegral(*_hby(X, y), [pG, pP])
    mu = np.random.default_rng(3).normal(0.05, 0.2, (3, 400))
    mu[:, :5] = [-50.0, 50.0, 0.0, 1e-4, 0.1]
    fast, ref = box._closed_form(mu), _numpy_closed_form(box, mu)
    assert np.all(np.isfinite(fast))
    np.testing.assert_allclose(fast, ref, rtol=1e-12, atol=1e-12)


def _kinked_problem(edge_sd=(30.0, 30.0, 30.0, 4.5)):
    """A trapezoid column whose Gaussian straddles its first kink, two uniforms inside their boxes
    (``edge_sd``: the first uniform's mode, in its marginal sd, above its lower edge, per row)."""
    n = len(edge_sd)
    c = np.linspace(0.65, 0.75, n)
    pri = [ColumnPrior("G", [Term.of("GF", 1e-4, 0.1), Term.of("GM", 1e-4, 0.1)], np.column_stack([c, 1 - c])),
           ColumnPrior("AF", [Term.of("P1", 1e-4, 0.5)], c[:, None]),
           ColumnPrior("AM", [Term.of("T1", 0.0, 3.0)], (1 - c)[:, None])]
    sd = np.array([0.004, 0.004, 0.02])
    corr = np.array([[1.0, -0.7, 0.4], [-0.7, 1.0, -0.2], [0.4, -0.2, 1.0]])
    cov = corr * np.outer(sd, sd)
    kink = pri[0].knots[:, 1]
    mode = np.column_stack([kink + 0.3 * sd[0], 1e-4 * c + np.asarray(edge_sd) * sd[1], np.full(n, 0.5)])
    H = np.broadcast_to(np.linalg.inv(cov), (n, 3, 3)).copy()
    b = np.einsum("nij,nj->ni", H, mode)
    yy = np.einsum("ni,ni->n", b, mode) + 20.0
    return H, b, yy, pri


def test_one_kinked_column_is_closed_form_and_its_error_bound_holds():
    """All columns but one constant on the mass: log I = the 1-D closed form of the kinked column's
    marginal (no margin needed there); the neglected edge mass of the others is bounded per row.
    The fine quadrature is the independent check."""
    H, b, yy, pri = _kinked_problem()
    box = BoxGaussianIntegral(H, b, yy, pri)
    inside, exact, bound, kink = box._interior()
    # rows 0–2 by the second rule (the G column across its kink), row 3 (4.5 sd from an edge) refused
    assert inside.tolist() == [True, True, True, False] and np.all(kink == 0)
    # the reference quadrature with a wider window (the default 5 sd window truncates ~7e-7 here)
    quad = BoxGaussianIntegral(H, b, yy, pri, width=9.0)._value(24)
    np.testing.assert_allclose(exact, quad[:3], atol=1e-9)
    assert np.all(bound < 1e-12)
    # accepted with a looser tolerance, row 3's real error (its edge mass) stays within its bound
    inside, exact, bound, _ = box._interior(tol=1e-3)
    assert inside.all()
    err = abs(exact[3] - quad[3])
    assert 1e-7 < err <= bound[3] < 1e-4, (err, bound[3])
    # and the default log_integral uses the quadrature for it
    v, e = box.log_integral(refine=True)
    assert v[3] == box._take([3])._value(box.nodes)[0] and np.all(e[:3] < 1e-12)


def test_draws_of_the_closed_form_rows_have_the_exact_moments():
    """Draws for a one-kinked-column row: the kinked column against its exact 1-D density on a fine
    grid, the others through the exact Gaussian conditional moments."""
    H, b, yy, pri = _kinked_problem((30.0,))
    m = 40000
    rep = [ColumnPrior(p.name, p.terms, np.repeat(p.weights, m, 0)) for p in pri]
    A = BoxGaussianIntegral(np.repeat(H, m, 0), np.repeat(b, m, 0), np.repeat(yy, m), rep).draw(np.random.default_rng(7))
    cov = np.linalg.inv(H[0])
    mode = np.linalg.solve(H[0], b[0])
    x = np.linspace(pri[0].lo[0], pri[0].hi[0], 200001)
    w = pri[0].pdf(x[None, :])[0] * np.exp(-0.5 * (x - mode[0]) ** 2 / cov[0, 0])
    w /= w.sum()
    mg = (w * x).sum()
    vg = (w * (x - mg) ** 2).sum()
    assert abs(mg - mode[0]) > 8 * np.sqrt(vg / m)  # the kink moves the mean: a plain Gaussian would fail
    for j in range(3):
        beta = cov[j, 0] / cov[0, 0]
        mean = mode[j] + beta * (mg - mode[0])
        var = vg if j == 0 else cov[j, j] - beta * cov[0, j] + beta ** 2 * vg
        assert abs(A[:, j].mean() - mean) < 4 * np.sqrt(var / m)
        assert A[:, j].std() == pytest.approx(np.sqrt(var), rel=4 * np.sqrt(0.5 / m) + 1e-3)
