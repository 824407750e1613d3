"""Organ-scale prediction from results folders (hbm.workflow.organ, hbm predict organ, hbm run --geometry).

The results folder is built from SpecimenResult/HierarchicalFile objects with known draws (two
specimens whose posteriors slide along the exact VOLF–T1 / VOLF–P1 / G manifold), so every
stored number can be checked against an independent computation: the closed-form force at which
the thinnest section reaches the tested strain, F = P(1 + ε_tested)·min A0, brentq on the
nominal stress, and quantiles of organ_response over the same draws.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from conftest import cli_error
from scipy.optimize import brentq

from hbm.data import Series, Specimen
from hbm import io
from hbm.errors import HbmError
from hbm.model import spyrou_model
from hbm.model.spyrou import identifiable_combinations
from hbm.organ import load_geometry, nominal_stress, organ_response
from hbm.workflow.organ import force_at_tested_strain

ROOT = Path(__file__).resolve().parents[1]
GEOMETRY = ROOT / "data" / "geometry" / "fusiform.toml"
NAMES = ("VOLF", "EOPT", "P1", "T1", "T2", "THETA", "GF", "GM")
TRUTHS = {
    "ratA": {"VOLF": 0.9, "EOPT": 0.15, "P1": 0.06, "T1": 1.0, "T2": 14.0, "THETA": 59.0, "GF": 0.03, "GM": 0.02},
    "ratB": {"VOLF": 0.85, "EOPT": 0.17, "P1": 0.08, "T1": 0.8, "T2": 18.0, "THETA": 59.5, "GF": 0.02, "GM": 0.02},
}
TESTED = {"ratA": 0.42, "ratB": 0.38}
N_DRAWS = 120
SETTINGS = dict(samples=1000, forces=50, seed=3)  # samples > N_DRAWS: every stored draw is used


def on_manifold(truth: dict, volf: np.ndarray, gf: np.ndarray) -> np.ndarray:
    """Parameter rows with the truth's identifiable combinations and the given VOLF, GF."""
    th = np.tile([truth[n] for n in NAMES], (volf.size, 1)).astype(float)
    comb = identifiable_combinations(NAMES, th[:1])
    th[:, 0] = volf
    th[:, 2] = comb["VOLF*P1"][0] / volf
    th[:, 3] = comb["(1-VOLF)*T1"][0] / (1 - volf)
    th[:, 6] = gf
    th[:, 7] = (comb["G"][0] - volf * gf) / (1 - volf)
    return th


def posterior_draws(truth: dict, rng: np.random.Generator, n: int) -> np.ndarray:
    """Draws along the manifold with a few percent scatter in the identified directions + sigma."""
    th = on_manifold(truth, rng.uniform(0.75, 0.95, n), rng.uniform(0.012, 0.02, n))
    th[:, 2] *= np.exp(0.02 * rng.standard_normal(n))
    th[:, 3] *= np.exp(0.03 * rng.standard_normal(n))
    th[:, 4] *= np.exp(0.03 * rng.standard_normal(n))
    th[:, 5] = np.clip(th[:, 5] + 0.2 * rng.standard_normal(n), 55.0, 60.0)
    return np.column_stack([th, np.full(n, 0.002)])


def specimen_result(sid: str, rng: np.random.Generator) -> io.SpecimenResult:
    model = spyrou_model()
    truth = TRUTHS[sid]
    strain = np.linspace(0.0, TESTED[sid], 25)
    stress = model.stress(strain, np.array([[truth[n] for n in NAMES]]))[0]
    names = list(NAMES) + ["sigma"]
    samples = posterior_draws(truth, rng, N_DRAWS)
    # CMA-ES optima: five sweep optima exactly on the manifold (same objective) and one off it
    on = on_manifold(truth, np.array([0.6, 0.7, 0.8, 0.9, 0.95]), np.array([0.015, 0.02, 0.01, 0.018, 0.012]))
    off = on[2].copy()
    off[3] *= 1.5  # T1 off the hyperbola (1 - VOLF)·T1 = const: a clearly worse fit
    optima = [{"params": {**dict(zip(NAMES, row)), "sigma": 0.002}, "objective": -100.0, "kind": "sweep"}
              for row in on]
    optima.append({"params": {**dict(zip(NAMES, off)), "sigma": 0.002}, "objective": -50.0, "kind": "restart"})
    bounds = np.vstack([model.bounds, [[1e-4, 0.1]]])
    return io.SpecimenResult(specimen_id=sid, names=names, samples=samples, log_likelihood=np.zeros(N_DRAWS),
                             log_evidence=-10.0, log_evidence_se=0.1, bounds=bounds,
                             data=Specimen(sid, strain, observed={"stress": Series.known("stress", stress)}),
                             optima=optima, effects=list(model.effect_names))


