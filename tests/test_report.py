"""The run report (hbm.workflow.report), one section at a time, on a synthetic workflow result.

The specimen samples are permuted arithmetic sequences, so every mean, sd and 90 % quantile in the
tables has a closed form; the variability test uses the two-specimen closed form of Cochran's Q
and its χ²(1) p-value erfc(sqrt(Q/2)); the manifolds lie exactly on (1 − VOLF)·T1 = k.
"""

from __future__ import annotations

import math
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

from hbm import io
from hbm.workflow import report
from hbm.identifiability.identify import volf_t1_manifold
from hbm.workflow import RunConfig

N = 401  # quantile positions 0.05·400 = 20 and 0.95·400 = 380 fall on samples: no interpolation
NAMES = ["VOLF", "EOPT", "P1", "T1", "T2", "THETA", "GF", "GM", "sigma"]
# per specimen: column -> (first, last) of an arithmetic sequence (VOLF constant)
SPECS = {
    "ratA": {"VOLF": (0.8, 0.8), "EOPT": (0.1, 0.2), "P1": (0.02, 0.06), "T1": (1.0, 3.0), "T2": (10.0, 30.0),
             "THETA": (56.0, 60.0), "GF": (0.01, 0.03), "GM": (0.02, 0.04), "sigma": (0.001, 0.003)},
    "ratB": {"VOLF": (0.6, 0.6), "EOPT": (0.1, 0.2), "P1": (0.04, 0.08), "T1": (2.0, 6.0), "T2": (60.0, 80.0),
             "THETA": (56.0, 60.0), "GF": (0.01, 0.03), "GM": (0.02, 0.04), "sigma": (0.001, 0.003)},
}


def _seq(a: float, b: float) -> np.ndarray:
    return np.linspace(a, b, N)


def _stats(a: float, b: float) -> tuple[float, float, float, float]:
    """Mean, sd (ddof 1), 5 % and 95 % quantiles of the arithmetic sequence a..b of N terms."""
    h = (b - a) / (N - 1)
    return (a + b) / 2, abs(h) * math.sqrt(N * (N + 1) / 12), a + 0.05 * (b - a), a + 0.95 * (b - a)


def _result(sid: str, seed: int) -> io.SpecimenResult:
    rng = np.random.default_rng(seed)  # only decorrelates the columns; marginals are the sequences
    samples = np.column_stack([rng.permutation(_seq(*SPECS[sid][n])) for n in NAMES])
    box = np.array([[0.5, 0.99], [0, 0.2], [1e-4, 0.5], [0, 20], [0, 200], [55, 60], [1e-4, 0.1], [1e-4, 0.1],
                    [1e-4, 0.05]])
    sobol = {"ST": {"VOLF": 0.9, "T2": 0.5, "P1": float("nan")}, "S1": {}, "S1_conf": {}, "ST_conf": {},
             "relevance": {"VOLF": "very important", "T2": "important", "P1": "irrelevant"},
             "qoi": "log_integrated_stress"}
    return io.SpecimenResult(specimen_id=sid, names=list(NAMES), samples=samples, log_likelihood=np.zeros(N),
                             log_evidence=-12.3456 - seed, log_evidence_se=0.0432, bounds=box,
                             stages=[{}] * (5 + seed), sobol=sobol if sid == "ratA" else None)


def _hierarchical(mode: str = "combinations") -> io.HierarchicalFile:
    m = 201  # quantile positions 10, 100, 190: exact
    mu_g = np.linspace(-4.0, -3.0, m)
    mu_t2 = np.linspace(-1.0, 1.0, m)
    hyper = np.column_stack([mu_g, np.full(m, 0.3), mu_t2, np.full(m, 0.7)])
    t2_new = np.linspace(20.0, 60.0, m)
    upd = np.zeros((m, 2, len(NAMES)))
    upd[:, 0, NAMES.index("T2")] = np.linspace(10.0, 30.0, m)
    upd[:, 1, NAMES.index("T2")] = np.linspace(30.0, 50.0, m)
    attrs = {"mode": mode, "pooled": ["log_G", "T2"], "transforms": {"log_G": "identity", "T2": "logit"},
             "bounds": {"T2": [0.0, 200.0]}, "outside_support_fraction": 0.0123,
             "hyperprior": {"sd": "loguniform on (0.05, 1.0) x mu range"},
             "ess_summary": {"ratA": {"min": 3.0, "q10": 12.0}, "ratB": {"min": 150.0, "q10": 210.0}},
             "refined": ["ratA"], "warnings": ["w1", "w2"]}
    if mode == "informed":
        attrs["pool_reasons"] = {"T2": "T2: informed in 2 of 2", "GF": "not informed"}
    return io.HierarchicalFile(param_names=list(NAMES), hyper_names=["mu_log_G", "sd_log_G", "mu_T2", "sd_T2"],
                               hyper_samples=hyper, specimen_ids=["ratA", "ratB"], updated=upd,
                               new_specimen=np.column_stack([np.zeros(m), t2_new]), log_evidence=4.56789,
                               log_evidence_se=0.1234, attrs=attrs, pooled_names=["log_G", "T2"])


