"""The detective across loading modes (issue 35, item 6), against tests/independent3d.py and hand computations."""

from __future__ import annotations

import json
import math
import sys
from pathlib import Path

import numpy as np
import pytest
from scipy import stats

from hbm.cli import main
from hbm.data import load_specimen
from hbm.detective.modes import compare_readings, diagnose_modes, lateral_checks
from hbm.runtime import seeds

sys.path.insert(0, str(Path(__file__).resolve().parent))
import independent3d as ind  # noqa: E402

SMALL = (("uniaxial_f", np.array([0.05, 0.15, 0.25])), ("uniaxial_c", np.array([0.04, 0.12, 0.2])),
         ("shear_fc", np.array([0.1, 0.2, 0.3])))
FAST = {"max_steps": 6}


def lateral_csv(path, seed: int, nu_c: float, nu_n: float, sd: float = 0.002, n: int = 10) -> None:
    """One along-fibre tension test with measured lateral strains λc = λ^-nu_c, λn = λ^-nu_n (+ noise sd);
    the stress is the independent implementation's (Calvo parameters, cone) with 2 % noise."""
    rng = np.random.default_rng(seed)
    e = np.linspace(0.03, 0.30, n)
    lam = 1 + e
    s = np.array([ind.predict("uniaxial_f", float(x), ind.CALVO, "cone")["stress"] for x in e])
    s = s + 0.02 * s.max() * rng.standard_normal(n)
    c = lam ** -nu_c - 1 + sd * rng.standard_normal(n)
    m = lam ** -nu_n - 1 + sd * rng.standard_normal(n)
    rows = [f"{a!r},{b!r},{x!r},{y!r}" for a, b, x, y in zip(e.tolist(), s.tolist(), c.tolist(), m.tolist())]
    Path(path).write_text(f"# id: lateral_{seed}\nstrain,stress,strain_c,strain_n\n" + "\n".join(rows) + "\n")


def test_lateral_checks_detect_volume_and_isotropy(tmp_path):
    """J != 1 named as compressibility, strain_c != strain_n as a loss of transverse isotropy, incompressible
    transversely isotropic data not flagged."""
    cases = {"null": (0.5, 0.5), "compressible": (0.4, 0.4), "anisotropic": (0.4, 0.6)}
    got = {}
    for name, (nc, nn) in cases.items():
        lateral_csv(tmp_path / f"{name}.csv", 1, nc, nn)
        got[name] = {r["check"]: r for r in lateral_checks(load_specimen(tmp_path / f"{name}.csv"))}
    assert not any(r["flagged"] for r in got["null"].values())
    v = got["compressible"]["volume"]
    assert v["flagged"] and not got["compressible"]["isotropy"]["flagged"]
    # ln J = (1 - 2*nu)*ln(lambda) = 0.2*ln(lambda): J = 1.3^0.2 at the largest strain
    assert v["J_at"] == pytest.approx(1.3 ** 0.2, rel=3e-3) and "compressibility" in v["message"]
    a = got["anisotropic"]
    assert a["isotropy"]["flagged"] and not a["volume"]["flagged"]
    assert a["isotropy"]["ratio_at"] == pytest.approx(1.3 ** 0.2, rel=3e-3)
    assert "loss of transverse isotropy" in a["isotropy"]["message"]
    # the F-test's p equals the two-sided t-test of the slope through the origin, computed independently
    spec = load_specimen(tmp_path / "compressible.csv")
    x = np.log1p(spec.strain)
    y = x + np.log1p(spec.observed["strain_c"].values) + np.log1p(spec.observed["strain_n"].values)
    k = np.sum(x * y) / np.sum(x * x)
    se = math.sqrt(np.sum((y - k * x) ** 2) / (x.size - 1) / np.sum(x * x))
    assert v["p"] == pytest.approx(2 * stats.t.sf(abs(k / se), x.size - 1), rel=1e-6)
    assert v["slope"] == pytest.approx(k, rel=1e-12)


def test_lateral_false_alarm_rate(tmp_path):
    """Over 300 incompressible, transversely isotropic records the family-wise rate of a flag stays near
    its 5 % (binomial sd 1.3 %); at nu = 0.45 with the same noise every record is flagged."""
    e = np.linspace(0.03, 0.30, 10)
    from hbm.data.specimen import Series, Specimen

    def flags(nu, seed):
        rng = np.random.default_rng(seed)
        lat = [(1 + e) ** -nu - 1 + 0.002 * rng.standard_normal(e.size) for _ in range(2)]
        spec = Specimen("x", e, observed={"stress": Series.known("stress", e),
                                          "strain_c": Series.known("strain_c", lat[0]),
                                          "strain_n": Series.known("strain_n", lat[1])})
        return any(r["flagged"] for r in lateral_checks(spec))
    null = np.mean([flags(0.5, s) for s in range(300)])
    assert 0.01 <= null <= 0.09
    assert all(flags(0.45, s) for s in range(50))