@pytest.fixture(scope="module")
def results_dir(tmp_path_factory):
    d = tmp_path_factory.mktemp("results")
    rng = np.random.default_rng(7)
    res = {sid: specimen_result(sid, rng) for sid in sorted(TRUTHS)}
    for sid, r in res.items():
        io.write_specimen_result(r, io.specimen_path(d, sid))
    ids = sorted(res)
    updated = np.stack([posterior_draws(TRUTHS[s], rng, 80) for s in ids], axis=1)  # (80, 2, 9)
    new = np.vstack([posterior_draws(TRUTHS[s], rng, 40)[:, :8] for s in ids])
    h = io.HierarchicalFile(param_names=list(NAMES) + ["sigma"], hyper_names=["mu_T2", "sd_T2"],
                            hyper_samples=rng.uniform(size=(80, 2)), specimen_ids=ids, updated=updated,
                            new_specimen=new, pooled_names=list(NAMES))
    io.write_hierarchical(h, d / "hierarchical.nc")
    return d, res


@pytest.fixture(scope="module")
def prediction(results_dir, tmp_path_factory):
    from hbm.workflow.organ import predict_organ

    out = tmp_path_factory.mktemp("organ")
    return predict_organ(results_dir[0], GEOMETRY, out=out, **SETTINGS)


def _theta(r: io.SpecimenResult) -> np.ndarray:
    return r.samples[:, :8]


def _f_tested(theta: np.ndarray, tested: float) -> np.ndarray:
    """Independent: force at which the thinnest section reaches the tested strain (brentq on F)."""
    geom = load_geometry(GEOMETRY)
    a_min = float(geom.area(geom.nodes).min())
    model = spyrou_model()
    out = np.empty(theta.shape[0])
    for i, th in enumerate(theta):  # test-only loop: an independent scalar root find per draw
        def g(F, th=th):
            # strain of the thinnest section at force F minus the tested strain
            lam = brentq(lambda x: nominal_stress(model, th[None], np.array([x]))[0, 0] * a_min - F, 1.0, 3.0,
                         xtol=1e-14)
            return lam - 1.0 - tested
        out[i] = brentq(g, 1e-9, 1e3, xtol=1e-13)
    return out


def test_organ_file_written_and_readable(prediction):
    org = io.read_organ(prediction.path)
    assert org.complete and org.specimen_ids == ["ratA", "ratB"]
    for sid in ("ratA", "ratB"):
        assert set(org.curves[sid]) == {"posterior", "updated", "optima"}
        for src, ds in org.curves[sid].items():
            ref = prediction.organ.curves[sid][src]
            np.testing.assert_array_equal(ds["elongation"].values, ref["elongation"].values)
            np.testing.assert_array_equal(ds["force"].values, ref["force"].values)
        # one force grid per specimen, shared by its sources
        f = org.curves[sid]["posterior"]["force"].values
        assert f.size == SETTINGS["forces"] and f[0] == 0.0
        for src in ("updated", "optima"):
            np.testing.assert_array_equal(org.curves[sid][src]["force"].values, f)
        assert org.curves[sid]["posterior"].attrs["n_draws"] == N_DRAWS
        assert org.curves[sid]["updated"].attrs["n_draws"] == 80
    assert org.population is not None and org.population.attrs["n_draws"] == 80
    assert org.attrs["geometry"]["length"] == 30.0 and org.attrs["samples"] == SETTINGS["samples"]
    with pytest.raises(HbmError, match="no such result file"):
        io.read_organ(prediction.path.parent / "nope.nc")


