"""One specimen from several files, one per direction (issue 35): ``FILE:MODE`` and the keyed joint fit."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from hbm.cli import main
from hbm.cli._common import load_specimens_arg, split_mode
from hbm.data import load_specimen
from hbm.errors import DataError
from hbm.io import read_attrs
from hbm.io.identity import data_key


def _file(path: Path, rows, mode: str | None = None, meta: str = "# stress_measure: nominal\n") -> Path:
    head = "strain,stress_kPa,test" + (",mode" if mode else "") + "\n"
    body = "".join(f"{e},{s},{t}" + (f",{mode}" if mode else "") + "\n" for e, s, t in rows)
    path.write_text(f"# id: {path.stem}\n" + meta + head + body)
    return path


SHEAR = [(0.1, 0.3, 1), (0.2, 0.7, 1), (0.3, 1.2, 1), (0.4, 1.9, 1), (0.5, 2.9, 1)]
ACROSS = [(0.05, 0.5, 1), (0.10, 2.0, 1), (0.15, 4.0, 1), (0.05, 0.6, 2), (0.10, 2.2, 2)]
ALONG = [(0.05, 0.2, 1), (0.10, 0.6, 1), (0.15, 1.4, 1), (0.20, 3.0, 1), (0.25, 5.5, 1)]


@pytest.mark.parametrize("mode,rows", [("shear_fc", SHEAR), ("uniaxial_c", ACROSS), ("cross", ACROSS)])
def test_given_mode_is_the_mode_column(tmp_path, mode, rows):
    """A mode given to a file without a mode column converts exactly like the column: nominal shear stays P
    (P = sigma in simple shear), nominal cross-fibre stress becomes (1 + e)*P."""
    given = load_specimen(_file(tmp_path / "a.csv", rows), mode=mode)
    column = load_specimen(_file(tmp_path / "b.csv", rows, mode=mode))
    np.testing.assert_array_equal(given.stress, column.stress)
    assert [t.load_case for t in given.tests] == [t.load_case for t in column.tests]
    strain = np.array([r[0] for r in rows])
    factor = 1.0 if mode.startswith("shear") else 1.0 + strain
    np.testing.assert_allclose(given.stress, factor * np.array([r[1] for r in rows]) / 1000.0, rtol=1e-15)


def test_uniaxial_f_given_is_the_file_as_it_is(tmp_path):
    path = _file(tmp_path / "a.csv", ALONG)
    plain, given = load_specimen(path), load_specimen(path, mode="uniaxial")
    assert data_key(plain) == data_key(given) and plain.attrs == given.attrs


def test_given_mode_refused_over_a_mode_column_and_unknown(tmp_path):
    path = _file(tmp_path / "a.csv", ACROSS, mode="uniaxial_c")
    with pytest.raises(DataError, match="names its tests' modes in its column 'mode'"):
        load_specimen(path, mode="uniaxial_c")
    with pytest.raises(DataError, match="unknown mode 'sideways'"):
        load_specimen(_file(tmp_path / "b.csv", ALONG), mode="sideways")


def test_split_mode(tmp_path):
    assert split_mode("a.csv:uniaxial_c") == ("a.csv", "uniaxial_c")
    assert split_mode("dir/a.csv:shear_sf") == ("dir/a.csv", "shear_sf")
    assert split_mode(r"C:\data\a.csv") == (r"C:\data\a.csv", None)  # a drive, not a mode
    assert split_mode("a.csv:later") == ("a.csv:later", None)
    odd = tmp_path / "x.csv:uniaxial_c"  # a file whose name has a colon is the file
    odd.write_text("")
    assert split_mode(str(odd)) == (str(odd), None)


def test_several_files_are_one_specimen(tmp_path):
    """The files' tests in order, each in its mode, the same numbers as one file with a mode column."""
    a = _file(tmp_path / "along.csv", ALONG)
    b = _file(tmp_path / "across.csv", ACROSS)
    spec = load_specimens_arg([str(a), f"{b}:uniaxial_c"])
    assert spec.id == "along+across"
    assert [t.load_case for t in spec.tests] == ["uniaxial_f", "uniaxial_c", "uniaxial_c"]
    one = tmp_path / "both.csv"
    rows = [(e, s, t, "uniaxial_f") for e, s, t in ALONG] + [(e, s, t + 1, "uniaxial_c") for e, s, t in ACROSS]
    one.write_text("# id: both\n# stress_measure: nominal\nstrain,stress_kPa,test,mode\n"
                   + "".join(f"{e},{s},{t},{m}\n" for e, s, t, m in rows))
    ref = load_specimen(one)
    np.testing.assert_array_equal(spec.strain, ref.strain)
    np.testing.assert_array_equal(spec.stress, ref.stress)
    assert json.loads(spec.attrs["test_labels"]) == ["along:1", "across:1", "across:2"]
    with pytest.raises(Exception, match="name the same specimen twice"):
        load_specimens_arg([str(a), str(a)])


def test_joint_fit_is_keyed_and_refuses_settings_it_ignores(tmp_path, capsys):
    """``hbm fit along.csv across.csv:MODE``: one command; a result of other settings is never replaced
    silently; a setting the joint fit would ignore is refused before any computation."""
    a = _file(tmp_path / "along.csv", ALONG)
    b = _file(tmp_path / "across.csv", ACROSS)
    out = tmp_path / "r.nc"
    base = ["fit", str(a), f"{b}:uniaxial_c", "--form", "energy", "--samples", "64", "--max-evaluations", "700",
            "--out", str(out), "--no-progress", "--no-plot"]
    assert main(base + ["--noise", "ar1"]) == 2
    assert "--noise: the tests are in several loading modes" in capsys.readouterr().err
    assert not out.exists()
    assert main(base) == 0
    text = capsys.readouterr().out
    assert "test along:1 [uniaxial_f] stress" in text and "test across:2 [uniaxial_c] stress" in text
    config = read_attrs(out)["config"]
    assert config["identity"]["data"] and config["settings_hash"]
    before = out.read_bytes()
    assert main(base + ["--collagen3d", "gst"]) == 2
    assert "holds a result of along+across with other settings" in capsys.readouterr().err
    assert out.read_bytes() == before
    assert main(base + ["--collagen3d", "cone"]) == 0  # the default reading named: the same content


def test_run_refuses_a_multimode_specimen_before_any_fit(tmp_path, capsys):
    data = tmp_path / "data"
    data.mkdir()
    _file(data / "along.csv", ALONG)
    _file(data / "across.csv", ACROSS, mode="uniaxial_c")
    out = tmp_path / "out"
    assert main(["run", "--data", str(data), "--out", str(out), "--quick", "--no-hierarchical", "--no-progress"]) == 2
    assert "across hold(s) tests in other loading modes" in capsys.readouterr().err
    assert not out.exists()


def test_run_workflow_refuses_a_multimode_specimen_before_any_fit(tmp_path):
    from hbm.settings import RunSettings
    from hbm.workflow.run import run_workflow

    data = tmp_path / "data"
    data.mkdir()
    _file(data / "along.csv", ALONG)
    _file(data / "across.csv", ACROSS, mode="uniaxial_c")
    out = tmp_path / "out"
    with pytest.raises(DataError, match="across hold\\(s\\) tests in other loading modes"):
        run_workflow(RunSettings(data=str(data), out=str(out), hierarchical=False))
    assert not out.exists()
