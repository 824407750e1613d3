"""Placements of an effect: a pre-stress carried by the tissue (``prestress``) is the load-cell
``offset`` moved before the history stage.  Checked against the analytic relaxation of a
constant under QLV, against the offset where no history effect separates them, and in the
detective's candidate list and refit models."""

from __future__ import annotations

import numpy as np
import pytest

from hbm.detective.inputs import resolve_candidates
from hbm.detective.refits import placement_models
from hbm.effects import Offset, Prestress, Viscoelastic, family, make_effect, placements
from hbm.model.core import Loading, Model
from hbm.model.spyrou import spyrou_model

TH = np.array([0.82, 0.11, 0.16, 0.9, 12.0, 58.8, 0.014, 0.009])


def _three_rates(n=25):
    e, t, k = [], [], []
    for j, rate in enumerate((1e-3, 1e-2, 1e-1)):
        ej = np.linspace(0.0, 0.3, n)
        e.append(ej), t.append(ej / rate), k.append(np.full(n, j + 1))
    return Loading(np.concatenate(e), np.concatenate(t), np.concatenate(k))


def test_prestress_relaxes_with_qlv_as_the_analytic_solution_and_the_offset_does_not():
    """A constant S0 in the tissue under one Prony term relaxes as S0·(g∞ + g·e^{−(t−t0)/τ}) along
    each history; the load-cell offset added after the history stage stays S0."""
    t = np.array([0.0, 0.5, 2.0, 7.0, 30.0, 0.0, 1.0, 100.0])       # two histories (time restarts)
    load = Loading(np.zeros(t.size), t, np.r_[np.ones(5), np.full(3, 2)])
    s0, g, logtau = 0.004, 0.35, 1.2
    tau = 10.0 ** logtau
    pre = Model([Prestress(), Viscoelastic()]).stress(load, np.array([s0, g, logtau]))
    t0 = np.r_[np.zeros(5), np.zeros(3)]
    np.testing.assert_allclose(pre, s0 * ((1 - g) + g * np.exp(-(t - t0) / tau)), rtol=1e-12)
    off = Model([Viscoelastic(), Offset()]).stress(load, np.array([g, logtau, s0]))
    np.testing.assert_allclose(off, s0, rtol=1e-12)


def test_placements_are_one_model_without_a_history_effect_and_two_with_one():
    load = _three_rates()
    rng = np.random.default_rng(3)
    x = np.c_[np.tile(TH, (5, 1)), rng.uniform(-0.02, 0.02, 5)]
    a = spyrou_model().with_effects(Offset()).stress(load, x)
    b = spyrou_model().with_effects(Prestress()).stress(load, x)
    np.testing.assert_array_equal(a, b)
    mv = spyrou_model().with_effects(Viscoelastic(), Offset())
    mp = mv.replacing("offset", Prestress())
    assert mp.parameter_names == mv.parameter_names and mp.effect_names[-1] == "prestress"
    xv = np.r_[TH, 0.3, 1.5, 0.006]
    diff = mv.stress(load, xv) - mp.stress(load, xv)
    assert np.max(np.abs(diff)) > 1e-3                                  # the pre-stress relaxed
    # replacing keeps every other effect: the same model as building it directly
    direct = spyrou_model().with_effects(Viscoelastic(), Prestress())
    np.testing.assert_array_equal(direct.stress(load, xv), mp.stress(load, xv))
    with pytest.raises(ValueError, match="no effect 'damage'"):
        mv.replacing("damage", Prestress())


def test_prestress_jacobian_against_finite_differences():
    m = spyrou_model().with_effects(Prestress())
    assert m.has_analytic_jacobian
    load = _three_rates(10)
    x = np.r_[TH, 0.005]
    jac = m.stress_jacobian(load, x)
    h = 1e-7
    fd = (m.stress(load, x + h * np.eye(9)[-1]) - m.stress(load, x - h * np.eye(9)[-1])) / (2 * h)
    np.testing.assert_allclose(jac[:, -1], fd, rtol=1e-6, atol=1e-9)


def test_placement_registry():
    assert family(Prestress()) == "offset" and family(Offset()) == "offset" and family(Viscoelastic()) == "viscoelastic"
    assert [type(p) for p in placements(Offset())] == [Prestress]
    assert [type(p) for p in placements(Prestress())] == [Offset]
    assert placements(make_effect("damage")) == []


@pytest.mark.parametrize("cands, model, expect", [
    ("all", None, "offset"),                              # the family once, by its own name
    ("prestress", None, "prestress"),                     # asked for alone: kept
    ("prestress,offset", None, "offset"),
    ("all", ["offset"], None),                            # already in the model in one placement
    ("all", ["prestress"], None),
])
def test_candidates_screen_each_placement_family_once(cands, model, expect):
    m = spyrou_model() if model is None else spyrou_model().with_effects(*[make_effect(k) for k in model])
    names = [e.name for e in resolve_candidates(cands, m)]
    fam = [n for n in names if n in ("offset", "prestress")]
    assert fam == ([] if expect is None else [expect])
    assert len(names) == len(set(names))


def test_refit_models_try_the_other_placement_only_where_it_matters():
    load = _three_rates()
    base = spyrou_model()
    visco = base.with_effects(Viscoelastic())
    off = base.with_effects(Offset())

    def summary(model, e):
        return [(m.effect_names[3:], moved) for m, _, moved in placement_models(model, e, load)]

    # no history effect: the two placements are one model, refitted once
    assert summary(base, Offset()) == [(("offset",), {})]
    # with a viscoelastic base the offset candidate is refitted in both placements
    assert summary(visco, Offset()) == [(("viscoelastic", "offset"), {}),
                                        (("viscoelastic", "prestress"), {"offset": "prestress"})]
    # an offset named first is moved when the viscoelastic candidate makes its placement matter
    assert summary(off, Viscoelastic()) == [(("offset", "viscoelastic"), {}),
                                            (("prestress", "viscoelastic"), {"offset": "prestress"})]
    # ... but not when the model already tells the placements apart (its placement was chosen)
    both = visco.with_effects(Prestress())
    assert summary(both, make_effect("damage")) == [(("viscoelastic", "prestress", "damage"), {})]
    # an elastic-stage candidate cannot separate them
    assert summary(off, make_effect("recruitment")) == [(("offset", "recruitment"), {})]


