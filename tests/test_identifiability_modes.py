"""What a specimen's tests identify (issue 35 item 5, hbm.identifiability.modes): the Jacobian against
tests/independent3d.py, the Fisher numbers of the recorded loading-mode design, the structural Voigt null
space in every set of homogeneous tests, and the report/JSON/netCDF hooks -- no TMCMC (the analysis takes
a point and the likelihood)."""

from __future__ import annotations

import functools
import json
import sys
from pathlib import Path

import numpy as np
import pytest

from hbm.data import load_specimen
from hbm.fit.modes import ModesFit, _identifiability
from hbm.identifiability.modes import series_jacobians, linearised_identifiability
from hbm.io.modes import read_modes_observed, write_modes_result
from hbm.likelihood.modes import TEST_SCALE_SD, make_modes_likelihood
from hbm.model import spyrou_model
from hbm.model.energy3d import Energy3D
from hbm.model.loadcases import LOAD_CASES, predict_observables
from hbm.model.spec import spec_of

sys.path.insert(0, str(Path(__file__).resolve().parent))
import independent3d as ind  # noqa: E402

ENERGY = spyrou_model(form="energy")
#: the shipped calvo2010_rat1 generating parameters (its file's "# parameters:" line)
RAT1 = dict(VOLF=0.9, EOPT=0.184, P1=0.13, T1=1.5, T2=9.3, THETA=60.0, GF=0.012, GM=0.009)


def _write(path, tests, prm, n=None) -> None:
    """A specimen CSV: ``tests`` = [(mode, strains, observables)], values from hbm's own model at ``prm``
    (only the noise sds, 2 % of each series' largest |value|, enter the Fisher information)."""
    cone = Energy3D(collagen3d="cone")
    cols = ["stress_2", "strain_f"]
    lines = ["# id: design", "strain,stress,test,mode," + ",".join(cols)]
    for k, (mode, strains, names) in enumerate(tests):
        out = predict_observables(cone, mode, {q: np.array([[v]]) for q, v in prm.items()}, strains)
        for j, e in enumerate(strains):
            extra = [repr(float(out[c][0, j])) if c in names else "" for c in cols]
            lines.append(",".join([repr(float(e)), repr(float(out["stress"][0, j])), str(k), mode, *extra]))
    Path(path).write_text("\n".join(lines) + "\n")


def _likelihood_at(path, prm, noise=0.02):
    """The likelihood of the file and the row at ``prm`` with each kind's σ = ``noise`` × its largest |value|."""
    lik = make_modes_likelihood(ENERGY, load_specimen(path))
    row = np.r_[[prm[n] for n in lik.model_names], np.zeros(len(lik.kinds))]
    top = dict.fromkeys(lik.kinds, 0.0)
    for s, m in zip(lik.series, lik.predict_series(row[None])):
        top[s.kind] = max(top[s.kind], float(np.abs(m).max()))
    row[lik.n_model:] = np.log([noise * top[k] for k in lik.kinds])
    return lik, row


def test_jacobian_matches_independent_finite_differences(tmp_path):
    """Every series' Jacobian (one batched predict_series call) against central differences of the
    independent implementation, in all four kinds of solve (free lateral root, shear, prescribed F)."""
    tests = [("uniaxial_f", np.array([0.1, 0.25]), ()), ("uniaxial_c", np.array([0.12]), ("strain_f",)),
             ("shear_fc", np.array([0.2]), ()), ("planar_c_hold_n", np.array([0.15]), ("stress_2",))]
    _write(tmp_path / "j.csv", tests, ind.CALVO)
    lik, row = _likelihood_at(tmp_path / "j.csv", ind.CALVO)
    calls = []
    orig = lik.predict_series
    lik.predict_series = lambda theta: calls.append(np.shape(theta)) or orig(theta)
    J, _, _ = series_jacobians(lik, row)
    assert calls == [(16, lik.d)]                      # one call over all 2 x 8 rows
    assert [s.name for s in lik.series] == ["stress[0]", "stress[1]", "strain_f[1]", "stress[2]", "stress[3]",
                                            "stress_2[3]"]
    @functools.cache
    def independent(mode, e, name, sign):   # every observable of one (mode, strain, perturbation)
        prm = dict(ind.CALVO)
        prm[name] += sign * 1e-4 * ind.CALVO[name]
        return ind.predict(mode, e, prm, "cone")

    for s, Js in zip(lik.series, J):
        for j, e in enumerate(lik.data.strain[s.rows]):
            mode, e = s.test.load_case, float(e)
            ref = [(independent(mode, e, n, 1)[s.observable] - independent(mode, e, n, -1)[s.observable])
                   / (2e-4 * ind.CALVO[n]) for n in lik.model_names]
            np.testing.assert_allclose(Js[j], ref, rtol=2e-5, atol=1e-6 * np.max(np.abs(ref)),
                                       err_msg=f"{s.name} at {e}")


