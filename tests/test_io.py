"""Round trips of the netCDF result files and ArviZ compatibility."""

from __future__ import annotations

import math
import warnings

import numpy as np
import pytest
import xarray as xr

from hbm import io
from hbm.data import Series, Specimen
from hbm.samplers import StageInfo
from hbm.samplers.tmcmc import tmcmc


def _result(n=200, p=15, seed=1, complete=True):
    rng = np.random.default_rng(seed)
    names = ["VOLF", "T1", "sigma"]
    samples = np.column_stack([rng.uniform(0.5, 0.99, n), rng.uniform(0, 20, n), rng.uniform(0.01, 0.1, n)])
    strain = np.linspace(0, 0.4, p)
    stages = [{"beta": b, "log_evidence_increment": -1.0 * i, "acceptance_rate": 0.3, "cov_weights": 1.0,
               "evaluations": 100 * (i + 1)} for i, b in enumerate([0.0, 0.1, 0.5, 1.0])]
    optima = [{"params": {"VOLF": 0.6, "T1": 1.0, "sigma": 0.02}, "objective": 3.0, "kind": "restart"},
              {"params": {"VOLF": 0.8, "T1": 2.0, "sigma": 0.02}, "objective": 3.5, "kind": "sweep",
               "window_lower": 0.75, "window_upper": 0.85}]
    sobol = {"S1": {"VOLF": 0.1, "T1": 0.6}, "ST": {"VOLF": 0.2, "T1": 0.8},
             "S1_conf": {"VOLF": 0.01, "T1": 0.02}, "ST_conf": {"VOLF": 0.01, "T1": 0.03},
             "relevance": {"VOLF": "low", "T1": "high"},
             "ST_point": {"VOLF": np.linspace(0, 1, p), "T1": np.linspace(1, 0, p)}, "qoi": "misfit", "n": 64}
    return io.SpecimenResult(
        specimen_id="rat1", names=names, samples=samples, log_likelihood=rng.normal(size=n),
        log_evidence=12.5, log_evidence_se=0.3, bounds=np.array([[0.5, 0.99], [0, 20], [1e-4, 1.0]]),
        stages=stages, data=Specimen("rat1", strain, np.arange(p, dtype=float), np.zeros(p, int),
                                     {"stress": Series.known("stress", strain ** 2)}), pointwise_log_likelihood=rng.normal(size=(n, p)),
        predictive=rng.normal(size=(n, p)), predictive_model=rng.normal(size=(n, p)), optima=optima,
        sobol=sobol, effects=["offset"], config={"samples": n, "fix": None, "flag": True},
        seed=7, timings={"tmcmc": 1.5}, fixed={"EOPT": 0.192}, complete=complete)


def test_round_trip(tmp_path):
    r = _result()
    path = io.write_specimen_result(r, tmp_path / "specimens" / "rat1.nc")
    assert io.is_complete(path)
    back = io.read_specimen_result(path)
    assert back.names == r.names
    np.testing.assert_array_equal(back.samples, r.samples)
    np.testing.assert_array_equal(back.log_likelihood, r.log_likelihood)
    np.testing.assert_array_equal(back.pointwise_log_likelihood, r.pointwise_log_likelihood)
    np.testing.assert_array_equal(back.predictive, r.predictive)
    np.testing.assert_array_equal(back.bounds, r.bounds)
    for v in ("strain", "stress", "time", "test"):
        np.testing.assert_array_equal(getattr(back.data, v), getattr(r.data, v))
    assert back.data.observed["stress"].unit == "MPa"
    assert back.log_evidence == 12.5 and back.log_evidence_se == 0.3
    assert [s.beta for s in back.stages] == [0.0, 0.1, 0.5, 1.0]
    assert [s.evaluations for s in back.stages] == [100, 200, 300, 400]
    assert type(back.stages[0].evaluations) is int
    # fields the stages did not report are NaN on reading and not stored at all
    assert all(math.isnan(s.proposal_scale) and math.isnan(s.ess) for s in back.stages)
    stored = xr.open_datatree(path)["sample_stats"].ds
    assert {v for v in stored.data_vars if "stage" in stored[v].dims} == {
        "beta", "log_evidence_increment", "acceptance_rate", "cov_weights", "evaluations"}
    assert back.optima[1]["params"]["VOLF"] == 0.8 and back.optima[1]["kind"] == "sweep"
    assert back.optima[1]["window_lower"] == 0.75 and "window_lower" not in back.optima[0]
    assert back.sobol["relevance"]["T1"] == "high" and back.sobol["ST"]["T1"] == 0.8
    np.testing.assert_allclose(back.sobol["ST_point"]["VOLF"], np.linspace(0, 1, 15))
    assert back.config == {"samples": 200, "fix": None, "flag": True}
    assert back.fixed == {"EOPT": 0.192} and back.seed == 7 and back.effects == ["offset"]
    np.testing.assert_array_equal(back.column("EOPT"), 0.192)
    # no temp files left behind
    assert [p.name for p in (tmp_path / "specimens").iterdir()] == ["rat1.nc"]


def _stage_columns(stages):
    """(stage, field) float array of StageInfo records (bool -> 0/1); NaN compares equal below."""
    return np.array([[float(v) for v in s] for s in stages])


