"""Effects per test in the loading modes (issue 35 item 2, hbm.model.modes_effects): QLV on each stress
observable's own history against a direct quadrature of the hereditary integral over tests/independent3d.py's
elastic response, offsets per stress observable, the along-fibre identity, and the refusals."""

from __future__ import annotations

import math
import sys
from pathlib import Path

import numpy as np
import pytest
from scipy.integrate import quad

from hbm.cli import main
from hbm.data import load_specimen
from hbm.effects import make_effect
from hbm.errors import HbmError, HbmWarning
from hbm.fit.simulate import simulate_tests
from hbm.likelihood.modes import make_modes_likelihood
from hbm.model import spyrou_model

sys.path.insert(0, str(Path(__file__).resolve().parent))
import independent3d as ind  # noqa: E402

ENERGY = spyrou_model(form="energy")
PRM = dict(ind.CALVO, T2=20.0)
#: a ramp (0 -> 10 s) then a hold (-> 200 s), as two tests of one history; the time restarts for the next pair
RAMP_T = np.linspace(0.0, 10.0, 6)
HOLD_T = np.array([12.0, 20.0, 40.0, 80.0, 140.0, 200.0])
PEAK = 0.12


def _rows(mode, first_test):
    """``strain,time,test,mode`` rows of a ramp+hold pair, with its strain and time."""
    # from 2 %: near λ = 1 the independent implementation's difference stencil straddles the slack kink (off by 1e-6 MPa at 0)
    strain = np.r_[0.02 + (PEAK - 0.02) * RAMP_T / RAMP_T[-1], np.full(HOLD_T.size, PEAK)]
    time = np.r_[RAMP_T, HOLD_T]
    test = np.r_[np.full(RAMP_T.size, first_test), np.full(HOLD_T.size, first_test + 1)]
    return [f"{e!r},{t!r},{k},{mode}" for e, t, k in zip(strain.tolist(), time.tolist(), test.tolist())], strain, time


def _csv(path, parts, measured=("stress",)):
    """parts: (mode, first test id); measured columns filled on every row (per mode, blank if the mode lacks it)."""
    lines = ["# id: qlv_modes", "strain,time,test,mode," + ",".join(measured)]
    for mode, k, own in parts:
        rows, _, _ = _rows(mode, k)
        # the measured values do not enter the predictions; an empty cell is "not measured"
        lines += [r + "," + ",".join("0.001" if m in own else "" for m in measured) for r in rows]
    path.write_text("\n".join(lines) + "\n")
    return load_specimen(path)


def _direct_qlv(t, s_e, g, tau):
    """σ(t_k) = G(t_k − t_0)·σ_e(t_0) + Σ_j (Δσ_e/Δt)_j ∫_{t_{j−1}}^{t_j} G(t_k − s) ds, σ_e linear between points,
    each integral by adaptive quadrature (no recursion: independent of the kernel)."""
    G = lambda x: 1.0 - g * (1.0 - math.exp(-x / tau))  # noqa: E731
    out = []
    for k in range(t.size):
        total = G(t[k] - t[0]) * s_e[0]
        for j in range(1, k + 1):
            rate = (s_e[j] - s_e[j - 1]) / (t[j] - t[j - 1])
            total += rate * quad(lambda s: G(t[k] - s), t[j - 1], t[j], epsabs=0, epsrel=1e-12)[0]
        out.append(total)
    return np.array(out)


def _row(lik, values):
    return np.array([[values[n] if n in values else 0.01 for n in lik.names]])


@pytest.fixture(scope="module")
def cross(tmp_path_factory):
    """uniaxial_c ramp+hold (stress, strain_f measured), then planar_c_hold_f ramp+hold (stress, stress_2)."""
    path = tmp_path_factory.mktemp("qlv") / "cross.csv"
    return _csv(path, [("uniaxial_c", 0, {"stress", "strain_f"}), ("planar_c_hold_f", 2, {"stress", "stress_2"})],
                measured=("stress", "stress_2", "strain_f"))


@pytest.fixture(scope="module")
def elastic_truth():
    """The independent implementation's elastic observables at the ramp/hold strains (gst: closed form)."""
    _, strain, time = _rows("x", 0)
    uc = [ind.predict("uniaxial_c", float(e), PRM, "gst") for e in strain]
    pl = [ind.predict("planar_c_hold_f", float(e), PRM, "gst") for e in strain]
    return time, {"uc": {k: np.array([d[k] for d in uc]) for k in uc[0]},
                  "pl": {k: np.array([d[k] for d in pl]) for k in pl[0]}}