def test_compare_readings_rule():
    assert compare_readings({"cone": (100.0, 0.5), "gst": (104.0, 0.5)})["named"] == "gst"
    # 4 nats but 4 < 3 * hypot(1, 1) = 4.24 combined SE: not named
    r = compare_readings({"cone": (100.0, 1.0), "gst": (104.0, 1.0)})
    assert r["named"] is None and "do not tell the readings apart" in r["message"]
    assert compare_readings({"cone": (100.0, 0.1), "gst": (97.5, 0.1)})["named"] is None


@pytest.fixture(scope="module")
def small_gst(tmp_path_factory):
    path = tmp_path_factory.mktemp("dm") / "small.csv"
    ind.synthetic_csv(path, 4, reading="gst", tests=SMALL)
    spec = load_specimen(path)
    return spec, diagnose_modes(spec, samples=150, seed=3, tmcmc_options=FAST)


def test_leave_one_mode_out_equals_hand_computation(small_gst):
    """Every held-out number recomputed by hand: the training posterior's draws through the independent
    implementation, the band's replicates from the documented seed stream and noise sd."""
    spec, d = small_gst
    assert set(d.held_out) == {"uniaxial_f", "uniaxial_c", "shear_fc"}
    best = d.fits[d.reading]
    modes = list(spec.load_cases)
    for mode, h in d.held_out.items():
        fit = h["fit"]
        assert mode not in fit.likelihood.data.load_cases and h["trained_on"] == [m for m in modes if m != mode]
        test = next(t for t in spec.tests if t.load_case == mode)
        strain = spec.strain[test.rows]
        y = spec.stress[test.rows]
        draws = [dict(zip(fit.names, row)) for row in fit.samples]
        pred = np.array([[ind.predict(mode, float(e), p, d.reading)["stress"] for e in strain] for p in draws])
        mean = pred.mean(axis=0)
        (row,) = h["series"]
        assert row["rmse"] == pytest.approx(np.sqrt(np.mean((mean - y) ** 2)), rel=1e-5)
        assert row["rmse_rel"] == pytest.approx(row["rmse"] / np.max(np.abs(y)), rel=1e-12)
        k = int(np.argmax(np.abs(strain)))
        assert row["strain_at"] == strain[k] and row["ratio"] == pytest.approx(mean[k] / y[k], rel=1e-5)
        sd = np.median(best.samples[:, best.names.index(f"sigma_{mode}_stress")])
        rng = np.random.default_rng(seeds.seed_int(seeds.stream(3, "detective_modes", 200 + modes.index(mode))))
        rep = pred + sd * rng.standard_normal(pred.shape)
        lo, hi = np.quantile(rep, [0.05, 0.95], axis=0)
        assert row["inside90"] == np.mean((y >= lo) & (y <= hi))
        mlo, mhi = np.quantile(pred, [0.05, 0.95], axis=0)
        assert row["inside_model90"] == np.mean((y >= mlo) & (y <= mhi))
        assert f"fitted on the {', '.join(h['trained_on'])} tests" in h["message"]


def test_reading_named_on_a_clear_case(tmp_path):
    """Along + across + shear generated in the gst reading: gst named by evidence (the 20-seed rate in both
    readings is workflows/benchmarks/modes_reading.py)."""
    ind.synthetic_csv(tmp_path / "s.csv", 0, reading="gst")
    d = diagnose_modes(load_specimen(tmp_path / "s.csv"), samples=200, seed=0, tmcmc_options={"max_steps": 8},
                       leave_one_out=False)
    assert d.readings["named"] == "gst" and d.readings["difference"] > 10
    assert set(d.fits) == {"cone", "gst"} and not d.held_out
    assert "the data name the gst reading" in d.summary()


def test_cli_lateral_only_file_one_reading_and_output_rules(tmp_path, capsys):
    """An along-fibre file with lateral strains: one fit (the readings are identical there), the volume flag,
    the result files; a second diagnosis with other settings into the same folder is refused."""
    lateral_csv(tmp_path / "lat.csv", 2, 0.4, 0.4)
    out = tmp_path / "res"
    args = ["diagnose", str(tmp_path / "lat.csv"), "--form", "energy", "--samples", "150", "--out", str(out),
            "--no-progress"]
    assert main(args + ["--json"]) == 0
    body = json.loads(capsys.readouterr().out)
    assert list(body["readings"]["fits"]) == ["cone"] and body["readings"]["differ"] is False
    assert body["held_out"] == {} and any(r["flagged"] and r["check"] == "volume" for r in body["lateral"])
    assert sorted(p.name for p in out.iterdir() if not p.name.startswith(".")) == \
        ["diagnosis.json", "diagnosis.txt", "joint_cone.nc"]
    assert "readings (cone, gst) are identical" in (out / "diagnosis.txt").read_text()
    assert main(args + ["--seed", "1"]) == 2
    assert "holds a diagnosis with other settings" in capsys.readouterr().err
    # a file in other modes under the thesis form: refused before any fit, nothing written
    ind.synthetic_csv(tmp_path / "m.csv", 0, tests=SMALL)
    assert main(["diagnose", str(tmp_path / "m.csv"), "--out", str(tmp_path / "r2"), "--no-progress"]) == 2
    assert "hbm: error:" in capsys.readouterr().err
    assert not (tmp_path / "r2" / "diagnosis.json").exists()


