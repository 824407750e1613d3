"""Effect library: null values, closed forms, qualitative signatures, composition, user effects."""

from __future__ import annotations

import inspect

import numpy as np
import pytest
from scipy.integrate import quad
from scipy.optimize import brentq

import hbm
from hbm.data import cycle, hold, protocol, ramp, specimen_loading
from hbm.effects import (
    CONFUSABLE_GROUPS, REGISTRY, SEPARATING_EXPERIMENT, group_of, load_effect, make_effect, resolve_effect)
from hbm.errors import HbmError
from hbm.model.core import Effect, Loading, Model, Parameter

BASE = hbm.spyrou_model()
THETA = np.array([0.9, 0.15, 0.06, 1.0, 14.0, 58.0, 0.03, 0.02])  # VOLF EOPT P1 T1 T2 THETA GF GM
IDS = ["offset", "prestress", "slack", "fiber_exponential", "recruitment", "dispersion", "series_compliance",
       "viscoelastic", "damage", "viscoelastic_2", "viscoelastic_3"]


def coll(lam, theta_deg, t2):
    """Independent scalar collagen kernel exp(T2<λH−1>+) − 1."""
    t = np.deg2rad(theta_deg)
    lh = np.sqrt(np.cos(t) ** 2 * lam ** 2 + np.sin(t) ** 2 / lam)
    return np.expm1(t2 * max(lh - 1.0, 0.0))


def multi_protocol():
    return specimen_loading(protocol(ramp(0.45, 1e-3, 20), [ramp(0.3, 1e-2, 10), hold(300.0, 8)],
                                     cycle(0.4, 5e-3, 8, eps_min=0.1, reload_to=0.45)))


def with_effect(effect_id, value, theta=THETA, **kw):
    model = BASE + make_effect(effect_id, **kw)
    th = model.null_theta(theta)
    th[model.index(model.effects[-1].strength)] = value
    return model, th


# ------------------------------------------------------------------------------------ registry
def test_registry_ids_docs_and_nulls():
    assert list(REGISTRY) == IDS
    for eid, cls in REGISTRY.items():
        e = cls()
        assert e.name == eid and isinstance(e, Effect)
        doc = inspect.getdoc(cls)
        assert "Parameters" in doc and "null" in doc and any(ch.isdigit() for ch in e.reference)
        assert all(q.null is not None and q.lower <= q.null <= q.upper for q in e.parameters)
        assert e.strength in {q.name for q in e.parameters}
        names = BASE.parameter_names
        assert not set(q.name for q in e.parameters) & set(names)  # new parameters only
    flat = [x for g in CONFUSABLE_GROUPS for x in g]
    assert set(flat) <= set(REGISTRY) and len(flat) == len(set(flat))
    assert all(len(SEPARATING_EXPERIMENT[g]) > 50 for g in CONFUSABLE_GROUPS)
    assert group_of("slack") == frozenset({"slack", "fiber_exponential"})
    assert group_of("offset") is None
    with pytest.raises(HbmError, match="unknown effect 'nope'"):
        make_effect("nope")


@pytest.mark.parametrize("eid", IDS)
def test_null_reproduces_base_exactly(eid):
    loading = multi_protocol()
    rng = np.random.default_rng(1)
    lo, hi = BASE.bounds.T
    theta = lo + rng.random((50, BASE.n_params)) * (hi - lo)
    model = BASE + make_effect(eid)
    assert model.parameter_names[:8] == BASE.parameter_names
    s0 = BASE.stress(loading, theta)
    s1 = model.stress(loading, model.null_theta(theta))
    np.testing.assert_array_equal(s1, s0)
    # compression and large strains too (slack and series compliance touch the kinematics)
    eps = np.linspace(-0.4, 1.0, 31)
    np.testing.assert_array_equal(model.stress(Loading(eps, np.arange(31.0)), model.null_theta(theta)),
                                  BASE.stress(eps, theta))


@pytest.mark.parametrize("eid", IDS)
def test_finite_over_the_box(eid):
    model = BASE + make_effect(eid)
    rng = np.random.default_rng(2)
    lo, hi = model.bounds.T
    theta = lo + rng.random((400, model.n_params)) * (hi - lo)
    theta[:4] = np.where(np.arange(model.n_params) % 2, hi, lo)  # corners
    s = model.stress(multi_protocol(), theta)
    assert s.shape == (400, multi_protocol().n_points) and np.all(np.isfinite(s))


