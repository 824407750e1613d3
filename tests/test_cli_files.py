"""Output files of the ``hbm`` command: paths checked before computing, one-line write errors
(also a full disk), permissions from the umask, no temporary file left, a lock on ``hbm run
--out``, and clean Ctrl-C / SIGTERM endings (subprocesses, real signals).

Unwritable locations are made from a path under a regular FILE (``<file>/sub``): that fails for
root too, where a chmod-0500 folder would still be writable.
"""

from __future__ import annotations

import errno
import os
import shutil
import signal
import stat
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import xarray as xr

import hbm
import hbm.cli as cli
from hbm.model import spyrou_model
from hbm.runtime.files import (
    LOCK_NAME, atomic_path, atomic_write_text, output_lock, prepare_output_dir, prepare_output_file,
    remove_stale_temps)

ROOT = Path(__file__).resolve().parents[1]
GEOMETRY = ROOT / "data" / "geometry" / "fusiform.toml"
SPECIMENS = ROOT / "data" / "specimens"
TRUTH = np.array([0.97, 0.192, 0.005, 0.127, 162.0, 59.8, 0.006, 0.006])
TINY_FIT = ["--samples", "20", "--restarts", "0", "--no-progress"]


@pytest.fixture
def specimen(tmp_path):
    e = np.linspace(0.0, 0.42, 25)
    s = spyrou_model().stress(e, TRUTH) + np.random.default_rng(0).normal(0, 0.002, e.size)
    path = tmp_path / "toy.csv"
    path.write_text("# id: toy\nstrain,stress\n" + "".join(f"{a:.6f},{b:.8f}\n" for a, b in zip(e, s)))
    return str(path)


@pytest.fixture
def afile(tmp_path):
    """A regular file: anything below it cannot be created, not even by root."""
    f = tmp_path / "afile"
    f.write_text("x")
    return f


class EngineReached(Exception):
    pass


@pytest.fixture
def no_engines(monkeypatch):
    monkeypatch.setenv("HBM_DEBUG", "1")  # main() re-raises EngineReached

    def reached(*args, **kwargs):
        raise EngineReached
    for name in ("hbm.cli.run.run_workflow", "hbm.cli.fit.fit_specimen", "hbm.cli.predict.predict_organ",
                 "hbm.cli.diagnose.diagnose"):
        monkeypatch.setattr(name, reached)


def one_line_error(argv, capsys) -> str:
    capsys.readouterr()
    rc = cli.main([str(a) for a in argv])
    err = capsys.readouterr().err
    assert rc == 2, (rc, err)
    lines = err.splitlines()
    assert len(lines) == 1 and lines[0].startswith("hbm: error: "), err
    return lines[0]


def temps(folder: Path) -> list[Path]:
    return [p for p in Path(folder).rglob("*.tmp")]


# ------------------------------------------------------------------ paths checked before any work
@pytest.mark.parametrize("argv, words", [
    (["fit", "{s}", "--out", "{f}/sub/x.nc"], ["--out", "afile is a file"]),
    (["fit", "{s}", "--out", "{t}"], ["--out", "is a folder"]),
    (["fit", "{s}", "--checkpoint-dir", "{f}/sub", "--out", "{t}/x.nc"], ["--checkpoint-dir", "afile is a file"]),
    (["fit", "{s}", "--checkpoint-dir", "{f}", "--out", "{t}/x.nc"], ["--checkpoint-dir", "is a file, expected a folder"]),
    (["run", "--out", "{f}"], ["--out", "is a file, expected a folder"]),
    (["run", "--out", "{f}/sub"], ["--out", "afile is a file"]),
    (["run", "--out", "{t}/r", "--data", "{sp}"], ["--out", "specimens is a file"]),
    (["predict", "organ", "{t}", "--geometry", "{g}", "--out", "{f}"], ["--out", "is a file"]),
    (["predict", "organ", "{t}", "--geometry", "{g}", "--out", "{f}/organ"], ["--out", "afile is a file"]),
    (["diagnose", "{s}", "--plot", "{f}/d.png"], ["--plot", "no folder"]),
])
def test_output_paths_refused_before_computing(argv, words, tmp_path, afile, specimen, capsys, no_engines):
    (tmp_path / "r").mkdir()
    (tmp_path / "r" / "specimens").write_text("not a folder")
    argv = [a.replace("{s}", specimen).replace("{f}", str(afile)).replace("{t}", str(tmp_path))
            .replace("{g}", str(GEOMETRY)).replace("{sp}", str(SPECIMENS)) for a in argv]
    line = one_line_error(argv, capsys)
    for w in words:
        assert w in line, line


