"""Every option of every ``hbm`` subcommand is validated before anything is computed.

The parser is walked: every option with a value rule (``type=``) or a list of choices gets bad
values, and each must end as exit status 2 with exactly one stderr line ``hbm: error: ...``
naming the option.  The engines (fit, run, optimize, Sobol, diagnose, organ prediction) are
replaced by a sentinel that fails the test if reached, so no case can pass by computing.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import pytest

import hbm
import hbm.cli as cli
from hbm.cli import _common as rules
from hbm.settings import rules as setting_rules
from hbm.model import spyrou_model

ROOT = Path(__file__).resolve().parents[1]
GEOMETRY = ROOT / "data" / "geometry" / "fusiform.toml"
TRUTH = np.array([0.97, 0.192, 0.005, 0.127, 162.0, 59.8, 0.006, 0.006])
ENGINES = {"run": ["run_workflow"], "fit": ["fit_specimen"], "optimize": ["optimize"], "sobol": ["sobol"],
           "diagnose": ["diagnose", "extend"], "predict": ["predict_organ"], "export": ["export"]}


class EngineReached(Exception):
    """Raised by the patched engines: the command got past its checks."""


@pytest.fixture
def no_engines(monkeypatch):
    """Replace every engine the CLI calls by a sentinel raising EngineReached (propagated:
    HBM_DEBUG makes hbm.cli.main re-raise unexpected exceptions)."""
    monkeypatch.setenv("HBM_DEBUG", "1")

    def reached(*args, **kwargs):
        raise EngineReached
    for module, names in ENGINES.items():
        for name in names:
            monkeypatch.setattr(f"hbm.cli.{module}.{name}", reached)


@pytest.fixture
def specimen(tmp_path):
    e = np.linspace(0.0, 0.42, 25)
    s = spyrou_model().stress(e, TRUTH) + np.random.default_rng(0).normal(0, 0.002, e.size)
    path = tmp_path / "toy.csv"
    lines = ["# id: toy", "strain,stress"] + [f"{a:.6f},{b:.8f}" for a, b in zip(e, s)]
    path.write_text("\n".join(lines) + "\n")
    return str(path)


def run_cli(argv, capsys):
    capsys.readouterr()
    rc = cli.main([str(a) for a in argv])
    out, err = capsys.readouterr()
    return rc, out, err


def one_line_error(argv, capsys) -> str:
    rc, _, err = run_cli(argv, capsys)
    assert rc == 2, (argv, rc, err)
    lines = err.splitlines()
    assert len(lines) == 1 and lines[0].startswith("hbm: error: "), (argv, err)
    return lines[0]


# ------------------------------------------------------------------ the walk over the parser
def _subparsers(parser: argparse.ArgumentParser, prefix=()):
    """(command words, parser) for every leaf command."""
    subs = [a for a in parser._actions if isinstance(a, argparse._SubParsersAction)]
    if not subs:
        yield prefix, parser
        return
    for name, sub in subs[0].choices.items():
        yield from _subparsers(sub, prefix + (name,))


def _bad_prior(tmp_path: Path) -> str:
    """A prior file whose loguniform lower edge is not positive."""
    path = tmp_path / "bad_prior.toml"
    path.write_text("[P1]\nlo = 0\nhi = 1\nform = 'loguniform'\n")
    return str(path)


def _bad_values(action: argparse.Action, tmp_path: Path) -> list[str]:
    """Values that the option's rule must refuse."""
    t = action.type
    if action.choices is not None:
        return ["bogus"]
    named = {rules.seed: ["-1", str(rules.SEED_LIMIT), "1.5", "x"],
             rules.positive_int: ["0", "-3", "2.5"], rules.non_negative_int: ["-1", "x"],
             rules.workers: ["-1", "x", "100000"],
             rules.sample_size: [str(rules.MIN_SAMPLES - 1), "0", "-5", "many"],
             rules.power_of_two: ["0", "1", "1000", "-8"], rules.power_of_two_or_zero: ["3", "-2"],
             rules.positive_float: ["0", "-1", "nan", "inf"], rules.name_list: ["a,,b", "a,a", ","],
             rules.fix_item: ["EOPT", "EOPT=nan", "=1", "EOPT=x"],
             rules.bounds_item: ["VOLF=0.7", "VOLF=0.8:0.7", "VOLF=a:b", "VOLF=0:inf"],
             rules.sweep: ["VOLF", "VOLF:0", "VOLF:-0.1", "VOLF:nan"], rules.run_sweep: ["VOLF", "VOLF:0", "VOLF:nan"],
             rules.value_range: ["1:0", "1", "0:nan"], setting_rules.RANGE: ["1:0", "1", "0:nan"],
             rules.plot_path: [str(tmp_path / "nowhere" / "f.png"), str(tmp_path / "f.xyz"), str(tmp_path)],
             rules.prior_file: [str(tmp_path / "none.toml"), str(tmp_path), _bad_prior(tmp_path)]}
    if t in named:
        return named[t]
    name = getattr(t, "__name__", "")
    if name.startswith("integer>="):
        lo = int(name.split(">=")[1])
        return [str(lo - 1), "x"]
    if name == "number":  # real(minimum)
        return ["nan", "-inf", "abc", "-1e9"]
    raise AssertionError(f"{action.option_strings}: no bad values known for rule {t!r}")