def test_extend_applies_the_diagnosed_placements():
    """``extend --auto`` rebuilds the diagnosed model: a placement recorded for an effect already
    in the model moves it; one recorded for the named effect itself is what gets added."""
    from hbm.detective import place_as_diagnosed

    m = spyrou_model().with_effects(Offset())
    moved, add = place_as_diagnosed(m, "viscoelastic", {"offset": "prestress"})
    assert moved.effect_names[3:] == ("prestress",) and add == "viscoelastic"
    same, add = place_as_diagnosed(spyrou_model().with_effects(Viscoelastic()), "offset", {"offset": "prestress"})
    assert same.effect_names[3:] == ("viscoelastic",) and add == "prestress"
    plain, add = place_as_diagnosed(m, "damage", {})
    assert plain is m and add == "damage"


@pytest.mark.parametrize("refined, max_logl, kept, ties", [
    ((483.0, 510.0), (524.0, 522.0), {"offset": "prestress"}, {}),       # clearly in the tissue
    ((483.0, 486.0), (524.0, 527.0), {}, {"offset placed as prestress": (3.0, 3.0)}),  # not told apart
    ((490.0, 470.0), (524.0, 512.0), {}, {}),                            # clearly a load-cell offset
    ((483.0, 484.7), (524.0, 539.0), {"offset": "prestress"}, {}),       # fits better, evidence agrees
    ((483.0, 482.0), (524.0, 539.0), {}, {"offset placed as prestress": (-1.0, 15.0)}),  # evidence disagrees
])
def test_a_placement_is_kept_only_when_its_refined_evidence_is_clearly_better(monkeypatch, refined, max_logl,
                                                                              kept, ties):
    """The choice between placements rests on the refined evidence reruns (the standard runs
    scatter by ~10 nats on these models): another placement replaces the plain one when its
    refined log Z is more than 5 nats higher, or its maximum log-likelihood is and the refined
    log Z agrees in sign; otherwise the plain one stays and the tie is reported with both
    differences."""
    from types import SimpleNamespace

    from hbm.detective import refits
    from hbm.detective.results import CandidateResult, FitSummary

    visco = spyrou_model().with_effects(Viscoelastic())
    models = [(visco.with_effects(Offset()), Offset(), {}),
              (visco.with_effects(Prestress()), Prestress(), {"offset": "prestress"})]
    monkeypatch.setattr(refits, "placement_models", lambda model, e, loading: models)
    made = iter(range(2))

    def refit_model(c, mc, e, base, fitter, noises, seed, gate=False):
        assert not gate          # several placements: every one gets its evidence run
        k = next(made)
        return FitSummary(effects=[e.name], noise="iid", names=["S0"], theta_max=np.zeros(1),
                          max_log_likelihood=max_logl[k], bic=0.0, rmse=0.001 * (k + 1), model=mc,
                          log_evidence=470.0 - 20 * k, log_evidence_se=1.0)  # standard runs: noise

    def refine(fs, seed):
        fs.refined_log_evidence = refined[0 if fs.effects == ["offset"] else 1]

    monkeypatch.setattr(refits, "_refit_model", refit_model)
    monkeypatch.setattr(refits, "_null_test", lambda c, e, fs: None)
    fitter = SimpleNamespace(data=SimpleNamespace(loading=None), refine=refine, log=lambda msg: None)
    c = CandidateResult(effect="offset", score=0, chi2=0, dof=1, absorbed=0, effect_instance=Offset())
    refits.refit_candidate(c, SimpleNamespace(model=visco), fitter, ["iid"], 0)
    assert c.placements == kept and c.placement_ties == ties
    assert c.effect_instance.name == ("prestress" if kept else "offset")
    assert c.fit.model.effect_names[-1] == c.effect_instance.name


@pytest.mark.slow
def test_diagnose_names_an_offset_carried_by_a_viscoelastic_tissue():
    """hbm's own viscoelastic + prestress generator (a pre-stress of 0.01 MPa relaxing by 45 %
    with τ ≈ 32 s), three rates, 0.8 % noise: both effects are named and the offset is placed in
    the tissue (refined log Z ≈ +20–30 nats over the load-cell placement on this data)."""
    from hbm.data import protocol, ramp, synthetic_specimen
    from hbm.detective import diagnose

    th = dict(VOLF=0.75, EOPT=0.08, P1=0.20, T1=0.6, T2=18.0, THETA=58.0, GF=0.02, GM=0.008,
              G1=0.45, LOGTAU1=1.5, S0=0.01)
    m = spyrou_model().with_effects(Viscoelastic(), Prestress())
    prot = protocol(ramp(0.36, 1e-3, 35), ramp(0.36, 1e-2, 35), ramp(0.36, 1e-1, 35))
    dg = diagnose(synthetic_specimen(m, th, prot, 0.008, seed=5, relative=True), seed=3, removal=False)
    assert dg.verdict == "effect" and set(dg.selected) == {"viscoelastic", "offset"}, dg.message
    final = [st for st in dg.steps if st["selected"]]
    assert any(st["placements"] for st in final), dg.steps
    assert "prestress" in dg.steps[-1]["model"], dg.steps
