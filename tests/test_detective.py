"""Tests of the detective (hbm.detective): the control, the screens, verdicts on data with a
hidden effect, extend, the CLI and user-written candidates.  The noise estimate, whitening and
misfit windows are tested in test_detective_noise_check.py.

Default selection: building blocks against known generators plus one seed of the cheap
end-to-end cases.  The multi-seed validations (false-alarm rate with iid and AR(1) noise,
every hidden effect over several seeds) are marked slow: ``pytest -m slow tests/test_detective.py``.
"""

from __future__ import annotations

import json

import numpy as np
import pytest

from hbm.data import cycle, protocol, ramp, synthetic_specimen
from hbm.detective import LocalMisfit, diagnose, extend, local_refit_screen, score_screen
from hbm.detective.inputs import as_data
from hbm.detective.noise_check import whitener
from hbm.effects import make_effect
from hbm.model.core import Effect, Parameter
from hbm.model.spyrou import spyrou_model

# generating parameters: deliberately not the demo's (workflows/hidden_effect_demo.py)
TH = dict(VOLF=0.8, EOPT=0.1, P1=0.15, T1=0.8, T2=14.0, THETA=58.5, GF=0.015, GM=0.01)


class Bump(Effect):
    """Not in the library: a localized sin² stress bump between ε = A and ε = B."""

    name = "test_bump"
    stage = "output"
    parameters = (Parameter("KA", 0.0, 0.1, "MPa", "bump height", null=0.0),)

    def __init__(self, a=0.15, b=0.23):
        self.a, self.b = a, b

    def modify(self, state, p, stress):
        x = np.clip((state.loading.strain - self.a) / (self.b - self.a), 0, 1)
        return stress + p["KA"] * np.sin(np.pi * x) ** 2


def hidden(kind: str, seed: int, noise: str = "iid", rho: float = 0.5, n: int = 50):
    """Synthetic specimen with a hidden effect; returns (dataset, fix, noise sd)."""
    m, th, fix, sd = spyrou_model(), dict(TH), None, 0.0015
    if kind == "clean":
        prot = protocol(ramp(0.33, 2e-3, n), ramp(0.33, 2e-2, n))
    elif kind == "offset":
        m = m + make_effect("offset")
        th["S0"] = 0.0065
        prot = protocol(ramp(0.33, 2e-3, int(1.5 * n)))
    elif kind == "viscoelastic":
        m = m + make_effect("viscoelastic")
        th.update(G1=0.35, LOGTAU1=1.2)
        prot = protocol(ramp(0.33, 2e-3, n), ramp(0.33, 2e-2, n), ramp(0.33, 2e-1, n))
    elif kind == "damage":
        m = m + make_effect("damage")
        th["DMG"] = 0.5
        prot = protocol(cycle(0.28, 2e-3, n, eps_min=0.08, reload_to=0.33))
    elif kind == "slack":
        m = m + make_effect("slack")
        th.update(VOLF=0.88, EOPT=0.06, P1=0.25, T1=0.4, T2=9.0, THETA=59.2, SLACK=0.045)
        fix = {"EOPT": 0.06}
        sd = 0.0012
        prot = protocol(ramp(0.33, 2e-3, n), ramp(0.33, 2e-2, n))
    elif kind == "unknown":
        m = m + Bump()
        th["KA"] = 0.007
        prot = protocol(ramp(0.33, 2e-3, n), ramp(0.33, 2e-2, n))
    else:  # pragma: no cover
        raise ValueError(kind)
    ds = synthetic_specimen(m, th, prot, sd, seed=seed, noise=noise, rho=rho)
    return ds, fix, sd


# ------------------------------------------------------------------------------------------
# building blocks against known generators
# ------------------------------------------------------------------------------------------
def test_local_misfit_is_a_gaussian_bump():
    ctl = LocalMisfit(0.2, (0.0, 0.4))
    m = spyrou_model() + ctl
    eps = np.linspace(0, 0.4, 41)
    th0 = m.null_theta(np.array([0.8, 0.1, 0.1, 1.0, 10.0, 59.0, 0.01, 0.01]))
    th = th0.copy()
    th[m.index("BUMP_A")], th[m.index("BUMP_C")], th[m.index("BUMP_W")] = 0.03, 0.2, 0.05
    diff = m.stress(eps, th) - m.stress(eps, th0)
    np.testing.assert_allclose(diff, 0.03 * np.exp(-0.5 * ((eps - 0.2) / 0.05) ** 2), atol=1e-14)
    np.testing.assert_allclose(m.stress(eps, th0), spyrou_model().stress(eps, th0[:8]), atol=1e-15)


