"""The detective on raw machine records (issue 36): artefact rows name a data problem before any
physics; dropped (or kept under robust noise) the physics is named; a dense record's two relaxation
times are named from its bin means.

Truths: the measured raw record's known pre-test reading (its header); a synthetic 8000-reading record
generated with two relaxation times (``viscoelastic`` with ``terms=2``, an independent implementation of
the Prony series the detective builds from ``viscoelastic`` + ``viscoelastic_2``).
"""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from hbm import cli
from hbm.data import load_specimen
from hbm.detective import diagnose
from hbm.model.spyrou import spyrou_model

RAW = Path(__file__).parent / "data" / "annemil2025_porcine_compression_raw_machine.csv"
ENERGY = spyrou_model(form="energy")


def test_the_pretest_reading_is_a_data_problem_naming_its_line():
    dg = diagnose(load_specimen(RAW), model=ENERGY, candidates=[], n_samples=200, removal=False, workers=1)
    assert dg.verdict == "data_problem"
    assert "line 10: pre-test reading" in dg.message and "--drop-artefacts" in dg.message
    assert "--noise student_t" in dg.message
    assert dg.to_dict()["record"]["artefacts"][0]["lines"] == [10]
    # the calibrated detective reports the data problem before any physics: no round calibrated
    assert dg.to_dict()["calibration"]["method"] == "none"


@pytest.mark.slow
@pytest.mark.parametrize("how", ["drop", "student_t"])
def test_without_the_row_or_robust_to_it_the_physics_is_named(how, capsys):
    """Dropped by the option, or kept under Student-t noise: viscoelasticity is named (Δlog Z ≈ 280
    and ≈ 300 on a loaded 2-core machine, 5 and 6 minutes)."""
    args = ["diagnose", str(RAW), "--form", "energy", "--json", "--no-progress", "--max-time", "3000"]
    args += ["--drop-artefacts"] if how == "drop" else ["--noise", "student_t"]
    assert cli.main(args) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["verdict"] == "effect" and out["selected"][0] == "viscoelastic", out["message"]
    if how == "drop":
        assert "1 artefact row dropped (line 10: pre-test reading)" in out["input"]
        assert out["record"]["dropped"][0]["lines"] == [10]
    else:
        assert "rows flagged as artefacts are kept" in out["message"]


@pytest.mark.slow
def test_a_dense_record_with_two_relaxation_times_names_both(tmp_path, capsys):
    import sys
    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "workflows" / "benchmarks"))
    from dense_records import record            # the benchmark's own record
    from hbm.data import save_specimen
    path = save_specimen(record(8000, 1, 2), tmp_path / "dense.csv")
    assert cli.main(["diagnose", str(path), "--json", "--no-progress", "--max-time", "3000"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["selected"][:2] == ["viscoelastic", "viscoelastic_2"], out["message"]
    assert "8000 rows reduced to" in out["input"]