def test_qlv_and_offsets_per_observable_in_cross_fibre_ramp_hold(cross, elastic_truth):
    model = ENERGY + make_effect("viscoelastic") + make_effect("offset")
    lik = make_modes_likelihood(model, cross, collagen3d="gst")
    assert {"G1", "LOGTAU1", "S0", "S0_2"} <= set(lik.names)   # one load-cell zero per stress observable
    time, truth = elastic_truth
    # three particles at once (vectorised over particles x points), each checked against the direct integral
    particles = [dict(G1=0.6, LOGTAU1=1.0, S0=2e-3, S0_2=-1e-3), dict(G1=0.3, LOGTAU1=0.2, S0=0.0, S0_2=5e-3),
                 dict(G1=0.85, LOGTAU1=2.4, S0=-4e-3, S0_2=0.0)]
    rows = np.vstack([_row(lik, {**PRM, **q}) for q in particles])
    pred = lik.predict_series(rows)
    got = {(s.test.id, s.observable): m for s, m in zip(lik.series, pred)}
    n = RAMP_T.size
    for i, q in enumerate(particles):
        tau = 10.0 ** q["LOGTAU1"]
        for key, first, obs, s0 in (("uc", 0, "stress", "S0"), ("pl", 2, "stress", "S0"),
                                    ("pl", 2, "stress_2", "S0_2")):
            want = _direct_qlv(time, truth[key][obs], q["G1"], tau) + q[s0]
            have = np.r_[got[(first, obs)][i], got[(first + 1, obs)][i]]
            np.testing.assert_allclose(have, want, rtol=2e-6, atol=1e-9)
        # kinematics stay elastic: the lateral strain is the elastic solve's at every time (module docstring)
        have = np.r_[got[(0, "strain_f")][i], got[(1, "strain_f")][i]]
        np.testing.assert_allclose(have, truth["uc"]["strain_f"], rtol=1e-6, atol=1e-12)
    # the hold relaxes: over 190 s at tau = 10 s the stress falls towards g_inf = 0.4 of the elastic value
    hold = got[(1, "stress")][0] - particles[0]["S0"]
    assert hold[-1] / truth["uc"]["stress"][-1] == pytest.approx(0.4, abs=1e-6)
    # the same numbers from hbm simulate (one row)
    sim = simulate_tests(cross, {**PRM, **particles[0]}, model=model, collagen3d="gst")
    np.testing.assert_allclose(sim["stress_2_model"][2 * n:], np.r_[got[(2, "stress_2")][0], got[(3, "stress_2")][0]],
                               rtol=1e-13)


def test_along_fibre_per_test_equals_the_1d_effect(tmp_path):
    """uniaxial_f ramp+hold, twice (two histories): the modes likelihood's per-test application equals
    Model.stress with the along-fibre effects to round-off (QLV with two relaxation times, an offset; and an
    along-fibre-only effect, slack, through the 1-D path)."""
    spec = _csv(tmp_path / "f.csv", [("uniaxial_f", 0, {"stress"}), ("uniaxial_f", 2, {"stress"})])
    rng = np.random.default_rng(7)
    for effects in (("viscoelastic", "viscoelastic_2", "offset"), ("slack", "viscoelastic")):
        model = ENERGY.with_effects(*[make_effect(e) for e in effects])
        lik = make_modes_likelihood(model, spec)
        theta = rng.uniform(model.bounds[:, 0], model.bounds[:, 1], size=(5, model.n_params))
        theta[:, model.index("T2")] = rng.uniform(1.0, 30.0, 5)
        rows = np.hstack([theta, np.full((5, lik.d - model.n_params), 0.01)])
        pred = np.hstack(lik.predict_series(rows))
        want = model.stress(spec.loading, theta)
        np.testing.assert_allclose(pred, want, rtol=1e-11, atol=1e-15)


