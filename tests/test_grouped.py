"""Three-level (population → group → specimen) layer against independent numbers.

* the target (log p̂(D | ψ, group means)) against a direct scipy implementation, pointwise;
* the u (inverse-CDF) coordinates of the group means against the truncated normal: integrating
  the target over u equals integrating over m with the N_trunc(mu, sd_between) density;
* the hyper-evidence of a 1-D, two-group toy against nested quadrature;
* recovery of a known group-mean difference from synthetic stage-1 posteriors.
"""

from __future__ import annotations

import re
import time
from types import SimpleNamespace

import numpy as np
import pytest
from scipy.special import logsumexp
from scipy.stats import norm, truncnorm

from hbm.errors import HbmError
from hbm.population import run_population
from hbm.samplers.hierarchical import grouped_hierarchical
from hbm.samplers.truncnorm import ppf as truncnorm_ppf
from hbm.samplers.tmcmc import tmcmc

L = 5.0  # stage-1 box [-L, L]
FAST = {"n_steps": 12}


def toy_stage1(centres, s, n, seed, lo=-L, hi=L):
    """Stage-1 posteriors N(c, s²) truncated to [lo, hi] (d = 1) with their exact log Z (data y = c)."""
    rng = np.random.default_rng(seed)
    out = {}
    for key, c in centres.items():
        a, b = (lo - c) / s, (hi - c) / s
        x = truncnorm.rvs(a, b, loc=c, scale=s, size=n, random_state=rng)
        out[key] = (x[:, None], float(np.log(norm.cdf(b) - norm.cdf(a)) - np.log(hi - lo)))
    return out


def direct_log_phat(x_samples, m, sdw):
    """log mean_j N_trunc(z_j; m, sdw²) / (1/(2L)) on [-L, L] by scipy, for arrays m, sdw (broadcast)."""
    m, sdw = np.asarray(m, float), np.asarray(sdw, float)
    # the normal log density written out (scipy's logpdf is slow on grids of this size)
    lp = -0.5 * ((x_samples - m[..., None]) / sdw[..., None]) ** 2 - np.log(sdw[..., None]) - 0.5 * np.log(2 * np.pi)
    mass = np.log(norm.cdf((L - m) / sdw) - norm.cdf((-L - m) / sdw))
    return logsumexp(lp, axis=-1) - mass - np.log(x_samples.size) + np.log(2 * L)


class _Capture:
    """A sampler wrapper that keeps the target and box it was called with."""

    def __call__(self, target, box, n, **kw):
        self.target, self.box = target, np.asarray(box)
        return tmcmc(target, box, n, **kw)


GROUPS = {"a1": "frog", "a2": "frog", "b1": "toad", "b2": "toad"}
CENTRES = {"a1": -0.8, "a2": -0.4, "b1": 0.9, "b2": 1.3}
SD_RANGE = (0.01, 0.5)  # sd in [0.1, 5] (width of mu's range: 10)