def test_composition_adds_parameters():
    model = BASE + make_effect("offset") + make_effect("viscoelastic")
    assert model.parameter_names == BASE.parameter_names + ("S0", "G1", "LOGTAU1")
    assert model.bounds.shape == (11, 2)
    assert model.effect_names[-2:] == ("offset", "viscoelastic")
    two = BASE + make_effect("viscoelastic", terms=2)
    assert two.parameter_names[8:] == ("G1", "LOGTAU1", "G2", "LOGTAU2")
    fixed = BASE + make_effect("viscoelastic", tau=50.0)
    assert fixed.parameter_names[8:] == ("G1",)
    assert resolve_effect("damage").name == "damage"


# ------------------------------------------------------------------------------------ offset, slack
def test_offset_shifts_everywhere_and_shows_at_zero_strain():
    model, th = with_effect("offset", 0.004)
    eps = np.linspace(0, 0.45, 12)
    s = model.stress(eps, th)
    np.testing.assert_allclose(s - BASE.stress(eps, THETA), 0.004, rtol=0, atol=1e-15)
    assert s[0] == pytest.approx(0.004)


def test_slack_is_stress_free_then_shifted_right():
    s_slack = 0.05
    model, th = with_effect("slack", s_slack)
    eps = np.linspace(0, 0.45, 46)
    s = model.stress(eps, th)
    assert np.all(s[eps <= s_slack] == 0.0)
    tissue = (1 + eps) / (1 + s_slack) - 1
    expected = np.where(eps > s_slack, BASE.stress(np.maximum(tissue, 0), THETA), 0.0)
    np.testing.assert_allclose(s, expected, rtol=1e-14, atol=1e-16)
    base = BASE.stress(eps, THETA)
    assert np.all(s[1:] < base[1:])  # curve moves to the right
    # the strain at which 0.05 MPa is reached moves right by about the slack
    e_base, e_slack = (np.interp(0.05, c, eps) for c in (base, s))
    assert e_slack - e_base == pytest.approx(s_slack * (1 + e_base), rel=0.05)


# ------------------------------------------------------------------------------------ fiber_exponential
def test_fiber_exponential_closed_form_and_jacobian():
    model, th = with_effect("fiber_exponential", 0.01)
    th[model.index("FEXP_B")] = 12.0
    eps = np.array([0.1, 0.15, 0.2, 0.3, 0.42])
    x = np.maximum(eps - 0.15, 0)
    expected = BASE.stress(eps, THETA) + (1 + eps) * 0.9 * 0.01 * (np.exp(12 * x) - 1 - 12 * x)
    np.testing.assert_allclose(model.stress(eps, th), expected, rtol=1e-13)
    assert model.has_analytic_jacobian
    eps = np.array([0.05, 0.12, 0.2, 0.33, 0.44])  # away from the kinks
    jac = model.stress_jacobian(eps, th)
    h = 1e-6 * np.diff(model.bounds).ravel()
    fd = np.stack([(model.stress(eps, th + np.eye(10)[k] * h[k]) - model.stress(eps, th - np.eye(10)[k] * h[k]))
                   / (2 * h[k]) for k in range(10)], axis=-1)
    np.testing.assert_allclose(jac, fd, rtol=1e-5, atol=1e-9)


# ------------------------------------------------------------------------------------ recruitment, dispersion
@pytest.mark.parametrize("t2, theta, w", [(14.0, 58.0, 0.01), (150.0, 59.8, 0.005), (1e-9, 60.0, 0.02), (40.0, 56.0, 0.02)])
def test_recruitment_matches_quadrature(t2, theta, w):
    th0 = THETA.copy()
    th0[4], th0[5] = t2, theta
    model, th = with_effect("recruitment", w, theta=th0)
    eps = np.array([0.0, 0.1, 0.2, 0.3, 0.32, 0.35, 0.4, 0.45, 0.8])
    s = model.stress(eps, th)
    base = BASE.stress(eps, th0)
    for i, e in enumerate(eps):
        lam = 1 + e
        tt = np.deg2rad(theta)
        xx = max(np.sqrt(np.cos(tt) ** 2 * lam ** 2 + np.sin(tt) ** 2 / lam) - 1, 0)
        avg = quad(lambda u: np.expm1(t2 * max(xx - u, 0)), 0, w, points=[min(xx, w)], epsabs=1e-15)[0] / w
        corr = lam * 0.1 * 1.0 * (avg - coll(lam, theta, t2))
        assert s[i] - base[i] == pytest.approx(corr, rel=1e-7, abs=1e-14)
    assert np.all(s <= base + 1e-15)  # later recruitment -> less collagen stress


