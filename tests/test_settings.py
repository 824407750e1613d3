"""The settings records (hbm.settings): one declaration per setting gives the rule, the key, the stored
form and the command-line option; renamed concepts keep their stored names; registries feed the choices."""

from __future__ import annotations

import dataclasses
import warnings

import numpy as np
import pytest

from hbm import cli
from hbm._version import __version__
from hbm.errors import HbmWarning, SettingError
from hbm.io.identity import settings_key
from hbm.samplers.moves import MOVES, RandomWalk
from hbm.settings import FitRecord, FitSettings, PopulationSettings, RunSettings, canonical

#: ``run.json``'s ``config`` keys as hbm wrote them before the records (RunConfig's fields, commit 68827b1)
RUN_JSON_KEYS = {"data", "out", "samples", "kernel", "noise", "workers", "scheduler", "seed", "sobol", "sobol_n",
                 "restarts", "sweep", "maxfevals", "fix", "bounds", "hierarchical", "hier_samples", "hier_max_steps",
                 "hier_pooled", "hier_estimator", "hier_transforms", "hier_sd_range", "hier_exact", "hier_extend", "figures",
                 "progress", "retries", "quick", "tmcmc_options", "likelihood", "prior", "sl0", "group_by"}


def _old_record(options: dict) -> dict:
    """How hbm keyed a fit before the records: the keyword arguments given to fit_specimen, unset ones
    left out, in canonical JSON form, plus the version (identity.fit_record of commit 68827b1)."""
    out = {k: canonical(v) for k, v in options.items() if v is not None}
    out["version"] = __version__
    return out


def test_records_key_results_as_before_the_records():
    """The result keys of ``hbm fit`` at its defaults and of every specimen of ``hbm run`` are the ones the
    older option dictionaries gave: a re-run reuses an old run's specimen files."""
    fit_cli = {"samples": 2000, "kernel": "rw", "noise": "iid", "fix": None, "bounds": None, "prior": None, "seed": 0,
               "restarts": 4, "sweep": None, "sobol_n": None, "optimize_options": {"maxfevals": 5000},
               "sigma_bounds": None, "max_evaluations": None, "likelihood": "auto"}
    args = cli.build_parser().parse_args(["fit", "x"])
    assert FitSettings.from_args(args).record() == _old_record(fit_cli)
    seq = np.random.SeedSequence(0).spawn(3)[2]
    run = {"samples": 500, "kernel": "rw", "noise": "iid", "fix": {"EOPT": 0.1}, "bounds": None, "restarts": 2,
           "sweep": "VOLF:0.1", "sobol_n": 128, "tmcmc_options": {"max_evaluations": 9000},
           "optimize_options": {"maxfevals": 2000}, "sigma_bounds": (1e-4, 0.05), "likelihood": "auto", "seed": seq}
    cfg = RunSettings(quick=True, fix={"EOPT": 0.1}, max_evaluations=9000).with_sweep("VOLF")
    new = cfg.fit_settings((1e-4, 0.05), seed=seq).record()
    assert new == _old_record(run) and settings_key(new) == settings_key(_old_record(run))
    assert set(cfg.to_attrs()) == RUN_JSON_KEYS
    assert cfg.to_attrs()["sweep"] == "VOLF:0.1" and cfg.to_attrs()["tmcmc_options"] == {"max_evaluations": 9000}


def test_every_keyed_setting_changes_the_key_and_only_those():
    base = FitSettings(samples=100)
    for name, (_, s) in FitSettings.declared().items():
        other = FitSettings.stored(**{**{n: getattr(base, n) for n in FitSettings.declared()}, name: {"k": 1} if name.endswith(("options", "fix", "bounds")) else 12345})
        assert (settings_key(other.record()) != settings_key(base.record())) == s.keyed, name
    pop = PopulationSettings()
    assert settings_key(pop.replace(progress=False, retries=5).record()) == settings_key(pop.record())
    assert settings_key(pop.replace(layer_keep=50).record()) != settings_key(pop.record())


