"""The population layer's driver around the joint sampler: settings, coordinates, the file, the report, the CLI."""

from types import SimpleNamespace

import numpy as np
import pytest

import hbm.cli as cli
import hbm.cli.run as cli_run
from hbm import io
from hbm.errors import HbmError


def test_layer_settings_and_combination_coordinates():
    from hbm.identifiability.combinations import log_density, support_hull, to_features
    from hbm.model import spyrou_model
    from hbm.population import PopulationConfig
    from hbm.population.driver import joint_applies
    from hbm.population.pooling import PhiCoordinates

    with pytest.raises(HbmError, match="gibbs"):
        PopulationConfig(exact="nuts")
    with pytest.raises(HbmError, match="layer_chains"):
        PopulationConfig(layer_chains=1)
    assert PopulationConfig().exact == "gibbs"  # on by default (README, results/benchmarks/hierarchical_gold.md)
    data = {"a": None, "b": None}
    assert joint_applies(PopulationConfig(progress=False), data, "ab")
    assert not joint_applies(PopulationConfig(groups={"a": "x"}, progress=False), data, "ab")  # grouped: reuse
    assert not joint_applies(PopulationConfig(progress=False), None, "ab")  # no data: reuse
    assert not joint_applies(PopulationConfig(progress=False), data, "abc")
    assert not joint_applies(PopulationConfig(exact=None, progress=False), data, "ab")
    # the fibre map: a θ with the given combinations exactly where p0(φ) > 0 (its support)
    m = spyrou_model()
    names, b = list(m.parameter_names), np.asarray(m.bounds)
    hull = np.log(support_hull(b, names))
    co = PhiCoordinates(names, b, hull, 0.0)
    rng = np.random.default_rng(0)
    phi = rng.uniform(hull[:, 0], hull[:, 1], (3000, 3))
    rest = b[co.other, 0] + rng.random((3000, len(co.other))) * np.ptp(b[co.other], axis=1)
    th, ok = co.theta_of(np.column_stack([phi, rest]))
    assert np.array_equal(ok, np.isfinite(log_density(phi, b, names)))
    assert 0.5 < ok.mean() < 1.0
    assert np.allclose(np.log(to_features(names, th[ok])), phi[ok], atol=1e-12)
    assert np.all((th >= b[:, 0]) & (th <= b[:, 1]))


def test_chains_and_evaluations_round_trip_and_arviz_reads_them(tmp_path):
    """Several chains go to (chain, draw), the evaluations to the root attribute; ArviZ's R-hat of the file
    is that of the chains; a file of one chain (before issue 37) reads as before."""
    az = pytest.importorskip("arviz")
    rng = np.random.default_rng(4)
    C, n, S = 4, 50, 3
    hyper = rng.standard_normal((C * n, 2)) + np.repeat(np.arange(C), n)[:, None]  # chains that disagree
    hf = io.HierarchicalFile(param_names=["a", "b"], hyper_names=["mu_a", "sd_a"], hyper_samples=hyper,
                             specimen_ids=["x", "y", "z"], updated=rng.standard_normal((C * n, S, 2)),
                             new_specimen=rng.standard_normal((C * n - 3, 1)), pooled_names=["a"], chains=C,
                             evaluations=12345)
    path = io.write_hierarchical(hf, tmp_path / "hierarchical.nc")
    back = io.read_hierarchical(path)
    assert back.chains == C and back.evaluations == 12345
    assert np.array_equal(back.hyper_samples, hyper) and np.array_equal(back.updated, hf.updated)
    assert np.array_equal(back.new_specimen, hf.new_specimen)
    post = az.from_netcdf(path).posterior
    assert dict(post.sizes) == {"chain": C, "draw": n}
    assert float(az.rhat(post)["mu_a"]) > 1.5  # the chains' disagreement is seen
    one = io.HierarchicalFile(param_names=["a"], hyper_names=["mu_a"], hyper_samples=hyper[:, :1], specimen_ids=["x"],
                              updated=rng.standard_normal((C * n, 1, 1)))
    back = io.read_hierarchical(io.write_hierarchical(one, tmp_path / "one.nc"))
    assert back.chains == 1 and back.evaluations is None and back.updated.shape == (C * n, 1, 1)
    with pytest.raises(HbmError, match="chains"):
        io.write_hierarchical(io.HierarchicalFile(param_names=["a"], hyper_names=["mu_a"], hyper_samples=hyper[:7, :1],
                                                  specimen_ids=["x"], chains=2), tmp_path / "bad.nc")


