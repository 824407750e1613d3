"""The multi-specimen workflow end to end on two tiny specimens, with a shared 2-worker LocalCluster.

Checks: files, ArviZ compatibility, the report and figures; re-running skips complete files;
an interrupted specimen resumes from its checkpoint with a result bitwise equal to an
uninterrupted run; the worker count (serial, 1, 2 workers) does not change results.
"""

from __future__ import annotations

import json
import warnings

import numpy as np
import pytest
from conftest import cli_error

from hbm import io
from hbm.data import save_specimen, synthetic_specimen
from hbm.model import spyrou_model

TRUTHS = {
    "ratA": {"VOLF": 0.9, "EOPT": 0.15, "P1": 0.06, "T1": 1.0, "T2": 14.0, "THETA": 59.0, "GF": 0.03, "GM": 0.02},
    "ratB": {"VOLF": 0.85, "EOPT": 0.17, "P1": 0.08, "T1": 0.8, "T2": 18.0, "THETA": 59.5, "GF": 0.02, "GM": 0.02},
}
TINY = dict(samples=150, restarts=1, maxfevals=200, sweep=None, sobol_n=16, hier_samples=100,
            tmcmc_options={"max_steps": 6}, progress=False, quick=True)  # quick: the population layer's chains short


@pytest.fixture(scope="module")
def data_dir(tmp_path_factory):
    d = tmp_path_factory.mktemp("specimens")
    for k, (sid, th) in enumerate(sorted(TRUTHS.items())):
        ds = synthetic_specimen(spyrou_model(), th, np.linspace(0, 0.42, 25), 0.002, 100 + k, attrs={"id": sid})
        save_specimen(ds, d / f"{sid}.csv")
    return d


@pytest.fixture(scope="module")
def client():
    pytest.importorskip("distributed")
    from hbm.runtime.parallel import dask_client

    with dask_client(workers=2) as c:
        assert len(c.scheduler_info()["workers"]) == 2
        yield c


@pytest.fixture(scope="module")
def first_run(data_dir, client, tmp_path_factory):
    from hbm.workflow import run_workflow

    out = tmp_path_factory.mktemp("run")
    res = run_workflow(data=str(data_dir), out=str(out), client=client, **TINY)
    return res


def _samples(out, sid):
    return io.read_specimen_result(io.specimen_path(out, sid)).samples


def test_end_to_end_outputs(first_run):
    res = first_run
    out = res.out
    assert sorted(res.results) == ["ratA", "ratB"] and not res.errors and not res.skipped
    for sid in ("ratA", "ratB"):
        p = io.specimen_path(out, sid)
        assert io.is_complete(p)
        r = io.read_specimen_result(p)
        assert r.samples.shape == (150, 9) and r.sobol and r.optima
        assert r.config["seed_spawn_key"] == [sorted(TRUTHS).index(sid)]
    assert not list((out / "checkpoints").rglob("*.npz"))  # superseded by the result files
    h = io.read_hierarchical(out / "hierarchical.nc")
    assert "mu_T2" in h.hyper_names and "sd_T2" in h.hyper_names
    # default pool for the base model: the identifiable combinations; a new specimen still gets all
    # 8 model parameters (VOLF, P1, T1, GF, GM drawn given its combinations) inside the box
    assert h.attrs["mode"] == "combinations" and "mu_log_G" in h.hyper_names
    from hbm.model import spyrou_model
    from hbm.organ import theta_from_samples
    m = spyrou_model()
    th = theta_from_samples(m, h.pooled_names, h.new_specimen)
    assert th.shape == (h.new_specimen.shape[0], 8)
    assert np.all((th >= m.bounds[:, 0]) & (th <= m.bounds[:, 1]))
    # the joint sampler's draws: all chains x kept draws (at least --hier-samples), stored as its chains; the
    # updated individuals from the same chains (at most 4000 per specimen); its model evaluations recorded
    n_draws = h.hyper_samples.shape[0]
    layer = h.attrs["layer"]
    assert h.chains == layer["chains"] >= 2 and n_draws == layer["chains"] * layer["n_keep"] >= 100
    assert h.updated.shape == (min(n_draws, 4000), 2, 9)
    assert h.evaluations == layer["evaluations"] > 0
    assert json.loads((out / "run.json").read_text())["timings"]["hierarchical_evaluations"] == h.evaluations
    assert not np.isfinite(h.log_evidence)  # this sampler estimates no hyper-evidence (the report says so)
    report = (out / "report.md").read_text()
    for key in ("## Run settings", "## Timings", "### ratA", "### ratB", "Population estimates",
                "Specimen variability", "(1-VOLF)*T1"):
        assert key in report
    figs = {p.name for p in (out / "figures").iterdir()}
    for name in ("ratA_corner.png", "ratA_predictive.png", "ratA_sobol.png", "forest.png",
                 "manifolds_volf_t1.png", "hyperposterior.png"):
        assert name in figs
    run = json.loads((out / "run.json").read_text())
    assert run["timings"]["specimens_wall"] > 0 and run["specimens"] == ["ratA", "ratB"]
    assert (out / "manifolds.nc").exists()