def test_recruitment_smooths_the_onset():
    model, th = with_effect("recruitment", 0.01)
    eps = np.linspace(0.0, 0.45, 2001)
    window = (eps[1:-1] > 0.16) & (eps[1:-1] < 0.25)  # around the onset (0.176 at 58°), past EOPT
    spike = lambda s: np.max(np.abs(np.diff(s, 2))[window])  # noqa: E731 - largest curvature spike
    assert spike(model.stress(eps, th)) < 0.05 * spike(BASE.stress(eps, THETA))


@pytest.mark.parametrize("t2, theta, d", [(14.0, 58.0, 6.0), (100.0, 57.0, 10.0), (200.0, 60.0, 15.0), (5.0, 60.0, 1.0)])
def test_dispersion_matches_quadrature(t2, theta, d):
    th0 = THETA.copy()
    th0[4], th0[5] = t2, theta
    model, th = with_effect("dispersion", d, theta=th0)
    eps = np.linspace(-0.3, 0.6, 19)
    s = model.stress(eps, th)
    base = BASE.stress(eps, th0)
    ref = np.array([base[i] + (1 + e) * 0.1 * (quad(lambda ph: coll(1 + e, theta + ph, t2), -d, d, limit=200,
                                                    epsabs=1e-14, epsrel=1e-12)[0] / (2 * d) - coll(1 + e, theta, t2))
                    for i, e in enumerate(eps)])
    np.testing.assert_allclose(s - base, ref - base, rtol=1e-3, atol=1e-12)
    # dispersion engages collagen earlier: stress rises before the sharp onset
    onset = hbm.model.collagen_onset_stretch(theta) - 1
    if theta - d < theta and onset > 0.05:
        pre = (eps > onset - 0.05) & (eps < onset)
        assert np.all((s - base)[pre] > 0)


# ------------------------------------------------------------------------------------ series compliance
def test_series_compliance_solves_the_series_equation():
    c = 0.5
    model, th = with_effect("series_compliance", c)
    eps = np.linspace(0, 0.45, 25)
    s = model.stress(eps, th)
    for e, si in zip(eps, s):
        et = brentq(lambda x: x + c * BASE.stress(np.array([x]), THETA)[0] - e, -1e-3, e + 1e-12, xtol=1e-15)
        assert si == pytest.approx(BASE.stress(np.array([et]), THETA)[0], rel=1e-9, abs=1e-14)
    base = BASE.stress(eps, THETA)
    assert np.all(s[1:] < base[1:])
    # the strain lost to the series element grows with the stress: ε_a − ε_t = C·σ
    fine = np.linspace(0, 0.45, 200001)
    lost = eps - np.interp(s, BASE.stress(fine, THETA), fine)
    np.testing.assert_allclose(lost[1:], c * s[1:], rtol=1e-3, atol=1e-7)


def test_series_compliance_population():
    model = BASE + make_effect("series_compliance")
    rng = np.random.default_rng(4)
    lo, hi = model.bounds.T
    theta = lo + rng.random((300, model.n_params)) * (hi - lo)
    eps = np.linspace(0, 0.45, 30)
    s = model.stress(eps, theta)
    # the implied tissue strain satisfies ε_t + C σ(ε_t) = ε_a for every sample and point
    from hbm.effects.series_compliance import solve_series
    p = model._params(theta)
    elastic = model._elastic(p, Loading(eps))
    et = solve_series(np.broadcast_to(eps, s.shape), p["C_S"], elastic)
    np.testing.assert_allclose(et + p["C_S"] * elastic(et), np.broadcast_to(eps, s.shape), atol=1e-10)
    np.testing.assert_allclose(s, elastic(et), rtol=1e-12, atol=1e-15)