def test_report_says_what_the_sampler_did(tmp_path):
    """The joint sampler's summary in the population section; a file of the exact fallback (before issue
    37) is still reported with its own words."""
    from hbm.workflow.report import _how_sampled, _reuse

    layer = {"chains": 16, "n_keep": 250, "n_burn": 300, "evaluations": 98765, "wall_s": 7.5, "rhat_hyper_max": 1.004,
             "ess_hyper_min": 812.0, "rhat_specimen_max": 1.02}
    h = SimpleNamespace(attrs={"layer": layer, "warnings": []}, log_evidence=float("nan"), log_evidence_se=float("nan"))
    txt = _how_sampled(h)
    assert "98,765 model evaluations" in txt and "max R-hat 1.004" in txt and "No hyper-evidence" in txt
    assert "not converged" not in txt
    h.attrs["warnings"] = ["population layer not converged"]
    assert "not converged" in _how_sampled(h)
    reuse = {"a": {"unreliable": True, "reasons": ["population mass beyond the samples"], "ess_q10": 300.0},
             "b": {"unreliable": False, "reasons": [], "ess_q10": 900.0}}
    exact = {"exact": ["a"], "n_chains": 128, "n_keep": 60, "n_burn": 600, "evaluations": {"a": 12345},
             "wall_s": 9.0, "rhat_max": 1.2, "ess_min": 400.0}
    old = SimpleNamespace(reuse=reuse, attrs={"refined": [], "exact": exact})
    txt = _reuse(SimpleNamespace(hierarchical=old), tmp_path)
    assert "joint Gibbs, real likelihood" in txt and "12345 likelihood evaluations" in txt
    old.attrs = {"refined": ["a"]}
    txt = _reuse(SimpleNamespace(hierarchical=old), tmp_path)
    assert "fresh TMCMC" in txt


def test_run_option_hier_exact_reaches_the_population_layer(monkeypatch, tmp_path):
    """``--hier-exact none`` switches the joint sampler off; the default is gibbs; --quick shortens it."""
    class Captured(Exception):
        pass

    def capture(cfg, **kw):
        raise Captured(cfg.population_settings())

    monkeypatch.setenv("HBM_DEBUG", "1")
    monkeypatch.setattr(cli_run, "run_workflow", capture)
    got = {}
    for label, extra in (("default", []), ("none", ["--hier-exact", "none"]), ("quick", ["--quick"])):
        with pytest.raises(Captured) as exc:
            cli.main(["run", "--out", str(tmp_path / "r"), "--no-progress", *extra])
        got[label] = exc.value.args[0]
    assert got["default"].exact == "gibbs" and got["none"].exact is None
    assert got["quick"].layer_burn < got["default"].layer_burn and got["quick"].layer_keep < got["default"].layer_keep


def test_a_layer_short_of_the_targets_keeps_its_warning(capsys):
    """R-hat above 1.01 or bulk ESS below 400 for a hyper-parameter: the warning is printed and returned (the
    file's ``warnings`` and the report carry it); within the targets nothing is."""
    from hbm.population import PopulationConfig
    from hbm.population.layer import _report

    def info(rhat, ess):
        return {"evaluations": 10, "wall_s": 1.0, "rhat_hyper_max": rhat, "rhat_specimen_max": 1.0,
                "ess_hyper_min": ess, "hyper": {"mu_x": {"rhat": rhat, "ess": ess}, "sd_x": {"rhat": 1.0, "ess": 900.0}},
                "chains": 6, "n_keep": 100, "rhat_specimen_worst": "a:x"}

    cfg = PopulationConfig(progress=False)
    assert _report(info(1.005, 900.0), ["x"], cfg) == []
    for rhat, ess in ((1.02, 900.0), (1.005, 58.0)):
        msgs = _report(info(rhat, ess), ["x"], cfg)
        assert len(msgs) == 1 and "not converged: mu_x" in msgs[0] and "--hier-samples 1200" in msgs[0]
        assert "--hier-extend 3" in msgs[0]  # chains that could not go on: how to let them
    assert "WARNING: population layer not converged" in capsys.readouterr().err
    # chains that went on to their cap (300 of 100 planned): the planned draws doubled raise it, no --hier-extend
    capped = {**info(1.02, 900.0), "n_keep": 300, "n_keep_planned": 100, "max_keep": 300}
    msg = _report(capped, ["x"], cfg)[0]
    assert "after extending its chains to 300 draws each" in msg and "--hier-samples 1200 doubles the planned" in msg
    assert "--hier-extend" not in msg