@pytest.mark.slow
@pytest.mark.parametrize("truth", ["cone", "gst"])
def test_reading_named_full_diagnosis(tmp_path, truth):
    """The whole diagnosis (both readings, leave one mode out) of along + across + shear generated in each
    reading: the generating one named, every test followed by the joint fit, a held-out check per mode."""
    ind.synthetic_csv(tmp_path / "s.csv", 7, reading=truth)
    d = diagnose_modes(load_specimen(tmp_path / "s.csv"), samples=300, seed=7)
    assert d.readings["named"] == truth
    assert set(d.held_out) == {"uniaxial_f", "uniaxial_c", "shear_fc"}
    assert all("MISSED" not in s for v in d.verdicts.values() for s in v)


def test_cli_two_files_with_modes(tmp_path, capsys):
    """`hbm diagnose along.csv:uniaxial_f across.csv:uniaxial_c`: the files are one specimen's tests, diagnosed
    across modes (both readings, each direction held out once)."""
    for name, mode, strains in (("along", "uniaxial_f", [0.05, 0.1, 0.15, 0.2, 0.25]),
                                 ("across", "uniaxial_c", [0.04, 0.08, 0.12, 0.16, 0.2])):
        s = [float(ind.predict(mode, e, ind.CALVO, "gst")["stress"]) for e in strains]
        (tmp_path / f"{name}.csv").write_text(f"# id: {name}\nstrain,stress\n" +
                                              "\n".join(f"{e!r},{v * (1 + 0.01 * (-1) ** k)!r}"
                                                        for k, (e, v) in enumerate(zip(strains, s))) + "\n")
    argv = ["diagnose", f"{tmp_path / 'along.csv'}:uniaxial_f", f"{tmp_path / 'across.csv'}:uniaxial_c", "--form",
            "energy", "--samples", "100", "--out", str(tmp_path / "res"), "--no-progress", "--json"]
    assert main(argv) == 0
    body = json.loads(capsys.readouterr().out)
    assert set(body["readings"]["fits"]) == {"cone", "gst"} and set(body["held_out"]) == {"uniaxial_f", "uniaxial_c"}
    assert body["held_out"]["uniaxial_c"]["trained_on"] == ["uniaxial_f"]


def test_a_mode_whose_tests_need_parameters_the_others_lack_gets_no_held_out_fit(tmp_path):
    """An offset per stress observable (S0, S0_2) on along-fibre tension + equibiaxial tests: only the biaxial
    tests measure stress_2, so the other mode cannot determine S0_2 -- that mode gets no leave-one-out fit
    (said up front and in the diagnosis), instead of a traceback after the fits."""
    from hbm.effects import make_effect
    from hbm.model import spyrou_model

    rng = np.random.default_rng(5)
    lines = ["# id: offset_two_modes", "strain,stress,stress_2,test,mode"]
    for k, mode in enumerate(("uniaxial_f", "biaxial_fc")):
        for e in (0.04, 0.08, 0.12, 0.16):
            p = ind.predict(mode, e, ind.CALVO, "cone")
            s2 = "" if "stress_2" not in p else repr(float(p["stress_2"]) * (1 + 0.02 * rng.standard_normal()))
            lines.append(f"{e!r},{float(p['stress']) * (1 + 0.02 * rng.standard_normal())!r},{s2},{k},{mode}")
    (tmp_path / "o.csv").write_text("\n".join(lines) + "\n")
    said = []
    model = spyrou_model(form="energy").with_effects(make_effect("offset"))
    d = diagnose_modes(load_specimen(tmp_path / "o.csv"), model=model, samples=100, seed=2, tmcmc_options=FAST,
                       log=said.append)
    assert any("no leave-one-out fit for biaxial_fc (its tests need S0_2" in s for s in said), said
    assert d.held_out["biaxial_fc"]["fit"] is None and "not predicted" in d.held_out["biaxial_fc"]["message"]
    assert d.held_out["uniaxial_f"]["fit"] is not None      # predicted from the biaxial tests as before
    assert d.to_dict()["held_out"]["biaxial_fc"]["fit"] is None and d.n_evaluations > 0
