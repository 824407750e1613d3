"""Measured-data options on the command line (issue 18): --sl0, --form energy and the thesis
form's refusal of compressive data, --json error objects, few-point warnings."""

from __future__ import annotations

import json
import warnings

import numpy as np
import pytest
import xarray as xr

from hbm.cli import main
from hbm.errors import DataError, HbmWarning
from hbm.io import read_specimen_result
from hbm.likelihood import make_likelihood
from hbm.model import spyrou_model


def _compression_csv(path, n=20):
    eps = np.linspace(0.0, -0.3, n)
    theta = np.array([[0.9, 0.1, 0.1, 5.0, 10.0, 60.0, 0.01, 0.01]])
    sig = spyrou_model(form="energy").stress(eps, theta)[0]
    path.write_text("strain,stress\n" + "".join(f"{e:.6f},{s:.8f}\n" for e, s in zip(eps, sig)))
    return path


def test_thesis_form_refuses_compression_and_names_the_option(tmp_path, capsys):
    csv = _compression_csv(tmp_path / "comp.csv")
    rc = main(["fit", str(csv), "--samples", "50", "--restarts", "0", "--out", str(tmp_path / "o.nc")])
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 2 and len(err) == 1 and "--form energy" in err[0], err
    assert not (tmp_path / "o.nc").exists()


def test_api_refuses_compression_with_thesis_form_only():
    eps = np.linspace(0.0, -0.3, 20)
    ds = xr.Dataset({"strain": ("point", eps), "stress": ("point", -0.01 * np.ones_like(eps))}, attrs={"id": "c"})
    with pytest.raises(DataError, match="energy"):
        make_likelihood(spyrou_model(), ds)
    lik = make_likelihood(spyrou_model(form="energy"), ds)
    assert lik.n_model == 8
    # a tension test starting slightly below zero still loads
    eps_t = np.r_[-0.004, -0.002, np.linspace(0.0, 0.4, 18)]
    ok = xr.Dataset({"strain": ("point", eps_t), "stress": ("point", np.linspace(0, 0.1, 20))})
    make_likelihood(spyrou_model(), ok)


def test_energy_form_fits_compression_from_the_cli(tmp_path, capsys):
    csv = _compression_csv(tmp_path / "comp.csv", n=12)
    rc = main(["optimize", str(csv), "--form", "energy", "--restarts", "1", "--maxfevals", "300", "--json"])
    out = capsys.readouterr().out
    assert rc == 0, out
    json.loads(out)


def test_sl0_on_the_command_line(capsys):
    assert main(["data", "check", "data/measured"]) == 2
    capsys.readouterr()
    assert main(["data", "check", "data/measured", "--sl0", "2.0"]) == 0
    assert "SL0 2.0 um" in capsys.readouterr().out


@pytest.mark.parametrize("argv", [["diagnose", "nosuch.csv", "--json"],
                                  ["optimize", "nosuch.csv", "--json"],
                                  ["diagnose", "data/specimens/calvo2010_rat1.csv", "--json", "--seed", "-1"]])
def test_json_failure_is_one_json_object(argv, capsys):
    rc = main(argv)
    cap = capsys.readouterr()
    assert rc == 2
    obj = json.loads(cap.out)
    assert set(obj) == {"error"} and obj["error"]
    assert len(cap.err.strip().splitlines()) == 1


def test_detective_accepts_five_points_with_a_warning():
    from hbm.detective.inputs import as_data
    eps = np.linspace(0.0, 0.4, 6)
    ds = xr.Dataset({"strain": ("point", eps), "stress": ("point", eps ** 2)})
    with pytest.warns(HbmWarning, match="only 6 points"):
        d = as_data(ds)
    assert d.strain.size == 6
    with pytest.raises(Exception, match=">= 5 points"):
        as_data(ds.isel(point=slice(0, 4)))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        as_data(xr.Dataset({"strain": ("point", np.linspace(0, .4, 12)), "stress": ("point", np.ones(12))}))


def test_hbm_warnings_print_as_one_line(capsys):
    from hbm.cli import _show_warning
    _show_warning("a prior edge\nsecond line", HbmWarning, "x.py", 1)
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("hbm: warning: a prior edge")


def test_bounds_may_widen_the_thesis_box_with_a_notice(capsys):
    rc = main(["optimize", "data/specimens/calvo2010_rat1.csv", "--bounds", "VOLF=0.1:0.7", "--restarts", "1",
               "--maxfevals", "200", "--json"])
    cap = capsys.readouterr()
    assert rc == 0, cap.err
    notice = [l for l in cap.err.splitlines() if "departs from the thesis box" in l]
    assert notice == ["hbm: warning: prior departs from the thesis box: VOLF [0.5, 0.99] -> [0.1, 0.7]"]
    best = json.loads(cap.out)["optima"][0]["params"]["VOLF"]
    assert 0.1 <= best <= 0.7
    # narrowing alone is the old path: no notice
    assert main(["optimize", "data/specimens/calvo2010_rat1.csv", "--bounds", "VOLF=0.6:0.7", "--restarts", "1",
                 "--maxfevals", "200", "--json"]) == 0
    assert "departs" not in capsys.readouterr().err