def test_refusals(tmp_path, cross, capsys):
    with pytest.raises(HbmError, match=r"qlv_modes: effect 'damage' is not defined in mode uniaxial_c \(stress\): "
                                       "its softening is driven by the running maximum of the along-fibre stress"):
        make_modes_likelihood(ENERGY + make_effect("damage"), cross)
    # along the fibres an along-fibre effect is refused for the lateral strain it does not know
    f = _csv(tmp_path / "lat.csv", [("uniaxial_f", 0, {"stress", "strain_c"})], measured=("stress", "strain_c"))
    with pytest.raises(HbmError, match=r"effect 'slack' is not defined in mode uniaxial_f \(strain_c\)"):
        make_modes_likelihood(ENERGY + make_effect("slack"), f)
    make_modes_likelihood(ENERGY + make_effect("viscoelastic"), f)   # QLV passes strains untouched
    # a history that continues into another mode
    path = tmp_path / "mixed.csv"
    rows_a, _, _ = _rows("uniaxial_f", 0)
    rows_b, _, _ = _rows("uniaxial_c", 0)
    cont = []
    for r in rows_b[RAMP_T.size:]:   # the hold rows as test 1 in another mode, the time continuing
        e, t, _, m = r.split(",")
        cont.append(f"{e},{t},1,{m}")
    path.write_text("# id: mixed\nstrain,time,test,mode,stress\n"
                    + "\n".join(r + ",0.001" for r in rows_a[: RAMP_T.size] + cont) + "\n")
    with pytest.raises(HbmError, match=r"tests 0 \(uniaxial_f\) and 1 \(uniaxial_c\) are one loading history"):
        make_modes_likelihood(ENERGY + make_effect("viscoelastic"), load_specimen(path))
    make_modes_likelihood(ENERGY + make_effect("offset"), load_specimen(path))  # pointwise: no history needed
    # no time column: refused when the likelihood is built, not inside the sampler
    notime = tmp_path / "notime.csv"
    notime.write_text("# id: nt\nstrain,test,mode,stress\n"
                      + "".join(f"{0.02 * k},0,uniaxial_c,0.001\n" for k in range(1, 7)))
    with pytest.raises(HbmError, match="viscoelastic effect needs a 'time' column"):
        make_modes_likelihood(ENERGY + make_effect("viscoelastic"), load_specimen(notime))
    # the CLI: one line, exit 2, before any computation
    rc = main(["fit", str(tmp_path / "lat.csv"), "--form", "energy", "--effect", "prestress", "--no-progress",
               "--out", str(tmp_path / "r.nc")])
    err = capsys.readouterr().err
    assert rc == 2 and err.count("\n") == 1 and not (tmp_path / "r.nc").exists()
    assert err.startswith("hbm: error: qlv_modes: effect 'prestress' is not defined in mode uniaxial_f (strain_c): ")


def test_fit_with_qlv_writes_its_result(tmp_path, cross):
    from hbm.fit.modes import fit_modes

    with pytest.warns(HbmWarning, match="the evaluation cap"):   # a smoke budget: the wiring, not the posterior
        fit = fit_modes(cross, model=ENERGY + make_effect("viscoelastic") + make_effect("offset"),
                        collagen3d="gst", samples=60, max_evaluations=400, progress=False, out=tmp_path / "q.nc")
    assert fit.path.exists() and "S0_2" in fit.names and np.isfinite(fit.log_likelihood).all()


def test_cli_simulate_with_effects(tmp_path, cross, capsys):
    theta = {**PRM, "G1": 0.6, "LOGTAU1": 1.0, "S0": 2e-3, "S0_2": -1e-3}
    args = ["simulate", cross.source_file, "--form", "energy", "--collagen3d", "gst", "--effect", "viscoelastic",
            "--effect", "offset", "--theta", ",".join(f"{k}={v!r}" for k, v in theta.items())]
    assert main(args + ["--out", str(tmp_path / "s.csv")]) == 0
    lines = [ln for ln in (tmp_path / "s.csv").read_text().splitlines() if not ln.startswith("#")]
    col = lines[0].split(",").index("stress_2_model")
    got = np.array([float(ln.split(",")[col] or "nan") for ln in lines[1:]])
    want = simulate_tests(cross, theta, model=ENERGY + make_effect("viscoelastic") + make_effect("offset"),
                          collagen3d="gst")["stress_2_model"]
    np.testing.assert_allclose(got, want, rtol=1e-12)
    assert np.isnan(got[: 2 * RAMP_T.size]).all() and np.isfinite(got[2 * RAMP_T.size:]).all()
    capsys.readouterr()
    damage = ",".join(f"{k}={v!r}" for k, v in {**PRM, "DMG": 0.1}.items())
    assert main(args[:6] + ["--effect", "damage", "--theta", damage, "--out", str(tmp_path / "d.csv")]) == 2
    assert not (tmp_path / "d.csv").exists()
    assert capsys.readouterr().err.startswith("hbm: error: simulate: effect 'damage' is not defined in mode uniaxial_c")