def test_rules_refuse_bad_settings_when_a_record_is_built():
    with pytest.raises(SettingError, match=r"^samples: expected a sample size >= 20, got 5$"):
        FitSettings(samples=5)
    with pytest.raises(SettingError, match=r"move: expected a TMCMC move: one of rw, manifold, local"):
        FitSettings(move="hmc")
    with pytest.raises(SettingError, match="tier: expected a likelihood tier"):
        FitSettings(tier="fast")
    with pytest.raises(SettingError, match="max_evaluations 99: expected at least the TMCMC population size 100"):
        FitSettings(samples=100, max_evaluations=99)
    with pytest.raises(SettingError, match="sweep"):
        FitSettings(sweep="VOLF:-1")
    with pytest.raises(dataclasses.FrozenInstanceError):
        FitSettings().samples = 30
    assert FitSettings(sobol_n=0).sobol_n is None and FitSettings(sweep=["VOLF", 0.1]).sweep_pair == ("VOLF", 0.1)


def test_older_names_still_work_and_warn():
    with pytest.warns(DeprecationWarning, match="kernel"):
        assert FitSettings(kernel="manifold").move == "manifold"
    with pytest.warns(DeprecationWarning, match="likelihood"):
        assert RunSettings(likelihood="full").tier == "full"
    with pytest.raises(SettingError, match="not both"):
        FitSettings(kernel="rw", move="manifold")
    parser = cli.build_parser()
    with pytest.warns(HbmWarning) as said:  # the command line says it (a DeprecationWarning would be hidden)
        args = parser.parse_args(["fit", "x", "--kernel", "manifold", "--likelihood", "full"])
    assert [str(w.message) for w in said] == ["--kernel is deprecated; use --move",
                                              "--likelihood is deprecated; use --tier"]
    assert (args.move, args.tier) == ("manifold", "full")
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert parser.parse_args(["fit", "x"]).move == "rw"   # the new flags do not warn


def test_a_registered_move_is_a_choice_of_every_command(capsys):
    MOVES["toy_walk"] = RandomWalk
    try:
        for command in ("fit", "run"):
            capsys.readouterr()
            with pytest.raises(SystemExit):
                cli.build_parser().parse_args([command, "--help"])
            assert "toy_walk" in capsys.readouterr().out
        assert FitSettings(move="toy_walk").move == "toy_walk"
    finally:
        MOVES.pop("toy_walk")
    with pytest.raises(SettingError, match="toy_walk"):
        FitSettings(move="toy_walk")


def test_one_tier_vocabulary_and_a_refusal_that_says_why(capsys):
    parser = cli.build_parser()
    for command, extra in (("fit", ["x"]), ("run", []), ("diagnose", ["x"])):
        action = next(a for a in parser._subparsers._group_actions[0].choices[command]._actions
                      if "--tier" in a.option_strings)
        assert tuple(action.choices) == ("auto", "collapsed", "full"), command
    assert parser.parse_args(["diagnose", "x"]).tier == "full"      # diagnose: full by default (its help says why)
    assert parser.parse_args(["run"]).tier == "auto"
    assert cli.main(["run", "--tier", "collapsed", "--no-progress"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--tier collapsed is not offered here" in err[0], err


def test_stored_config_round_trips_and_older_files_read():
    s = FitSettings(samples=300, move="manifold", sweep=("VOLF", 0.05), maxfevals=100, max_evaluations=5000,
                    sigma_bounds=(1e-4, 0.2), tmcmc_options={"n_steps": 3})
    rec = FitRecord(s, seeds={"cmaes": 1}, n_evaluations=10, n_stages=2, tier_used="full", tier_note="why",
                    source_file="f.csv", input="stress kPa->MPa", settings_hash="abc", extra={"flag": True})
    attrs = rec.to_attrs()
    assert attrs["kernel"] == "manifold" and attrs["tmcmc_options"] == {"n_steps": 3, "max_evaluations": 5000}
    assert attrs["optimize_options"] == {"maxfevals": 100} and attrs["sweep"] == ["VOLF", 0.05]
    back = FitRecord.from_attrs(attrs)
    assert back.to_attrs() == attrs and back.settings.move == "manifold" and back.input == "stress kPa->MPa"
    # a file of an older hbm (no tier, no identity) and one of a noise model not registered here
    old = FitRecord.from_attrs({"samples": 10, "kernel": "rw", "noise": "mine"})
    assert (old.settings.noise, old.tier_used, old.identity, old.input) == ("mine", "full", None, "")
