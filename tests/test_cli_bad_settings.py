"""Every subcommand refuses bad settings at parse time: exit 2 and exactly one stderr line
``hbm: error: ...`` naming the option, before any fit runs (issue 14).  Hand-picked cases of the
issue's list; tests/test_cli_validation.py walks every option, tests/test_cli_files.py the
signals and files."""

from __future__ import annotations

import os
import stat
import time
from pathlib import Path

import pytest

from hbm.cli import main

SPEC = "data/specimens/calvo2010_rat1.csv"

BAD = [
    # argparse-level errors: bad int, bad choice, missing argument, unknown subcommand
    ["frob"],
    ["fit"],
    ["fit", SPEC, "--samples", "abc"],
    ["fit", SPEC, "--move", "nope"],
    ["fit", SPEC, "--kernel", "nope"],
    ["fit", SPEC, "--seed", "-1"],
    ["fit", SPEC, "--samples", "3"],
    ["fit", SPEC, "--fix", "EOPT=0.1", "--fix", "EOPT=0.2"],
    ["fit", SPEC, "--fix", "NOPE=1"],
    ["fit", SPEC, "--sweep", "VOLF:0"],
    ["fit", SPEC, "--sweep", "NOPE:0.1"],
    ["fit", SPEC, "--fix", "VOLF=0.8", "--sweep", "VOLF:0.05"],
    ["fit", SPEC] + sum((["--fix", f"{n}={v}"] for n, v in
                         [("VOLF", .8), ("EOPT", .1), ("P1", .1), ("T1", 1), ("T2", 10), ("THETA", 59),
                          ("GF", .01), ("GM", .01)]), []),
    ["fit", SPEC, "--samples", "100000000000"],
    ["optimize", SPEC, "--popsize", "-5"],
    ["optimize", SPEC, "--maxfevals", "-1"],
    ["optimize", SPEC, "--seed", "-1"],
    ["sobol", SPEC, "--n", "1073741824"],
    ["sobol", SPEC, "--n", "1000"],
    ["sobol", SPEC, "--seed", "-1"],
    ["run", "--restarts", "-1"],
    ["run", "--maxfevals", "0"],
    ["run", "--sobol-n", "0"],
    ["run", "--iso-factor", "nan"],
    ["run", "--pool", "NOSUCH"],
    ["run", "--hier-samples", "0"],
    ["run", "--sweep", "VOLF:0"],
    ["run", "--sweep", "NOPE:0.1"],
    ["run", "--seed", "-1"],
    ["run", "--samples", "4"],
    ["diagnose", SPEC, "--plot", "/nonexistent-folder/x.png"],
    ["diagnose", SPEC, "--plot", "fig.nosuchformat"],
    ["diagnose", SPEC, "--seed", "-1"],
    ["extend", SPEC, "--add", "offset,offset"],
    ["extend", SPEC, "--add", "nosuch"],
    ["predict", "organ", "nosuch-results", "--geometry", "nosuch.toml"],
    ["data", "check", "nosuch.csv"],
]


@pytest.mark.parametrize("argv", BAD, ids=[" ".join(a)[:60] for a in BAD])
def test_bad_setting_is_one_line_exit_2(argv, capsys):
    t0 = time.perf_counter()
    rc = main(argv)
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 2, err
    assert len(err) == 1 and err[0].startswith("hbm: error: "), err
    assert time.perf_counter() - t0 < 20  # refused before any fit


def test_out_under_a_file_is_refused_before_fitting(tmp_path, capsys):
    blocker = tmp_path / "file"
    blocker.write_text("x")
    for argv in (["run", "--out", str(blocker)], ["run", "--out", str(blocker / "sub")],
                 ["fit", SPEC, "--out", str(blocker / "sub" / "x.nc")],
                 ["fit", SPEC, "--checkpoint-dir", str(blocker / "ck"), "--out", str(tmp_path / "o.nc")]):
        rc = main(argv)
        err = capsys.readouterr().err.strip().splitlines()
        assert rc == 2 and len(err) == 1 and err[0].startswith("hbm: error: "), (argv, err)
        assert str(blocker) in err[0]


def test_results_honour_the_umask(tmp_path):
    from hbm.runtime.files import atomic_write_text
    old = os.umask(0o022)
    try:
        atomic_write_text(tmp_path / "a.txt", "hello")
        os.umask(0o077)
        atomic_write_text(tmp_path / "b.txt", "hello")
    finally:
        os.umask(old)
    assert stat.S_IMODE((tmp_path / "a.txt").stat().st_mode) == 0o644
    assert stat.S_IMODE((tmp_path / "b.txt").stat().st_mode) == 0o600
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.txt", "b.txt"]  # no temp file left


def test_failed_write_leaves_no_temp_file(tmp_path):
    from hbm.runtime.files import atomic_path

    with pytest.raises(Exception, match="(?i)space|disk"):
        with atomic_path(tmp_path / "r.nc") as tmp:
            tmp.write_text("partial")
            raise OSError(28, "No space left on device")
    assert list(tmp_path.iterdir()) == []


def test_second_run_on_a_locked_out_is_refused(tmp_path, capsys):
    from hbm.runtime.files import output_lock
    with output_lock(tmp_path):
        rc = main(["run", "--out", str(tmp_path), "--quick"])
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 2 and len(err) == 1 and "in use" in err[0], err
