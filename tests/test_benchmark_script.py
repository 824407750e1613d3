"""The muscle-posterior benchmark script runs end to end at tiny N (timings are not asserted)."""

from __future__ import annotations

import importlib.util
import json
import re
from pathlib import Path

import pytest

SCRIPT = Path(__file__).resolve().parents[1] / "workflows" / "benchmarks" / "muscle_posterior.py"
BENCH = Path(__file__).resolve().parents[2] / "shared" / "bench"


def _load():
    spec = importlib.util.spec_from_file_location("muscle_posterior_bench", SCRIPT)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


@pytest.mark.skipif(not (BENCH / "muscle_benchmark.csv").exists(), reason="benchmark data not present")
def test_quick_run_writes_table(tmp_path, monkeypatch, capsys):
    monkeypatch.setenv("HBM_PYMC_PYTHON", str(tmp_path / "no-such-python"))
    mod = _load()
    rc = mod.main(["--quick", "--n", "120", "--out", str(tmp_path), "--peers"])
    assert rc == 0
    md = (tmp_path / "muscle_posterior_quick.md").read_text()
    assert "| config | N |" in md and "| default | 120 |" in md
    assert "PyMC peer skipped" in md
    rows = json.loads((tmp_path / "muscle_posterior_quick.json").read_text())
    assert len(rows) == 1
    r = rows[0]
    # even at N = 120 the evidence is in the right region (gold 163.9) and the bookkeeping adds up
    assert abs(r["log_evidence"] - 163.9) < 10 and r["log_evidence_se"] > 0
    assert r["evaluations"] > 120 and 0 < r["lik_share"] <= 1 and r["stages"] >= 5
    assert re.search(r"\| default \| 120 \| 1 \|", capsys.readouterr().out)


def test_unknown_config_is_an_error(tmp_path, capsys):
    mod = _load()
    assert mod.main(["--configs", "nope", "--out", str(tmp_path)]) == 2
    assert "unknown config" in capsys.readouterr().err


def test_reads_header_and_rejects_bad_columns(tmp_path):
    mod = _load()
    f = tmp_path / "c.csv"
    f.write_text("# units_stress: MPa\nstrain,stress\n0,0.1\n0.1,0.2\n")
    e, s, meta = mod.read_curve(f)
    assert list(e) == [0, 0.1] and list(s) == [0.1, 0.2] and meta["units_stress"] == "MPa"
    f.write_text("x,y\n0,1\n")
    with pytest.raises(Exception, match="strain,stress"):
        mod.read_curve(f)


def test_model_throughput_script_runs(tmp_path, capsys):
    """The throughput benchmark runs at tiny n and reports consistent bookkeeping (no timing asserted)."""
    spec = importlib.util.spec_from_file_location("model_throughput_bench", SCRIPT.parent / "model_throughput.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    assert mod.main(["--n", "200", "--points", "10", "--repeat", "2", "--out", str(tmp_path)]) == 0
    res = json.loads((tmp_path / "model_throughput.json").read_text())
    assert res["meta"]["n"] == 200 and res["meta"]["points"] == 10
    whats = [r["what"] for r in res["rows"]]
    assert whats[:3] == ["Model.stress (numpy)", "Model.stress_jacobian (numpy, analytic)",
                         "log-likelihood, iid (numpy, hbm.make_likelihood)"]
    for r in res["rows"]:  # M evals/s and µs/particle are two views of the same time
        assert r["seconds"] > 0
        assert abs(r["M_strain_points_per_s"] - 200 * 10 / r["seconds"] / 1e6) < 1e-9 * r["M_strain_points_per_s"]
    assert "| Model.stress (numpy) |" in capsys.readouterr().out
