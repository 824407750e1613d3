"""Fast tests of the detective's issue-17 rules against known generators: the generic controls,
the unit check, the protocol features, the decision rule (one evidence number, no second gate;
adequate only without any sign of misfit; a physical effect must match the best control), the
base re-optimisation from a refit, and the detection-power scaling law."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from hbm.data import Specimen, cycle, hold, protocol, ramp, synthetic_specimen
from hbm.detective.controls import KinkMisfit, LocalMisfit, StepMisfit, TimeTrend, controls_for
from hbm.detective.decision import decide
from hbm.detective.fitting import Fitter
from hbm.detective.inputs import as_data, unit_anomaly
from hbm.detective.noise_check import model_free_noise, noise_prior_box
from hbm.detective.power import detection_power
from hbm.detective.protocols import experiments_for, protocol_features
from hbm.detective.refits import reoptimise_base
from hbm.detective.results import CandidateResult
from hbm.effects import make_effect
from hbm.model.core import Loading
from hbm.model.spyrou import spyrou_model

TH = dict(VOLF=0.82, EOPT=0.11, P1=0.16, T1=0.9, T2=12.0, THETA=58.8, GF=0.014, GM=0.009)
BASE = np.array([TH[k] for k in spyrou_model().parameter_names])


# ------------------------------------------------------------------------------------------
# controls: each shape against its formula
# ------------------------------------------------------------------------------------------
@pytest.mark.parametrize("cls, prefix, formula", [
    (LocalMisfit, "BUMP", lambda e, c, w: np.exp(-0.5 * ((e - c) / w) ** 2)),
    (StepMisfit, "STEP", lambda e, c, w: 1.0 / (1.0 + np.exp(-(e - c) / w))),
    (KinkMisfit, "KINK", lambda e, c, w: w * np.log1p(np.exp((e - c) / w)) / 0.4),
])
def test_strain_controls_add_their_shape(cls, prefix, formula):
    ctl = cls(0.2, (0.0, 0.4))
    m = spyrou_model() + ctl
    eps = np.linspace(0, 0.4, 41)
    th0 = m.null_theta(BASE)
    th = th0.copy()
    th[m.index(f"{prefix}_A")], th[m.index(f"{prefix}_C")], th[m.index(f"{prefix}_W")] = 0.03, 0.2, 0.02
    diff = m.stress(eps, th) - m.stress(eps, th0)
    np.testing.assert_allclose(diff, 0.03 * formula(eps, 0.2, 0.02), atol=1e-12)
    axis, lo, hi = ctl.region({f"{prefix}_C": 0.2, f"{prefix}_W": 0.02}, Loading(eps))
    assert axis == "strain" and lo < 0.2 < hi


def test_time_trend_control_and_which_controls_apply():
    ds = protocol(ramp(0.3, 1e-2, 20), ramp(0.3, 1e-3, 20))
    d = as_data(ds.with_series("stress", np.linspace(0, 0.05, ds.n_points)))
    ctl = TimeTrend.for_data(d.time, d.stress)
    m = spyrou_model() + ctl
    th = m.null_theta(BASE)
    th[m.index("TREND_A")], th[m.index("TREND_P")] = 0.01, 2.0
    diff = m.stress(d.loading, th) - m.stress(d.loading, m.null_theta(BASE))
    np.testing.assert_allclose(diff, 0.01 * (d.time / d.time.max()) ** 2, atol=1e-12)
    assert [c.name for c in controls_for(d)] == ["local_misfit", "local_step", "local_kink", "time_trend",
                                                 "time_step", "periodic"]
    no_time = as_data(Specimen(ds.id, ds.strain, test=ds.test, attrs=ds.attrs).with_series("stress", d.stress))
    assert "time_trend" not in [c.name for c in controls_for(no_time)]


# ------------------------------------------------------------------------------------------
# inputs and protocols
# ------------------------------------------------------------------------------------------
def test_unit_anomaly_flags_kpa_but_not_mpa():
    ds = synthetic_specimen(spyrou_model(), TH, protocol(ramp(0.35, 1e-3, 40)), 0.001, seed=0)
    assert unit_anomaly(as_data(ds)) is None
    kpa = ds.with_series("stress", ds.stress * 1000.0)
    msg = unit_anomaly(as_data(kpa))
    assert msg is not None and "kPa" in msg and "1e3" in msg
    pa = ds.with_series("stress", ds.stress * 1e6)
    assert "Pa" in unit_anomaly(as_data(pa)) and "1e6" in unit_anomaly(as_data(pa))


def test_protocol_features_and_experiments_look_at_the_file():
    three = as_data(protocol(ramp(0.3, 1e-3, 20), ramp(0.3, 1e-2, 20), ramp(0.3, 1e-1, 20)).with_series(
        "stress", np.zeros(60)))
    f = protocol_features(three)
    np.testing.assert_allclose(f["rates"], [1e-3, 1e-2, 1e-1], rtol=1e-6)
    assert not f["hold"] and not f["unloading"]
    text = experiments_for(["viscoelastic"], f)
    assert "already has 3 strain rates" in text and "relaxation hold" in text and "decade" not in text
    lur = as_data(protocol(cycle(0.3, 1e-3, 15, eps_min=0.1, reload_to=0.35)).with_series(
        "stress", np.zeros(45)))
    g = protocol_features(lur)
    assert g["unloading"] and g["reload_beyond"]
    assert "already has a load-unload-reload" in experiments_for(["damage"], g)
    held = as_data(protocol([ramp(0.3, 1e-2, 20), hold(300.0, 15)]).with_series("stress", np.zeros(35)))
    assert protocol_features(held)["hold"]
    assert "ramps at strain rates" in experiments_for(["viscoelastic"], protocol_features(held))


def test_experiment_advice_is_the_effects_own():
    """An effect hbm knows no protocol for is not told that the file already contains one; a user's
    effect that describes its experiment is quoted."""
    import hbm

    f = protocol_features(as_data(protocol(ramp(0.3, 1e-2, 20)).with_series("stress", np.zeros(20))))
    unknown = experiments_for(["my_effect"], f)
    assert "already" not in unknown and "hbm knows no protocol" in unknown and "my_effect" in unknown

    class Swelling(hbm.Effect):
        name = "swelling"
        stage = "output"
        parameters = (hbm.Parameter("SW", 0.0, 1.0, "-", "swelling", null=0.0),)

        def modify(self, state, p, stress):
            return stress * (1 + p["SW"])

        def experiment(self, protocol):
            return ["a test in a hypertonic bath"], ([f"{protocol['n_points']} points"])

    text = experiments_for([Swelling()], f)
    assert text == "a test in a hypertonic bath (the file already has 20 points)"
    assert experiments_for(["prestress"], f) == experiments_for(["offset"], f)


# ------------------------------------------------------------------------------------------
# the decision rule
# ------------------------------------------------------------------------------------------
def _cand(name, dz, dl, physical=True, windows_after=0, null_excluded=True, region=None):
    c = CandidateResult(effect=name, score=3.0, chi2=9.0, dof=1, absorbed=0.1, refit=True, physical=physical,
                        delta_log_evidence=dz, delta_log_evidence_se=1.0, delta_max_log_likelihood=dl,
                        rmse_before=1.0, rmse_after=0.9, noise="iid", excludes_null=null_excluded,
                        effect_instance=make_effect("offset") if physical else StepMisfit(0.1, (0.0, 0.4)))
    c.windows_after, c.region = windows_after, region
    return c


def _data():
    return as_data(protocol(ramp(0.4, 1e-3, 30)).with_series("stress", np.linspace(0, 0.1, 30)))


OK_NOISE = {"consistent": True}


def test_decision_names_on_evidence_alone():
    """An effect with Δlog Z 6.1 whose interval does not exclude the null is named (the null
    test no longer double-counts the evidence rule)."""
    v = decide([_cand("offset", 6.1, 9.0, null_excluded=False)], [_cand("local_step", 1.0, 6.5, physical=False)],
               [{"eps_lo": 0.1, "eps_hi": 0.2, "sign": 1, "z": 4.0}], OK_NOISE, "iid", _data())
    assert v.verdict == "effect" and v.selected == ["offset"]


def test_decision_control_that_explains_better_gives_unexplained_with_its_region():
    phys = _cand("offset", 8.0, 12.0, windows_after=1)
    ctrl = _cand("local_step", 9.0, 20.0, physical=False, windows_after=0, region=("strain", 0.21, 0.25))
    v = decide([phys], [ctrl], [{"eps_lo": 0.2, "eps_hi": 0.26, "sign": -1, "z": -5.0}], OK_NOISE, "iid", _data())
    assert v.verdict == "unexplained" and v.unexplained["range"] == [0.21, 0.25]
    assert "ε ∈ [0.21, 0.25]" in v.message and "best physical candidate offset Δlog Z = 8.0 " in v.message
    # an evidence estimate above the likelihood gain is capped, and the message names both numbers
    # (beside the window: a shape gaining 9 nats without one is no sign of misfit, issue 28)
    win = [{"eps_lo": 0.2, "eps_hi": 0.26, "sign": -1, "z": -5.0}]
    capped = decide([_cand("offset", 8.7, 4.2, windows_after=1)], [ctrl], win, OK_NOISE, "iid", _data())
    assert "offset gain 4.2 nats (its Δlog Z 8.7 capped by its maximum-likelihood gain)" in capped.message
    # a physical effect better in evidence but leaving misfit the control removes is not named
    # outright: tentatively, with this round's unexplained verdict as the fallback
    phys2 = _cand("offset", 10.0, 12.0, windows_after=2)
    v2 = decide([phys2], [ctrl], [], OK_NOISE, "iid", _data())
    assert v2.verdict == "partial" and v2.selected == ["offset"]
    assert v2.fallback.verdict == "unexplained" and v2.fallback.unexplained["range"] == [0.21, 0.25]


def test_decision_physical_effect_that_fits_better_wins_an_evidence_tie_with_a_control():
    ctrl = _cand("time_trend", 33.1, 40.0, physical=False, windows_after=0, region=("time", 0.0, 360.0))
    ctrl.delta_log_evidence_se = 2.8
    phys = _cand("viscoelastic", 28.1, 60.0, windows_after=0)
    phys.delta_log_evidence_se = 2.3          # trails by 5.0 < 2·hypot(2.3, 2.8) = 7.2, fits better
    assert decide([phys], [ctrl], [], OK_NOISE, "iid", _data()).verdict == "effect"
    phys.delta_max_log_likelihood = 35.0      # the generic shape fits better: it wins the tie
    assert decide([phys], [ctrl], [], OK_NOISE, "iid", _data()).verdict == "unexplained"
    phys.delta_max_log_likelihood, phys.delta_log_evidence = 60.0, 24.0   # trails by 9.1 > 7.2
    assert decide([phys], [ctrl], [], OK_NOISE, "iid", _data()).verdict == "unexplained"


def test_calibrated_decision_reads_a_kept_placement_under_its_own_name():
    """The validation's offset + QLV case (seed 17, offset+qlv_0), replayed: with viscoelastic in the model
    the offset refit keeps its ``prestress`` placement, so the calibration screened it as ``prestress``; the
    candidate (Δlog Z 41.1, beating the generic bump's 24.1 and fitting better) is named -- it read as
    "unexplained" while its statistic was looked up as ``offset``."""
    from hbm.detective.calibration import Calibration

    def stat(kind, observed, p_family):
        return {"kind": kind, "observed": observed, "p": p_family / 8, "p_family": p_family, "critical": 10.0,
                "unit": "nats"}

    cal = Calibration(replicates=400, alpha=0.05, p_family=0.02, window_thresholds={}, null="the fitted model",
                      stats={"prestress": stat("candidate", 62.0, 0.02),
                             "local_misfit": {**stat("control", 61.7, 0.02), "region": ("strain", 0.0, 0.083),
                                              "shape": "Gaussian stress bump in strain", "detail": ""}})
    phys = _cand("offset", 41.1, 66.8)
    phys.effect_instance, phys.placements = make_effect("prestress"), {"offset": "prestress"}
    ctrl = _cand("local_misfit", 24.1, 64.5, physical=False, region=("strain", 0.0, 0.17))
    v = decide([phys], [ctrl], [], OK_NOISE, "iid", _data(), cal)
    assert v.verdict == "effect" and v.selected == ["offset"], v.message
    assert "likelihood gain 62.0 nats at the screen's optimum" in v.message and "placed as prestress" in v.message
    # not significant under its own name: not named on the calibrated rule
    cal.stats["prestress"]["p_family"] = 0.3
    assert decide([phys], [ctrl], [], OK_NOISE, "iid", _data(), cal).verdict == "unexplained"


def _scripted_rounds(script):
    """A run_round for detective._greedy that plays back (verdict, selected) per round, optionally
    with the round's evidence: (log Z, max log L) of its model and of each refitted control."""
    from hbm.detective import _Step
    from hbm.detective.decision import Verdict

    def run_round(current, remaining, k):
        verdict, sel, *ev = script[k]
        fb = Verdict("unexplained", [], [], "", f"unexplained at round {k}") if verdict == "partial" else None
        res = [SimpleNamespace(effect=e, fit=f"fit+{e}") for e in sel]
        base, ctrls = current, []
        if ev:
            (z, lmax), cz = ev
            base = SimpleNamespace(name=current, log_evidence=z, max_log_likelihood=lmax)
            ctrls = [SimpleNamespace(refit=True, fit=SimpleNamespace(log_evidence=a, max_log_likelihood=b))
                     for a, b in cz]
        st = _Step(base, None, res, ctrls, {}, Verdict(verdict, list(sel), [], "", f"round {k}", fallback=fb))
        if ev:
            # _greedy hands on the chosen refit: keep the scripted names as the "current" fit
            st.base = SimpleNamespace(**vars(base))
        return st
    return run_round


@pytest.mark.parametrize("script, kept, selected, verdicts", [
    # tentative offset, then viscoelastic explains the rest: both named, in order
    ([("partial", ["offset"]), ("effect", ["viscoelastic"]), ("adequate", [])],
     3, ["offset", "viscoelastic"], ["effect", "effect", "adequate"]),
    # tentative effect, nothing left after it: kept
    ([("partial", ["offset"]), ("adequate", [])], 2, ["offset"], ["effect", "adequate"]),
    # tentative effect, the next round still unexplained: reverted to the first round's verdict
    ([("partial", ["slack"]), ("unexplained", [])], 1, [], ["unexplained"]),
    # two tentative rounds in a row: the first is reverted
    ([("effect", ["damage"]), ("partial", ["slack"]), ("partial", ["offset"])],
     2, ["damage"], ["effect", "unexplained"]),
])
def test_greedy_keeps_a_tentative_effect_only_when_the_next_round_settles(script, kept, selected, verdicts):
    from hbm.detective import _greedy
    rounds, sel, current = _greedy(_scripted_rounds(script), "base", [SimpleNamespace(name="offset")], 3)
    assert len(rounds) == kept and sel == selected
    assert [r.verdict.verdict for r in rounds] == verdicts
    assert current == (f"fit+{selected[-1]}" if selected else "base")


@pytest.mark.parametrize("script, selected, verdicts, beyond", [
    # offset + a relaxing offset: the tentative offset leaves a small time trend, but with or
    # without any generic shape it is worth 565.6 - 550.0 = 15.6 nats (max log L: +6.6): kept
    ([("effect", ["viscoelastic"]),
      ("partial", ["offset"], (466.9, 494.1), [(550.0, 616.6), (517.1, 585.0)]),
      ("unexplained", [], (557.8, 608.6), [(565.6, 623.2), (551.1, 620.2)])],
     ["viscoelastic", "offset"], ["effect", "effect", "unexplained"], 6.6),
    # the same, but the best shape without the effect is as good as anything with it: reverted
    ([("effect", ["viscoelastic"]),
      ("partial", ["offset"], (466.9, 494.1), [(563.0, 625.0)]),
      ("unexplained", [], (557.8, 608.6), [(565.6, 623.2)])],
     ["viscoelastic"], ["effect", "unexplained"], -1.8),
    # a large evidence gain that the best fits do not show is capped by the max log L: reverted
    ([("partial", ["slack"], (400.0, 430.0), [(420.0, 470.0)]),
      ("unexplained", [], (440.0, 460.0), [(445.0, 472.0)])],
     [], ["unexplained"], 2.0),
    # a tentative effect needed beside the shapes, then a second tentative one that is not
    ([("partial", ["viscoelastic"], (405.8, 427.0), [(454.8, 482.8)]),
      ("partial", ["offset"], (458.4, 488.1), [(506.0, 558.1)]),
      ("unexplained", [], (500.0, 546.0), [(507.0, 560.0)])],
     ["viscoelastic"], ["effect", "unexplained"], 1.0),
])
def test_greedy_keeps_a_tentative_effect_that_no_generic_shape_replaces(script, selected, verdicts, beyond):
    """A tentatively named effect whose next round is still unexplained is kept when the best
    evidence with it (alone or with any control) beats the best without it by > 5 nats, capped
    by the max log L of the same fits; its message says so, the unexplained rest is reported."""
    from hbm.detective import _greedy, gain_beyond_controls
    run = _scripted_rounds(script)
    rounds, sel, _ = _greedy(run, "base", [SimpleNamespace(name=e) for e in ("offset", "slack")], 3)
    assert sel == selected and [r.verdict.verdict for r in rounds] == verdicts
    t = max(k for k, row in enumerate(script) if row[0] == "partial")     # the last tentative effect
    assert gain_beyond_controls(run("m", [], t), run("m", [], t + 1)) == pytest.approx(beyond)
    # kept despite an unexplained next round: said in its message (the first of two tentatives, too)
    notes = [r.verdict.message for r in rounds if "needed beside the best generic shape" in r.verdict.message]
    assert len(notes) == len(selected) - sum(row[0] == "effect" for row in script)


def test_greedy_tentative_at_the_effect_cap_is_not_named():
    from hbm.detective import _greedy
    rounds, sel, _ = _greedy(_scripted_rounds([("effect", ["offset"]), ("partial", ["damage"])]), "base", [], 1)
    assert sel == ["offset"] and [r.verdict.verdict for r in rounds] == ["effect", "unexplained"]


def test_adequate_only_without_any_sign_of_misfit():
    quiet = [_cand("offset", 1.0, 2.0)], [_cand("local_step", -3.0, 2.0, physical=False)]
    assert decide(*quiet, [], OK_NOISE, "iid", _data()).verdict == "adequate"
    win = [{"eps_lo": 0.1, "eps_hi": 0.2, "sign": 1, "z": 4.0}]
    assert decide(*quiet, win, OK_NOISE, "iid", _data()).verdict == "unexplained"
    assert decide(*quiet, [], {"consistent": False}, "iid", _data()).verdict == "unexplained"
    # AR(1) chosen, but white noise + a smooth misfit (a control at iid) gains: misfit, not noise
    ar = [_cand("offset", 1.0, 2.0)], [_cand("local_step", 2.0, 7.0, physical=False)]
    assert decide(*ar, [], OK_NOISE, "ar1", _data()).verdict == "adequate"
    ar[1][0].white_gain = 3.0
    v = decide(*ar, [], OK_NOISE, "ar1", _data())
    assert v.verdict == "unexplained" and "prefer white noise" in v.message


# ------------------------------------------------------------------------------------------
# base re-optimisation from a refit
# ------------------------------------------------------------------------------------------
def test_base_reoptimised_from_a_refit_optimum():
    """A base fit left short of its optimum is improved from a refit's optimum with the new
    parameter at its null; the refit's base-parameter point is a lower bound for the result."""
    ds = synthetic_specimen(spyrou_model(), TH, protocol(ramp(0.35, 1e-3, 40), ramp(0.35, 1e-2, 40)), 0.0015, seed=4)
    d = as_data(ds)
    mf = model_free_noise(d.stress, d.segment)
    f = Fitter(d, None, 0, 300, noise_prior_box(mf, d.stress), False)
    good = f.fit(spyrou_model(), ["iid"], None, 1, sample=False, global_restarts=1)
    m_off = spyrou_model() + make_effect("offset")
    starts = f.warm_starts(good, m_off, ["iid"], [{"S0": 0.0}])
    refit = f.fit(m_off, ["iid"], starts, 2, sample=False)
    # a poor base: the optimum moved away in T1/T2
    poor = f.fit(spyrou_model(), ["iid"], {"iid": [good.theta_max * np.r_[1, 1, 1, 1.6, 0.6, 1, 1, 1, 1]]}, 3,
                 sample=False)
    poor.noise_fits["iid"]["x"] = good.theta_max * np.r_[1, 1, 1, 1.6, 0.6, 1, 1, 1, 1]
    lik = poor.noise_fits["iid"]["lik"]
    poor.noise_fits["iid"]["max_log_likelihood"] = float(lik(poor.noise_fits["iid"]["x"][None, :])[0])
    restricted = dict(zip(refit.names, refit.theta_max))
    floor = float(lik(np.array([[restricted[n] for n in lik.names]]))[0])
    assert floor > poor.noise_fits["iid"]["max_log_likelihood"] + 5
    c = CandidateResult(effect="offset", score=0, chi2=0, dof=1, absorbed=0, refit=True, fit=refit)
    assert reoptimise_base(poor, [c], f, 5)
    assert poor.max_log_likelihood >= floor - 1e-9
    assert poor.max_log_likelihood == pytest.approx(good.max_log_likelihood, abs=1.0)


# ------------------------------------------------------------------------------------------
# detection power
# ------------------------------------------------------------------------------------------
def test_power_limit_of_a_linear_effect_scales_with_the_noise():
    """For an offset (linear in its parameter) the gain grows as (S0/σ)²: halving the noise
    halves the detection limit among the physical candidates (within the bisection's 10 %
    resolution); letting the controls compete can only raise it."""
    prot = protocol(ramp(0.35, 1e-3, 30), ramp(0.35, 1e-2, 30))
    ds = synthetic_specimen(spyrou_model(), TH, prot, 0.001, seed=6)
    d = as_data(ds)
    mf = model_free_noise(d.stress, d.segment)
    f = Fitter(d, None, 0, 300, noise_prior_box(mf, d.stress), False)
    fit = f.fit(spyrou_model(), ["iid"], None, 1, sample=False, global_restarts=1)
    limits = []
    for sd in (0.001, 0.0005):
        # the same fitted curve with the noise sd set: only σ differs
        fit.theta_max = fit.theta_max.copy()
        fit.theta_max[fit.names.index("sigma")] = sd
        p = detection_power(fit, d, [make_effect("offset"), make_effect("damage")], seed=3, n_rep=100,
                            with_controls=False)
        row = {r["effect"]: r for r in p["effects"]}
        limits.append(row["offset"]["limit"])
        assert row["damage"]["limit"] is None and "load-unload-reload" in row["damage"]["protocol"]
        shares = [s for _, s in row["offset"]["levels"]]
        assert shares[0] < 0.5 and shares[-1] >= 0.8
    assert 0.4 < limits[1] / limits[0] < 0.62, limits
    strict = detection_power(fit, d, [make_effect("offset")], seed=3, n_rep=100)["effects"][0]["limit"]
    assert strict is not None and strict >= limits[1]


# ------------------------------------------------------------------------------------------
# refined evidence of the decisive comparisons
# ------------------------------------------------------------------------------------------
def _refit(name, dz, dl, se=1.0, physical=True):
    """A refitted candidate with TMCMC gain ``dz`` ± ``se`` and likelihood gain ``dl``."""
    c = _cand(name, dz, dl, physical=physical)
    c.delta_log_evidence_tmcmc, c.delta_log_evidence_se = dz, se
    c.fit = SimpleNamespace(effects=[name])
    return c


@pytest.mark.parametrize("cands, rerun", [
    # a clean curve: nothing could pass the threshold -> nothing rerun
    ([("offset", 1.0, 4.0, True), ("local_misfit", -3.0, 4.5, False)], []),
    # a clearly named effect, the rest far behind it: its verdict cannot change
    ([("viscoelastic", 51.9, 58.3, True), ("offset", 3.0, 7.4, True), ("time_trend", 39.4, 45.8, False)], []),
    # round 2 of qlv>offset: the offset gains 12 nats of max log L but -1.5 of evidence -> the
    # base, the offset and the controls that can pass the threshold are rerun (not a weak one)
    ([("offset", -1.5, 12.3, True), ("local_misfit", -7.6, 8.6, False), ("local_step", -2.0, 3.9, False)],
     ["offset", "local_misfit"]),
    # decided by evidence: 12 - 2 SE > 5
    ([("offset", 12.0, 14.0, True)], []),
    # within 2 SE of the threshold: rerun
    ([("offset", 8.0, 14.0, True)], ["offset"]),
])
def test_decisive_comparisons_are_those_that_can_change_the_verdict(cands, rerun):
    from hbm.detective.refits import to_refine
    cs = [_refit(n, dz, dl, se=1.9, physical=p) for n, dz, dl, p in cands]
    assert [c.effect for c in to_refine(cs)] == rerun


def test_refined_gains_compare_runs_of_the_same_settings():
    """The decisive refits are measured against the base's refined run, the others against its
    standard run; the base is rerun once, and its standard evidence (the next round's and the
    controls' yardstick) is left alone."""
    from hbm.detective.refits import refine_decisive
    from hbm.detective.results import FitSummary
    from hbm.detective.rules import TMCMC_SE_FACTOR

    def fs(name, z, z_ref, se=0.5, se_ref=0.3):
        f = FitSummary(effects=[name], noise="iid", names=["a"], theta_max=np.zeros(1), max_log_likelihood=0.0,
                       bic=0.0, rmse=0.0, log_evidence=z, log_evidence_se=se)
        f.likelihood = (z_ref, se_ref)       # what the stub's rerun will report
        return f

    calls = []

    def refine(f, seed):
        if np.isfinite(f.refined_log_evidence):
            return
        calls.append(f.effects[0])
        f.refined_log_evidence, f.refined_log_evidence_se = f.likelihood

    fitter = SimpleNamespace(refine=refine, log=lambda msg: None, out_of_time=lambda: False, pool=lambda: None,
                             refine_seconds=0.0)
    base = fs("base", 375.0, 377.0)
    off = _refit("offset", -1.5, 12.3, se=2.6)
    off.fit = fs("offset", 373.5, 383.0)
    bump = _refit("local_misfit", -7.6, 8.6, physical=False)
    bump.fit = fs("local_misfit", 367.4, 377.5)
    weak = _refit("local_step", -2.0, 3.9, physical=False)
    weak.fit = fs("local_step", 373.0, 399.0)
    assert refine_decisive([off, bump, weak], base, fitter, 0) == ["offset", "local_misfit"]
    assert calls == ["base", "offset", "local_misfit"]
    assert off.delta_log_evidence == pytest.approx(6.0) and off.evidence_method == "tmcmc-refined"
    assert off.delta_log_evidence_se == pytest.approx(TMCMC_SE_FACTOR * np.hypot(0.3, 0.3))
    assert bump.delta_log_evidence == pytest.approx(0.5)
    assert weak.delta_log_evidence == -2.0 and weak.evidence_method == ""   # untouched
    assert base.log_evidence == 375.0 and off.fit.log_evidence == 373.5
    # a second call (the next round, same base) reruns nothing already rerun
    refine_decisive([off, bump], base, fitter, 1)
    assert calls == ["base", "offset", "local_misfit"]


@pytest.mark.slow
def test_refined_evidence_credits_a_second_effect_the_25_step_runs_under_credit():
    """QLV relaxation + a load-cell offset added after it (hbm's own viscoelastic and offset
    effects), three rates, 30 points each: the offset's evidence gain beside the viscoelastic
    model.  The standard runs (25 global MH steps per stage) leave the larger model's late stages
    under-mixed and its log Z low; the refined runs (the local walk) credit the offset above the
    naming threshold on every seed, and by more than the standard runs on average."""
    from hbm.detective.fitting import sample
    from hbm.detective.rules import DELTA_LOGZ_MIN, TMCMC_REFINE_MOVE, TMCMC_REFINE_STEPS

    th = dict(VOLF=0.75, EOPT=0.08, P1=0.20, T1=0.6, T2=18.0, THETA=58.0, GF=0.02, GM=0.008,
              G1=0.3, LOGTAU1=1.6, S0=0.0065)
    m2 = spyrou_model() + make_effect("viscoelastic") + make_effect("offset")
    prot = protocol(ramp(0.36, 1e-3, 30), ramp(0.36, 1e-2, 30), ramp(0.36, 1e-1, 30))
    d = as_data(synthetic_specimen(m2, th, prot, 0.012, seed=3, relative=True))
    mf = model_free_noise(d.stress, d.segment)
    f = Fitter(d, None, 0, 800, noise_prior_box(mf, d.stress), False)
    m1 = spyrou_model() + make_effect("viscoelastic")
    a = f.fit(m1, ["iid"], None, 1, sample=False, global_restarts=2)
    b = f.fit(m2, ["iid"], f.warm_starts(a, m2, ["iid"], [{"S0": 0.0}, {"S0": 0.005}]), 2, sample=False,
              global_restarts=1)
    assert b.max_log_likelihood - a.max_log_likelihood > DELTA_LOGZ_MIN + 3   # the offset is in the data
    std, ref = [], []
    for s in range(2):
        std.append(sample(b.likelihood, 800, 20 + s).log_evidence - sample(a.likelihood, 800, 10 + s).log_evidence)
        kw = dict(max_steps=TMCMC_REFINE_STEPS, move=TMCMC_REFINE_MOVE)
        ref.append(sample(b.likelihood, 800, 20 + s, **kw).log_evidence
                   - sample(a.likelihood, 800, 10 + s, **kw).log_evidence)
    assert min(ref) > DELTA_LOGZ_MIN, (std, ref)
    assert np.mean(ref) > np.mean(std) + 1.0, (std, ref)


def test_refined_reruns_stop_at_the_deadline_and_keep_standard_comparisons():
    """--max-time passing between two reruns: the refit already rerun is compared with the base's
    rerun, the next keeps its standard comparison, and the skipped reruns are recorded."""
    from hbm.detective.refits import refine_decisive
    from hbm.detective.results import FitSummary

    def fs(name, z, z_ref):
        f = FitSummary(effects=[name], noise="iid", names=["a"], theta_max=np.zeros(1), max_log_likelihood=0.0,
                       bic=0.0, rmse=0.0, log_evidence=z, log_evidence_se=0.5)
        f.likelihood = (z_ref, 0.3)
        return f

    calls, skipped = [], []

    def refine(f, seed):
        calls.append(f.effects[0])
        f.refined_log_evidence, f.refined_log_evidence_se = f.likelihood

    fitter = SimpleNamespace(refine=refine, log=lambda msg: None, out_of_time=lambda: len(calls) >= 2,
                             skip=lambda what, why: skipped.append(what), pool=lambda: None, refine_seconds=0.0)
    base = fs("base", 375.0, 377.0)
    off = _refit("offset", -1.5, 12.3, se=2.6)
    off.fit = fs("offset", 373.5, 383.0)
    bump = _refit("local_misfit", -7.6, 8.6, physical=False)
    bump.fit = fs("local_misfit", 367.4, 377.5)
    assert refine_decisive([off, bump], base, fitter, 0) == ["offset"]
    assert calls == ["base", "offset"] and skipped == ["refined evidence of local_misfit"]
    assert off.evidence_method == "tmcmc-refined" and off.delta_log_evidence == pytest.approx(6.0)
    assert bump.evidence_method != "tmcmc-refined" and bump.delta_log_evidence == pytest.approx(-7.6)
