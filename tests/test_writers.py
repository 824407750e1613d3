"""The one writer rule (issue 26): one lock per output path, temporary files swept only by the
lock holder, completion marked on an existing file only, every command writing into a run
folder under the run's lock.  Real processes (subprocesses hold the locks), real fits.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

import hbm.cli as cli
from hbm import io
from hbm.errors import OutputError
from hbm.model import spyrou_model
from hbm.utils import file_lock, file_lock_path, remove_stale_temps
from test_cli_files import one_line_error

ROOT = Path(__file__).resolve().parents[1]
GEOMETRY = ROOT / "data" / "geometry" / "fusiform.toml"
TRUTH = np.array([0.97, 0.192, 0.005, 0.127, 162.0, 59.8, 0.006, 0.006])
TINY_FIT = ["--samples", "20", "--restarts", "0", "--no-progress", "--no-plot"]
ENV = {**os.environ, "PYTHONPATH": str(ROOT)}


def toy_csv(path: Path, sid: str = "toy", scale: float = 1.0) -> str:
    e = np.linspace(0.0, 0.42, 25)
    s = scale * spyrou_model().stress(e, TRUTH) + np.random.default_rng(0).normal(0, 0.002, e.size)
    path.write_text(f"# id: {sid}\nstrain,stress\n" + "".join(f"{a:.6f},{b:.8f}\n" for a, b in zip(e, s)))
    return str(path)


def holder(code: str) -> subprocess.Popen:
    """A process that runs ``code`` (which takes a lock), prints 'locked' and waits for stdin."""
    p = subprocess.Popen([sys.executable, "-c", code + "\n    print('locked', flush=True)\n    sys.stdin.read()\n"],
                         stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True, cwd=ROOT, env=ENV)
    assert p.stdout.readline().strip() == "locked"
    return p


def test_completion_is_never_marked_on_a_missing_file(tmp_path):
    # before: netCDF's append mode created a 239-byte file that is_complete() accepted
    gone = tmp_path / "gone.nc"
    with pytest.raises(OutputError, match="vanished"):
        io._mark_complete(gone)
    assert not gone.exists() and not io.is_complete(gone)


def test_a_live_writers_temp_file_is_not_swept(tmp_path, capsys):
    out = tmp_path / "toy.nc"
    live = tmp_path / ".toy.nc.abcdefgh.tmp"  # the first fit's temp file, being written
    live.write_text("x")
    p = holder("import sys\nfrom hbm.utils import file_lock\n"
               f"with file_lock({str(out)!r}, '--out'):")
    try:
        assert remove_stale_temps(tmp_path, recursive=True) == []  # e.g. hbm run's sweep of its folder
        assert remove_stale_temps(tmp_path, recursive=False, target="toy.nc") == []
        line = one_line_error(["fit", toy_csv(tmp_path / "toy.csv"), "--out", out, *TINY_FIT], capsys)
        assert line == (f"hbm: error: --out {out} is being written by another hbm process; wait for it to finish "
                        f"or choose another output (pid {p.pid})")
        assert live.exists() and not out.exists()
    finally:
        p.communicate("", timeout=30)
    # released with the process: the lock holder now sweeps the leftover
    with file_lock(out):
        assert remove_stale_temps(tmp_path, recursive=False, target="toy.nc") == [live]


def test_two_fits_into_one_out(tmp_path):
    """The second fit starts while the first runs (held by SIGSTOP so that the order is certain):
    refused with one line; the first fit's file is complete."""
    csv = toy_csv(tmp_path / "toy.csv")
    out = tmp_path / "toy.nc"
    argv = [sys.executable, "-m", "hbm", "fit", csv, "--out", str(out), *TINY_FIT, "--samples", "200"]
    first = subprocess.Popen(argv, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=tmp_path, env=ENV)
    lock = file_lock_path(out)
    deadline = time.time() + 60
    while not (lock.is_file() and lock.read_text().strip() == str(first.pid)) and time.time() < deadline:
        assert first.poll() is None, first.communicate()
        time.sleep(0.01)
    os.kill(first.pid, signal.SIGSTOP)
    try:
        second = subprocess.run(argv, capture_output=True, text=True, cwd=tmp_path, env=ENV, timeout=120)
    finally:
        os.kill(first.pid, signal.SIGCONT)
    o1, e1 = first.communicate(timeout=300)
    assert first.returncode == 0, e1
    assert second.returncode == 2, second.stderr
    assert second.stderr.splitlines() == [f"hbm: error: --out {out} is being written by another hbm process; wait "
                                          f"for it to finish or choose another output (pid {first.pid})"]
    assert io.is_complete(out)
    r = io.read_specimen_result(out)
    assert r.specimen_id == "toy" and r.samples.shape[0] == 200
    assert not list(tmp_path.glob(".toy.nc.*.tmp"))


def test_predict_against_a_running_run_is_refused(tmp_path, capsys):
    run = tmp_path / "run"
    (run / "specimens").mkdir(parents=True)
    p = holder(f"import sys\nfrom hbm.utils import output_lock\nwith output_lock({str(run)!r}):")
    try:
        line = one_line_error(["predict", "organ", run, "--geometry", GEOMETRY, "--no-figures"], capsys)
        assert line == f"hbm: error: {run} is in use by another hbm run (pid {p.pid})"
        assert not (run / "organ" / "organ.nc").exists()
    finally:
        p.communicate("", timeout=30)
