"""Issue 28, parts 4-5: `extend` and `diagnose` agree on the evidence of the effects they both
add, and a diagnosis has a bounded, announced cost: an estimate before it starts and, at
``--max-time``, the verdict so far with what was left undecided, written like a full one."""

from __future__ import annotations

import json
import math
import multiprocessing as mp
import os
import time

import pytest

import hbm
from hbm.cli import main
from hbm.data import protocol, ramp, save_specimen, synthetic_specimen
from hbm.detective import diagnose, extend
from hbm.effects import make_effect
from hbm.model.spyrou import spyrou_model

TH = dict(VOLF=0.8, EOPT=0.1, P1=0.15, T1=0.8, T2=14.0, THETA=58.5, GF=0.015, GM=0.01)


def _offset_curve(seed: int = 3, n: int = 45):
    m = spyrou_model() + make_effect("offset")
    return synthetic_specimen(m, {**TH, "S0": 0.0065}, protocol(ramp(0.33, 2e-3, n)), 0.0015, seed=seed)


def test_max_time_writes_the_verdict_so_far_and_what_is_undecided(tmp_path, capsys):
    """A limit far below one refit: the base fit finishes, every refit it did not start is
    listed with why, the removal test is skipped, and text, JSON and figure are still written
    (exit 0).  The verdict never claims a comparison it did not make."""
    csv = tmp_path / "spec.csv"
    save_specimen(_offset_curve(), csv)
    fig = tmp_path / "dg.png"
    rc = main(["diagnose", str(csv), "--samples", "200", "--max-time", "0.5", "--json", "--plot", str(fig),
               "--candidates", "offset,viscoelastic"])
    out = json.loads(capsys.readouterr().out)
    assert rc == 0 and fig.exists()
    st = out["stopped"]
    assert st["max_time"] == 0.5 and st["elapsed"] > 0.5
    whats = [u["what"] for u in st["undecided"]]
    assert "the removal test of the base parts" in whats and out["removal"] == []
    refitted = {c["effect"] for c in out["candidates"] if c["refit"]}
    not_run = {w.removeprefix("refit of ") for w in whats if w.startswith("refit of ")}
    assert not_run and not (not_run & refitted)          # exactly the refits not made are listed
    assert "stopped at --max-time (0 s" not in out["message"] and "stopped at --max-time" in out["message"]
    if out["verdict"] != "effect":
        assert "no candidate or generic shape gains" not in out["message"]
    assert out["timings"]["estimate"]["seconds"] > 0


def test_extend_steps_share_one_noise_model():
    ext = extend(_offset_curve(4), add=["offset"], seed=4, n_samples=200)
    assert len({s.noise for s in ext.steps}) == 1
    assert ext.steps[0].noise == ext.steps[-1].noise


@pytest.mark.slow
def test_extend_auto_and_diagnose_report_the_same_evidence():
    """The same effect on the same data: extend --auto's Δlog Z equals the diagnosis's within
    the SE they state (independent seeds: extend diagnoses with seed + 17)."""
    ds = _offset_curve(5)
    kw = dict(candidates=["offset", "viscoelastic", "series_compliance"], n_samples=300)
    dg = diagnose(ds, seed=0, **kw)
    ext = extend(ds, auto=True, seed=0, **kw)
    assert dg.selected == ["offset"] and [s.effects for s in ext.steps] == [[], ["offset"]]
    c = next(c for c in dg.candidates if c.effect == "offset")
    g = ext.step_gain(1)
    se = math.hypot(c.delta_log_evidence_se, g["delta_log_evidence_se"])
    assert abs(g["delta_log_evidence"] - c.delta_log_evidence) <= se, (g, c.delta_log_evidence, se)
    # the table prints that gain, the JSON carries it
    assert f"{g['delta_log_evidence']:.1f} ± {g['delta_log_evidence_se']:.1f}" in ext.table()
    assert ext.to_dict()["steps"][1]["gain_over_previous"]["delta_log_evidence"] == pytest.approx(
        g["delta_log_evidence"])


class _SlowOffset(hbm.Effect):
    """An offset whose every stress batch sleeps: a user model far slower than the base model,
    so that one refit of it outlasts the whole --max-time."""

    name = "slow_offset"
    stage = "output"
    description = "constant offset, evaluated slowly (a stand-in for an expensive user model)"
    parameters = (hbm.Parameter("SLOW_S0", -0.02, 0.02, "MPa", "offset", null=0.0),)

    def modify(self, state, p, stress):
        time.sleep(0.05)
        return stress + p["SLOW_S0"]


def test_a_fit_under_way_stops_at_max_time():
    """The deadline falls inside a refit that would take minutes (≥ 0.05 s per batch, thousands
    of batches): the refit is interrupted at its next batch and listed as undecided, and the
    diagnosis returns within --max-time (it keeps a reserve for what follows the last fit),
    not after the refit's end."""
    ds = _offset_curve(6)
    t0 = time.perf_counter()
    dg = diagnose(ds, seed=1, n_samples=200, candidates=[_SlowOffset()], max_time=12.0, removal=True)
    wall = time.perf_counter() - t0
    assert wall < 12.0, wall
    whats = {u["what"]: u["why"] for u in dg.stopped["undecided"]}
    assert "interrupted at --max-time" in whats["refit of slow_offset"]
    slow = next(c for c in dg.candidates if c.effect == "slow_offset")
    assert not slow.refit and slow.fit is None       # nothing half-fitted is reported as a result
    assert dg.verdict != "adequate"


