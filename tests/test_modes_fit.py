"""The joint likelihood across loading modes and the fit (issue 35, items 4, 5, 7), against tests/independent3d.py."""

from __future__ import annotations

import json
import math
import sys
from pathlib import Path

import numpy as np
import pytest

from hbm.cli import main
from hbm.data import load_specimen
from hbm.effects import make_effect
from hbm.errors import HbmError
from hbm.fit.modes import fit_modes
from hbm.likelihood import make_likelihood
from hbm.likelihood.modes import TEST_SCALE_SD, is_multimode, make_modes_likelihood
from hbm.model import spyrou_model

sys.path.insert(0, str(Path(__file__).resolve().parent))
import independent3d as ind  # noqa: E402

ENERGY = spyrou_model(form="energy")
SMALL = (("uniaxial_f", np.array([0.05, 0.15, 0.25])), ("uniaxial_c", np.array([0.04, 0.12])),
         ("shear_fc", np.array([0.1, 0.2])))


@pytest.fixture(scope="module")
def small(tmp_path_factory):
    path = tmp_path_factory.mktemp("modes") / "small.csv"
    ind.synthetic_csv(path, 3, tests=SMALL)
    return load_specimen(path)


def _row(lik, prm, sigmas):
    return np.r_[[prm[n] for n in lik.model_names], np.log(sigmas)]


def test_loglik_matches_independent(small):
    lik = make_modes_likelihood(ENERGY, small)
    assert lik.kinds == ("uniaxial_f.stress", "uniaxial_c.stress", "shear_fc.stress") and lik.n_points == 7
    prm = dict(ind.HAWKINS)
    sig = np.array([2e-3, 5e-3, 1e-3])
    ref = 0.0
    for s in lik.series:
        k = lik.kinds.index(s.kind)
        for e, y in zip(small.strain[s.rows], s.observed):
            m = ind.predict(s.test.load_case, float(e), prm, "cone")[s.observable]
            ref += -0.5 * ((y - m) / sig[k]) ** 2 - math.log(sig[k]) - 0.5 * math.log(2 * math.pi)
    got = lik(_row(lik, prm, sig))
    assert abs(got - ref) <= 1e-6 * abs(ref)
    # vectorised over particles: a population gives each row's own value
    rows = np.stack([_row(lik, ind.random_box(s) | {"THETA": 57.0}, sig) for s in range(5)] + [_row(lik, prm, sig)])
    each = np.array([lik(r) for r in rows])
    np.testing.assert_allclose(lik(rows), each, rtol=1e-12)
    assert lik(rows)[-1] == got
    out = rows[0].copy()
    out[0] = 2.0  # VOLF outside its box
    assert lik(out) == -np.inf


def test_empty_cells_and_test_scale(small, tmp_path):
    lik = make_modes_likelihood(ENERGY, small)
    row = _row(lik, ind.CALVO, [2e-3, 5e-3, 1e-3])
    # a cell left empty is not measured: the series drops that value, nothing else changes
    text = (Path(small.source_file)).read_text().splitlines()
    i = next(j for j, ln in enumerate(text) if ln.endswith(",uniaxial_c"))
    parts = text[i].split(",")
    text[i] = ",".join([parts[0], "", *parts[2:]])
    (tmp_path / "gap.csv").write_text("\n".join(text) + "\n")
    gap = make_modes_likelihood(ENERGY, load_specimen(tmp_path / "gap.csv"))
    k = next(j for j, s in enumerate(lik.series) if s.kind == "uniaxial_c.stress")
    dropped = lik.pointwise(row)[k][0, 0]
    assert gap.n_points == lik.n_points - 1
    assert gap(row) == pytest.approx(lik(row) - dropped, rel=1e-12)
    # the per-test scale: at s = 1 only its prior density times the box width is added
    sc = make_modes_likelihood(ENERGY, small, test_scale=True)
    assert sc.noise_names[-3:] == ("scale_test0", "scale_test1", "scale_test2")
    prior = 3 * (-math.log(TEST_SCALE_SD) - 0.5 * math.log(2 * math.pi) + math.log(8 * TEST_SCALE_SD))
    assert sc(np.r_[row, 1.0, 1.0, 1.0]) == pytest.approx(lik(row) + prior, rel=1e-12)
    # a scale multiplies the test's predicted stresses
    m = sc.predict_series(np.r_[row, 1.1, 1.0, 1.0][None])
    np.testing.assert_allclose(m[0], 1.1 * lik.predict_series(row[None])[0], rtol=1e-14)