def test_target_matches_direct_scipy_and_u_prior():
    st = toy_stage1(CENTRES, 0.3, 300, seed=4)
    cap = _Capture()
    grouped_hierarchical(st, ["x"], [[-L, L]], GROUPS, n_samples=200, seed=1, progress=False, sampler=cap,
                         sd_range=SD_RANGE, tmcmc_options={"n_steps": 2})
    # box: mu, log sd_between, log sd_within, u_frog, u_toad
    np.testing.assert_allclose(cap.box[:3], [[-L, L], np.log([0.1, 5.0]), np.log([0.1, 5.0])])
    np.testing.assert_allclose(cap.box[3:], [[0, 1], [0, 1]])
    rng = np.random.default_rng(0)
    x = np.column_stack([rng.uniform(-3, 3, 40), rng.uniform(np.log(0.1), np.log(5), (40, 2)),
                         rng.uniform(0.02, 0.98, (40, 2))])
    got = cap.target(x)
    mu, sdb, sdw = x[:, 0], np.exp(x[:, 1]), np.exp(x[:, 2])
    want = np.zeros(40)
    for g, col in (("frog", 3), ("toad", 4)):
        m = truncnorm.ppf(x[:, col], (-L - mu) / sdb, (L - mu) / sdb, loc=mu, scale=sdb)  # scipy's quantile
        for k, grp in GROUPS.items():
            if grp == g:
                want += direct_log_phat(st[k][0][:, 0], m, sdw)
    np.testing.assert_allclose(got, want, rtol=0, atol=1e-8)

    # integrating over u (uniform) == integrating over m with the truncated-normal prior density
    mu0, sdb0, sdw0 = 0.4, 0.7, 0.35
    u = (np.arange(8000) + 0.5) / 8000
    xs = np.column_stack([np.full_like(u, mu0), np.full_like(u, np.log(sdb0)), np.full_like(u, np.log(sdw0)),
                          u, np.full_like(u, 0.5)])
    lt = cap.target(xs)
    m_toad = truncnorm_ppf(0.5, mu0, sdb0, -L, L)
    lt -= sum(direct_log_phat(st[k][0][:, 0], m_toad, sdw0) for k in ("b1", "b2"))  # keep the frog factor
    by_u = logsumexp(lt) - np.log(u.size)
    m = np.linspace(-L, L, 20001)
    lm = truncnorm.logpdf(m, (-L - mu0) / sdb0, (L - mu0) / sdb0, loc=mu0, scale=sdb0)
    lm += sum(direct_log_phat(st[k][0][:, 0], m, sdw0) for k in ("a1", "a2"))
    by_m = logsumexp(lm) + np.log(m[1] - m[0])
    assert abs(by_u - by_m) < 2e-3, (by_u, by_m)


def test_truncnorm_ppf_matches_scipy_in_both_tails():
    u = np.array([1e-9, 0.01, 0.3, 0.5, 0.9, 1 - 1e-9])
    for mu, sd, lo, hi in ((0.0, 1.0, -np.inf, np.inf), (4.0, 0.5, -2.0, 3.0), (-3.0, 0.4, -1.0, 5.0),
                           (0.2, 2.0, -1.0, 1.0)):
        want = truncnorm.ppf(u, (lo - mu) / sd, (hi - mu) / sd, loc=mu, scale=sd)
        np.testing.assert_allclose(truncnorm_ppf(u, mu, sd, lo, hi), want, rtol=0, atol=1e-7)
    # continuous across the mirror switch at a = 0 (mu = lo)
    lo = 0.0
    left, right = truncnorm_ppf(0.37, lo + 1e-12, 1.0, lo, 4.0), truncnorm_ppf(0.37, lo - 1e-12, 1.0, lo, 4.0)
    assert abs(left - right) < 1e-9


