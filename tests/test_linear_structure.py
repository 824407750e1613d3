"""The linear structure of models (hbm.model.linear): stress = X(φ)·A(θ)."""

from __future__ import annotations

import numpy as np
import pytest

import hbm
from hbm.effects import REGISTRY, make_effect
from hbm.errors import HbmError
from hbm.model.core import Loading
from hbm.model.linear import structure_of, why_not_linear
from hbm.model.spyrou import identifiable_combinations

EPS = np.concatenate([np.linspace(-0.05, 0.45, 30), np.linspace(0.45, 0.2, 10)])
TIME = np.linspace(0.0, 120.0, EPS.size)
LOADING = Loading(EPS, TIME)


def _random_theta(model, n, seed=0):
    b = model.bounds
    return np.random.default_rng(seed).uniform(b[:, 0], b[:, 1], (n, model.n_params))


def _readme_columns(theta, names, k_iso=1.0):
    """The three unit-amplitude columns written out from the README's formulas (thesis form)."""
    col = {n: theta[..., i, None] for i, n in enumerate(names)}
    lam = 1.0 + EPS
    th = np.deg2rad(col["THETA"])
    lh = np.sqrt(np.cos(th) ** 2 * lam ** 2 + np.sin(th) ** 2 / lam)
    matrix = k_iso * (lam ** 2 - 1.0 / lam) + 0.0 * col["VOLF"]
    fibres = lam * np.maximum(EPS - col["EOPT"], 0.0)
    collagen = np.where(lh > 1.0, lam * np.expm1(col["T2"] * (lh - 1.0)), 0.0)
    return np.stack(np.broadcast_arrays(matrix, fibres, collagen), axis=-1)


@pytest.mark.parametrize("k_iso", [1.0, 2.0 / 3.0])
def test_base_columns_match_the_formulas(k_iso):
    model = hbm.spyrou_model(iso_factor=k_iso)
    s = structure_of(model)
    assert s.columns == ("G", "VOLF*P1", "(1-VOLF)*T1")
    assert set(s.amplitude_parameters) == {"GF", "GM", "P1", "T1"}
    assert s.nonlinear_parameters == ("VOLF", "EOPT", "T2", "THETA")
    theta = _random_theta(model, 16)
    np.testing.assert_allclose(s.basis(LOADING, theta), _readme_columns(theta, model.parameter_names, k_iso),
                               rtol=1e-12, atol=1e-15)
    comb = identifiable_combinations(model.parameter_names, theta)
    np.testing.assert_allclose(s.amplitudes(theta), np.stack([comb[c] for c in s.columns], axis=-1), rtol=1e-14)


def test_basis_ignores_the_amplitudes():
    model = hbm.spyrou_model()
    s = structure_of(model)
    a, b = _random_theta(model, 8, seed=1), _random_theta(model, 8, seed=2)
    for name in s.nonlinear_parameters:
        b[:, model.index(name)] = a[:, model.index(name)]
    np.testing.assert_array_equal(s.basis(LOADING, a), s.basis(LOADING, b))


@pytest.mark.parametrize("form", ["thesis", "energy"])
@pytest.mark.parametrize("effect", ["offset", "prestress", "slack", "fiber_exponential", "recruitment", "dispersion",
                                    "viscoelastic"])
def test_library_effects_reproduce_the_stress(form, effect):
    model = hbm.spyrou_model(form=form) + make_effect(effect)
    s = structure_of(model)
    assert s is not None, why_not_linear(model)
    rel = s.verify(LOADING, np.random.default_rng(3), n=12)
    assert rel < 1e-12
    theta = _random_theta(model, 20, seed=4)
    ref = model.stress(LOADING, theta)
    np.testing.assert_allclose(s.stress(LOADING, theta), ref, rtol=1e-10, atol=1e-12 * np.abs(ref).max())


def test_two_history_terms_with_offset_and_prestress_columns():
    model = hbm.spyrou_model() + make_effect("viscoelastic", terms=2) + make_effect("slack") + make_effect("offset")
    s = structure_of(model)
    assert s.columns[-1] == "S0"
    assert s.verify(LOADING, np.random.default_rng(5), n=12) < 1e-12


def test_prestress_column_relaxes_as_the_analytic_qlv_solution():
    """A constant stress carried from t0 relaxes as S0·(g∞ + g·exp(−(t − t0)/τ)); an offset stays S0."""
    t = np.linspace(0.0, 50.0, 26)
    loading = Loading(np.full(t.size, 0.1), t)
    g, tau = 0.4, 10.0
    for effect, expected in (("prestress", (1 - g) + g * np.exp(-t / tau)), ("offset", np.ones_like(t))):
        model = hbm.spyrou_model() + make_effect("viscoelastic") + make_effect(effect)
        theta = model.null_theta(_random_theta(hbm.spyrou_model(), 1)[0])
        theta[model.index("G1")], theta[model.index("LOGTAU1")] = g, np.log10(tau)
        x = structure_of(model).basis(loading, theta)
        np.testing.assert_allclose(x[:, -1], expected, rtol=1e-12)


@pytest.mark.parametrize("effect", ["damage", "series_compliance"])
def test_nonlinear_effects_have_no_structure(effect):
    model = hbm.spyrou_model() + make_effect(effect)
    assert structure_of(model) is None
    assert effect in why_not_linear(model)


class _Undeclared(hbm.Effect):
    name = "black_box"
    stage = "elastic"
    parameters = (hbm.Parameter("BB", 0.0, 1.0, "MPa", "a black box", null=0.0),)

    def stress(self, state, p):
        return p["BB"] * state.eps ** 2


class _LinearUser(_Undeclared):
    name = "user_linear"
    linear_parameters = ("BB",)


class _WronglyDeclared(_Undeclared):
    name = "user_wrong"
    linear_parameters = ("BB",)

    def stress(self, state, p):
        return p["BB"] ** 2 * state.eps  # quadratic in its "amplitude"


class _ReadsAnAmplitude(_Undeclared):
    name = "reads_p1"
    uses = ("P1",)
    linear_parameters = ("BB",)

    def stress(self, state, p):
        return p["BB"] * np.tanh(p["P1"] * state.eps)


def test_user_effects():
    assert structure_of(hbm.spyrou_model() + _Undeclared()) is None
    assert "does not declare" in why_not_linear(hbm.spyrou_model() + _Undeclared())
    s = structure_of(hbm.spyrou_model() + _LinearUser())
    assert s.columns[-1] == "BB" and s.verify(LOADING, np.random.default_rng(6)) < 1e-12
    wrong = structure_of(hbm.spyrou_model() + _WronglyDeclared())
    with pytest.raises(HbmError, match="not linear in its declared amplitudes"):
        wrong.verify(LOADING, np.random.default_rng(7))
    assert "reads ['P1']" in why_not_linear(hbm.spyrou_model() + _ReadsAnAmplitude())


def test_damage_declared_linear_is_caught():
    """Mullins damage is homogeneous in the stress but not additive: filtering each column differs."""

    class ClaimsLinear(type(make_effect("damage"))):
        preserves_linearity = True

    s = structure_of(hbm.spyrou_model() + ClaimsLinear())
    with pytest.raises(HbmError, match="not linear"):
        s.verify(LOADING, np.random.default_rng(8), n=16)


def test_every_library_effect_states_its_structure():
    """A new library effect must take a side: linear columns, a linear operator, or none (listed here)."""
    nonlinear = {"damage", "series_compliance"}
    for name, cls in REGISTRY.items():
        declared = bool(cls.linear_parameters) or cls.preserves_linearity
        assert declared == (name not in nonlinear), name
