"""Fit quality first: at_bounds, map_estimate, fit_quality, FitResult.report/to_json, the fit figure."""

from __future__ import annotations

import json

import numpy as np
import pytest
import xarray as xr

from hbm import io
from hbm.data import Series, Specimen
from hbm.fit import FitResult, RIDGE_NOTE, at_bounds, fit_quality, map_estimate, summary_table
from hbm.io import SpecimenResult


def _tiny(prior=None, optima=None):
    """3 posterior samples, 4 points, hand-set predictions (numbers chosen for hand computation)."""
    samples = np.array([[1.0, 0.10], [2.0, 0.20], [3.0, 0.30]])  # columns: A, sigma
    ll = np.array([-5.0, -1.0, -3.0])  # sample 1 is the best
    pm = np.array([[1.0, 2.0, 3.0, 4.0],
                   [1.5, 2.5, 2.5, 3.0],
                   [0.0, 0.0, 0.0, 0.0]])
    stress = np.array([1.0, 2.0, 3.0, -5.0])
    # predictive replicates: 21 rows per point 0..20 -> 5 % / 95 % quantiles 1 and 19
    pred = np.tile(np.arange(21.0)[:, None], (1, 4))
    pred[:, 3] -= 30.0  # point 3 band [-29, -11]: stress -5 is outside
    pred[:, 0] += 0.5   # point 0 band [1.5, 19.5]: stress 1 is outside
    return SpecimenResult(specimen_id="tiny", names=["A", "sigma"], samples=samples, log_likelihood=ll,
                          log_evidence=-2.5, log_evidence_se=0.25, bounds=np.array([[0.0, 4.0], [0.0, 1.0]]),
                          data=Specimen("tiny", np.linspace(0, 0.3, 4), observed={"stress": Series.known("stress", stress)}),
                          predictive=pred, predictive_model=pm,
                          config={"noise": "iid"}, optima=optima, prior=prior)


def test_rmse_coverage_map_against_hand_computation():
    q = fit_quality(_tiny())
    # MAP = best sample (index 1); residuals 0.5, 0.5, -0.5, 8 -> RMSE sqrt((0.25*3 + 64)/4)
    rmse = np.sqrt((0.25 * 3 + 64.0) / 4)
    assert q["rmse"] == pytest.approx(rmse, rel=1e-14)
    assert q["rmse_rel"] == pytest.approx(rmse / 5.0, rel=1e-14)  # a fraction, like coverage90
    # points 1 and 2 are inside [1, 19]; 0 and 3 are not
    assert q["coverage90"] == 0.5
    assert q["map"] == {"A": 2.0, "sigma": 0.2} and q["map_source"] == "sample"
    assert q["noise"]["sigma"]["map"] == 0.2 and q["noise"]["sigma"]["median"] == pytest.approx(0.2)
    assert (q["log_evidence"], q["log_evidence_se"]) == (-2.5, 0.25)
    # data passed explicitly win over the stored curve
    ds = xr.Dataset({"stress": ("point", [1.5, 2.5, 2.5, 3.0]), "strain": ("point", np.linspace(0, 0.3, 4))})
    assert fit_quality(_tiny(), ds)["rmse"] == 0.0


def test_map_prefers_a_better_optimum():
    opt = [{"params": {"A": 2.5, "sigma": 0.15}, "objective": 0.5, "kind": "restart"},   # ll -0.5 > -1
           {"params": {"A": 3.9, "sigma": 0.15}, "objective": 7.0, "kind": "restart"}]
    r = _tiny(optima=opt)
    assert map_estimate(r) == {"A": 2.5, "sigma": 0.15}
    q = fit_quality(r)
    assert q["map_source"] == "optimum" and q["map_log_likelihood"] == -0.5
    # no model at hand: the best sample's stored prediction stands in for the RMSE
    assert q["rmse"] == pytest.approx(np.sqrt((0.25 * 3 + 64.0) / 4))