def test_hyper_evidence_matches_nested_quadrature():
    st = toy_stage1(CENTRES, 0.3, 300, seed=7)
    t0 = time.perf_counter()
    r = grouped_hierarchical(st, ["x"], [[-L, L]], GROUPS, n_samples=2000, seed=3, progress=False,
                             sd_range=SD_RANGE, tmcmc_options=FAST)
    elapsed = time.perf_counter() - t0
    # nested quadrature: mu, log sd_b, log sd_w on grids (uniform priors), m per group on a grid
    mu = np.linspace(-L, L, 161)
    ls = np.linspace(np.log(0.1), np.log(5.0), 49)
    m = np.linspace(-L, L, 801)
    sdw = np.exp(ls)
    logp = {k: direct_log_phat(st[k][0][:, 0], m[:, None], sdw[None, :]) for k in st}  # (m, sd_w)
    total = np.zeros((mu.size, ls.size, ls.size))  # (mu, sd_b, sd_w)
    for g in ("frog", "toad"):
        lg = sum(logp[k] for k, grp in GROUPS.items() if grp == g)  # (m, sd_w)
        sdb = np.exp(ls)
        mm, ss = mu[:, None, None], sdb[None, :, None]
        prior = norm.pdf(m[None, None, :], mm, ss) / (norm.cdf((L - mm) / ss) - norm.cdf((-L - mm) / ss))
        mx = lg.max()
        with np.errstate(divide="ignore"):  # corners of the grid where the product underflows
            # one 2-D product (a stacked 3-D matmul does not reach BLAS)
            inner = np.log((prior.reshape(-1, m.size) @ np.exp(lg - mx)).reshape(mu.size, ls.size, ls.size)
                           * (m[1] - m[0])) + mx  # (mu, sd_b, sd_w)
        total += inner
    w_mu = np.full(mu.size, mu[1] - mu[0]); w_mu[[0, -1]] /= 2
    w_s = np.full(ls.size, ls[1] - ls[0]); w_s[[0, -1]] /= 2
    lw = (np.log(w_mu)[:, None, None] + np.log(w_s)[None, :, None] + np.log(w_s)[None, None, :]
          - np.log(2 * L) - 2 * np.log(ls[-1] - ls[0]))
    exact = logsumexp(total + lw) + sum(v[1] for v in st.values())
    print(f"hyper-evidence {r.log_evidence:.3f} ± {r.log_evidence_se:.3f}, quadrature {exact:.3f}; {elapsed:.1f} s")
    assert abs(r.log_evidence - exact) < 3 * r.log_evidence_se + 0.05, (r.log_evidence, r.log_evidence_se, exact)
    assert elapsed < 30


def test_recovers_known_group_difference():
    """Two groups of three specimens whose group means differ by 2.0 (specimens spread by 0.3 within)."""
    rng = np.random.default_rng(11)
    truth = {"frog": -1.0, "mouse": 1.0}
    sdw, s, n = 0.3, 0.2, 500
    stage1, groups = {}, {}
    for g, m in truth.items():
        for k in range(3):
            y = m + sdw * rng.standard_normal() + s * rng.standard_normal()  # a specimen, then its data
            stage1[f"{g}{k}"] = ((y + s * rng.standard_normal(n))[:, None], -np.log(2 * 20.0))
            groups[f"{g}{k}"] = g
    t0 = time.perf_counter()
    r = grouped_hierarchical(stage1, ["a"], [[-20, 20]], groups, n_samples=1000, seed=0, progress=False,
                             tmcmc_options={"n_steps": 25})
    elapsed = time.perf_counter() - t0
    assert r.groups == ["frog", "mouse"] and r.group_means.shape == (1000, 2, 1)
    (diff,) = r.group_differences(0.9)
    assert (diff["a"], diff["b"]) == ("frog", "mouse")
    assert diff["lo"] < 2.0 < diff["hi"] and diff["lo"] > 0.5 and diff["p_positive"] > 0.97, diff
    vs = r.variance_split()["a"]
    assert vs["between_fraction"] > 0.5 and vs["sd_within_lo"] < sdw < vs["sd_within_hi"], vs
    # updated individuals and predictives have the two-level shapes; a known group's predictive
    # sits at its group mean
    assert set(r.updated) == set(stage1) and r.predictive.shape == (1000, 1)
    assert abs(np.median(r.group_predictive[:, 1, 0]) - np.median(r.group_means[:, 1, 0])) < 0.1
    print(f"group difference: {diff['median']:.3f} [{diff['lo']:.3f}, {diff['hi']:.3f}] (truth 2.0), "
          f"P(>0) {diff['p_positive']:.3f}; {elapsed:.1f} s")


