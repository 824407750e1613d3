"""Benchmark helpers of issue 6: the PyMC peer's prior box and model, the hierarchical-scaling script.

Timings are never asserted; the PyMC model check runs only where the separate bench environment
exists (it is not an hbm dependency).
"""

from __future__ import annotations

import importlib.util
import json
import os
from pathlib import Path

import numpy as np
import pytest

HERE = Path(__file__).resolve().parents[1] / "workflows" / "benchmarks"
# as muscle_posterior.BENCH: $HBM_BENCH_DIR, else ../shared/bench next to the repository
BENCH = Path(os.environ.get("HBM_BENCH_DIR", Path(__file__).resolve().parents[2] / "shared" / "bench"))
needs_bench = pytest.mark.skipif(not (BENCH / "muscle_benchmark.csv").exists(), reason="benchmark data not present")


def _load(name):
    spec = importlib.util.spec_from_file_location(f"bench_{name}", HERE / f"{name}.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


@needs_bench
def test_peer_reads_the_same_problem_as_hbm():
    """pymc_peer.py (numpy-only at import) parses the gold prior box and data exactly as hbm's side."""
    peer, main = _load("pymc_peer"), _load("muscle_posterior")
    eps, obs, box, gold = peer.read_bench(BENCH)
    lik, gold2, _ = main.make_problem()
    assert gold == gold2
    assert list(box) == list(lik.names)  # same parameters, same order
    np.testing.assert_array_equal(np.array([box[n] for n in lik.names]), lik.bounds)
    np.testing.assert_array_equal(eps, lik.data.strain)
    np.testing.assert_array_equal(obs, lik.data.stress)


@pytest.mark.skipif(not _load("muscle_posterior").peer_python().exists(), reason="PyMC bench environment absent")
@needs_bench
def test_pytensor_model_agrees_with_hbm(tmp_path):
    main = _load("muscle_posterior")
    lik, _, _ = main.make_problem()
    worst, msg = main.check_peer_model(main.peer_python(), lik, tmp_path)
    assert worst <= 1e-10, msg


@needs_bench
def test_evidence_peers_likelihood_equals_hbms():
    """evidence_peers.py's numpy likelihood (what pocoMC, nautilus and dynesty see) against hbm's.

    Prior draws (where log L reaches −1e10) and rows near the posterior (where the target's
    0.3-nat resolution matters); outside the box both must give −inf.
    """
    peers, main = _load("evidence_peers"), _load("muscle_posterior")
    lik, _, _ = main.make_problem()
    ours = peers.Likelihood(main.BENCH)
    rng = np.random.default_rng(7)
    b = np.asarray(lik.bounds, float)
    theta = b[:, 0] + rng.random((64, len(b))) * (b[:, 1] - b[:, 0])
    near = np.array([[0.7, 0.165, 0.14, 0.23, 19.5, 59.3, 0.008, 0.007, 0.0024],
                     [0.9, 0.184, 0.13, 1.5, 9.3, 60.0, 0.012, 0.009, 0.00297]])
    rows = np.vstack([theta, near])
    ref = lik(rows)
    got = ours(rows)
    np.testing.assert_allclose(got, ref, rtol=1e-12, atol=1e-9)
    assert ours.rows == len(rows)  # evaluations are counted by rows
    outside = near[:1].copy()
    outside[0, 0] = b[0, 1] + 0.01
    assert ours(outside)[0] == -np.inf


def test_peers_round_rows_and_table():
    """A capped peer run never counts as reaching the target; time to accuracy needs half the runs."""
    pr = _load("peers_round")
    gold = {"log_evidence": 164.03}
    ok = pr.finish_row({"setting": "a", "seed": 0, "status": "completed", "evaluations": 30000, "cpu": 2.0,
                        "log_evidence": 164.1, "log_evidence_se": 0.03, "max_mean_err_sd": 0.2}, gold)
    assert ok["reached"] and not ok["covered_2se"] and ok["virtual_1ms"] == 32.0
    stopped = pr.finish_row({"setting": "b", "seed": 0, "status": "stopped at its own timeout", "evaluations": 5,
                             "cpu": 1.0, "log_evidence": 164.03, "log_evidence_se": float("nan"),
                             "max_mean_err_sd": 0.0}, gold)
    capped = pr.finish_row({"setting": "b", "seed": 1, "status": "capped", "evaluations": 10, "cpu": 1.0}, gold)
    assert not stopped["reached"] and not capped["reached"]
    miss = pr.finish_row({"setting": "a", "seed": 1, "status": "completed", "evaluations": 30000, "cpu": 3.0,
                          "log_evidence": 163.5, "log_evidence_se": 0.3, "max_mean_err_sd": 0.1}, gold)
    lines = pr.table([ok, miss, stopped, capped]).splitlines()
    assert lines[2].startswith("| a |") and lines[2].rstrip().endswith("| 1/2 | **32 s** |")
    assert lines[3].startswith("| b |") and lines[3].rstrip().endswith("| 0/2 | not reached |")


def test_hierarchical_scaling_quick(tmp_path):
    mod = _load("hierarchical_scaling")
    assert mod.main(["--quick", "--cache", str(tmp_path / "cache"), "--out", str(tmp_path), "--repeats", "1"]) == 0
    res = json.loads((tmp_path / "hierarchical_scaling_quick.json").read_text())
    rows = res["rows"]
    assert [r["N"] for r in rows] == [200, 400] and res["meta"]["n_specimens"] == 6
    assert res["meta"]["n_pooled"] == 8
    for r in rows:
        assert r["N_total"] == 6 * r["N"]
        assert r["layer"]["calls"] > 0 and r["layer"]["psi_rows"] >= r["layer"]["calls"]
        assert np.isfinite(r["layer"]["log_evidence"]) and r["fixed"]["cpu"] >= 0
    # nested subsets: the N=200 set is the first half of the N=400 set
    st, _, _ = mod.stage1_samples(400, 0, tmp_path / "cache")
    a, b = mod.subsets(st, 200, 0), mod.subsets(st, 400, 0)
    for sid in st:
        np.testing.assert_array_equal(a[sid][0], b[sid][0][:200])
    assert "| 400 | 2400 |" in (tmp_path / "hierarchical_scaling_quick.md").read_text()