# ------------------------------------------------------------------------------------ viscoelastic
class LinearElastic(Effect):
    name = "linear"
    stage = "elastic"
    parameters = (Parameter("E", 0.0, 10.0, "MPa", "modulus"),)

    def stress(self, state, p):
        return p["E"] * state.eps


def test_viscoelastic_matches_qlv_closed_form_for_linear_elastic():
    g1, tau, E, rate = 0.4, 20.0, 2.0, 1e-2
    model = Model([LinearElastic(), make_effect("viscoelastic")])
    th = np.array([E, g1, np.log10(tau)])
    prot = protocol([ramp(0.3, rate, 31), hold(100.0, 21)], ramp(0.3, 10 * rate, 31))
    loading = specimen_loading(prot)
    s = model.stress(loading, th)
    t = loading.time
    n1 = 31 + 21
    # ramp: σ = E r [g∞ t + g1 τ (1 − e^{−t/τ})]
    tr = t[:31]
    np.testing.assert_allclose(s[:31], E * rate * ((1 - g1) * tr + g1 * tau * (1 - np.exp(-tr / tau))), rtol=1e-12)
    # hold after the ramp ending at t1 = 30 s: σ = E r [g∞ t1 + g1 τ (e^{−(t−t1)/τ} − e^{−t/τ})]
    t1, th_ = 30.0, t[31:n1]
    np.testing.assert_allclose(s[31:n1], E * rate * ((1 - g1) * t1 + g1 * tau * (np.exp(-(th_ - t1) / tau)
                                                                                   - np.exp(-th_ / tau))), rtol=1e-12)
    # relaxation toward g∞ σ_e with time constant τ
    excess = s[30:n1] - (1 - g1) * E * 0.3
    np.testing.assert_allclose(excess / excess[0], np.exp(-(t[30:n1] - t1) / tau), rtol=1e-10)
    # second history (10x faster, from rest at t = 0) is independent of the first
    tf = t[n1:]
    np.testing.assert_allclose(s[n1:], E * 10 * rate * ((1 - g1) * tf + g1 * tau * (1 - np.exp(-tf / tau))), rtol=1e-12)


def test_viscoelastic_rate_dependence_and_relaxation_on_muscle_model():
    model, th = with_effect("viscoelastic", 0.5)
    th[model.index("LOGTAU1")] = np.log10(30.0)
    prot = protocol(ramp(0.42, 1e-3, 40), ramp(0.42, 1e-2, 40), ramp(0.42, 1e-1, 40),
                    [ramp(0.42, 1e-2, 40), hold(300.0, 30)])
    loading = specimen_loading(prot)
    s = model.stress(loading, th)
    elastic = BASE.stress(loading, THETA)
    peaks = [s[40 * k + 39] for k in range(3)]
    assert peaks[0] < peaks[1] < peaks[2] < elastic[39]  # faster ramp -> higher stress, below elastic
    assert np.all(s[:120] <= elastic[:120] + 1e-15)
    h = s[160:]  # the hold: monotone decay toward g∞ σ_e
    assert np.all(np.diff(h) < 0)
    assert h[-1] == pytest.approx(0.5 * elastic[-1], rel=1e-3)  # 300 s = 10 τ
    # a finer sampling of the same protocol gives nearly the same stress (recursion is consistent)
    fine = specimen_loading(protocol(ramp(0.42, 1e-2, 400)))
    sf = model.stress(fine, th)
    assert sf[-1] == pytest.approx(s[79], rel=2e-3)


def test_viscoelastic_needs_time():
    model, th = with_effect("viscoelastic", 0.3)
    with pytest.raises(HbmError, match="needs a 'time' column"):
        model.stress(np.linspace(0, 0.4, 10), th)
    with pytest.raises(HbmError):
        make_effect("viscoelastic", terms=3)


def test_viscoelastic_two_terms_and_fixed_tau():
    g, taus, E, rate = (0.3, 0.2), (5.0, 80.0), 1.5, 2e-3
    loading = specimen_loading(protocol(ramp(0.3, rate, 41)))
    t = loading.time
    expected = E * rate * ((1 - sum(g)) * t + sum(gi * ti * (1 - np.exp(-t / ti)) for gi, ti in zip(g, taus)))
    m2 = Model([LinearElastic(), make_effect("viscoelastic", terms=2)])
    s2 = m2.stress(loading, np.array([E, g[0], np.log10(taus[0]), g[1], np.log10(taus[1])]))
    np.testing.assert_allclose(s2, expected, rtol=1e-12)
    mf = Model([LinearElastic(), make_effect("viscoelastic", terms=2, tau=list(taus))])
    np.testing.assert_allclose(mf.stress(loading, np.array([E, *g])), expected, rtol=1e-12)