@pytest.mark.parametrize("kernel", ["rw", "manifold"])
def test_sampler_stage_records_round_trip(tmp_path, kernel):
    """Every StageInfo field the sampler produced is stored under its own name and read back equal."""
    f = lambda x: -0.5 * x[:, 0] ** 2 - 0.5 * (x[:, 1] - 1.0) ** 2  # noqa: E731
    gf = lambda x: (-(x - [0.0, 1.0]), np.broadcast_to(np.eye(2), (len(x), 2, 2)).copy())  # noqa: E731
    res = tmcmc(f, [[-5, 5], [-5, 5]], 200, seed=3, move=kernel, gradient_fim=gf, progress=False)
    assert len(res.stages) >= 2
    r = _result()
    r.stages = res.stages
    path = io.write_specimen_result(r, tmp_path / "rat1.nc")
    stored = xr.open_datatree(path)["sample_stats"].ds
    for name in StageInfo._fields:
        np.testing.assert_array_equal(stored[name].values[0], [float(getattr(s, name)) for s in res.stages],
                                      err_msg=name)
    # the proposal scale is stored and it is the adapted one (it moved off its initial 0.2)
    scales = stored["proposal_scale"].values[0]
    assert np.all(np.isfinite(scales) & (scales > 0))
    if kernel == "rw":
        assert np.any(scales != 0.2)
    back = io.read_specimen_result(path)
    assert all(type(s) is StageInfo for s in back.stages)
    np.testing.assert_array_equal(_stage_columns(back.stages), _stage_columns(res.stages))
    assert [type(v) for v in back.stages[0]] == [type(v) for v in res.stages[0]]
    # the hierarchical file stores the same schema
    h = io.HierarchicalFile(param_names=["a"], hyper_names=["mu_a"], hyper_samples=np.zeros((3, 1)),
                            specimen_ids=["x"], stages=res.stages)
    hback = io.read_hierarchical(io.write_hierarchical(h, tmp_path / "hierarchical.nc"))
    np.testing.assert_array_equal(_stage_columns(hback.stages), _stage_columns(res.stages))


def test_incomplete_and_garbage(tmp_path):
    path = io.write_specimen_result(_result(complete=False), tmp_path / "a.nc")
    assert not io.is_complete(path)
    assert not io.read_specimen_result(path).complete
    bad = tmp_path / "b.nc"
    bad.write_bytes(b"not a netcdf file")
    assert not io.is_complete(bad) and not io.is_complete(tmp_path / "missing.nc")
    from hbm.errors import HbmError
    with pytest.raises(HbmError, match="b.nc"):
        io.read_specimen_result(bad)


def test_arviz_opens(tmp_path):
    az = pytest.importorskip("arviz")
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    r = _result()
    path = io.write_specimen_result(r, tmp_path / "rat1.nc")
    idata = az.from_netcdf(str(path))
    for g in ("posterior", "sample_stats", "log_likelihood", "posterior_predictive", "observed_data"):
        assert g in idata.groups()
    assert idata.posterior.sizes["draw"] == 200 and idata.sample_stats.sizes["stage"] == 4
    assert "stage" not in idata.posterior.dims
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        summ = az.summary(idata, kind="stats")
        axes = az.plot_pair(idata, var_names=["VOLF", "T1"])
    np.testing.assert_allclose(summ.loc["T1", "mean"], r.samples[:, 1].mean(), atol=1e-3)
    assert np.size(axes) >= 1
    plt.close("all")


def test_hierarchical_round_trip(tmp_path):
    rng = np.random.default_rng(3)
    h = io.HierarchicalFile(param_names=["T1", "T2"], hyper_names=["mu_T1", "mu_T2", "sd_T1", "sd_T2"],
                            hyper_samples=rng.normal(size=(50, 4)), specimen_ids=["a", "b", "c"],
                            updated=rng.normal(size=(50, 3, 2)), new_specimen=rng.normal(size=(50, 2)),
                            log_evidence=-3.0, log_evidence_se=0.1,
                            stages=[{"beta": 0.0}, {"beta": 1.0}], ess=np.array([40.0, 30, 20]),
                            attrs={"transform": "log"})
    path = io.write_hierarchical(h, tmp_path / "hierarchical.nc")
    back = io.read_hierarchical(path)
    np.testing.assert_array_equal(back.hyper_samples, h.hyper_samples)
    np.testing.assert_array_equal(back.updated, h.updated)
    np.testing.assert_array_equal(back.new_specimen, h.new_specimen)
    assert back.hyper_names == h.hyper_names and back.specimen_ids == ["a", "b", "c"]
    assert back.log_evidence == -3.0 and back.attrs == {"transform": "log"} and back.complete
    assert [s.beta for s in back.stages] == [0.0, 1.0]
    az = pytest.importorskip("arviz")
    idata = az.from_netcdf(str(path))
    assert "mu_T1" in idata.posterior and idata.updated.sizes["specimen"] == 3


def test_population_summary(tmp_path):
    man = {"a": {"x": np.linspace(0.5, 0.9, 5), "y": np.arange(5.0), "x_name": "VOLF", "y_name": "T1"},
           "b": {"x": np.linspace(0.5, 0.9, 3), "y": np.arange(3.0)}}
    path = io.write_population_summary(tmp_path / "m.nc", specimen_ids=["a", "b"], manifolds=man,
                                       combinations={"G": {"mean": [1, 2], "lower": [0, 1], "upper": [2, 3]}})
    back = io.read_population_summary(path)
    np.testing.assert_array_equal(back["manifolds"]["b"]["y"], np.arange(3.0))
    assert back["manifolds"]["a"]["x_name"] == "VOLF"
