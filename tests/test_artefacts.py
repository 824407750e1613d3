"""The artefact screen (issue 36): rows that are not the tissue, named before any fit.

Truths: the measured raw record's known artefact (its first row is a reading before the test,
named in its header); artefacts injected into independently generated clean curves at known
rows; and clean curves -- shipped, measured and synthetic of many protocols, sizes and noise
kinds -- in which nothing may be flagged.
"""

from __future__ import annotations

import glob
import json
from pathlib import Path

import numpy as np
import pytest

from hbm.data import cycle, hold, load_specimen, protocol, ramp, synthetic_specimen
from hbm.data.artefacts import drop_rows, screen_artefacts
from hbm.data.prepare import dropped_summary, prepare_record, screen_dataset
from hbm.effects import make_effect
from hbm.model.spyrou import spyrou_model

ROOT = Path(__file__).resolve().parents[1]
RAW = Path(__file__).parent / "data" / "annemil2025_porcine_compression_raw_machine.csv"
THETA = dict(VOLF=0.8, EOPT=0.05, P1=0.15, T1=0.5, T2=12.0, THETA=57.0, GF=0.02, GM=0.01, G1=0.3, LOGTAU1=1.0)


def _screen(ds):
    return screen_artefacts(ds.strain, ds.stress, ds.time, ds.test)


def test_the_raw_records_pretest_reading_is_its_only_flag():
    ds = load_specimen(RAW)
    found, lines = screen_dataset(ds)
    assert [(a.kind, a.rows) for a in found] == [("pre-test reading", (0,))]
    assert lines[0] == 10 and "t = 0 s" in found[0].detail


def test_shipped_and_measured_curves_are_clean():
    files = sorted(glob.glob(str(ROOT / "data" / "specimens" / "*.csv")))
    files += sorted(glob.glob(str(ROOT / "data" / "measured" / "*.csv")))
    assert len(files) >= 8
    for f in files:
        assert _screen(load_specimen(f, sl0=2.0 if "smith2011" in f else None)) == [], f


def _clean(kind: str, n: int, seed: int, noise: str = "iid", rel: float = 0.01):
    model = spyrou_model() + make_effect("viscoelastic")
    protos = {
        "ramp_hold": lambda: protocol([ramp(0.3, 0.01, n // 4), hold(120.0, n - n // 4)]),
        "rates": lambda: protocol(*[ramp(0.35, r, n // 3) for r in (1e-3, 1e-2, 1e-1)]),
        "cycle": lambda: protocol(cycle(0.35, 0.01, n // 3, eps_min=0.1)),
        "step_hold": lambda: protocol(hold(100.0, n, at=0.2)),
    }
    return synthetic_specimen(model, THETA, protos[kind](), rel, seed=seed, relative=True, noise=noise,
                              rho=0.7 if noise == "ar1" else 0.0)


@pytest.mark.parametrize("kind", ["ramp_hold", "rates", "cycle", "step_hold"])
@pytest.mark.parametrize("n, noise", [(40, "iid"), (150, "ar1"), (600, "iid"), (8000, "iid")])
def test_clean_synthetic_records_are_not_flagged(kind, n, noise):
    for seed in range(3 if n < 8000 else 1):
        assert _screen(_clean(kind, n, seed, noise)) == [], (kind, n, noise, seed)


def test_noise_free_corners_are_not_flagged():
    """A noise-free curve: every corner (ramp end, reversal, a hold that opens with a step) is far
    beyond any noise, and still no row is flagged."""
    for kind in ("ramp_hold", "cycle", "step_hold", "rates"):
        assert _screen(_clean(kind, 90, 0, rel=1e-9)) == [], kind


def _inject(ds, rows, values):
    s = ds.stress.copy()
    s[list(rows)] = values
    return ds.with_series("stress", s)


@pytest.mark.parametrize("seed", range(4))
def test_injected_artefacts_are_found_where_they_are(seed):
    ds = _clean("ramp_hold", 400, seed)
    s = ds.stress
    peak = float(np.max(np.abs(s)))
    rng = np.random.default_rng(seed)
    spike, drop, dip = rng.integers(40, 90), rng.integers(150, 220), rng.integers(250, 350)
    bad = _inject(ds, [0, spike, drop, dip, dip + 1],
                  [3.0 * peak, s[spike] + 0.5 * peak, 0.0, 0.5 * s[dip], 0.5 * s[dip + 1]])
    found = {a.rows: a.kind for a in _screen(bad)}
    assert found == {(0,): "pre-test reading", (int(spike),): "spike", (int(drop),): "dropout",
                     (int(dip), int(dip) + 1): "dip during a hold"}


def test_post_failure_tail():
    ds = _clean("rates", 150, 1)
    s, test = ds.stress.copy(), ds.test
    rows = np.flatnonzero(test == test[-1])
    tail = rows[-12:]
    s[tail] = 0.002 * s[rows[-13]] * np.random.default_rng(0).standard_normal(12)   # the specimen broke
    found = _screen(_inject(ds, tail, s[tail]))
    assert [(a.kind, a.rows) for a in found] == [("post-failure tail", tuple(int(r) for r in tail))]


def test_dropping_rows_is_recorded_and_a_clean_record_is_left_as_it_is():
    ds = load_specimen(RAW)
    prep = prepare_record(ds, artefacts="drop")
    assert prep.data.n_points == ds.n_points - 1
    np.testing.assert_array_equal(prep.data.stress, ds.stress[1:])
    record = json.loads(prep.data.attrs["dropped_rows"])
    assert record[0]["kind"] == "pre-test reading" and record[0]["lines"] == [10]
    assert dropped_summary(prep.data.attrs) == "1 artefact row dropped (line 10: pre-test reading)"
    assert prepare_record(ds).artefacts and prepare_record(ds).data is ds      # flagged, kept
    clean = load_specimen(ROOT / "data" / "specimens" / "calvo2010_rat1.csv")
    assert prepare_record(clean, artefacts="drop").data is clean
    assert drop_rows(clean, []) is clean


def test_drop_artefacts_is_one_declared_setting_recorded_only_when_set(tmp_path):
    """--drop-artefacts / --reduce are FitSettings fields: the flag sets artefacts='drop', a fit
    drops the row and records it (config and input line), and unset settings leave the result key
    and config as they were."""
    import warnings

    from hbm.cli import build_parser
    from hbm.errors import SettingError, HbmWarning
    from hbm.fit import fit_specimen
    from hbm.settings import FitRecord, FitSettings

    args = build_parser().parse_args(["fit", str(RAW), "--drop-artefacts", "--reduce", "off"])
    assert (args.artefacts, args.reduce) == ("drop", "off")
    assert build_parser().parse_args(["diagnose", str(RAW)]).artefacts is None
    plain = FitSettings()
    assert "artefacts" not in plain.record() and "reduce" not in FitRecord(settings=plain).to_attrs()
    s = FitSettings(artefacts="drop", reduce="off")
    assert s.record()["artefacts"] == "drop" and FitRecord.from_attrs(FitRecord(settings=s).to_attrs()).settings == s
    with pytest.raises(SettingError, match="artefacts"):
        FitSettings(artefacts="remove")
    spec = load_specimen(RAW)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", HbmWarning)
        res = fit_specimen(spec, model=spyrou_model(form="energy"), samples=40, restarts=0, maxfevals=200,
                           artefacts="drop", progress=False, tier="full", max_evaluations=400)
    assert res.result.config["artefacts"] == "drop"
    assert "1 artefact row dropped (line 10: pre-test reading)" in res.result.config["input"]
    assert res.result.data.n_points == spec.n_points - 1