def test_reuse_diagnostics_see_a_group_population_beyond_a_one_sided_specimen():
    """Group "low": three specimens whose data put them near -6 (narrow Gaussian posteriors) and one
    whose data bound the parameter only from above (likelihood flat below 0, zero above; its
    stage-1 samples stop at -4).  Its group's population N(m_low, sd_within) sits at about -6,
    beyond its samples: the population mass beyond them is nearly 1 and it is flagged, while the
    informed specimens of both groups are not.  Against the population of its own group, not the
    whole population's (group "high" sits at +3)."""
    rng = np.random.default_rng(5)
    n, s = 1500, 0.3
    stage1, groups, ll = {}, {}, {}
    for g, m in {"low": -6.0, "high": 3.0}.items():
        for k in range(3):
            c = m + 0.2 * rng.standard_normal()
            x = c + s * rng.standard_normal(n)
            stage1[f"{g}{k}"] = (x[:, None], -np.log(4 * L))  # normalised likelihood, uniform prior on the box
            ll[f"{g}{k}"] = norm.logpdf(x, c, s)
            groups[f"{g}{k}"] = g
    stage1["low_onesided"] = (rng.uniform(-4.0, 0.0, (n, 1)), np.log(0.5))  # L = 1 below 0: half the box
    ll["low_onesided"] = np.zeros(n)
    groups["low_onesided"] = "low"
    r = grouped_hierarchical(stage1, ["a"], [[-L * 2, L * 2]], groups, n_samples=600, seed=1, progress=False,
                             tmcmc_options={"n_steps": 15}, log_likelihood=ll)
    beyond = {k: v["population_beyond"] for k, v in r.reuse.items()}
    # the trigger is 0.35; the informed specimens sit at 0.13-0.18
    assert beyond["low_onesided"] > 0.6 and max(v for k, v in beyond.items() if k != "low_onesided") < 0.3, beyond
    assert r.reuse["low_onesided"]["unreliable"], r.reuse["low_onesided"]
    assert not any(r.reuse[k]["unreliable"] for k in stage1 if k != "low_onesided"), {
        k: r.reuse[k].get("reasons") for k in stage1}


def test_bad_groups():
    st = toy_stage1(CENTRES, 0.3, 50, seed=1)
    with pytest.raises(HbmError, match="no group for specimens"):
        grouped_hierarchical(st, ["x"], [[-L, L]], {"a1": "frog"}, n_samples=50, progress=False)
    with pytest.raises(HbmError, match="at least two groups"):
        grouped_hierarchical(st, ["x"], [[-L, L]], dict.fromkeys(st, "frog"), n_samples=50, progress=False)


# ----------------------------------------------------------------------------------------
# groups from the data: loader metadata, --group-by, the population layer, netCDF, report
# ----------------------------------------------------------------------------------------
import hbm.cli as cli  # noqa: E402
from hbm import io  # noqa: E402
from hbm.data import load_specimen, load_specimens, specimen_groups  # noqa: E402
from hbm.errors import DataError  # noqa: E402
from hbm.model import spyrou_model  # noqa: E402
from hbm.population import run_population  # noqa: E402
from hbm.workflow.report import render_report  # noqa: E402
from hbm.workflow import RunConfig, run_workflow  # noqa: E402

CURVE = "strain,stress\n0.0,0.0\n0.1,0.002\n0.2,0.006\n0.3,0.015\n0.4,0.03\n"


def write_specimens(folder, meta):
    """Specimen CSVs with the given metadata lines ({id: {key: value}}); the curve is irrelevant here."""
    folder.mkdir(parents=True, exist_ok=True)
    for sid, kv in meta.items():
        head = "".join(f"# {k}: {v}\n" for k, v in {"id": sid, **kv}.items())
        (folder / f"{sid}.csv").write_text(head + CURVE)
    return folder