def test_extend_add_guards_against_ar1_absorbing_a_misfit():
    """The issue's case: the given effect (an offset) is real, but a second, unlisted one
    (viscoelastic relaxation on two rates) leaves a smooth misfit that AR(1) noise would soak
    up.  extend --add runs diagnose's guard on the most complete model: AR(1) is rejected (the
    data prefer white noise + a generic shape), every step is compared at a white noise model,
    and the table says why."""
    m = spyrou_model() + make_effect("offset") + make_effect("viscoelastic")
    prot = protocol([ramp(0.25, 1e-3, 30)], [ramp(0.25, 1e-1, 30)])
    ds = synthetic_specimen(m, {**TH, "S0": 0.006, "G1": 0.25, "LOGTAU1": 0.5}, prot, 0.0012, seed=3)
    plain = extend(ds, add=["offset"], seed=3, n_samples=200, noise_models=("iid", "ar1"),
                   correlated="noise")
    assert {s.noise for s in plain.steps} == {"iid"}
    assert any(n.startswith("AR(1) noise rejected") for n in plain.notes)
    assert "AR(1) noise rejected" in plain.table() and plain.to_dict()["notes"] == plain.notes
    # without the guard (AR(1) forced) the misfit is absorbed and the offset's gain shrinks
    forced = extend(ds, add=["offset"], seed=3, n_samples=200, noise="ar1")
    assert plain.step_gain(1)["delta_log_evidence"] > forced.step_gain(1)["delta_log_evidence"] + 3


def test_refits_in_worker_processes_match_the_serial_ones(monkeypatch):
    """The candidate refits of a round run in forked worker processes: every number of the
    diagnosis is the serial one, bitwise (each refit has its own seed), and a user effect
    class crosses to the workers.  Both calibrations are computed (no cache)."""
    monkeypatch.setenv("HBM_CACHE_DIR", "off")
    ds = _offset_curve(7, n=30)
    kw = dict(seed=2, n_samples=200, candidates=["offset", _SlowOffsetFast()], removal=False, noise="iid",
              max_effects=1)
    one, two = diagnose(ds, workers=1, **kw), diagnose(ds, workers=2, **kw)
    assert two.timings["workers"] == 2 and one.timings["workers"] == 1
    a, b = one.to_dict(), two.to_dict()
    for x in (a, b):
        x.pop("timings")
    assert a == b
    assert sum(c.refit for c in two.candidates) >= 3      # the parallel path ran


class _SlowOffsetFast(_SlowOffset):
    """The user effect of the test above without the sleep (a class defined in this module)."""

    name = "user_offset"
    parameters = (hbm.Parameter("USER_S0", -0.02, 0.02, "MPa", "offset", null=0.0),)

    def modify(self, state, p, stress):
        return stress + p["USER_S0"]


_PARENT = os.getpid()


class _DiesInWorkers(_SlowOffsetFast):
    """A user effect whose evaluation kills any process but the test's own (a worker killed
    by the OS, out of memory): the diagnosis must carry on in this process."""

    name = "dies_in_workers"
    parameters = (hbm.Parameter("DIE_S0", -0.02, 0.02, "MPa", "offset", null=0.0),)

    def modify(self, state, p, stress):
        if os.getpid() != _PARENT:
            os._exit(9)
        return stress + p["DIE_S0"]


def test_a_dead_refit_worker_does_not_lose_the_diagnosis(monkeypatch):
    monkeypatch.setenv("HBM_CACHE_DIR", "off")  # both calibrations computed (no cache)
    ds = _offset_curve(7, n=30)
    kw = dict(seed=2, n_samples=200, candidates=["offset", _DiesInWorkers()], removal=False, noise="iid",
              max_effects=1)
    dg = diagnose(ds, workers=2, **kw)
    assert dg.timings["workers"] == 1          # it fell back to this process
    ref = diagnose(ds, workers=1, **kw)
    a, b = dg.to_dict(), ref.to_dict()
    a.pop("timings"), b.pop("timings")
    assert a == b


def _diagnose_in_a_daemon(_):
    ds = _offset_curve(7, n=30)
    dg = diagnose(ds, seed=2, n_samples=200, candidates=["offset"], removal=False, noise="iid", max_effects=1,
                  workers=2)
    return dg.verdict, dg.timings["workers"]


def test_diagnose_inside_a_worker_process_refits_there():
    """A daemonic process (a dask or multiprocessing worker) may not start processes: a diagnosis
    run there refits in its own process instead of failing."""
    with mp.get_context("fork").Pool(1) as pool:
        verdict, workers = pool.map(_diagnose_in_a_daemon, [0])[0]
    assert workers == 1 and verdict in ("effect", "adequate", "unexplained")


@pytest.mark.slow
def test_detection_limits_in_worker_processes_match_the_serial_ones():
    """--power computes each effect's limit in a worker: the same limits, bitwise."""
    ds = _offset_curve(7, n=30)
    kw = dict(seed=2, n_samples=200, candidates=["offset", "slack", _SlowOffsetFast()], removal=False,
              noise="iid", max_effects=1, power=True)
    one, two = diagnose(ds, workers=1, **kw), diagnose(ds, workers=2, **kw)
    assert len(two.power["effects"]) == 3 and two.power == one.power
