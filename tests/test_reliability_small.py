"""The smaller items of issue 26: Ctrl-C at the last moment, a figure's temp file after a kill,
a stale checkpoint of a finished specimen, a truncated hierarchical.nc, the API refusing what
the command line refuses (one rule per kind), the signed peak of a compression file."""

from __future__ import annotations

import shutil
import time
from pathlib import Path

import numpy as np
import pytest
from test_predict import GEOMETRY, SETTINGS, results_dir  # noqa: F401 - a fixture
from test_writers import TINY_FIT, toy_csv

import hbm
import hbm.cli as cli
from hbm import io
from hbm.errors import HbmError, HbmWarning, SettingError
from test_cli_files import one_line_error


def test_ctrl_c_while_an_error_is_reported_is_still_one_line(monkeypatch, capsys):
    """A Ctrl-C in main's own last moment (here: while it formats an error) ends as 'hbm: interrupted'."""
    def interrupted(exc):
        raise KeyboardInterrupt
    monkeypatch.setattr("hbm.cli._one_line", interrupted)
    capsys.readouterr()
    assert cli.main(["fit", "no_such_specimen"]) == 130
    assert capsys.readouterr().err == "hbm: interrupted\n"


def test_a_killed_figure_writes_temp_file_is_swept_by_the_next_fit(tmp_path):
    csv = toy_csv(tmp_path / "toy.csv")
    stale = tmp_path / ".toy.png.abcdefgh.tmp"  # left by a kill -9 during the figure write
    stale.write_bytes(b"\x89PNG half")
    keep = tmp_path / ".other.png.abcdefgh.tmp"
    keep.write_bytes(b"x")
    argv = ["fit", csv, "--out", tmp_path / "toy.nc", *[a for a in TINY_FIT if a != "--no-plot"]]
    assert cli.main([str(a) for a in argv]) == 0
    assert not stale.exists() and keep.exists() and (tmp_path / "toy.png").stat().st_size > 1000


def test_stale_checkpoint_of_a_finished_specimen_is_removed(tmp_path):
    from hbm.workflow import RunConfig, run_workflow

    data = tmp_path / "data"
    data.mkdir()
    toy_csv(data / "s1.csv", "s1")
    cfg = RunConfig(data=str(data), out=str(tmp_path / "out"), samples=40, restarts=0, sweep=None, sobol=False,
                    hierarchical=False, figures=False, workers=0, progress=False)
    run_workflow(cfg)
    key = io.read_attrs(tmp_path / "out" / "specimens" / "s1.nc")["config"]["settings_hash"]
    stale = tmp_path / "out" / "checkpoints" / f"s1-{key}" / "s1.npz"
    stale.parent.mkdir(parents=True)
    stale.write_bytes(b"left after the result was written")  # e.g. its removal failed
    w = run_workflow(cfg)
    assert w.skipped == ["s1"] and not stale.exists() and not stale.parent.exists()