def test_group_metadata_and_specimen_groups(tmp_path):
    d = write_specimens(tmp_path / "a", {"f1": {"group": "frog", "species": "Rana"},
                                         "f2": {"group": " frog ", "species": "Rana"},
                                         "m1": {"group": "mouse", "species": "Mus"}})
    ds = load_specimens(d)
    assert ds["f2"].attrs["group"] == "frog"  # the loader strips the value, like every metadata value
    assert specimen_groups(ds) == {"f1": "frog", "f2": "frog", "m1": "mouse"}
    assert specimen_groups(ds, "species") == {"f1": "Rana", "f2": "Rana", "m1": "Mus"}
    # no group lines: ungrouped; one group from '# group:' only: ungrouped too
    plain = load_specimens(write_specimens(tmp_path / "b", {"x": {}, "y": {}}))
    assert specimen_groups(plain) is None
    one = load_specimens(write_specimens(tmp_path / "c", {"x": {"group": "rat"}, "y": {"group": "rat"}}))
    assert specimen_groups(one) is None
    with pytest.raises(DataError, match=r"every specimen has group 'rat', expected at least two groups"):
        specimen_groups(one, "group")
    with pytest.raises(DataError, match=r"grouping by 'muscle': specimens f1, f2, m1 have no '# muscle: NAME'"):
        specimen_groups(ds, "muscle")
    part = load_specimens(write_specimens(tmp_path / "d", {"x": {"group": "a"}, "y": {}}))
    with pytest.raises(DataError, match=r"specimen y has no '# group: NAME' metadata line"):
        specimen_groups(part)
    (tmp_path / "e.csv").write_text("# group:   \n" + CURVE)
    with pytest.raises(DataError, match=r"e.csv: line 1: metadata group is empty"):
        load_specimen(tmp_path / "e.csv")


@pytest.mark.parametrize("meta, argv, words", [
    ({"x": {"species": "frog"}, "y": {}}, ["--group-by", "species"], "specimen y has no '# species: NAME'"),
    ({"x": {"species": "frog"}, "y": {"species": "frog"}}, ["--group-by", "species"],
     "every specimen has species 'frog', expected at least two groups"),
    ({"x": {"group": "frog"}, "y": {}}, [], "specimen y has no '# group: NAME'"),
    ({"x": {}, "y": {}}, ["--group-by", "no such key!"], "is not a metadata key"),
])
def test_cli_group_errors_are_one_line_before_any_fit(meta, argv, words, tmp_path, capsys, monkeypatch):
    monkeypatch.setenv("HBM_DEBUG", "1")

    def reached(*a, **k):  # the run must be refused before the workflow starts
        raise AssertionError("run_workflow reached")

    monkeypatch.setattr("hbm.cli.run.run_workflow", reached)
    data = write_specimens(tmp_path / "data", meta)
    capsys.readouterr()
    rc = cli.main(["run", "--data", str(data), "--out", str(tmp_path / "out")] + argv)
    err = capsys.readouterr().err.splitlines()
    assert rc == 2 and len(err) == 1 and err[0].startswith("hbm: error: ") and words in err[0], (rc, err)
    assert not (tmp_path / "out").exists()


def test_run_workflow_checks_groups_before_fitting(tmp_path):
    data = write_specimens(tmp_path / "data", {"x": {"muscle": "EDL"}, "y": {"muscle": "EDL"}})
    with pytest.raises(DataError, match="every specimen has muscle 'EDL'"):
        run_workflow(RunConfig(data=str(data), out=str(tmp_path / "out"), group_by="muscle", workers=0,
                               progress=False))
    assert not (tmp_path / "out" / "specimens").exists() or not any((tmp_path / "out" / "specimens").iterdir())


def _t2_specimen(model, t2, seed, n=600):
    """Stage-1 posterior: uniform over the box except T2 ~ N(t2, 3²) (exact log Z of that likelihood)."""
    rng = np.random.default_rng(seed)
    names = list(model.parameter_names)
    th = rng.uniform(model.bounds[:, 0], model.bounds[:, 1], (n, len(names)))
    th[:, names.index("T2")] = rng.normal(t2, 3.0, n)
    return SimpleNamespace(names=names, bounds=model.bounds.copy(), samples=th, log_evidence=-np.log(200.0),
                           log_evidence_se=0.01, specimen_id=f"s{seed}")