def _valid_positionals(words, specimen, tmp_path) -> list[str]:
    """Valid required arguments, so that the error can only come from the option under test."""
    if words[0] == "run":  # (an --out of its own: a missed check must not write into the repository)
        return ["--out", str(tmp_path / "run-out")]
    if words[0] == "predict":
        return [str(tmp_path), "--geometry", str(GEOMETRY)]
    return [specimen]


def _cases(tmp_path, specimen):
    cases = []
    for words, parser in _subparsers(cli.build_parser()):
        for action in parser._actions:
            if not action.option_strings or action.help == argparse.SUPPRESS:
                continue
            if action.type is None and action.choices is None:
                continue
            for bad in _bad_values(action, tmp_path):
                cases.append((list(words) + _valid_positionals(words, specimen, tmp_path)
                              + [action.option_strings[0], bad], action.option_strings[0]))
    return cases


def test_walk_covers_every_command_and_rule(tmp_path, specimen):
    cases = _cases(tmp_path, specimen)
    commands = {c[0][0] for c in cases}
    assert commands == {"run", "fit", "optimize", "sobol", "diagnose", "extend", "predict", "data",  # data: --sl0
                        "export"}  # export: --to
    options = {(c[0][0], c[1]) for c in cases}
    for cmd in ("run", "fit", "optimize", "sobol", "diagnose", "extend", "predict"):
        assert (cmd, "--seed") in options, cmd
    for opt in ("--samples", "--sobol-n", "--hier-samples", "--restarts", "--maxfevals", "--workers", "--retries",
                "--sweep", "--pool", "--fix", "--bounds", "--iso-factor", "--move", "--tier", "--noise"):
        assert ("run", opt) in options, opt
    assert ("diagnose", "--plot") in options and ("extend", "--add") in options
    assert ("optimize", "--popsize") in options and ("predict", "--extrapolate") in options
    assert len(cases) >= 200  # 7 commands x their typed options x 1-4 bad values each


def test_every_bad_option_value_is_one_line_exit_2(tmp_path, specimen, capsys, no_engines):
    for argv, option in _cases(tmp_path, specimen):
        line = one_line_error(argv, capsys)
        assert option in line, (argv, line)


# ------------------------------------------------------------------ argparse's own errors
@pytest.mark.parametrize("argv, words", [
    (["nosuch"], ["invalid choice", "nosuch"]),
    (["fit"], ["fit:", "required", "SPECIMEN"]),
    (["fit", "x.csv", "--samples"], ["--samples", "expected one argument"]),
    (["run", "--no-such-option"], ["unrecognized arguments", "--no-such-option"]),
    (["predict", "organ", "results"], ["predict organ:", "--geometry"]),
    ([], ["expected a command", "run"]),
    (["data"], ["expected an action"]),
    (["predict"], ["expected a target"]),
])
def test_parser_errors_are_one_line(argv, words, capsys):
    line = one_line_error(argv, capsys)
    for w in words:
        assert w in line, line


