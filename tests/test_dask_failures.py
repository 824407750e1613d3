"""The dask layer never waits without a deadline (issue 26): a specimen whose worker keeps
dying fails after a bounded number of deaths, and a cluster without workers fails the run with
one line."""

from __future__ import annotations

import os
import subprocess
import sys
import time
from pathlib import Path

import pytest

from hbm import io
from hbm.errors import HbmError
from hbm.runtime.parallel import ALLOWED_FAILURES, map_specimens
from test_writers import toy_csv

sys.path.insert(0, str(Path(__file__).resolve().parent / "data"))
from kill_effect import KILL_STRAIN  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]


class _NeverDone:
    def done(self):
        return False


class _EmptyCluster:
    """A client whose workers are all gone: tasks never finish."""

    def submit(self, *args, **kwargs):
        return _NeverDone()

    def scheduler_info(self):
        return {"workers": {}}


def _never(item, seed):  # pragma: no cover - never runs
    raise AssertionError


def test_a_cluster_without_workers_fails_the_run_with_one_line():
    t = time.perf_counter()
    with pytest.raises(HbmError, match=r"no workers for 0 s; 2 specimen\(s\) unfinished \(a, b;"):
        map_specimens(_never, {"a": 1, "b": 2}, seed=0, client=_EmptyCluster(), progress=False, poll=0.01,
                      no_worker_timeout=0.1)
    assert time.perf_counter() - t < 10


@pytest.mark.slow
def test_a_worker_killed_three_times_fails_its_specimen_within_a_minute(tmp_path):
    data = tmp_path / "data"
    data.mkdir()
    toy_csv(data / "s1.csv", "s1")
    toy_csv(data / "s2.csv", "s2", 1.1)
    # s1 reaches the strain at which the test effect kills the worker that fits it
    s1 = (data / "s1.csv").read_text().replace("0.420000,", f"{KILL_STRAIN:.6f},")
    (data / "s1.csv").write_text(s1)
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    t = time.perf_counter()
    p = subprocess.run([sys.executable, "-m", "hbm", "run", "--data", str(data), "--out", str(tmp_path / "out"),
                        "--samples", "40", "--restarts", "0", "--sweep", "none", "--no-sobol", "--no-hierarchical",
                        "--no-figures", "--workers", "2", "--no-progress",
                        "--effect", f"{ROOT / 'tests' / 'data' / 'kill_effect.py'}:KillWorker"],
                       capture_output=True, text=True, env=env, timeout=120)
    wall = time.perf_counter() - t
    errors = [ln for ln in p.stderr.splitlines() if ln.startswith("hbm: error:")]
    assert p.returncode == 1, p.stderr
    assert errors == [f"hbm: error: 1 specimen(s) failed -- s1: its worker process died {ALLOWED_FAILURES + 1} "
                      "times while running it (killed by the system, e.g. out of memory?); not retried"], p.stderr
    assert "Traceback" not in p.stderr
    assert io.is_complete(tmp_path / "out" / "specimens" / "s2.nc")
    assert not (tmp_path / "out" / "specimens" / "s1.nc").exists()
    assert wall < 60, wall


def test_background_priority_lowers_a_process_to_its_niceness_once():
    """The workers that complete the specimens beside the layer run at BACKGROUND_NICENESS: raised once,
    never lowered (a process already nicer stays as it is)."""
    code = ("import os\nfrom hbm.runtime.parallel import BACKGROUND_NICENESS as n, background_priority as b\n"
            "s = os.nice(0)\nb()\nb()\nprint(s, os.nice(0), n)")
    for start in (0, 15):
        p = subprocess.run(["nice", "-n", str(start), sys.executable, "-c", code], capture_output=True, text=True,
                           env={**os.environ, "PYTHONPATH": str(ROOT)}, timeout=60)
        assert p.returncode == 0, p.stderr
        before, after, n = map(int, p.stdout.split())
        assert n == 10 and after == max(before, n)


class _Done:
    def __init__(self, value=None, exc=None):
        self.value, self.exc = value, exc

    def done(self):
        return True

    def result(self):
        if self.exc is not None:
            raise self.exc
        return self.value


class _ScriptedCluster:
    """Tasks finish at once: each submission of a key takes the next scripted outcome of its specimen."""

    def __init__(self, script):
        self.script, self.keys = {k: list(v) for k, v in script.items()}, []

    def submit(self, fn, func, item, seed, kwargs, key, pure):
        self.keys.append(key)
        outcome = self.script[item].pop(0)
        return _Done(exc=outcome) if isinstance(outcome, BaseException) else _Done(value=(outcome, 0.5))

    def scheduler_info(self):
        return {"workers": {"w": {}}}


def test_submitted_tasks_are_collected_with_their_values_retries_and_errors():
    """submit_specimens returns at once; wait() keeps each task's value (a path goes to ``paths`` too), re-submits
    a task that raised an ordinary error (within ``retries``) under a new key, and does not retry an HbmError."""
    from hbm.runtime.parallel import submit_specimens

    cluster = _ScriptedCluster({"a": [{"x": 1}], "b": [RuntimeError("flaky"), "b.nc"],
                                "c": [HbmError("bad input")]})
    pending = submit_specimens(_never, {"a": "a", "b": "b", "c": "c"}, seed=0, client=cluster, retries=1)
    assert sorted(cluster.keys) == ["fit-a", "fit-b", "fit-c"]
    res = pending.wait(progress=False, poll=0.0)
    assert res.values == {"a": {"x": 1}, "b": "b.nc"} and res.paths == {"b": "b.nc"}
    assert "fit-b-retry1" in cluster.keys and res.errors == {"c": "HbmError: bad input"}
    assert res.task_times == {"a": 0.5, "b": 0.5}
