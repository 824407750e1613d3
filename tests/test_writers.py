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
from hbm.io.common import _mark_complete as mark_complete
from hbm import io
from hbm.errors import OutputError
from hbm.model import spyrou_model
from hbm.runtime.files import file_lock, file_lock_path, remove_stale_temps
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
        mark_complete(gone)
    assert not gone.exists() and not io.is_complete(gone)


def test_a_live_writers_temp_file_is_not_swept(tmp_path, capsys):
    out = tmp_path / "toy.nc"
    live = tmp_path / ".toy.nc.abcdefgh.tmp"  # the first fit's temp file, being written
    live.write_text("x")
    p = holder("import sys\nfrom hbm.runtime.files import file_lock\n"
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
    p = holder(f"import sys\nfrom hbm.runtime.files import output_lock\nwith output_lock({str(run)!r}):")
    try:
        line = one_line_error(["predict", "organ", run, "--geometry", GEOMETRY, "--no-figures"], capsys)
        assert line == f"hbm: error: {run} is in use by another hbm run (pid {p.pid})"
        assert not (run / "organ" / "organ.nc").exists()
    finally:
        p.communicate("", timeout=30)


# ------------------------------------------------------------------ checkpoints keyed by content
def test_checkpoint_of_changed_data_is_never_resumed(tmp_path, capsys):
    """A checkpoint of other data (one stress value changed) in --checkpoint-dir is set aside with
    one notice; the fit equals a fresh fit bitwise."""
    from hbm.data import load_specimen
    from hbm.fit import fit_specimen

    csv_a = toy_csv(tmp_path / "a.csv")
    ck = tmp_path / "ck"
    # a finished TMCMC checkpoint of the data before the edit, unkeyed (as older hbm fit wrote
    # it) and under another key (as this hbm writes it)
    fit_specimen(load_specimen(csv_a), samples=60, restarts=0, seed=0, checkpoint_dir=ck, progress=False)
    old = ck / "toy.npz"
    assert old.is_file()
    keyed = ck / "toy-0123456789abcdef" / "toy.npz"
    keyed.parent.mkdir()
    keyed.write_bytes(old.read_bytes())
    lines = Path(csv_a).read_text().splitlines()
    k = next(i for i, ln in enumerate(lines) if ln and ln[0].isdigit()) + 10
    cells = lines[k].split(",")
    cells[1] = repr(float(cells[1]) + 0.01)
    lines[k] = ",".join(cells)
    csv_b = tmp_path / "b.csv"
    csv_b.write_text("\n".join(lines) + "\n")
    common = ["fit", csv_b, "--samples", "60", "--restarts", "0", "--no-progress", "--no-plot", "--json"]
    capsys.readouterr()
    assert cli.main([str(a) for a in common + ["--out", tmp_path / "resumed.nc", "--checkpoint-dir", ck]]) == 0
    err = capsys.readouterr().err
    notices = [ln for ln in err.splitlines() if "set aside" in ln]
    assert len(notices) == 1 and "2 checkpoint(s) of toy" in notices[0], err
    assert cli.main([str(a) for a in common + ["--out", tmp_path / "fresh.nc"]]) == 0
    a, b = io.read_specimen_result(tmp_path / "resumed.nc"), io.read_specimen_result(tmp_path / "fresh.nc")
    assert np.array_equal(a.samples, b.samples) and np.array_equal(a.log_likelihood, b.log_likelihood)
    assert a.log_evidence == b.log_evidence
    assert old.read_bytes() == keyed.read_bytes()  # set aside: kept, untouched
    # its own checkpoint is gone with the finished result; the key is stored with it
    assert set(ck.rglob("*.npz")) == {old, keyed}
    assert io.read_attrs(tmp_path / "resumed.nc")["config"]["settings_hash"] == \
        io.read_attrs(tmp_path / "fresh.nc")["config"]["settings_hash"]


def test_one_settings_record_keys_every_fit_argument():
    """Every keyed setting of the fit's record changes the key (the declarations are the list; see
    tests/test_settings.py), and fit_specimen takes exactly the record's settings besides its own."""
    import inspect

    from hbm.fit import fit_specimen
    from hbm.io.identity import settings_key
    from hbm.settings import FitSettings

    base = FitSettings(samples=100)
    for name, (_, s) in FitSettings.declared().items():
        changed = FitSettings.stored(**{**{n: getattr(base, n) for n in FitSettings.declared()}, name: {"k": 1} if name.endswith(("options", "fix", "bounds")) else 12345})
        assert (settings_key(changed.record()) != settings_key(base.record())) == s.keyed, name
    own = set(inspect.signature(fit_specimen).parameters) - {"options"}
    assert own == {"data", "model", "settings", "checkpoint_dir", "out", "progress", "config_extra", "on_phase"}


# ------------------------------------------------------------------ overwrites
def test_out_holding_a_result_of_other_content_is_refused_unless_force(tmp_path, capsys):
    out = tmp_path / "r.nc"
    a, b = toy_csv(tmp_path / "a.csv", "rat_a"), toy_csv(tmp_path / "b.csv", "rat_b", 1.1)
    fit = ["fit", "--out", out, *TINY_FIT]
    assert cli.main([str(x) for x in [fit[0], a, *fit[1:]]]) == 0
    before = out.read_bytes()
    line = one_line_error([fit[0], b, *fit[1:]], capsys)  # another specimen
    assert line == (f"hbm: error: --out {out} holds a result of rat_a with other data; pass --force to replace it, "
                    "or choose another --out")
    line = one_line_error([fit[0], a, *fit[1:], "--seed", "1"], capsys)  # same data, other settings
    assert "holds a result of rat_a with other settings" in line
    assert out.read_bytes() == before
    assert cli.main([str(x) for x in [fit[0], a, *fit[1:]]]) == 0  # the same content: replaced
    assert cli.main([str(x) for x in [fit[0], b, *fit[1:], "--force"]]) == 0
    assert io.read_specimen_result(out).specimen_id == "rat_b"
    other = tmp_path / "notes.nc"
    other.write_text("my notes")
    line = one_line_error([fit[0], a, "--out", other, *TINY_FIT], capsys)
    assert "holds a file that is not an hbm result" in line and other.read_text() == "my notes"


def test_default_outputs_are_untracked():
    """hbm run's (and hbm fit's) default output folder is ignored by git: the README's first command
    leaves 'git status' clean and the shipped reference report in results/ untouched."""
    from hbm.workflow import DEFAULT_OUT, RunConfig

    assert cli.build_parser().parse_args(["run"]).out == DEFAULT_OUT
    assert RunConfig().out == DEFAULT_OUT and not DEFAULT_OUT.startswith("results")
    for name in ("report.md", "run.json", "specimens/x.nc", "figures/x.png", ".hbm.lock", "specimens/.x.nc.lock"):
        res = subprocess.run(["git", "check-ignore", "-q", f"{DEFAULT_OUT}/{name}"], cwd=ROOT)
        assert res.returncode == 0, name
    assert subprocess.run(["git", "ls-files", "--error-unmatch", "results/report.md"], cwd=ROOT,
                          capture_output=True).returncode == 0