def test_help_still_exits_0(capsys):
    with pytest.raises(SystemExit) as info:
        cli.main(["fit", "--help"])
    assert info.value.code == 0
    assert "--checkpoint-dir" in capsys.readouterr().out


# ------------------------------------------------------------------ checks that need the model
@pytest.mark.parametrize("argv, words", [
    (["run", "--sweep", "NOPE:0.1"], ["--sweep", "NOPE", "not a model parameter"]),
    (["run", "--sweep", "VOLF:0.1", "--fix", "VOLF=0.9"], ["--sweep", "VOLF is fixed", "--sweep none"]),
    (["fit", "{s}", "--sweep", "VOLF:0.1", "--fix", "VOLF=0.9"], ["--sweep", "fixed"]),
    (["optimize", "{s}", "--sweep", "GG:0.1"], ["--sweep", "GG"]),
    (["run", "--pool", "NOSUCH"], ["--pool", "NOSUCH", "free model parameters"]),
    (["run", "--pool", "T2,EOPT", "--fix", "EOPT=0.1"], ["--pool", "EOPT"]),
    (["run", "--pool", "auto,T2"], ["--pool"]),
    (["optimize", "{s}", "--fix", "EOPT=0.1", "--fix", "EOPT=0.2"], ["--fix", "EOPT given twice"]),
    (["sobol", "{s}", "--bounds", "T2=150:175", "--bounds", "T2=160:170"], ["--bounds", "T2 given twice"]),
    (["optimize", "{s}", "--fix", "VOLF=0.9", "--fix", "EOPT=0.1", "--fix", "P1=0.01", "--fix", "T1=1", "--fix",
      "T2=100", "--fix", "THETA=58", "--fix", "GF=0.01", "--fix", "GM=0.01"], ["--fix", "all 8", "free"]),
    (["fit", "{s}", "--effect", "nosuch_effect"], ["nosuch_effect"]),
    (["extend", "{s}", "--add", "offset,offset"], ["--add", "offset given twice"]),
    (["extend", "{s}", "--model", "offset", "--add", "offset"], ["--add offset", "already in the model"]),
    (["extend", "{s}", "--add", "no_such_effect"], ["no_such_effect"]),
    (["extend", "{s}"], ["--add", "--auto"]),
    (["diagnose", "{s}", "--candidates", "no_such_effect"], ["no_such_effect"]),
    (["diagnose", "{s}", "--candidates", "none"], ["nothing to screen"]),
    (["diagnose", "{s}", "--fix", "S0=0"], ["--fix", "S0"]),
    (["diagnose", "{s}", "--plot", "{t}/missing/d.png"], ["--plot", "no folder"]),
    (["diagnose", "{s}", "--plot", "{t}/d.xyz"], ["--plot", ".xyz", ".png"]),
    (["run", "--data", "{t}/no_such_folder"], ["no_such_folder"]),
    (["optimize", "{t}/missing.csv"], ["missing.csv"]),
])
def test_model_dependent_checks_before_any_work(argv, words, tmp_path, specimen, capsys, no_engines):
    argv = [a.replace("{s}", specimen).replace("{t}", str(tmp_path)) for a in argv]
    line = one_line_error(argv, capsys)
    for w in words:
        assert w in line, line


def test_valid_settings_reach_the_engine(tmp_path, specimen, capsys, no_engines):
    """The checks refuse only what is wrong: valid command lines get through to the engine."""
    for argv in (["fit", specimen, "--fix", "VOLF=0.9", "--sweep", "T1:0.5", "--out", tmp_path / "a.nc",
                  "--checkpoint-dir", tmp_path / "ck", "--seed", str(rules.SEED_LIMIT - 1)],
                 ["optimize", specimen, "--popsize", "2", "--maxfevals", "1"],
                 ["sobol", specimen, "--n", "2", "--effect", "offset", "--fix", "S0=0"],
                 ["extend", specimen, "--model", "offset", "--add", "damage", "--samples", str(rules.MIN_SAMPLES)],
                 ["diagnose", specimen, "--candidates", "offset,slack", "--plot", tmp_path / "d.svg"],
                 ["predict", "organ", tmp_path, "--geometry", GEOMETRY, "--samples", str(rules.MIN_SAMPLES)],
                 ["run", "--data", ROOT / "data" / "specimens", "--out", tmp_path / "r", "--pool", "T2,THETA",
                  "--sweep", "none", "--fix", "VOLF=0.9"]):
        with pytest.raises(EngineReached):
            cli.main([str(a) for a in argv])