def test_prepare_output_checks(tmp_path, afile):
    out = prepare_output_dir(tmp_path / "a" / "b", "--out", files=("report.md",), subdirs=("figures",))
    assert out.is_dir() and not list(out.iterdir())  # the probe files are gone
    (out / "report.md").mkdir()
    with pytest.raises(hbm.OutputError, match="report.md is a folder"):
        prepare_output_dir(out, "--out", files=("report.md",))
    with pytest.raises(hbm.OutputError, match="cannot create the folder"):
        prepare_output_dir(afile / "x", "--out")
    with pytest.raises(hbm.OutputError, match="is a folder, expected a file name"):
        prepare_output_file(out, "--out")
    assert prepare_output_file(tmp_path / "new" / "x.nc", "--out").parent.is_dir()


@pytest.mark.skipif(os.geteuid() == 0, reason="root writes into read-only folders")
def test_read_only_folder_refused(tmp_path):
    ro = tmp_path / "ro"
    ro.mkdir()
    ro.chmod(0o500)
    try:
        with pytest.raises(hbm.OutputError, match="cannot create files"):
            prepare_output_dir(ro, "--out")
    finally:
        ro.chmod(0o700)


# ------------------------------------------------------------------ write errors, disk full
def _failing_to_netcdf(exc):
    def to_netcdf(self, path, *args, **kwargs):
        Path(path).write_bytes(b"CDF partial")  # a half-written file, as a real failure leaves
        raise exc
    return to_netcdf


@pytest.mark.parametrize("exc, words", [
    (OSError(errno.ENOSPC, "No space left on device"), ["no space left on the device"]),
    (OSError(errno.EDQUOT, "Disk quota exceeded"), ["disk quota exceeded"]),
    (RuntimeError("NetCDF: HDF error"), ["NetCDF: HDF error", "disk is full", "0 B free"]),
    (PermissionError(errno.EACCES, "Permission denied"), ["Permission denied"]),
])
def test_disk_full_while_writing_is_one_line(exc, words, tmp_path, specimen, capsys, monkeypatch):
    monkeypatch.setattr(xr.DataTree, "to_netcdf", _failing_to_netcdf(exc))
    monkeypatch.setattr("hbm.runtime.files._free_bytes", lambda folder: 0)  # what statvfs says on a full disk
    out = tmp_path / "res" / "toy.nc"
    line = one_line_error(["fit", specimen, "--out", out] + TINY_FIT, capsys)
    assert f"cannot write {out}" in line
    for w in words:
        assert w in line, line
    assert not out.exists() and temps(tmp_path) == []


def test_full_disk_aborts_the_specimen_map():
    """OutputError stops map_specimens (every later task would fail the same way); other task
    errors are collected."""
    from hbm.runtime.parallel import map_specimens

    calls = []

    def task(item, seed):
        calls.append(item)
        if item == "a":
            raise hbm.OutputError("cannot write a.nc: no space left on the device")
        return f"{item}.nc"

    with pytest.raises(hbm.OutputError, match="no space"):
        map_specimens(task, {"a": "a", "b": "b"}, seed=0, progress=False)
    assert calls == ["a"]

    def bad_data(item, seed):
        raise hbm.DataError(f"{item}: bad")
    res = map_specimens(bad_data, {"a": "a", "b": "b"}, seed=0, progress=False)
    assert res.errors == {"a": "a: bad", "b": "b: bad"}


def test_atomic_path_leaves_nothing_on_failure_or_interrupt(tmp_path):
    target = tmp_path / "x.txt"
    target.write_text("old")
    for exc in (ValueError("boom"), KeyboardInterrupt()):
        with pytest.raises(type(exc)):
            with atomic_path(target) as tmp:
                tmp.write_text("half")
                raise exc
        assert target.read_text() == "old" and temps(tmp_path) == []
    with pytest.raises(hbm.OutputError, match=r"cannot write .*afile/x\.txt"):
        (tmp_path / "afile").write_text("")
        atomic_write_text(tmp_path / "afile" / "x.txt", "new")


