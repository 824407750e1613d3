"""The population layer from Python (hbm.population.run_population): no dask, no files unless asked."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from hbm.errors import HbmError
from hbm.model import spyrou_model
from hbm.population import PopulationConfig, run_population
from hbm.workflow import RunConfig


def _specimen(model, t2_centre: float, seed: int, n: int = 800):
    """Stage-1 posterior: uniform over the box except T2 ~ N(t2_centre, 3²) (exact log Z of that likelihood)."""
    rng = np.random.default_rng(seed)
    names = list(model.parameter_names)
    th = rng.uniform(model.bounds[:, 0], model.bounds[:, 1], (n, len(names)))
    th[:, names.index("T2")] = rng.normal(t2_centre, 3.0, n)
    logz = -np.log(200.0)  # ∫ N(T2; c, 3²) / 200 dT2 over [0, 200], c far from the edges
    return SimpleNamespace(names=names, bounds=model.bounds.copy(), samples=th, log_evidence=logz,
                           log_evidence_se=0.01, specimen_id=f"s{seed}")


def test_run_population_in_memory(tmp_path):
    model = spyrou_model()
    centres = (40.0, 50.0, 60.0)
    results = {f"s{k}": _specimen(model, c, k) for k, c in enumerate(centres)}
    hf, path = run_population(results, None, model, pooled=["T2"], samples=300, progress=False, seed=3)
    assert path is None and not list(tmp_path.iterdir())
    assert hf.pooled_names == ["T2"] and hf.attrs["mode"] == "list"
    # the population median of T2 (logit on [0, 200]) sits near the specimens' centres
    med = 200.0 / (1.0 + np.exp(-np.median(hf.hyper("mu_T2"))))
    assert 40.0 < med < 60.0, med
    # reproducible from the seed alone, and the same result is what gets written
    again, written = run_population(results, None, model, config=PopulationConfig(pooled=["T2"], samples=300,
                                                                                  progress=False, seed=3),
                                    out=tmp_path)
    assert written == tmp_path / "hierarchical.nc" and written.exists()
    assert np.array_equal(hf.hyper_samples, again.hyper_samples)


def test_run_population_bad_input():
    model = spyrou_model()
    r = {"a": _specimen(model, 40.0, 0), "b": _specimen(model, 50.0, 1)}
    with pytest.raises(HbmError, match="at least two"):
        run_population({"a": r["a"]}, None, model)
    with pytest.raises(HbmError, match="NOPE not among the free model parameters"):
        run_population(r, None, model, pooled=["NOPE"])


def test_run_config_maps_to_population_config():
    cfg = RunConfig(seed=5, samples=600, hier_samples=222, hier_max_steps=9, hier_pooled="informed", noise="ar1",
                    retries=3, progress=False)
    pc = cfg.population_settings()
    assert (pc.seed, pc.samples, pc.stage1_samples, pc.max_steps, pc.pooled, pc.noise, pc.retries, pc.progress) == \
        (5, 222, 600, 9, "informed", "ar1", 3, False)


def test_sampler_options_reach_every_tmcmc_run_of_the_layer(monkeypatch):
    """PopulationConfig.sampler_options is the one field that sets how the layer samples: the stored stages
    of the two-level layer, of the grouped layer and of a fresh TMCMC refinement all ran with it."""
    import hbm.population.driver as driver
    import hbm.population.fallbacks as fallbacks
    from scipy.stats import norm

    model = spyrou_model()
    names = list(model.parameter_names)
    results = {f"s{k}": _specimen(model, c, k) for k, c in enumerate((40.0, 50.0, 60.0))}
    opts = {"n_steps": 3}
    hf, _ = run_population(results, None, model, pooled=["T2"], samples=300, progress=False, seed=3,
                           sampler_options=opts)
    plain, _ = run_population(results, None, model, pooled=["T2"], samples=300, progress=False, seed=3)
    assert hf.stages and all(s.n_steps == 3 for s in hf.stages)
    assert any(s.n_steps != 3 for s in plain.stages)  # the adaptive default: the check can fail

    # grouped layer and its refinements: capture what the sampler produced
    seen = {}
    real_grouped, real_refine = driver.grouped_hierarchical, fallbacks.refine_individual

    def grouped(*a, **kw):
        seen["grouped"] = real_grouped(*a, **kw)
        return seen["grouped"]

    def refine(*a, **kw):
        seen.setdefault("refine", []).append(real_refine(*a, **kw))
        return seen["refine"][-1]

    class Lik:  # the toy specimens' T2 likelihood, N(T2; centre, 3²), on the model's box
        def __init__(self, centre):
            self.centre, self.bounds = centre, model.bounds

        def __call__(self, theta):
            return norm.logpdf(theta[:, names.index("T2")], self.centre, 3.0)

    # four specimens in two groups, pooled by combinations: their prior-like stage-1 samples collapse the reuse
    centres = {"s0": 40.0, "s1": 50.0, "s2": 60.0, "s3": 70.0}
    results = {sid: _specimen(model, c, k) for k, (sid, c) in enumerate(centres.items())}
    monkeypatch.setattr(driver, "grouped_hierarchical", grouped)
    monkeypatch.setattr(fallbacks, "refine_individual", refine)
    monkeypatch.setattr(fallbacks, "specimen_likelihood", lambda cfg, res, sid, ds, m: Lik(centres[sid]))
    run_population(results, {sid: None for sid in results}, model, pooled="combinations", samples=300,
                   progress=False, seed=2, groups={"s0": "a", "s1": "a", "s2": "b", "s3": "b"}, sampler_options=opts)
    stages = seen["grouped"].sampler_result.stages
    assert stages and all(s.n_steps == 3 for s in stages)
    assert seen.get("refine"), "no refinement ran: the toy no longer exercises that path"
    assert all(s.n_steps == 3 for r in seen["refine"] for s in r.stages)


def test_reuse_key_keeps_retired_settings_and_sees_sampler_options():
    """A stored hierarchical.nc of a run from before issue 25 keeps its key (the retired reference rows and
    second pass at their old defaults); the sampler settings change the key only when set."""
    from hbm.io.identity import settings_key

    key = PopulationConfig().record()
    assert key["reference"] == 0.0 and key["second_pass"] is False
    assert "sampler_options" not in key and "progress" not in key and "groups" not in key
    assert settings_key(PopulationConfig(sampler_options={"n_steps": 3}).record()) != settings_key(key)
    assert settings_key(PopulationConfig(progress=False, retries=5).record()) == settings_key(key)