# ------------------------------------------------------------------ memory that cannot exist
def test_sizes_refused_from_a_memory_estimate(tmp_path, specimen, capsys, monkeypatch, no_engines):
    """The estimate is a lower bound, computed by hand here: Sobol N*(D+2) rows of (points + all
    parameters + free parameters) float64; a TMCMC population N x (points + parameters + noise)."""
    monkeypatch.setattr("hbm.runtime.memory.available_memory", lambda: 1 << 30)  # a 1 GiB machine
    n = 2 ** 20  # 8 free parameters, 25 points: 2^20 * 10 rows * (25 + 8 + 8) * 8 B = 3.2 GiB
    line = one_line_error(["sobol", specimen, "--n", str(n)], capsys)
    assert f"--n {n}" in line and "3.2 GiB" in line and "1.0 GiB available" in line
    with pytest.raises(EngineReached):  # 2^17 -> 0.4 GiB fits
        cli.main(["sobol", specimen, "--n", str(2 ** 17)])
    # fit: N * (25 points + 8 parameters + 2 noise) * 8 B: 4M -> 1.04 GiB > 1 GiB, 3M -> 0.78 GiB
    line = one_line_error(["fit", specimen, "--samples", "4000000", "--out", tmp_path / "x.nc"], capsys)
    assert "--samples 4000000" in line and "1.0 GiB" in line
    with pytest.raises(EngineReached):
        cli.main(["fit", specimen, "--samples", "3000000", "--out", str(tmp_path / "x.nc")])
    assert not (tmp_path / "x.nc").exists()
    line = one_line_error(["optimize", specimen, "--popsize", "1000000", "--restarts", "4"], capsys)
    assert "--popsize 1000000" in line and "8000000" in line  # IPOP doubles it three times
    line = one_line_error(["run", "--data", ROOT / "data" / "specimens", "--out", tmp_path / "r",
                           "--hier-samples", str(10 ** 6)], capsys)
    assert "--hier-samples" in line
    assert not (tmp_path / "r").exists()  # refused before the output folder was made
    line = one_line_error(["predict", "organ", tmp_path, "--geometry", GEOMETRY, "--samples", str(10 ** 6),
                           "--forces", "1000"], capsys)
    assert "--samples 1000000 with --forces 1000" in line


# ------------------------------------------------------------------ the API side
def test_error_hierarchy_is_exported():
    assert issubclass(hbm.SettingError, hbm.HbmError) and issubclass(hbm.SettingError, ValueError)
    assert issubclass(hbm.TooLargeError, hbm.SettingError)
    assert issubclass(hbm.OutputError, hbm.HbmError) and issubclass(hbm.OutputError, OSError)
    assert issubclass(hbm.OutputLockedError, hbm.OutputError)
    assert issubclass(hbm.DataError, hbm.HbmError) and hbm.errors.HbmError is hbm.HbmError
    for name in ("HbmError", "DataError", "SettingError", "TooLargeError", "OutputError", "OutputLockedError"):
        assert name in hbm.__all__


def test_require_memory_compares_with_available(monkeypatch):
    from hbm.runtime.memory import require_memory

    monkeypatch.setattr("hbm.runtime.memory.available_memory", lambda: 1000)
    require_memory(1000, "x")
    with pytest.raises(hbm.TooLargeError, match="needs at least 1001 B"):
        require_memory(1001, "x")
    monkeypatch.setattr("hbm.runtime.memory.available_memory", lambda: None)  # unknown: no refusal
    require_memory(1e30, "x")