#: the recorded design of workflows/benchmarks/loadcases.py (DESIGNS, fisher_table): 40 points per series
#: from top/40 to top; along-fibre tension and the shears to 44 %, the other stretch modes to 20 %
def _design(name):
    along = [("uniaxial_f", 0.44, ())]
    cross = along + [("uniaxial_c", 0.20, ())]
    shear = cross + [("shear_fc", 0.44, ())]
    every = [(m, 0.44 if m == "uniaxial_f" or m.startswith("shear") else 0.20,
              tuple(o.name for o in LOAD_CASES[m].observables if o.is_stress and o.name != "stress"))
             for m in LOAD_CASES]
    chosen = {"along": along, "cross": cross, "shear": shear, "every": every}[name]
    return [(m, np.linspace(top / 40, top, 40), names) for m, top, names in chosen]


#: data-only sd of (ln (1-VOLF)*T1, ln T2): DESIGN.md §8 states the along-fibre values as ≈ 10 and ≈ 9;
#: the rest are results/benchmarks/loadcases.md's table for this design (6-D φ space, its own Jacobian)
RECORDED = {"along": ((10.0, 0.5), (9.0, 0.5)), "cross": ((0.147, 0.002), (0.0876, 0.001)),
            "shear": ((0.0624, 0.001), (0.0315, 0.0005)), "every": ((0.00952, 0.0001), (0.00601, 0.0001))}


@pytest.mark.parametrize("design", list(RECORDED))
def test_fisher_numbers_of_the_recorded_design(tmp_path, design):
    _write(tmp_path / "d.csv", _design(design), RAT1)
    lik, row = _likelihood_at(tmp_path / "d.csv", RAT1)
    r = linearised_identifiability(lik, row)
    amp, rate = (r.quantity(n) for n in ("(1-VOLF)*T1", "T2"))
    assert amp["scale"] == rate["scale"] == "ln"
    (a0, ta), (r0, tr) = RECORDED[design]
    assert abs(amp["sd_data"] - a0) <= ta and abs(rate["sd_data"] - r0) <= tr, (amp["sd_data"], rate["sd_data"])
    assert r.n_structural == 2 and r.rank <= 6
    for q in r.quantities:   # the box regularises: never wider than the data alone or the box alone
        assert q["sd_all"] <= min(q["sd_data"], q["sd_prior"]) * (1 + 1e-9)
    # each test's contribution: alone it is no better than all together; leaving one out never helps
    for q in r.quantities:
        for t in q["sd_alone"]:
            assert q["sd_alone"][t] >= q["sd_all"] * (1 - 1e-9) and q["width_added"][t] >= 1 - 1e-9
    if design == "cross":   # the cross-fibre test is what pins the collagen: it adds > 20x to both
        assert amp["width_added"][1] > 20 and rate["width_added"][1] > 20
        assert not amp["prior_dominated"] and not rate["prior_dominated"]


def test_no_homogeneous_test_separates_the_voigt_parameters(tmp_path):
    """Each mode alone and all modes together: the two Voigt directions are null (rank <= 6 of 8), they
    involve exactly the fraction, the two amplitudes it scales and the two shear moduli, and the report
    says why in the spec's words."""
    spec = spec_of(ENERGY)
    roles = spec.mixture
    sets = [[(m, np.linspace(0.05, 0.4, 6), ())] for m in LOAD_CASES]
    sets.append([(m, np.linspace(0.05, 0.4, 6), ()) for m in LOAD_CASES])
    for k, tests in enumerate(sets):
        _write(tmp_path / f"m{k}.csv", tests, RAT1)
        lik, row = _likelihood_at(tmp_path / f"m{k}.csv", RAT1)
        r = linearised_identifiability(lik, row)
        assert r.n_structural == 2 and r.rank <= 6, (tests[0][0], r.rank)
        assert set(r.structural_parameters) == set(roles.params), r.structural_parameters
        assert spec.texts["modes_structural"] in "\n".join(r.report_lines())