def test_screens_rank_the_hidden_offset_first():
    """Residual = offset signature (exact truth as 'fit'): both screens flag offset, and
    an effect the base model absorbs (series compliance) scores low."""
    ds, _, sd = hidden("offset", 0)
    d = as_data(ds)
    m = spyrou_model()
    theta = np.array([TH[k] for k in m.parameter_names])
    resid = np.asarray(ds.stress) - m.stress(d.loading, theta)
    w = whitener(np.full(resid.size, sd), 0.0, d.ar_first)
    free = list(m.parameter_names)
    off = score_screen(m, theta, free, make_effect("offset"), resid, w, d)
    sc = score_screen(m, theta, free, make_effect("series_compliance"), resid, w, d)
    assert off["z"] > 3 and off["z"] > sc["z"]
    assert 0.0 < off["start"]["S0"] < 0.02
    lr = local_refit_screen(m, theta, free, make_effect("offset"), w, d, [off["start"]])
    assert lr["z"] > 3 and lr["start"]["S0"] == pytest.approx(0.0065, abs=0.003)


# ------------------------------------------------------------------------------------------
# end to end, one seed (default selection)
# ------------------------------------------------------------------------------------------
def test_diagnose_names_offset_on_a_single_ramp():
    ds, _, sd = hidden("offset", 1)
    dg = diagnose(ds, candidates=["offset", "viscoelastic", "series_compliance"], seed=1, n_samples=300)
    assert dg.verdict == "effect" and dg.selected == ["offset"], dg.summary()
    c = next(c for c in dg.candidates if c.effect == "offset")
    assert c.delta_log_evidence > 5 and c.excludes_null
    lo, hi, null = c.intervals["S0"]
    assert lo < 0.0065 < hi
    assert c.effect_instance.name == "offset" and c.score_start["S0"] > 0
    with pytest.raises(AttributeError):  # results declare every field: nothing is attached at run time
        c._effect = c.effect_instance
    assert c.rmse_after < c.rmse_before and c.rmse_after < 1.25 * sd
    assert any(w[2] == 1 and w[0] < 0.05 for w in dg.misfit_windows)
    out = dg.to_dict()
    json.dumps(out, allow_nan=False)
    assert set(out) >= {"verdict", "selected", "group", "misfit_windows", "noise", "candidates",
                        "suggested_experiment"}


def test_extend_error_falls_to_noise_level():
    ds, _, sd = hidden("viscoelastic", 2, n=35)
    ext = extend(ds, add=["viscoelastic"], seed=2, n_samples=300)
    assert [s.effects for s in ext.steps] == [[], ["viscoelastic"]]
    r0, r1 = ext.steps[0].rmse, ext.steps[1].rmse
    assert r0 > 1.5 * sd and r1 < 1.2 * sd
    assert ext.steps[1].log_evidence > ext.steps[0].log_evidence + 5
    d = ext.to_dict()
    assert list(d["steps"][0]) [:4] == ["effects", "rmse", "log_evidence", "log_evidence_se"]