def test_a_population_spread_at_the_hyperprior_floor_is_reported(capsys):
    """sd draws piled at the hyperprior's lower end (sd_range[0] × mu's range) are named with their fraction
    below 1.1 × the floor; a spread well above it is not; the run's warnings carry the line."""
    from hbm.population import PopulationConfig
    from hbm.population.layer import _report, at_floor
    from hbm.samplers.hierarchical import HierarchicalModel

    hm = HierarchicalModel(["a", "b"], np.array([[0.0, 10.0], [-5.0, 5.0]]), sd_range=(0.01, 1.0))
    assert np.allclose(hm.sd_lo, [0.1, 0.1])  # 0.01 × the width 10 of either mu range
    n = 4000
    sd_a = 0.1 * np.linspace(1.0, 1.2, n, endpoint=False)   # half of them below 0.11
    sd_b = np.full(n, 2.0)
    raw = np.column_stack([np.full(n, 5.0), np.zeros(n), np.log(sd_a), np.log(sd_b)])
    got = at_floor(hm, raw)
    assert list(got) == ["sd_a"] and got["sd_a"][0] == pytest.approx(0.5, abs=1e-3)
    assert got["sd_a"][1] == pytest.approx(0.1)
    info = {"evaluations": 10, "wall_s": 1.0, "rhat_hyper_max": 1.0, "rhat_specimen_max": 1.0, "ess_hyper_min": 900.0,
            "hyper": {"sd_a": {"rhat": 1.0, "ess": 900.0}}, "chains": 6, "n_keep": 100, "rhat_specimen_worst": "x:a",
            "sd_at_floor": got}
    msgs = _report(info, ["a", "b"], PopulationConfig(progress=False))
    assert len(msgs) == 1 and "sd_a (50 % of the draws below 1.1 x its floor 0.1)" in msgs[0]
    assert "hyperprior's lower end" in capsys.readouterr().err
    assert at_floor(hm, raw[:, [0, 1, 3, 3]]) == {}


def test_shards_go_to_the_workers_only_with_two_of_each():
    """The joint sampler's shards (at most SHARD_SIZE specimens each) run as actors when there are two shards and two
    workers at least; hbm run submits the specimens' figures after the layer then (not beside it on the same cores)."""
    from hbm.population import shards_on_workers
    from hbm.population.layer import SHARD_SIZE

    class Client:
        def __init__(self, n):
            self.n = n

        def scheduler_info(self):
            return {"workers": {f"w{i}": {} for i in range(self.n)}}

    assert not shards_on_workers(SHARD_SIZE, Client(2))          # one shard
    assert shards_on_workers(SHARD_SIZE + 1, Client(2))
    assert not shards_on_workers(SHARD_SIZE + 1, Client(1))
    assert not shards_on_workers(4 * SHARD_SIZE, None)


def test_the_not_converged_warning_names_what_missed():
    """The run's warning and the sampler's extension read one rule: a hyper-parameter with R-hat 1.02 or ESS 300, a
    specimen column with R-hat 1.06, are named (with the extended length); targets met give no warning."""
    from hbm.population import PopulationConfig
    from hbm.population.layer import _report, converged

    info = {"evaluations": 1, "wall_s": 1.0, "rhat_hyper_max": 1.02, "rhat_specimen_max": 1.06,
            "rhat_specimen_worst": "s1:T2", "ess_hyper_min": 300.0, "chains": 6, "n_keep": 4500, "n_keep_planned": 3000,
            "max_keep": 9000, "hyper": {"mu_a": {"rhat": 1.02, "ess": 900.0}, "sd_a": {"rhat": 1.0, "ess": 300.0},
                                        "mu_b": {"rhat": 1.005, "ess": 900.0}}}
    msg, = _report(info, ["a", "b"], PopulationConfig(progress=False))
    assert "mu_a (R-hat 1.020" in msg and "sd_a (R-hat 1.000, ESS 300)" in msg and "mu_b" not in msg
    assert "s1:T2 (R-hat 1.060)" in msg and "after extending its chains to 4500 draws each" in msg
    ok = {**info, "rhat_specimen_max": 1.01, "hyper": {"mu_b": {"rhat": 1.005, "ess": 900.0}}}
    assert _report(ok, ["b"], PopulationConfig(progress=False)) == []
    assert converged({"hyper:mu_b": 1.005, "0:1": 1.01}, {"hyper:mu_b": 900.0, "0:1": 50.0})
    assert not converged({"hyper:mu_b": 1.005, "0:1": 1.06}, {"hyper:mu_b": 900.0, "0:1": 50.0})