def test_at_bounds_known_fractions():
    rng = np.random.default_rng(0)
    n = 1000
    # A in [0, 4]: 300 samples within 2 % (0.08) of the upper edge, the rest in the middle
    a = np.r_[4.0 - 0.07 * rng.random(300), 1.0 + 2.0 * rng.random(700)]
    # GF loguniform [1e-4, 1]: log width 9.21, 2 % = 0.184 -> 150 samples below 1e-4 * e^0.18 (< 20 %)
    s = np.r_[1e-4 * np.exp(0.18 * rng.random(150)), 1e-2 * np.exp(rng.random(850))]
    ll = np.zeros(n)
    ll[0] = 1.0  # the MAP: a sample with A at the edge, GF at its lower edge
    r = SpecimenResult(specimen_id="edge", names=["A", "GF"], samples=np.c_[a, s], log_likelihood=ll,
                       log_evidence=0.0, log_evidence_se=0.0, bounds=np.array([[0.0, 4.0], [1e-4, 1.0]]),
                       prior={"A": {"lo": 0.0, "hi": 4.0, "form": "uniform"},
                              "GF": {"lo": 1e-4, "hi": 1.0, "form": "loguniform"}})
    got = at_bounds(r)
    assert got == [{"parameter": "A", "side": "upper", "edge": 4.0, "fraction": 0.3, "map_at_edge": True},
                   {"parameter": "GF", "side": "lower", "edge": 1e-4, "fraction": 0.15, "map_at_edge": True}]
    # GF uniform on the same box: 2 % of the width -> the draws below 1e-4 + 0.02 (1 - 1e-4)
    r.prior["GF"]["form"] = "uniform"
    g2 = {x["parameter"]: x for x in at_bounds(r)}
    assert g2["GF"]["fraction"] == pytest.approx(np.mean(s <= 1e-4 + 0.02 * (1 - 1e-4)))
    # nothing at an edge: empty; a 20 % pile (not more) without the MAP there is not reported
    r.samples[:, 0] = np.r_[np.full(200, 3.99), np.full(800, 2.0)]
    r.log_likelihood = np.r_[np.zeros(200), np.ones(800)]
    r.prior["GF"]["form"] = "loguniform"
    r.samples[:, 1] = 0.01
    assert at_bounds(r) == []
    # noise parameters only on request: a sigma piled on its floor
    r.names = ["A", "sigma"]
    r.prior["sigma"] = r.prior.pop("GF")
    r.samples[:, 1] = 1e-4
    assert at_bounds(r) == []
    assert [x["parameter"] for x in at_bounds(r, noise=True)] == ["sigma"]
    table = summary_table(_tiny(prior=None))
    assert "prior: A U[0, 4], sigma U[0, 1]" in table


def test_report_and_json_lead_with_fit_quality(tmp_path):
    r = _tiny()
    r.at_bounds = at_bounds(r)
    fr = FitResult(result=r, path=None, likelihood=None)
    text = fr.report()
    lines = text.splitlines()
    assert lines[1].startswith("fit quality: RMSE")
    i_note = lines.index(RIDGE_NOTE)
    assert all(not ln.startswith("A ") for ln in lines[:i_note])  # raw table after the note
    assert lines[i_note + 2].split()[0] == "A"
    js = fr.to_json()
    json.dumps(js)
    for key in ("rmse", "rmse_rel", "coverage90", "log_evidence", "log_evidence_se", "map", "combinations",
                "at_bounds"):
        assert key in js
    assert js["map"] == {"A": 2.0, "sigma": 0.2} and js["coverage90"] == 0.5
    # at_bounds is stored with the file and read back (the 21 replicates do not fit 3 draws: dropped)
    r.predictive = r.predictive_model = None
    p = io.write_specimen_result(r, tmp_path / "tiny.nc")
    back = io.read_specimen_result(p)
    assert back.at_bounds == r.at_bounds and back.prior_dict() == r.prior_dict()
    assert io.read_attrs(p)["prior"]["A"] == {"lo": 0.0, "hi": 4.0, "form": "uniform"}


def test_fit_figure_writes_a_file(tmp_path):
    from hbm.plots.fit import fit_plot

    r = _tiny()
    untimed = r.data
    r.data = Specimen("tiny", untimed.strain, np.array([0.0, 1.0, 2.0, 3.0]), observed=untimed.observed)
    p = fit_plot(FitResult(result=r, path=None, likelihood=None), path=tmp_path / "fit.png")
    assert p.stat().st_size > 1000
    r.data = untimed
    p = fit_plot(r, path=tmp_path / "fit2.png")
    assert p.stat().st_size > 1000