def test_one_along_fibre_test_leaves_the_collagen_amplitude_rate_direction(tmp_path):
    _write(tmp_path / "f.csv", [("uniaxial_f", np.linspace(0.02, 0.44, 20), ())], RAT1)
    lik, row = _likelihood_at(tmp_path / "f.csv", RAT1)
    r = linearised_identifiability(lik, row)
    weak = [u for u in r.unidentified if not u["structural"]]
    assert len(weak) == 1 and r.rank == 5
    roles = spec_of(ENERGY).mixture
    assert set(list(weak[0]["loadings"])[:2]) == {roles.matrix, "T2"}, weak[0]
    dominated = {q["name"] for q in r.quantities if q["prior_dominated"]}
    assert {"(1-VOLF)*T1", "T2"} <= dominated and "G" not in dominated and "VOLF*P1" not in dominated
    text = "\n".join(r.report_lines())
    assert "unidentified by these tests" in text and "prior-dominated" in text
    assert "linearised Fisher analysis at the given point" in text
    # a per-test stress scale (prior sd 0.05) multiplies every term: ln s + δ with every ln amplitude − δ is
    # null in the data, so the scale's prior adds in quadrature to each amplitude's sd
    scaled = make_modes_likelihood(ENERGY, lik.data, test_scale=True)
    rs = linearised_identifiability(scaled, np.r_[row, 1.0])
    assert rs.parameters[-1] == "scale_test0"
    for name in ("G", "VOLF*P1"):
        a, b = r.quantity(name)["sd_data"], rs.quantity(name)["sd_data"]
        assert b == pytest.approx(np.hypot(a, TEST_SCALE_SD), rel=0.02), (name, a, b)
        assert not rs.quantity(name)["prior_dominated"]


def test_fit_report_json_and_result_file(tmp_path):
    """The hooks, without TMCMC: a ModesFit of draws scattered round the generating point gets the
    section in its report, a JSON-able summary and the result file's attribute; the posterior sd is
    printed beside the linearised one."""
    tests = [("uniaxial_f", np.linspace(0.05, 0.4, 8), ()), ("uniaxial_c", np.linspace(0.04, 0.2, 6), ()),
             ("shear_fc", np.linspace(0.05, 0.3, 6), ())]
    _write(tmp_path / "s.csv", tests, RAT1)
    lik, row = _likelihood_at(tmp_path / "s.csv", RAT1)
    rng = np.random.default_rng(0)
    y = np.clip(row + 1e-3 * (lik.bounds[:, 1] - lik.bounds[:, 0]) * rng.standard_normal((50, lik.d)),
                lik.bounds[:, 0], lik.bounds[:, 1])
    ll = lik(y)
    pred = lik.predict_series(y)
    fit = ModesFit(lik, lik.to_natural(y), ll, 0.0, 0.0, pred, pred, lik.pointwise(y, pred), 50, [], {})
    fit.identifiability = _identifiability(fit)
    ident = fit.identifiability
    assert ident.point.startswith("the highest-likelihood draw")
    best = lik.to_natural(y[np.argmax(ll)])
    amp = ident.quantity("(1-VOLF)*T1")
    assert amp["value"] == pytest.approx((1 - best[0]) * best[lik.index("T1")], rel=1e-12)
    v = np.log(fit.combinations()["(1-VOLF)*T1"])
    assert amp["sd_posterior"] == pytest.approx(v.std(), rel=1e-12)
    text = fit.report()
    assert "what the tests identify (linearised Fisher analysis at the highest-likelihood draw" in text
    assert "posterior draws" in text and "x, test 1 [uniaxial_c]" in text
    blob = json.loads(json.dumps(ident.to_dict()))
    assert blob["rank"] == ident.rank and blob["n_structural"] == 2
    write_modes_result(fit, tmp_path / "r.nc", {"samples": 50})
    stored = json.loads(read_modes_observed(tmp_path / "r.nc")["/"].attrs["identifiability"])
    assert stored["quantities"][2]["sd_all"] == pytest.approx(ident.quantities[2]["sd_all"], rel=1e-12)