def test_predict_warns_about_a_truncated_hierarchical_file(results_dir, tmp_path):  # noqa: F811
    from hbm.workflow.organ import predict_organ

    src = results_dir[0]
    run = tmp_path / "run"
    shutil.copytree(src / "specimens", run / "specimens")
    h = (src / "hierarchical.nc").read_bytes()
    (run / "hierarchical.nc").write_bytes(h[: len(h) // 2])
    with pytest.warns(HbmWarning, match="hierarchical.nc is incomplete or unreadable"):
        pred = predict_organ(run, GEOMETRY, out=tmp_path / "organ", **SETTINGS)
    assert pred.organ.population is None  # without the layer, and said so
    assert all(set(by_source) == {"posterior", "optima"} for by_source in pred.organ.curves.values())


@pytest.mark.parametrize("call, fragment", [
    (lambda: hbm.spyrou_model(iso_factor=float("nan")), "iso_factor: expected a finite number > 0"),
    (lambda: hbm.spyrou_model(iso_factor=-1), "iso_factor"),
    (lambda: _fit(seed=-1), "seed: expected a seed"),
    (lambda: _fit(seed=2 ** 32), "seed"),
    (lambda: _fit(bounds={"VOLF": (0.0, 2.0)}), "VOLF=0:2: outside what VOLF can physically be ([0, 1])"),
    (lambda: _optimize(popsize=-5), "popsize: expected an integer >= 2"),
    (lambda: _optimize(seed=-1), "seed: expected an integer >= 0"),
])
def test_the_api_refuses_what_the_cli_refuses(call, fragment):
    with pytest.raises(SettingError) as info:
        call()
    assert fragment in str(info.value)
    assert isinstance(info.value, HbmError) and isinstance(info.value, ValueError)


def test_workers_capped_with_a_clear_message(capsys):
    from hbm.runtime.parallel import dask_client
    from hbm.settings.rules import MAX_WORKERS_PER_CORE

    with pytest.raises(SettingError, match="worker processes on .* expected at most"):
        with dask_client(100000):
            pass
    line = one_line_error(["run", "--workers", "100000"], capsys)
    assert "--workers" in line and f"({MAX_WORKERS_PER_CORE} per core" in line
    line = one_line_error(["fit", "calvo2010_rat1", "--bounds", "VOLF=0:2"], capsys)
    assert line == ("hbm: error: --bounds VOLF=0:2: outside what VOLF can physically be ([0, 1]); expected a box "
                    "inside it")


def test_data_check_prints_the_signed_peak_of_a_compression_file(tmp_path, capsys):
    e = -np.linspace(0, 0.2, 8)
    s = -0.0023 * (e / e.min()) ** 2
    p = tmp_path / "comp.csv"
    p.write_text("# id: comp\nstrain,stress\n" + "".join(f"{a:.4f},{b:.6g}\n" for a, b in zip(e, s)))
    capsys.readouterr()
    assert cli.main(["data", "check", str(p)]) == 0
    out = capsys.readouterr().out
    assert "peak stress [MPa]" in out and "-0.0023" in out.splitlines()[2]


def _fit(**kw):
    from hbm.data import load_specimen
    from hbm.fit import fit_specimen

    data = load_specimen(Path(__file__).resolve().parents[1] / "data" / "specimens" / "calvo2010_rat1.csv")
    return fit_specimen(data, samples=20, restarts=0, progress=False, **kw)


def _optimize(**kw):
    from hbm.data import load_specimen
    from hbm.likelihood import make_likelihood
    from hbm.fit.optimization import optimize

    data = load_specimen(Path(__file__).resolve().parents[1] / "data" / "specimens" / "calvo2010_rat1.csv")
    return optimize(make_likelihood(hbm.spyrou_model(), data), restarts=1, maxfevals=10, **kw)


@pytest.mark.slow
def test_ctrl_c_after_the_last_line_never_kills_by_the_signal(tmp_path):
    """A Ctrl-C right after `hbm fit` printed its last line (its process is finishing) ends with
    the command's status: 130 with 'hbm: interrupted', or 0 -- never death by SIGINT (-2)."""
    import os
    import signal
    import subprocess
    import sys

    csv = toy_csv(tmp_path / "toy.csv")
    env = {**os.environ, "PYTHONPATH": str(Path(__file__).resolve().parents[1])}
    argv = [sys.executable, "-m", "hbm", "fit", csv, "--samples", "100", "--restarts", "0", "--no-progress",
            "--no-plot", "--out", str(tmp_path / "t.nc"), "--force"]
    for k in range(6):
        p = subprocess.Popen(argv, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env,
                             preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
        for line in p.stdout:
            if line.startswith("wrote "):
                break
        time.sleep(0.01 * k)
        p.send_signal(signal.SIGINT)
        _, err = p.communicate(timeout=60)
        assert p.returncode in (0, 130), (k, p.returncode, err[-500:])
        assert p.returncode == 0 or err.splitlines()[-1] == "hbm: interrupted"
        assert "Traceback" not in err and "Fatal Python error" not in err