# ------------------------------------------------------------------------------------ damage
def test_damage_load_unload_reload():
    d = 0.5
    model, th = with_effect("damage", d)
    n = 15
    prot = protocol(cycle(0.35, 1e-2, n, eps_min=0.1, reload_to=0.45))
    loading = specimen_loading(prot)
    s = model.stress(loading, th)
    se = BASE.stress(loading, THETA)
    eps = loading.strain
    load, unload, reload = slice(0, n), slice(n, 2 * n), slice(2 * n, 3 * n)
    np.testing.assert_array_equal(s[load], se[load])  # virgin curve untouched
    smax = se[n - 1]
    np.testing.assert_allclose(s[unload], se[unload] * (1 - d * (1 - se[unload] / smax)), rtol=1e-14)
    assert np.all(s[unload][:-1] < se[unload][:-1])  # unloading below loading
    below = reload.start + np.flatnonzero(eps[reload] <= 0.35)
    above = reload.start + np.flatnonzero(eps[reload] > 0.35 + 1e-12)
    # reload follows the unloading path (same stress at the same strain) until the previous max
    np.testing.assert_allclose(s[below], np.interp(eps[below], eps[unload][::-1], s[unload][::-1]), rtol=0.05)
    np.testing.assert_allclose(s[below], se[below] * (1 - d * (1 - se[below] / smax)), rtol=1e-14)
    # beyond the previous maximum: back on the primary curve
    np.testing.assert_array_equal(s[above], se[above])


def test_damage_resets_per_history():
    model, th = with_effect("damage", 0.6)
    prot = protocol(cycle(0.4, 1e-2, 8, eps_min=0.0), ramp(0.3, 1e-2, 8))
    loading = specimen_loading(prot)
    s = model.stress(loading, th)
    np.testing.assert_array_equal(s[-8:], BASE.stress(loading, THETA)[-8:])  # new history from rest: virgin


# ------------------------------------------------------------------------------------ user effects
USER = '''
import numpy as np
import hbm


class Bump(hbm.Effect):
    """A Gaussian bump in strain (test effect)."""
    name = "bump"
    stage = "elastic"
    parameters = (hbm.Parameter("BUMP_A", 0.0, 0.05, "MPa", "bump height", null=0.0),)

    def stress(self, state, p):
        return p["BUMP_A"] * np.exp(-0.5 * ((state.eps - 0.2) / 0.03) ** 2)


class NotAnEffect:
    pass
'''


def test_load_effect_from_user_file(tmp_path):
    f = tmp_path / "my_effects.py"
    f.write_text(USER)
    effect = load_effect(f"{f}:Bump")
    assert effect.name == "bump"
    model = BASE + effect
    assert model.parameter_names[-1] == "BUMP_A"
    eps = np.linspace(0, 0.4, 9)
    th = np.append(THETA, 0.01)
    np.testing.assert_allclose(model.stress(eps, th) - BASE.stress(eps, THETA),
                               0.01 * np.exp(-0.5 * ((eps - 0.2) / 0.03) ** 2), rtol=1e-12, atol=1e-16)
    assert resolve_effect(f"{f}:Bump").name == "bump"


def test_load_effect_errors(tmp_path):
    f = tmp_path / "my_effects.py"
    f.write_text(USER)
    with pytest.raises(HbmError, match="not found"):
        load_effect(f"{tmp_path / 'missing.py'}:Bump")
    with pytest.raises(HbmError, match="has no class 'Nope'"):
        load_effect(f"{f}:Nope")
    with pytest.raises(HbmError, match="not a subclass of hbm.Effect"):
        load_effect(f"{f}:NotAnEffect")
    with pytest.raises(HbmError, match="expected 'path/to/file.py:ClassName'"):
        load_effect(str(f))
    broken = tmp_path / "broken.py"
    broken.write_text("raise RuntimeError('boom')\n")
    with pytest.raises(HbmError, match="import failed: RuntimeError: boom"):
        load_effect(f"{broken}:X")
