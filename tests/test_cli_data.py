"""``hbm data check``: summary table, one-line errors, exit codes (in-process via hbm.cli.main)."""

from __future__ import annotations

from pathlib import Path

import pytest

from hbm.cli import main

ROOT = Path(__file__).resolve().parents[1]
SPECIMENS = ROOT / "data" / "specimens"


def test_check_shipped_folder(capsys):
    assert main(["data", "check", str(SPECIMENS)]) == 0
    out, err = capsys.readouterr()
    lines = out.strip().splitlines()
    assert lines[0].split()[:4] == ["id", "points", "strain", "peak"]  # signed: compression files too
    body = [ln for ln in lines[2:] if ln.startswith(("calvo", "hawkins"))]
    assert len(body) == 6
    assert all("synthetic" in ln for ln in body)
    rat1 = next(ln for ln in body if ln.startswith("calvo2010_rat1 "))
    assert rat1.split()[1] == "45" and rat1.split()[2] == "0..0.44" and "Calvo" in rat1
    assert "6 specimen(s) OK" in out
    assert err == ""


def test_check_reports_every_bad_file_and_exits_2(tmp_path, capsys):
    good = tmp_path / "good.csv"
    good.write_text("strain,stress\n" + "".join(f"{0.1 * i},{0.01 * i}\n" for i in range(5)))
    bad1 = tmp_path / "bad1.csv"
    bad1.write_text("strain,stress\n0,0\n0.1,x\n0.2,0.2\n0.3,0.3\n0.4,0.4\n")
    bad2 = tmp_path / "bad2.csv"
    bad2.write_text("")
    rc = main(["data", "check", str(tmp_path), str(tmp_path / "missing.csv")])
    assert rc == 2
    out, err = capsys.readouterr()
    assert "good" in out and "1 specimen(s) OK, 3 failed" in out
    errs = err.strip().splitlines()
    assert len(errs) == 3  # one line each, no traceback
    assert "Traceback" not in err
    assert any(str(bad1) in e and "line 3" in e and "'stress'" in e and "expected a number" in e for e in errs)
    assert any(str(bad2) in e and "empty file" in e for e in errs)
    assert any("missing.csv" in e and "no such file" in e for e in errs)


def test_check_single_bad_file_and_empty_folder(tmp_path, capsys):
    bad = tmp_path / "b.csv"
    bad.write_text("# not metadata\nstrain,stress\n")
    assert main(["data", "check", str(bad)]) == 2
    out, err = capsys.readouterr()
    assert out == "" and err.count("\n") == 1 and "unknown metadata format" in err and "line 1" in err
    empty = tmp_path / "empty"
    empty.mkdir()
    assert main(["data", "check", str(empty)]) == 2
    assert "no *.csv" in capsys.readouterr().err


def test_check_duplicate_ids(tmp_path, capsys):
    text = "# id: same\nstrain,stress\n" + "".join(f"{0.1 * i},{0.01 * i}\n" for i in range(5))
    (tmp_path / "a.csv").write_text(text)
    (tmp_path / "b.csv").write_text(text)
    assert main(["data", "check", str(tmp_path)]) == 2
    assert "duplicate specimen id 'same'" in capsys.readouterr().err


def test_data_without_action_and_help(capsys):
    assert main(["data"]) == 2
    with pytest.raises(SystemExit) as info:
        main(["data", "check", "--help"])
    assert info.value.code == 0
    assert "strain,stress" in capsys.readouterr().out