@pytest.fixture
def wres(tmp_path):
    px = np.linspace(0.6, 0.95, 8)
    manifolds = {}
    for sid, k in (("ratA", 0.5), ("ratB", 2.0)):
        man = volf_t1_manifold(px, k / (1 - px), source="points")
        manifolds[sid] = {"source": "CMA-ES sweep optima", "points_x": px, "points_y": k / (1 - px),
                          "combination_rel_spread": 0.0123, "level": np.asarray(man.level), "object": man}
    fig = tmp_path / "figures"
    return SimpleNamespace(
        config=RunConfig(data="data/x", out=str(tmp_path), samples=123, seed=7, workers=1, sobol=False,
                         hierarchical=True, hier_samples=321),
        out=tmp_path, results={"ratA": _result("ratA", 0), "ratB": _result("ratB", 1)}, skipped=["ratB"],
        errors={"ratC": "boom"}, hierarchical=_hierarchical(), manifolds=manifolds,
        directions={"ratA": [{"expression": "(1-VOLF)*T1", "ratio": 0.0412, "median": 0.4, "lo": 0.2, "hi": 0.6}],
                    "ratB": []},
        figures=[fig / "ratA_corner.png", fig / "forest.png"],
        timings={"specimens_wall": 12.345, "tmcmc_cpu": 3.21, "hierarchical": 31.68})


def test_header_counts_reused_and_failed(wres, tmp_path):
    txt = report._header(wres, tmp_path)
    assert txt.startswith("# hbm run report\n\nGenerated ")
    assert "2 specimens from `data/x`; 1 reused from a previous run (ratB)." in txt
    assert txt.endswith("**Failed specimens:**\n\n- `ratC`: boom")


def test_settings_rows(wres, tmp_path):
    txt = report._settings(wres, tmp_path)
    for row in ("| samples (TMCMC N) | 123 |", "| seed | 7 |", "| workers | 1 |", "| Sobol N | off |",
                "| hierarchical samples | 321 |", "| fixed | none |", "| quick | no |"):
        assert row in txt.splitlines()


def test_timings_rows(wres, tmp_path):
    lines = report._timings(wres, tmp_path).splitlines()
    assert "| specimen fits (parallel phase, wall); 1 of 2 reused from an earlier run | 12.3 |" in lines
    assert "| TMCMC (sum over specimens, in tasks, as stored) | 3.21 |" in lines
    assert "| hierarchical layer | 31.7 |" in lines
    assert "| figures | – |" in lines  # not timed
    assert not any("beside the layer" in line for line in lines)
    # a split run: the parallel phase is the posteriors; the completing tasks' tail after the layer has its row
    wres.timings.update({"specimens_extras_beside_layer": True, "specimens_extras_wait": 7.25})
    lines = report._timings(wres, tmp_path).splitlines()
    assert ("| specimen posteriors (parallel phase, wall; optima, sweep and Sobol beside the layer); 1 of 2 reused "
            "from an earlier run | 12.3 |") in lines
    assert "| specimens' optima, sweep and Sobol: waited for after the layer (wall) | 7.25 |" in lines
    assert "| TMCMC (sum over specimens, in tasks, as stored) | 3.21 |" in lines
    assert any(line.startswith("| CMA-ES (sum over specimens, in tasks, as stored; beside the layer, stretched by it)")
               for line in lines)