def test_cli_diagnose_json_and_user_candidate(tmp_path, capsys, monkeypatch):
    """`hbm diagnose --json` prints exactly one JSON object; a user effect file is screened
    (no edit of hbm); `hbm extend --json` gives the steps with the base model first."""
    import hbm.cli as cli
    from hbm.data import save_specimen
    ds, _, _ = hidden("offset", 3, n=50)
    path = save_specimen(ds, tmp_path / "spec.csv")
    user = tmp_path / "my_effect.py"
    user.write_text(
        "import hbm\n"
        "class Zero(hbm.Effect):\n"
        "    name = 'my_zero'\n"
        "    stage = 'output'\n"
        "    parameters = (hbm.Parameter('Z0', -0.02, 0.02, 'MPa', 'zero shift', null=0.0),)\n"
        "    def modify(self, state, p, stress):\n"
        "        return stress + p['Z0']\n")
    rc = cli.main(["diagnose", str(path), "--candidates", "viscoelastic", "--candidate", f"{user}:Zero",
                   "--samples", "250", "--json", "--plot", str(tmp_path / "d.png")])
    out = capsys.readouterr().out
    assert rc == 0
    d = json.loads(out)  # exactly one object (json.loads fails on trailing data)
    assert d["verdict"] == "effect" and d["selected"] == ["my_zero"]
    assert {c["effect"] for c in d["candidates"]} == {"viscoelastic", "my_zero", "local_misfit", "local_step",
                                                      "local_kink", "time_trend", "time_step", "periodic"}
    assert {c["effect"] for c in d["candidates"] if c["physical"]} == {"viscoelastic", "my_zero"}
    assert (tmp_path / "d.png").stat().st_size > 10_000
    rc = cli.main(["extend", str(path), "--add", "offset", "--samples", "250", "--json"])
    e = json.loads(capsys.readouterr().out)
    assert rc == 0 and [s["effects"] for s in e["steps"]] == [[], ["offset"]]
    assert e["steps"][1]["rmse"] < e["steps"][0]["rmse"]
    rc = cli.main(["diagnose", str(path), "--candidates", "no_such_effect"])
    assert rc == 2 and "no_such_effect" in capsys.readouterr().err


# ------------------------------------------------------------------------------------------
# multi-seed validations (slow)
# ------------------------------------------------------------------------------------------
@pytest.mark.slow
@pytest.mark.parametrize("noise", ["iid", "ar1"])
def test_false_alarm_rate_clean_data(noise):
    """Clean data, all eight candidates: 'adequate' in ≥ 90 % of seeds (iid and AR(1) ρ = 0.6)."""
    seeds = range(100, 110)
    alarms = []
    for s in seeds:
        ds, _, _ = hidden("clean", s, noise=noise, rho=0.6, n=40)
        dg = diagnose(ds, seed=s, n_samples=400)
        alarms.append(dg.verdict != "adequate")
    assert np.mean(alarms) <= 0.10, alarms


@pytest.mark.slow
@pytest.mark.parametrize("kind,ok", [
    ("offset", lambda dg: dg.verdict == "effect" and dg.selected == ["offset"]),
    ("viscoelastic", lambda dg: dg.verdict == "effect" and dg.selected == ["viscoelastic"]),
    ("damage", lambda dg: dg.verdict == "effect" and dg.selected == ["damage"]),
    ("slack", lambda dg: (dg.verdict == "effect" and dg.selected == ["slack"])
     or (dg.verdict == "group" and "slack" in dg.group)),
])
def test_hidden_effect_is_named(kind, ok):
    # n=50 points per test (75 for the single offset ramp).  Power limit measured: an offset of
    # 3.3 noise sd on a 60-point ramp was named in 1 of 3 seeds (the base model absorbs ~85 %
    # of its signature), so the hidden effects here are ≈ 4-5 sd.
    hits = []
    for s in (21, 22, 23):
        ds, fix, _ = hidden(kind, s, n=50)
        dg = diagnose(ds, fix=fix, seed=s, n_samples=500)
        hits.append(bool(ok(dg)))
    assert sum(hits) >= 2, hits


@pytest.mark.slow
def test_unknown_effect_is_unexplained_with_the_right_window():
    hits = []
    for s in (31, 32, 33):
        ds, _, _ = hidden("unknown", s, n=50)
        dg = diagnose(ds, seed=s, n_samples=500)
        if dg.verdict == "unexplained":
            import re
            a, b = map(float, re.search(r"\[([-0-9.]+), ([-0-9.]+)\]", dg.message).groups())
            hits.append(a < 0.21 and b > 0.17)   # overlaps the bump's core (0.15–0.23)
        else:
            hits.append(False)
    assert sum(hits) >= 2, hits


@pytest.mark.slow
@pytest.mark.parametrize("kind,effect", [("damage", "damage"), ("offset", "offset")])
def test_extend_reaches_noise_level_several_seeds(kind, effect):
    for s in (41, 42):
        ds, fix, sd = hidden(kind, s, n=40)
        ext = extend(ds, add=[effect], fix=fix, seed=s, n_samples=400)
        assert ext.steps[-1].rmse < 1.15 * sd
        assert ext.steps[-1].rmse < ext.steps[0].rmse