def test_arviz_opens_workflow_file(first_run):
    az = pytest.importorskip("arviz")
    idata = az.from_netcdf(str(io.specimen_path(first_run.out, "ratA")))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        summ = az.summary(idata, kind="stats")
    assert {"VOLF", "T2", "sigma"} <= set(summ.index)
    assert idata.sample_stats.sizes["stage"] >= 2 and "stage" not in idata.posterior.dims
    assert idata.log_likelihood["stress"].shape == (1, 150, 25)


def test_rerun_skips_complete(first_run, data_dir, client):
    from hbm.workflow import run_workflow

    out = first_run.out
    mtimes = {sid: io.specimen_path(out, sid).stat().st_mtime_ns for sid in TRUTHS}
    res = run_workflow(data=str(data_dir), out=str(out), client=client, figures=False, hierarchical=False,
                       **{k: v for k, v in TINY.items()})
    assert sorted(res.skipped) == ["ratA", "ratB"]
    assert {sid: io.specimen_path(out, sid).stat().st_mtime_ns for sid in TRUTHS} == mtimes


def test_interrupted_specimen_resumes(first_run, data_dir, monkeypatch, tmp_path):
    """Kill ratB's TMCMC after 3 stages; the next run resumes from its checkpoint -> same samples."""
    import importlib
    import shutil

    from hbm.workflow import run_workflow

    tm = importlib.import_module("hbm.samplers.tmcmc")  # the module (hbm.samplers.tmcmc is also a function)

    out = tmp_path / "resume"
    shutil.copytree(first_run.out / "specimens", out / "specimens")
    (out / "specimens" / "ratB.nc").unlink()
    real_step, calls = tm.step, {"n": 0}

    def dying_step(*a, **k):
        calls["n"] += 1
        if calls["n"] > 3:
            raise KeyboardInterrupt("simulated crash")
        return real_step(*a, **k)

    monkeypatch.setattr(tm, "step", dying_step)
    with pytest.raises(KeyboardInterrupt):
        run_workflow(data=str(data_dir), out=str(out), workers=0, figures=False, hierarchical=False, **TINY)
    ck = list((out / "checkpoints").rglob("ratB.npz"))
    assert len(ck) == 1 and not io.is_complete(out / "specimens" / "ratB.nc")
    monkeypatch.setattr(tm, "step", real_step)
    res = run_workflow(data=str(data_dir), out=str(out), workers=0, figures=False, hierarchical=False, **TINY)
    assert res.skipped == ["ratA"]
    np.testing.assert_array_equal(_samples(out, "ratB"), _samples(first_run.out, "ratB"))
    assert not ck[0].exists()


def _fields_equal(a, b) -> list:
    """Names of the dataclass fields of two results that differ (arrays bit for bit; timings aside)."""
    import collections.abc as cabc
    import dataclasses

    def eq(x, y):
        if isinstance(x, cabc.Mapping):
            return isinstance(y, cabc.Mapping) and set(x) == set(y) and all(eq(x[k], y[k]) for k in x)
        if isinstance(x, (list, tuple)):
            return len(x) == len(y) and all(eq(p, q) for p, q in zip(x, y))
        if isinstance(x, np.ndarray):
            return np.array_equal(x, y, equal_nan=x.dtype.kind == "f")
        if dataclasses.is_dataclass(x):
            return all(eq(getattr(x, f.name), getattr(y, f.name)) for f in dataclasses.fields(x))
        if hasattr(x, "equals"):
            return bool(x.equals(y))
        return x == y or (x != x and y != y)

    return [f.name for f in dataclasses.fields(a) if f.name != "timings" and not eq(getattr(a, f.name),
                                                                                    getattr(b, f.name))]


def test_worker_count_does_not_change_results(first_run, data_dir, tmp_path):
    """Serial (no dask) and a 1-worker cluster reproduce the 2-worker results bit for bit; the 2-worker run
    splits each fit (the posterior first, its optima and Sobol indices beside the population layer), the
    serial one does not: the same files and the same layer."""
    from hbm.runtime.parallel import dask_client
    from hbm.workflow import run_workflow

    assert first_run.timings.get("specimens_extras_beside_layer") is True
    serial = run_workflow(data=str(data_dir), out=str(tmp_path / "serial"), workers=0, figures=False, **TINY)
    assert "specimens_extras_beside_layer" not in serial.timings
    for sid in TRUTHS:
        assert _fields_equal(io.read_specimen_result(io.specimen_path(serial.out, sid)),
                             io.read_specimen_result(io.specimen_path(first_run.out, sid))) == []
    hs, hp = (io.read_hierarchical(r.out / "hierarchical.nc") for r in (serial, first_run))
    np.testing.assert_array_equal(hs.hyper_samples, hp.hyper_samples)
    np.testing.assert_array_equal(hs.updated, hp.updated)
    assert hs.attrs["content_key"] == hp.attrs["content_key"]
    with dask_client(workers=1) as c1:
        one = run_workflow(data=str(data_dir), out=str(tmp_path / "one"), client=c1, figures=False,
                           hierarchical=False, **TINY)
    for sid in TRUTHS:
        ref = _samples(first_run.out, sid)
        np.testing.assert_array_equal(_samples(serial.out, sid), ref)
        np.testing.assert_array_equal(_samples(one.out, sid), ref)
    # and the two specimens got different streams
    assert not np.array_equal(first_run.results["ratA"].samples[:, 0], first_run.results["ratB"].samples[:, 0])