# ------------------------------------------------------------------ permissions from the umask
@pytest.mark.parametrize("umask, mode", [(0o022, 0o644), (0o027, 0o640), (0o002, 0o664)])
def test_written_files_honour_the_umask(umask, mode, tmp_path, specimen, capsys):
    from hbm.plots import plt, save
    from hbm.samplers.tmcmc import tmcmc

    old = os.umask(umask)
    try:
        out = tmp_path / "fit.nc"
        assert cli.main(["fit", specimen, "--out", str(out)] + TINY_FIT) == 0  # netCDF via io._write_tree
        fig = plt.figure()
        png = save(fig, tmp_path / "f.png")
        txt = tmp_path / "t.md"
        atomic_write_text(txt, "x")
        ck = tmp_path / "ck" / "c.npz"  # TMCMC checkpoint (kept by tmcmc itself)
        tmcmc(lambda th: -0.5 * np.sum(th ** 2, axis=1), np.array([[-3.0, 3.0]] * 2), 20, seed=0,
              checkpoint=ck, progress=False)
        for path in (out, png, txt, ck):
            assert stat.S_IMODE(path.stat().st_mode) == mode, (path, oct(path.stat().st_mode))
    finally:
        os.umask(old)


# ------------------------------------------------------------------ the lock on hbm run --out
def test_second_run_into_a_locked_folder_is_refused(tmp_path, capsys, no_engines):
    out = tmp_path / "res"
    out.mkdir()
    holder = subprocess.Popen([sys.executable, "-c", (
        "import sys, time\n"
        "from hbm.runtime.files import output_lock\n"
        f"with output_lock({str(out)!r}):\n"
        "    print('locked', flush=True)\n"
        "    sys.stdin.read()\n")], stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True, cwd=ROOT)
    try:
        assert holder.stdout.readline().strip() == "locked"
        line = one_line_error(["run", "--out", out, "--data", SPECIMENS], capsys)
        assert line == f"hbm: error: {out} is in use by another hbm run (pid {holder.pid})"
    finally:
        holder.communicate("", timeout=30)
    with pytest.raises(EngineReached):  # released with the process: the next run gets in
        cli.main(["run", "--out", str(out), "--data", str(SPECIMENS)])
    with output_lock(out):  # in this process too, a second lock on another descriptor is refused
        with pytest.raises(hbm.OutputLockedError, match=f"pid {os.getpid()}"):
            with output_lock(out):
                pass


def test_stale_temp_files_removed_at_the_next_start(tmp_path, monkeypatch, capsys):
    out = tmp_path / "res"
    stale = [out / ".report.md.a1b2c3d4.tmp", out / "specimens" / ".rat1.nc.zz_9xy01.tmp",
             out / "checkpoints" / "rat1-abc" / ".rat1.npz.q1w2e3r4.tmp", out / "figures" / ".f.png.00000000.tmp"]
    keep = [out / "specimens" / "notes.tmp", out / "specimens" / ".hidden.tmp", out / "specimens" / "rat1.nc"]
    for p in stale + keep:
        p.parent.mkdir(parents=True, exist_ok=True)
        p.write_text("x")
    seen = {}

    def fake_run(cfg, **kwargs):
        seen["left"] = sorted(str(p.relative_to(out)) for p in out.rglob("*") if p.is_file())
        raise EngineReached
    monkeypatch.setattr("hbm.cli.run.run_workflow", fake_run)
    monkeypatch.setenv("HBM_DEBUG", "1")
    with pytest.raises(EngineReached):
        cli.main(["run", "--out", str(out), "--data", str(SPECIMENS)])
    assert seen["left"] == sorted([LOCK_NAME] + [str(p.relative_to(out)) for p in keep])
    assert "removed 4 temporary file(s)" in capsys.readouterr().err
    # a fit cleans the temp files of its own output file only
    (out / ".toy.nc.abcdefgh.tmp").write_text("x")
    (out / ".other.nc.abcdefgh.tmp").write_text("x")
    assert remove_stale_temps(out, recursive=False, target="toy.nc") == [out / ".toy.nc.abcdefgh.tmp"]


# ------------------------------------------------------------------ Ctrl-C and SIGTERM, real signals
def _sigint_default():
    # A terminal job starts with SIGINT at its default; the test runner itself may not (a shell's
    # background job inherits SIGINT ignored, and hbm rightly keeps ignoring it then).
    signal.signal(signal.SIGINT, signal.SIG_DFL)


def _start(argv, tmp_path, sigint=_sigint_default):
    env = dict(os.environ, PYTHONPATH=str(ROOT), HBM_DEBUG="")
    return subprocess.Popen([sys.executable, "-m", "hbm", *map(str, argv)], cwd=tmp_path, env=env,
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True,
                            start_new_session=True,  # own process group, like a terminal job
                            preexec_fn=sigint)


def _wait_for(predicate, proc, timeout=60.0):
    t = time.monotonic()
    while not predicate():
        assert proc.poll() is None, f"ended early: {proc.returncode} {proc.stderr.read()}"
        assert time.monotonic() - t < timeout, "timed out"
        time.sleep(0.05)