def test_specimen_section_numbers(wres, tmp_path):
    txt = report._specimens(wres, tmp_path)
    assert txt.startswith("## Specimens\n\n### ratA\n")
    mean, sd, lo, hi = _stats(10.0, 30.0)  # ratA's T2
    assert f"| T2 | {mean:.4g} | {sd:.3g} | [{lo:.4g}, {hi:.4g}] |" in txt
    # G = c·GF + (1−c)·GM with c = 0.8 constant: linear in the columns
    g_mean = 0.8 * 0.02 + 0.2 * 0.03
    assert f"| G | {g_mean:.4g} |" in txt
    assert "log-evidence **-12.346 ± 0.043** (5 TMCMC stages, 401 samples)" in txt
    assert "log-evidence **-13.346 ± 0.043** (6 TMCMC stages, 401 samples)" in txt
    assert "`(1-VOLF)*T1` = 0.4 [0.2, 0.6] (sd ratio 0.041)" in txt
    assert "none (no combination of up to three parameters is pinned that tightly)" in txt  # ratB
    assert "VOLF ∈ [0.6, 0.95]" in txt and "level (1−VOLF)·T1 = 0.5 [0.5, 0.5]" in txt
    # ST order, NaN last
    assert ("Sobol (ST, log_integrated_stress): VOLF 0.9 (very important), T2 0.5 (important), P1 – (irrelevant)"
            in txt)
    assert "Figures: [corner](figures/ratA_corner.png)" in txt
    assert "Input converted" not in txt  # strain and MPa as read
    wres.results["ratB"].config["input"] = "stress kPa->MPa, nominal->Cauchy"
    txt = report._specimens(wres, tmp_path)
    assert txt.count("Input converted: stress kPa->MPa, nominal->Cauchy (stresses here are Cauchy, MPa).") == 1


def test_combinations_table(wres, tmp_path):
    txt = report._combinations(wres, tmp_path)
    assert txt.startswith("## Identifiable combinations (posterior mean [90% interval], MPa)")
    # ratB: c = 0.6, (1−c)·T1 = 0.4·T1 with T1 = 2..6 (scaling keeps the quantile positions)
    mean, _, lo, hi = _stats(0.4 * 2.0, 0.4 * 6.0)
    row = next(r for r in txt.splitlines() if r.startswith("| ratB |"))
    assert row.split(" | ")[3].rstrip(" |") == f"{mean:.4g} [{lo:.4g}, {hi:.4g}]"
    assert "| specimen | G | VOLF*P1 | (1-VOLF)*T1 |" in txt


def test_manifolds_section(wres, tmp_path):
    txt = report._manifolds(wres, tmp_path)
    assert "| ratA | 0.5 | [0.5, 0.5] |" in txt and "| ratB | 2 | [2, 2] |" in txt
    assert txt.endswith("Spread of the levels (max/min): 4.")  # 2.0 / 0.5
    wres.manifolds.pop("ratB")
    assert report._manifolds(wres, tmp_path) == ""  # one specimen: nothing to compare


def test_population_section(wres, tmp_path):
    txt = report._population(wres, tmp_path)
    assert "Hyper-evidence **4.568 ± 0.123**" in txt
    # log_G (identity) is shown as G with a log-normal population: median exp(mu), exact quantiles
    g = np.exp(np.linspace(-4.0, -3.0, 201)[[10, 100, 190]])
    assert f"| G | log | {g[1]:.4g} [{g[0]:.4g}, {g[2]:.4g}] |" in txt
    # T2 (logit on [0, 200]): 200·expit(mu)
    t = 200.0 / (1.0 + np.exp(-np.linspace(-1.0, 1.0, 201)[[10, 100, 190]]))
    new_lo, new_hi = 20.0 + 0.05 * 40.0, 20.0 + 0.95 * 40.0
    assert f"| T2 | logit | {t[1]:.4g} [{t[0]:.4g}, {t[2]:.4g}] | [{new_lo:.4g}, {new_hi:.4g}] | 0.7 |" in txt
    # new-specimen table: T2's median 40; median over both updated individuals (10..30 and 30..50) 30
    assert "| T2 | [22, 58] | 40 | 30 |" in txt
    assert "Pooled (`--pool combinations`, the default for the base model): log_G, T2." in txt
    assert "(rejected): 0.012." in txt
    assert "ratA 3/12, ratB 150/210. **ESS collapsed for ratA**" in txt and "(done for: ratA)" in txt
    assert txt.endswith("Warnings: w1; w2")
    # when the exact fallback sampled the collapsed specimen with its real likelihood, the population
    # estimates do not rest on its importance estimates: the report must not claim they do
    wres.hierarchical.attrs["exact"] = {"exact": ["ratA", "ratB"]}
    txt = report._population(wres, tmp_path)
    assert "draws of the reuse pass): ratA 3/12" in txt and "rests on importance" not in txt
    assert "ESS collapsed for ratA in the reuse pass; the exact fallback sampled" in txt
    assert "hyper-posterior by the exact fallback" in txt and "the importance estimate of the reuse pass" in txt
    assert "Hyper-evidence **4.568 ± 0.123**" in txt
    wres.hierarchical.attrs["exact"] = {"exact": ["ratB"]}  # flagged-only run that left ratA to reuse
    assert "**ESS collapsed for ratA**" in report._population(wres, tmp_path)
    del wres.hierarchical.attrs["exact"]
    wres.hierarchical = _hierarchical("informed")
    txt = report._population(wres, tmp_path)
    assert "\n- T2: informed in 2 of 2\n- GF: not informed\n" in txt
    wres.hierarchical = None
    assert report._population(wres, tmp_path) == ""


