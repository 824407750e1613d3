"""``hbm optimize`` and ``hbm sobol`` in-process: JSON shape, tables, one-line errors."""

import json

import numpy as np
import pytest

import hbm.cli as cli
from hbm.model import spyrou_model

TRUTH = np.array([0.97, 0.192, 0.005, 0.127, 162.0, 59.8, 0.006, 0.006])


@pytest.fixture
def specimen(tmp_path):
    e = np.linspace(0.0, 0.42, 25)
    s = spyrou_model().stress(e, TRUTH) + np.random.default_rng(0).normal(0, 0.002, e.size)
    path = tmp_path / "toy.csv"
    lines = ["# id: toy", "# provenance: synthetic test curve", "strain,stress"]
    lines += [f"{a:.6f},{b:.8f}" for a, b in zip(e, s)]
    path.write_text("\n".join(lines) + "\n")
    return str(path)


def _json(capsys):
    out = capsys.readouterr().out
    return json.loads(out)  # exactly one JSON document, or this raises


def test_optimize_json(specimen, capsys):
    code = cli.main(["optimize", specimen, "--restarts", "2", "--fix", "EOPT=0.192", "--maxfevals", "1500",
                     "--seed", "1", "--json"])
    assert code == 0
    out = _json(capsys)
    assert len(out["optima"]) == 2
    assert set(out["best"]) >= {"params", "objective"}
    assert out["best"]["params"]["EOPT"] == 0.192
    assert set(out["best"]["params"]) == {"VOLF", "EOPT", "P1", "T1", "T2", "THETA", "GF", "GM", "sigma"}
    assert out["best"]["objective"] == min(o["objective"] for o in out["optima"])


def test_optimize_sweep_and_table(specimen, capsys):
    code = cli.main(["optimize", specimen, "--restarts", "1", "--fix", "EOPT=0.192", "--sweep", "VOLF:0.25",
                     "--maxfevals", "1500", "--json"])
    assert code == 0
    out = _json(capsys)
    assert [o["window"] for o in out["optima"]] == [[0.5, 0.75], [0.75, 0.99]]
    code = cli.main(["optimize", specimen, "--restarts", "1", "--maxfevals", "600", "--noise", "ar1",
                     "--bounds", "VOLF=0.6:0.9"])
    assert code == 0
    text = capsys.readouterr().out
    assert "best:" in text and "rho" in text


def test_sobol_json(specimen, capsys):
    code = cli.main(["sobol", specimen, "--n", "128", "--fix", "EOPT=0.192", "--bounds", "T2=150:175", "--json"])
    assert code == 0
    out = _json(capsys)
    for key in ("S1", "ST", "S1_conf", "ST_conf", "relevance"):
        assert set(out[key]) == {"VOLF", "P1", "T1", "T2", "THETA", "GF", "GM"}
    assert out["bounds"]["T2"] == [150.0, 175.0]
    assert len(out["per_point"]["ST"]) == 25
    code = cli.main(["sobol", specimen, "--n", "64", "--qoi", "misfit", "--no-per-point"])
    assert code == 0
    assert "relevance" in capsys.readouterr().out


@pytest.mark.parametrize("argv, words", [
    (["optimize", "{s}", "--fix", "EOPT"], ["--fix", "NAME=VALUE"]),
    (["optimize", "{s}", "--fix", "EOPT=abc"], ["--fix", "not a number"]),
    (["optimize", "{s}", "--fix", "FOO=1"], ["--fix", "unknown parameter", "FOO"]),
    (["optimize", "{s}", "--fix", "VOLF=2"], ["--fix", "inside the box"]),
    (["optimize", "{s}", "--bounds", "VOLF=0.7"], ["--bounds", "NAME=LO:HI"]),
    (["optimize", "{s}", "--bounds", "VOLF=0.8:0.7"], ["--bounds", "LO < HI"]),
    (["optimize", "{s}", "--sweep", "VOLF"], ["--sweep", "NAME:WIDTH"]),
    (["optimize", "{s}", "--sweep", "XX:0.1"], ["--sweep", "free model parameter"]),
    (["optimize", "{s}", "--restarts", "0"], ["--restarts"]),
    (["sobol", "{s}", "--n", "1000"], ["--n", "power of 2"]),
    (["sobol", "{s}", "--bounds", "GG=0:1"], ["--bounds", "GG"]),
    (["optimize", "/nonexistent/x.csv"], ["x.csv"]),
])
def test_bad_options_exit_2_with_one_line(specimen, capsys, argv, words):
    argv = [a.replace("{s}", specimen) for a in argv]
    code = cli.main(argv)
    assert code == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1, err
    for w in words:
        assert w in err