def test_grouped_run_end_to_end_through_metadata(tmp_path):
    """'# group:' lines -> loader -> population layer -> hierarchical.nc -> report, on a known difference.

    T2 (logit on [0, 200]) of frogs is centred at logit 0.15 and of toads at logit 0.55 (difference
    1.94 logit units), specimens scatter by 0.3 around their group's centre.  (The run's sd range
    keeps sd_within >= 0.8 logit units, so the group means are known to about ±0.45 each.)
    """
    model = spyrou_model()
    rng = np.random.default_rng(5)
    truth = {"frog": np.log(0.15 / 0.85), "toad": np.log(0.55 / 0.45)}
    meta, results = {}, {}
    for g, m in truth.items():
        for k in range(3):
            sid = f"{g}{k}"
            meta[sid] = {"group": g}
            t2 = 200.0 / (1.0 + np.exp(-(m + 0.3 * rng.standard_normal())))
            results[sid] = _t2_specimen(model, t2, seed=len(results))
    datasets = load_specimens(write_specimens(tmp_path / "data", meta))
    groups = specimen_groups(datasets)
    t0 = time.perf_counter()
    hf, path = run_population(results, datasets, model, pooled=["T2"], samples=600, progress=False, seed=2,
                              groups=groups, group_by="group", out=tmp_path)
    elapsed = time.perf_counter() - t0
    back = io.read_hierarchical(path)
    assert back.groups["names"] == ["frog", "toad"] and back.groups["specimen_group"] == groups
    np.testing.assert_array_equal(back.groups["means"], hf.groups["means"])
    np.testing.assert_array_equal(back.groups["predictive"], hf.groups["predictive"])
    assert {"sd_between_T2", "sd_within_T2", "mu_T2", "sd_T2"} <= set(back.hyper_names)
    diff = back.groups["means"][:, 1, 0] - back.groups["means"][:, 0, 0]
    lo, hi = np.quantile(diff, [0.05, 0.95])
    want = truth["toad"] - truth["frog"]
    assert lo < want < hi and lo > 0, (lo, want, hi)
    wres = SimpleNamespace(hierarchical=back, results={}, config=RunConfig(), skipped=[], errors={}, timings={},
                           directions={}, manifolds={}, figures=[], out=tmp_path)
    from hbm.workflow.report import _groups
    txt = _groups(wres, tmp_path)
    assert "Specimens grouped by `group`" in txt and "**frog** (3: frog0, frog1, frog2)" in txt
    assert "| logit T2 | toad − frog |" in txt and "toad higher" in txt
    # words come from the data: no species, rats or mice the data did not name
    assert not re.search(r"\b(rats?|species|mouse|mice|human)\b", txt, re.I), txt
    print(f"T2 group difference (logit) {np.median(diff):.3f} [{lo:.3f}, {hi:.3f}], truth {want:.3f}; "
          f"{elapsed:.1f} s")


def test_view_refines_a_specimen_like_its_updated_posterior():
    """refine_individual on result.view(sid) (fresh TMCMC of p(θ_i | all data)) agrees with the
    importance-reweighted updated posterior of the same specimen."""
    from hbm.samplers.hierarchical import refine_individual

    st = toy_stage1(CENTRES, 0.3, 1000, seed=9)
    r = grouped_hierarchical(st, ["x"], [[-L, L]], GROUPS, n_samples=1000, seed=5, progress=False,
                             sd_range=SD_RANGE, tmcmc_options={"n_steps": 25})
    sid = "b2"
    view = r.view(sid)
    assert view.raw_samples.shape == (1000, 2) and view.model is r.model.base
    np.testing.assert_array_equal(view.raw_samples[:, 0], r.group_means[:, 1, 0])  # toad's mean, sd_within

    def loglik(theta):  # data y = centre, noise 0.3: the stage-1 posterior of the toy
        return norm.logpdf(CENTRES[sid], theta[:, 0], 0.3)

    fresh = refine_individual(view, sid, loglik, n_samples=1000, seed=2, progress=False, n_hyper=300, n_steps=12)
    a, b = np.asarray(fresh.samples)[:, 0], r.updated[sid][:, 0]
    # shrinkage toward the toad mean (below the specimen's own 1.3), the same under both methods
    assert np.mean(b) < CENTRES[sid] - 0.02
    assert abs(np.mean(a) - np.mean(b)) < 0.03 and abs(np.std(a) / np.std(b) - 1) < 0.1, (a.mean(), b.mean(),
                                                                                          a.std(), b.std())