def test_variability_closed_form(wres, tmp_path):
    txt = report._variability(wres, tmp_path)
    lt = {sid: np.log(_seq(*SPECS[sid]["T2"])) for sid in ("ratA", "ratB")}
    m = {k: v.mean() for k, v in lt.items()}
    s2 = {k: v.var(ddof=1) for k, v in lt.items()}
    q = (m["ratA"] - m["ratB"]) ** 2 / (s2["ratA"] + s2["ratB"])  # two specimens: Q in closed form
    p = math.erfc(math.sqrt(q / 2))  # χ²(1) survival function
    row = next(r for r in txt.splitlines() if r.startswith("| T2 |"))
    assert row == f"| T2 | {q:.1f} | 1 | {p:.2g} | differ | 1/1: ratA≠ratB |"
    # THETA has the same samples in both specimens: Q = 0
    assert "| THETA | 0.0 | 1 | 1 | compatible with one common value | 0/1:  |" in txt
    wres.results.pop("ratB")
    assert report._variability(wres, tmp_path) == ""


def test_population_figures_links(wres, tmp_path):
    assert report._population_figures(wres, tmp_path) == "## Figures across specimens\n\n![forest](figures/forest.png)"
    wres.figures = wres.figures[:1]
    assert report._population_figures(wres, tmp_path) == ""


def test_render_joins_sections_and_hooks(wres, tmp_path):
    def broken(_):
        raise ValueError("no organ")

    wres.hierarchical = None
    txt = report.render_report(wres, extra_sections=[lambda w: "  ## Extra\n\nhello  ", broken])
    heads = [ln for ln in txt.splitlines() if ln.startswith("## ")]
    assert heads == ["## Run settings", "## Timings (seconds)", "## Specimens", "## Fit quality and box edges",
                     "## Identifiable combinations (posterior mean [90% interval], MPa)",
                     "## VOLF–T1 manifolds across specimens", "## Specimen variability", "## Figures across specimens",
                     "## Extra", "## broken"]
    assert txt.endswith("\n\n## Extra\n\nhello\n\n## broken\n\n(failed: ValueError: no organ)\n")
    # the sections in order, empty ones left out (the header carries the time: compared up to it)
    sections = [f(wres, tmp_path) for f in report.SECTIONS]
    assert sections[7] == ""  # no hierarchical layer (_population, after the new _fit_quality)
    assert txt.startswith(sections[0].split(" UTC")[0][:-5])
    assert "\n\n".join(s for s in sections[1:] if s) + "\n\n## Extra" in txt


def test_fit_quality_section_rmse_and_edges():
    """The section's RMSE equals a hand computation at the MAP; an edge-piled posterior is listed."""
    import types

    import numpy as np

    from hbm.data import synthetic_specimen
    from hbm.fit import fit_specimen, map_prediction
    from hbm.model import spyrou_model
    from hbm.workflow.report import _fit_quality

    model = spyrou_model()
    theta = dict(VOLF=0.9, EOPT=0.1, P1=0.13, T1=1.5, T2=9.3, THETA=59.9, GF=0.012, GM=0.009)
    ds = synthetic_specimen(model, theta, np.linspace(0, 0.4, 25), 0.002, seed=3)
    res = fit_specimen(ds, model=model, samples=200, restarts=0, progress=False, seed=1)
    r = res.result
    mu = map_prediction(res)
    rmse = float(np.sqrt(np.mean((ds.stress - mu) ** 2)))
    text = _fit_quality(types.SimpleNamespace(results={"s": r}), None)
    row = [line for line in text.splitlines() if line.startswith("| s |")][0]
    assert float(row.split("|")[2]) == pytest.approx(rmse, rel=1e-3)
    from hbm.fit import at_bounds
    edges = at_bounds(r)
    assert edges  # THETA = 59.9 / T2 near the edges of the thesis box (tested with known fractions in test_fit_quality)
    for e in edges:
        assert f"s: {e['parameter']} at its {e['side']} bound {e['edge']:g}: {100 * e['fraction']:.0f}%" in text