def test_prior_file_errors_are_one_line(tmp_path, capsys):
    bad = tmp_path / "p.toml"
    bad.write_text("[P1]\nlo = 0\nhi = 1\nform = 'loguniform'\n")
    rc = main(["fit", "data/specimens/calvo2010_rat1.csv", "--prior", str(bad)])
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 2 and len(err) == 1 and "--prior" in err[0] and "loguniform" in err[0], err


def test_diagnose_reports_base_parameters_on_a_box_edge():
    import types

    from hbm.detective import _base_at_bounds
    model = spyrou_model()
    box = np.asarray(model.bounds, float)
    names = list(model.parameter_names) + ["sigma"]
    lik = types.SimpleNamespace(bounds=np.vstack([box, [[1e-4, 0.05]]]))
    best = box.mean(axis=1).tolist() + [1e-4]
    best[names.index("THETA")] = 59.95          # within 2 % of the 5-degree THETA box
    rng = np.random.default_rng(0)
    samples = np.tile(best, (1000, 1))
    samples[:, names.index("THETA")] = rng.uniform(55.0, 60.0, 1000)  # 2 % of the posterior at each edge
    base = types.SimpleNamespace(model=model, names=names, likelihood=lik, theta_max=np.array(best),
                                 samples=samples)
    with pytest.warns(HbmWarning, match="THETA at its upper bound 60"):
        found = _base_at_bounds(base, "spec")
    assert [(e["parameter"], e["side"], e["map_at_edge"]) for e in found] == [("THETA", "upper", True)]
    assert found[0]["fraction"] == pytest.approx(0.02, abs=0.01)  # uniform draws: 2 % near the edge


def test_fit_says_what_the_loader_converted(tmp_path, capsys):
    """A sarcomere-length file in nominal kPa: the fit's text report, its JSON and the stored
    result name the conversions the numbers rest on; the stored stress is the Cauchy stress in
    MPa computed independently here (sigma = lambda * P, lambda = SL/SL0)."""
    sl = np.linspace(2.0, 3.0, 12)
    lam = sl / 2.0
    cauchy = 0.01 * (lam ** 2 - 1 / lam) + 0.05 * np.clip(lam - 1.2, 0, None)
    nominal_kpa = 1e3 * cauchy / lam
    csv = tmp_path / "sl.csv"
    csv.write_text("# reference_sarcomere_length_um: 2.0\nsarcomere_length_um,nominal_stress_kPa\n"
                   + "".join(f"{a:.5f},{b:.6f}\n" for a, b in zip(sl, nominal_kpa)))
    out = tmp_path / "o.nc"
    argv = ["fit", str(csv), "--samples", "100", "--restarts", "0", "--no-plot", "--no-progress", "--out", str(out)]
    assert main(argv) == 0
    text = capsys.readouterr().out
    line = [ln for ln in text.splitlines() if ln.startswith("input converted:")]
    assert line and "kPa->MPa" in line[0] and "nominal->Cauchy" in line[0] and "SL0 2.0" in line[0], text
    r = read_specimen_result(out)
    assert "nominal->Cauchy" in r.config["input"]
    np.testing.assert_allclose(r.data.stress, cauchy, rtol=1e-5, atol=1e-9)
    assert main(argv[:-2] + ["--out", str(tmp_path / "o2.nc"), "--json"]) == 0
    assert "kPa->MPa" in json.loads(capsys.readouterr().out)["input"]
    assert main(["extend", str(csv), "--add", "offset", "--samples", "100", "--no-progress"]) == 0
    assert capsys.readouterr().out.startswith("input converted: stress kPa->MPa, nominal->Cauchy")


def test_fit_of_plain_strain_mpa_file_has_no_input_line(tmp_path, capsys):
    csv = tmp_path / "p.csv"
    eps = np.linspace(0, 0.3, 12)
    csv.write_text("strain,stress\n" + "".join(f"{e:.4f},{0.02 * e + 0.1 * e ** 2:.6f}\n" for e in eps))
    assert main(["fit", str(csv), "--samples", "100", "--restarts", "0", "--no-plot", "--no-progress",
                 "--out", str(tmp_path / "o.nc")]) == 0
    assert "input converted" not in capsys.readouterr().out