def test_settings_change_refits(first_run, data_dir, tmp_path):
    import shutil

    from hbm.workflow import run_workflow

    out = tmp_path / "changed"
    shutil.copytree(first_run.out / "specimens", out / "specimens")
    res = run_workflow(data=str(data_dir), out=str(out), workers=0, figures=False, hierarchical=False,
                       **{**TINY, "seed": 1})
    assert res.skipped == []
    assert not np.array_equal(_samples(out, "ratA"), _samples(first_run.out, "ratA"))


def test_map_specimens_seeds_follow_sorted_ids():
    from hbm.runtime.parallel import spawn_specimen_seeds

    a = spawn_specimen_seeds(3, ["b", "a", "c"])
    b = spawn_specimen_seeds(3, ["a", "b", "c"])
    assert [s.spawn_key for s in a.values()] == [s.spawn_key for s in b.values()]
    assert a["a"].spawn_key == (0,) and a["c"].spawn_key == (2,)


def test_cli_run(data_dir, tmp_path, run_cli):
    out = tmp_path / "cli"
    rc, text, _ = run_cli(["run", "--data", data_dir, "--out", out, "--workers", "0", "--samples", "40",
                           "--restarts", "0", "--no-sobol", "--no-figures", "--no-hierarchical", "--no-progress"])
    assert rc == 0 and io.is_complete(io.specimen_path(out, "ratA"))
    assert "2 specimens fitted" in text and (out / "report.md").exists()
    assert "power of 2" in cli_error(run_cli, ["run", "--data", data_dir, "--sobol-n", "100"])
    assert "not a directory" in cli_error(run_cli, ["run", "--data", tmp_path / "nope", "--out", out])


def test_a_specimen_completed_beside_the_layer_keeps_its_result_when_its_figures_fail(data_dir, tmp_path):
    """The second task of a split fit writes the result (the one-task fit's file) and retires the checkpoint;
    a figure that cannot be drawn is reported, not raised."""
    from hbm.data import load_specimens
    from hbm.fit.specimen import fit_posterior, fit_specimen
    from hbm.settings import FitSettings
    from hbm.workflow.run import _complete_one

    spec = load_specimens(str(data_dir))["ratA"]
    settings = FitSettings(samples=150, restarts=1, maxfevals=200, sweep=None, sobol_n=16,
                           tmcmc_options={"max_steps": 6}, seed=3)
    ckpt = tmp_path / "ck" / "ratA.npz"
    post = fit_posterior(spec, settings=settings, checkpoint_dir=ckpt.parent)
    assert post.optima is None and post.sobol is None and ckpt.exists()
    blocked = tmp_path / "not_a_folder"
    blocked.write_text("a file where the figures' folder should be")
    out = tmp_path / "ratA.nc"
    got = _complete_one((post, spec, str(out), str(ckpt), "key", {}, settings, str(blocked / "figures")),
                        seed=None, model=None)
    assert got["path"] == str(out) and got["figures"] == [] and got["figure_error"]
    assert io.is_complete(out) and not ckpt.exists()
    one = fit_specimen(spec, settings=settings, out=tmp_path / "one.nc", progress=False)
    assert _fields_equal(io.read_specimen_result(out), io.read_specimen_result(one.path)) == []


def test_a_split_run_pools_the_new_posteriors_not_the_files_they_replace(first_run, data_dir, client, tmp_path,
                                                                          monkeypatch):
    """Changed settings refit every specimen; while the old files are still on disk the layer gets the new
    posteriors (and is keyed by them): the samples it pooled are those of the files the run then writes."""
    import shutil

    import hbm.workflow.run as run_mod
    from hbm.workflow import run_workflow

    out = tmp_path / "changed_split"
    shutil.copytree(first_run.out / "specimens", out / "specimens")
    seen = {}
    real = run_mod.run_population

    def spy(results, *a, **k):
        seen.update({sid: np.array(r.samples) for sid, r in results.items()})
        return real(results, *a, **k)

    monkeypatch.setattr(run_mod, "run_population", spy)
    res = run_workflow(data=str(data_dir), out=str(out), client=client, figures=False, **{**TINY, "seed": 1})
    assert res.timings.get("specimens_extras_beside_layer") is True and res.skipped == []
    assert sorted(seen) == ["ratA", "ratB"]
    for sid in TRUTHS:
        np.testing.assert_array_equal(seen[sid], _samples(out, sid))
        assert not np.array_equal(seen[sid], _samples(first_run.out, sid))