def _signal_and_collect(proc, sig, whole_group=True) -> tuple[int, str]:
    if whole_group:
        os.killpg(proc.pid, sig)  # what a terminal's Ctrl-C does: every process of the job
    else:
        proc.send_signal(sig)
    err = proc.communicate(timeout=60)[1]
    return proc.returncode, err


def test_ctrl_c_during_a_dask_run(tmp_path):
    """SIGINT to the whole process group (main process and dask worker) while a specimen's TMCMC
    runs: exit 130, last line 'hbm: interrupted', no traceback from any process, the checkpoint
    kept, no temporary file."""
    data = tmp_path / "data"
    data.mkdir()
    for sid in ("calvo2010_rat1", "calvo2010_rat2"):
        shutil.copy(SPECIMENS / f"{sid}.csv", data)
    out = tmp_path / "out"
    proc = _start(["run", "--quick", "--data", data, "--out", out, "--workers", "1", "--restarts", "0", "--sweep",
                   "none", "--no-sobol", "--no-figures", "--no-progress"], tmp_path)
    _wait_for(lambda: any((out / "checkpoints").rglob("*.npz")), proc)
    rc, err = _signal_and_collect(proc, signal.SIGINT)
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert rc == 130, err
    assert lines[-1] == "hbm: interrupted", err
    assert "Traceback" not in err and "Error" not in err, err
    assert list((out / "checkpoints").rglob("*.npz")), "checkpoints must be kept"
    assert temps(out) == []


def test_ctrl_c_while_importing(tmp_path):
    proc = _start(["fit", "x.csv"], tmp_path)
    time.sleep(0.3)  # hbm's imports take ~1 s
    rc, err = _signal_and_collect(proc, signal.SIGINT)
    assert (rc, err) == (130, "hbm: interrupted\n")


def test_ctrl_c_ignored_when_started_ignoring_it(tmp_path):
    """Started with SIGINT ignored (``nohup``, a shell's background job), hbm keeps ignoring it:
    the command runs to its own end (here: the missing file's error)."""
    proc = _start(["fit", "x.csv"], tmp_path, sigint=lambda: signal.signal(signal.SIGINT, signal.SIG_IGN))
    time.sleep(0.3)
    rc, err = _signal_and_collect(proc, signal.SIGINT)
    assert rc == 2 and err.startswith("hbm: error:") and "x.csv" in err, err


def test_sigterm_during_a_fit_removes_temp_files(tmp_path, specimen):
    ck = tmp_path / "ck"
    out = tmp_path / "o" / "toy.nc"
    proc = _start(["fit", specimen, "--samples", "3000", "--restarts", "0", "--no-progress", "--checkpoint-dir", ck,
                   "--out", out], tmp_path)
    _wait_for(lambda: list(ck.glob("toy-*/toy.npz")), proc)  # keyed by content: <dir>/<id>-<key>/<id>.npz
    rc, err = _signal_and_collect(proc, signal.SIGTERM, whole_group=False)
    assert rc == 143 and err.splitlines()[-1] == "hbm: interrupted" and "Traceback" not in err, err
    assert len(list(ck.glob("toy-*/toy.npz"))) == 1 and not out.exists()
    assert temps(tmp_path) == []


def test_sigint_handler_of_the_import_guard_only_in_the_command():
    """``import hbm`` elsewhere leaves SIGINT alone (KeyboardInterrupt as usual)."""
    code = "import signal, hbm; print(signal.getsignal(signal.SIGINT) is signal.default_int_handler)"
    res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT,
                         env=dict(os.environ, PYTHONPATH=str(ROOT)), preexec_fn=_sigint_default)
    assert res.stdout.strip() == "True", res.stderr


def test_shipped_specimen_id_resolves_from_another_folder(tmp_path, monkeypatch):
    """``hbm fit calvo2010_rat1`` (the --help example) works from any folder of an editable
    install; a file of that name in ./data/specimens still wins; an unknown id is one error."""
    from hbm.cli._common import load_specimen_arg
    from hbm.errors import HbmError
    monkeypatch.chdir(tmp_path)
    ds = load_specimen_arg("calvo2010_rat1")
    assert ds.id == "calvo2010_rat1" and ds.n_points > 10
    local = tmp_path / "data" / "specimens"
    local.mkdir(parents=True)
    (local / "calvo2010_rat1.csv").write_text("# id: mine\nstrain,stress\n0,0\n0.1,0.01\n0.2,0.03\n0.3,0.06\n0.4,0.1\n0.5,0.15\n")
    assert load_specimen_arg("calvo2010_rat1").attrs["id"] == "mine"
    with pytest.raises(HbmError, match="no_such_rat"):
        load_specimen_arg("no_such_rat")