def test_bands_ordered_and_monotone(prediction):
    dsets = [ds for c in prediction.organ.curves.values() for s, ds in c.items() if s != "optima"]
    dsets.append(prediction.organ.population)
    for ds in dsets:
        lo, med, hi = ds["elongation"].values
        ok = np.isfinite(hi)
        assert ok[: len(ok) // 2].all()
        assert np.all(lo[ok] <= med[ok]) and np.all(med[ok] <= hi[ok])
        assert np.all(np.diff(med[np.isfinite(med)]) > 0)  # elongation increases with force
        assert med[0] == 0.0  # no force, no elongation
        ms = ds["max_strain"].values
        okm = np.isfinite(ms).all(axis=0)
        assert np.all(ms[0, okm] <= ms[1, okm]) and np.all(ms[1, okm] <= ms[2, okm])
        # the most strained section strains at least as much as mid-belly
        assert np.all(ds["mid_strain"].values[1, okm] <= ms[1, okm] + 1e-12)
    for c in prediction.organ.curves.values():
        e = c["optima"]["elongation"].values
        assert np.all(np.diff(e, axis=1) > 0)


def test_extrapolation_flags_against_independent_check(prediction, results_dir):
    _, res = results_dir
    for sid in ("ratA", "ratB"):
        post = prediction.organ.curves[sid]["posterior"]
        F = post["force"].values
        theta = _theta(res[sid])
        geom = load_geometry(GEOMETRY)
        # per draw: largest section strain of organ_response's stretch field vs the tested strain
        resp = organ_response(spyrou_model(), theta, geom, F, return_stretch=True)
        ext = np.max(resp.stretch - 1.0, axis=1) > TESTED[sid]  # (draw, force)
        share = post["extrapolated_share"].values
        np.testing.assert_array_equal(share, ext.mean(axis=0))
        assert share[0] == 0.0 and share[1] == 0.0  # small forces: inside the tested range
        assert share[-1] == 1.0  # the grid ends at 2x the median threshold: all draws extrapolated
        assert ((share > 0) & (share < 1)).any()  # the draws' thresholds spread over the grid
        # the threshold force per draw (closed form in hbm.workflow.organ) against nested brentq
        f_t = force_at_tested_strain(spyrou_model(), theta, geom, TESTED[sid])
        np.testing.assert_allclose(f_t[:6], _f_tested(theta[:6], TESTED[sid]), rtol=1e-8)
        np.testing.assert_allclose(post["tested_range_force"].values, np.quantile(f_t, [0.05, 0.5, 0.95]),
                                   rtol=1e-12)
        first = np.argmax(ext, axis=1)  # each draw leaves the tested range between two grid forces
        assert np.all(F[first - 1] <= f_t * (1 + 1e-9)) and np.all(F[first] >= f_t * (1 - 1e-9))
        # per optimum: the stored flag against the section strains of organ_response's stretch field
        opt = prediction.organ.curves[sid]["optima"]
        th = opt["parameters"].sel(parameter=list(NAMES)).values
        resp = organ_response(spyrou_model(), th, load_geometry(GEOMETRY), F, return_stretch=True)
        section_max = np.max(resp.stretch - 1.0, axis=1)  # (optimum, force)
        np.testing.assert_array_equal(opt["extrapolated"].values.astype(bool), section_max > TESTED[sid])
        assert not opt["extrapolated"].values[:, :2].any() and opt["extrapolated"].values[:, -1].all()


def test_elongation_at_reference_force(prediction, results_dir):
    _, res = results_dir
    f_ref = prediction.organ.attrs["ref_force"]
    # default: a round number <= 0.8 x the smallest median threshold force
    med = min(np.median(force_at_tested_strain(spyrou_model(), _theta(res[s]), load_geometry(GEOMETRY), TESTED[s]))
              for s in res)
    assert 0.8 * med / 2.5 < f_ref <= 0.8 * med
    mant = f_ref / 10 ** np.floor(np.log10(f_ref))
    assert min(abs(mant - m) for m in (1.0, 2.0, 2.5, 5.0)) < 1e-9
    for sid in ("ratA", "ratB"):
        ds = prediction.organ.curves[sid]["posterior"]
        e = organ_response(spyrou_model(), _theta(res[sid]), load_geometry(GEOMETRY), [f_ref]).elongation[:, 0]
        np.testing.assert_allclose(ds["elongation_at_ref"].values, np.quantile(e, [0.05, 0.5, 0.95]), rtol=1e-9)
    rows = prediction.rows
    assert [(r["specimen"], r["source"]) for r in rows] == [
        ("ratA", "posterior"), ("ratA", "updated"), ("ratB", "posterior"), ("ratB", "updated"),
        ("population", "new specimen")]


def test_cmaes_optima_on_manifold_give_one_curve(prediction):
    from hbm.workflow.organ import optima_spread

    for sid in ("ratA", "ratB"):
        opt = prediction.organ.curves[sid]["optima"]
        assert opt.sizes["optimum"] == 5 and opt.attrs["dropped"] == 1  # the off-manifold set is not near-optimal
        volf = opt["parameters"].sel(parameter="VOLF").values
        assert volf.min() == 0.6 and volf.max() == 0.95
        e = opt["elongation"].values
        np.testing.assert_allclose(e[:, 1:], np.broadcast_to(e[:1, 1:], e[:, 1:].shape), rtol=1e-6)
        within, beyond = optima_spread(opt)
        assert within < 1e-6 and beyond < 1e-6


def test_off_manifold_optimum_differs(results_dir, tmp_path):
    """With a wide --near the off-manifold set is kept, and its curve differs (the check can fail)."""
    from hbm.workflow.organ import optima_spread, predict_organ

    pred = predict_organ(results_dir[0], GEOMETRY, out=None, samples=20, forces=20, near=100.0, figures=False)
    opt = pred.organ.curves["ratA"]["optima"]
    assert opt.sizes["optimum"] == 6 and opt.attrs["dropped"] == 0
    within, _ = optima_spread(opt)
    assert within > 1e-3


def test_figures_are_real_pngs(prediction):
    import matplotlib.image as mpimg

    names = {p.name for p in prediction.figures}
    assert {"organ_overlay.png", "organ_ratA.png", "organ_ratB.png"} <= names
    assert any(n.startswith("organ_optima_") for n in names)
    for p in prediction.figures:
        assert p.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and p.stat().st_size > 20_000
        img = mpimg.imread(p)
        assert img.shape[0] > 300 and img.shape[1] > 600
        assert img[..., :3].std() > 0.05  # not a blank canvas


def test_report_section(prediction):
    from hbm.workflow.organ import organ_section

    md = organ_section(prediction, base=prediction.path.parent.parent)
    assert md.startswith("## Organ-scale prediction")
    assert "| ratA | posterior |" in md and "| population | new specimen |" in md
    assert "organ/figures/organ_overlay.png" in md or "figures/organ_overlay.png" in md
    assert "Extrapolation" in md and "Computation:" in md


@pytest.fixture
def cli(run_cli):
    return run_cli


def test_cli_predict_organ(results_dir, tmp_path, cli):
    out = tmp_path / "o"
    rc, text, _ = cli(["predict", "organ", results_dir[0], "--geometry", GEOMETRY, "--out", out, "--samples", "30",
                       "--forces", "20", "--no-figures", "--ref-force", "0.2"])
    assert rc == 0, text
    assert "ratA" in text and "population" in text and "F_ref = 0.2 N" in text and "time:" in text
    org = io.read_organ(out / "organ.nc")
    assert org.curves["ratB"]["posterior"].attrs["n_draws"] == 30 and org.attrs["ref_force"] == 0.2
    assert not (out / "figures").exists()


def test_cli_predict_errors(results_dir, tmp_path, cli):
    res = results_dir[0]
    assert "no such folder" in cli_error(cli, ["predict", "organ", tmp_path / "nope", "--geometry", GEOMETRY])
    (tmp_path / "empty").mkdir()
    assert "no complete specimen results" in cli_error(cli, ["predict", "organ", tmp_path / "empty",
                                                             "--geometry", GEOMETRY])
    bad = tmp_path / "bad.toml"
    bad.write_text("[belly]\nlength = 30.0\nradius_mid = -1.0\nradius_end = 2.0\n")
    err = cli_error(cli, ["predict", "organ", res, "--geometry", bad])
    assert "bad.toml" in err and "radius_mid" in err
    assert "geometry file not found" in cli_error(cli, ["predict", "organ", res, "--geometry", tmp_path / "x.toml"])
    assert "--forces" in cli_error(cli, ["predict", "organ", res, "--geometry", GEOMETRY, "--forces", "1"])
    assert "expected a target" in cli_error(cli, ["predict"])
    assert "optima specimen" in cli_error(cli, ["predict", "organ", res, "--geometry", GEOMETRY, "--optima-specimen",
                                                "ratZ", "--no-figures", "--out", tmp_path / "z"])


def test_run_with_geometry_adds_report_section(tmp_path, run_cli):
    """hbm run --geometry: the real workflow (tiny settings) followed by the organ prediction."""
    from hbm.data import save_specimen, synthetic_specimen

    data = tmp_path / "data"
    for k, (sid, th) in enumerate(sorted(TRUTHS.items())):
        ds = synthetic_specimen(spyrou_model(), th, np.linspace(0, 0.42, 25), 0.002, 100 + k, attrs={"id": sid})
        save_specimen(ds, data / f"{sid}.csv")
    out = tmp_path / "run"
    rc, text, _ = run_cli(["run", "--data", data, "--out", out, "--workers", "0", "--samples", "40", "--restarts",
                           "1", "--maxfevals", "150", "--sweep", "none", "--no-sobol", "--no-figures",
                           "--no-hierarchical", "--no-progress", "--geometry", GEOMETRY])
    assert rc == 0, text
    assert "organ prediction:" in text
    report = (out / "report.md").read_text()
    assert "## Organ-scale prediction (fusiform muscle)" in report and "| ratB | posterior |" in report
    org = io.read_organ(out / "organ" / "organ.nc")
    assert org.specimen_ids == ["ratA", "ratB"] and "optima" in org.curves["ratA"]
    bad = tmp_path / "bad.toml"
    bad.write_text("not toml [")
    assert "invalid TOML" in cli_error(run_cli, ["run", "--data", data, "--out", out, "--geometry", bad])