def test_refusals(small):
    with pytest.raises(HbmError, match="mode uniaxial_c needs the energy form .*not convex"):
        make_modes_likelihood(spyrou_model(), small)
    with pytest.raises(HbmError, match="collagen3d"):
        make_modes_likelihood(ENERGY, small, collagen3d="helix")
    with pytest.raises(HbmError, match=r"effect 'slack' is not defined in mode uniaxial_c \(stress\): it is "
                                       "written on the 1-D along-fibre strain path"):
        make_modes_likelihood(ENERGY.with_effects(make_effect("slack")), small)
    with pytest.raises(HbmError, match="this likelihood fits along-fibre stress only; fit the file with 'hbm fit'"):
        make_likelihood(ENERGY, small)  # never fitted as if every test were along the fibres
    assert is_multimode(small)
    assert not is_multimode(load_specimen(Path(__file__).resolve().parents[1] / "data" / "specimens" /
                                          "calvo2010_rat1.csv"))


def test_synthetic_recovery_one_seed(tmp_path):
    """Along + across + shear tests of the independent generator (2 % noise, seed 0): the generating
    (1-VOLF)*T1, T2 and the other combinations inside their 90 % intervals (the >= 20-seed coverage is
    workflows/benchmarks/modes_coverage.py)."""
    ind.synthetic_csv(tmp_path / "s.csv", 0)
    fit = fit_modes(load_specimen(tmp_path / "s.csv"), model=ENERGY, samples=300, seed=1, progress=False,
                    tmcmc_options={"max_steps": 10})
    q = fit.combinations()
    q["T2"] = fit.samples[:, fit.names.index("T2")]
    truth = {"G": 0.9 * 0.012 + 0.1 * 0.009, "VOLF*P1": 0.9 * 0.13, "(1-VOLF)*T1": 0.1 * 1.5, "T2": 9.3}
    for k, v in truth.items():
        lo, hi = fit.interval(q[k])
        assert lo <= v <= hi, (k, v, lo, hi)
    # identified: the collagen's amplitude to +-35 %, its rate to +-25 % (along the fibres alone: the whole box)
    lo, hi = fit.interval(q["(1-VOLF)*T1"])
    assert hi - lo < 0.7 * truth["(1-VOLF)*T1"]
    lo, hi = fit.interval(q["T2"])
    assert hi - lo < 0.5 * truth["T2"]
    assert all(0.6 <= t["coverage90"] for t in fit.quality())


def test_cli_fit_writes_one_variable_per_observable(tmp_path, capsys):
    import arviz as az

    path = tmp_path / "m.csv"
    ind.synthetic_csv(path, 5, tests=SMALL)
    text = path.read_text().replace("strain,stress,test,mode", "strain,stress,test,mode,strain_f")
    lines = [ln + ("," + ("-0.02" if ln.endswith("uniaxial_c") else "") if not ln.startswith(("#", "strain")) else "")
             for ln in text.splitlines()]
    path.write_text("\n".join(lines) + "\n")
    out = tmp_path / "r.nc"
    rc = main(["fit", str(path), "--form", "energy", "--collagen3d", "gst", "--samples", "100",
               "--max-evaluations", "3000", "--out", str(out), "--no-progress"])
    assert rc == 0
    text, err = capsys.readouterr()
    assert "hbm: warning: synthetic_modes_5: the evaluation cap (3000) bound the TMCMC run" in err
    assert "tier: full tier" in text and "collagen3d=gst" in text
    assert "test 1 [uniaxial_c] strain_f: 2 points" in text and "test 2 [shear_fc] stress: 2 points" in text
    assert "what the tests identify (linearised Fisher analysis at the highest-likelihood draw" in text
    assert out.with_suffix(".png").exists()
    idata = az.from_netcdf(out)
    assert set(idata.observed_data.data_vars) == {"stress", "strain_f"}
    assert idata.observed_data["stress"].dims == ("stress_point",)
    assert idata.log_likelihood["strain_f"].shape == (1, 100, 2)
    assert list(idata.observed_data["stress_mode"].values) == ["uniaxial_f"] * 3 + ["uniaxial_c"] * 2 + ["shear_fc"] * 2
    assert json.loads(idata.attrs["config"])["collagen3d"] == "gst"
    assert json.loads(idata.attrs["identifiability"])["n_structural"] == 2
