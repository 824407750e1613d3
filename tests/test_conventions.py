"""Result files follow the ecosystem's conventions: UDUNITS units + long_name, ArviZ groups and
attributes, prior draws and lp, hyper-parameter transforms, SALib settings, fractions in JSON."""

import json

import numpy as np
import pytest
import xarray as xr

from hbm.io import conventions
from hbm import io
from hbm.fit import fit_quality
from hbm.model.spyrou import spyrou_model

from test_export import NAMES, _result
from test_fit_quality import _tiny

GROUPS = ("posterior", "prior", "observed_data", "posterior_predictive", "constant_data", "log_likelihood")


def _tree(path):
    with xr.open_datatree(path) as tree:  # loaded and closed: netCDF4/HDF5 dislike files left open
        return tree.load()


def _group(path, group):
    with xr.open_dataset(path, group=group) as ds:
        return ds.load()


@pytest.fixture
def nc(tmp_path):
    return _result(tmp_path, name="conv")


def test_units_and_long_names_everywhere(nc):
    tree = _tree(nc)
    for g in GROUPS:
        ds = tree[g].to_dataset()
        for name in list(ds.data_vars) + list(ds.coords):
            attrs = ds[name].attrs
            assert "long_name" in attrs, (g, name)
            if not (g == "constant_data" and name in ("prior_lower", "prior_upper")):
                assert attrs["units"] != "-" and attrs["units"], (g, name)
        for key in ("created_at", "inference_library", "inference_library_version"):
            assert key in ds.attrs, (g, key)
    post = tree["posterior"].to_dataset()
    assert post["THETA"].attrs["units"] == "degree" and post["VOLF"].attrs["units"] == "1"
    assert post["P1"].attrs["units"] == "MPa"
    assert "THETA: degree" in tree["constant_data"].attrs["units_by_parameter"]


def test_pint_and_cf_xarray_quantify_posterior(nc):
    pint_xarray = pytest.importorskip("pint_xarray")  # noqa: F841 - registers the .pint accessor
    cf_units = pytest.importorskip("cf_xarray.units")
    for g in ("posterior", "observed_data", "posterior_predictive"):
        ds = _group(nc, g)
        q = ds.pint.quantify(unit_registry=cf_units.units)
        for name in ds.data_vars:
            assert hasattr(q[name].data, "units"), (g, name)
    post = _group(nc, "posterior").pint.quantify(unit_registry=cf_units.units)
    # MPa really is a pressure: 1 MPa = 1e6 Pa
    raw = _group(nc, "posterior")["P1"].values
    assert float(post["P1"].pint.to("Pa").pint.magnitude[0, 0]) == pytest.approx(raw[0, 0] * 1e6, rel=1e-12)


def test_prior_group_and_lp(nc):
    tree = _tree(nc)
    prior = tree["prior"].to_dataset()
    r = io.read_specimen_result(nc)
    b = r.bounds
    for i, n in enumerate(NAMES):
        x = prior[n].values.ravel()
        assert x.size == r.n_samples and x.min() >= b[i, 0] and x.max() <= b[i, 1]
        # uniform on the box: mean near the centre (n = 120 draws; 5 standard errors)
        assert abs(x.mean() - b[i].mean()) < 5 * (b[i, 1] - b[i, 0]) / np.sqrt(12 * x.size)
    lp = tree["sample_stats"]["lp"].values.ravel()
    expected = r.log_likelihood - np.sum(np.log(b[:, 1] - b[:, 0]))
    inside = np.all((r.samples >= b[:, 0]) & (r.samples <= b[:, 1]), axis=1)
    np.testing.assert_allclose(lp[inside], expected[inside], rtol=1e-12)
    assert np.all(np.isneginf(lp[~inside]))


def test_log_prior_loguniform_density_integrates_to_one():
    prior = {"A": {"lo": 0.01, "hi": 10.0, "form": "loguniform"}}
    x = np.linspace(0.01, 10.0, 200001)[:, None]
    dens = np.exp(conventions.log_prior(x, ["A"], prior))
    assert np.trapezoid(dens, x[:, 0]) == pytest.approx(1.0, rel=1e-4)


def test_arviz_reads_groups(nc):
    az = pytest.importorskip("arviz")
    idata = az.from_netcdf(str(nc))
    assert {"posterior", "prior", "sample_stats", "observed_data"} <= set(idata.groups())
    assert "lp" in idata.sample_stats


def test_hierarchical_transform_attribute(tmp_path):
    names = ["mu_VOLF", "sd_VOLF", "mu_THETA", "sd_THETA", "mu_log_G"]
    h = io.HierarchicalFile(param_names=["VOLF", "THETA"], hyper_names=names, hyper_samples=np.ones((5, 5)),
                            specimen_ids=["a", "b"], attrs={"transforms": {"VOLF": "logit", "THETA": "identity",
                                                                           "log_G": "identity"}})
    path = io.write_hierarchical(h, tmp_path / "hierarchical.nc")
    post = _group(path, "posterior")
    assert post["mu_VOLF"].attrs["transform"] == "logit" and post["sd_VOLF"].attrs["units"] == "1"
    assert post["mu_THETA"].attrs["transform"] == "identity" and post["mu_THETA"].attrs["units"] == "degree"
    assert all("transform" in post[n].attrs for n in names)


def test_salib_settings_recorded():
    from hbm.fit.specimen import run_sobol
    from hbm.data import load_specimen

    ds = load_specimen("data/specimens/calvo2010_rat1.csv")
    out = run_sobol(spyrou_model(), ds, n=8, seed=3)
    assert out["calc_second_order"] == 0 and out["num_resamples"] == 100 and out["conf_level"] == 0.95
    assert out["sampler_seed"] == 3 and out["salib_sampler"].startswith("SALib.sample.sobol")


def test_fractions_and_coverage_at_its_prob():
    q = fit_quality(_tiny())
    q50 = fit_quality(_tiny(), prob=0.5)
    assert 0 <= q["rmse_rel"] < 1  # a fraction
    assert q50["coverage90"] == q["coverage90"]  # always the 90 % band, whatever prob
    assert q50["coverage_prob"] == 0.5 and q["coverage"] == q["coverage90"]


def test_summary_cli_csv(run_cli, nc):
    rc, out, _ = run_cli(["summary", nc, "--csv"])
    assert rc == 0
    rows = [line.split(",") for line in out.strip().splitlines()]
    assert rows[0][:2] == ["parameter", "units"]
    table = {r[0]: r for r in rows[1:]}
    assert table["THETA"][1] == "degree" and table["P1"][1] == "MPa" and table["G"][1] == "MPa"
    r = io.read_specimen_result(nc)
    assert float(table["VOLF"][5]) == pytest.approx(np.median(r.column("VOLF")), rel=1e-5)


def test_scheduler_file(tmp_path):
    from distributed import Client, LocalCluster

    from hbm.cli.run import scheduler_address
    from hbm.errors import SettingError

    with LocalCluster(n_workers=1, threads_per_worker=1, processes=False, dashboard_address=":0") as cl:
        with Client(cl) as c:
            path = tmp_path / "scheduler.json"
            c.write_scheduler_file(str(path))
            assert scheduler_address(None, str(path)) == cl.scheduler_address
            assert json.loads(path.read_text())["address"] == cl.scheduler_address
    with pytest.raises(SettingError, match="--scheduler-file"):
        scheduler_address(None, str(tmp_path / "missing.json"), wait=0.0)
    with pytest.raises(SettingError, match="one of them"):
        scheduler_address("tcp://x:1", str(path))
