"""The generic layers ask the model for its vocabulary: no module outside hbm/model and hbm/effects names a
base-model parameter, and a second, made-up base model (declared here, nowhere in the package) runs through
fit_specimen, the population layer and the report without editing any generic module."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pytest

import hbm
from hbm import io
from hbm.data import synthetic_specimen
from hbm.model import BASES, Effect, Model, Parameter
from hbm.model.spec import Combination, ModelSpec, register_base, spec_of
from hbm.workflow import run_workflow

ROOT = Path(__file__).resolve().parents[1]
#: the check of the project's before-stop hook: a base-model parameter name as a string literal
PARAMETER_STRING = re.compile(r"[\"'](VOLF|EOPT|THETA|GF|GM|T1|T2|P1)[\"']")


def test_no_generic_module_names_a_base_model_parameter():
    offenders = []
    for path in sorted((ROOT / "hbm").rglob("*.py")):
        rel = path.relative_to(ROOT).as_posix()
        if rel.startswith(("hbm/model/", "hbm/effects/")):
            continue
        for k, line in enumerate(path.read_text(encoding="utf-8").splitlines(), 1):
            if PARAMETER_STRING.search(line):
                offenders.append(f"{rel}:{k}: {line.strip()}")
    assert not offenders, "\n".join(offenders)


# ------------------------------------------------------------------ a made-up base: σ = A·(exp(B·ε) − 1)
A = Parameter("A", 1e-4, 0.5, "MPa", "stress scale")
B = Parameter("B", 0.5, 20.0, "-", "exponential stiffening rate")


class ExpLaw(Effect):
    """σ = A·(exp(B·ε) − 1): one linear amplitude (A) and one shape parameter (B)."""

    name = "exp_law"
    stage = "elastic"
    parameters = (A, B)
    linear_parameters = ("A",)

    def stress(self, state, p):
        return p["A"] * np.expm1(p["B"] * state.eps)


def _initial_modulus(c):
    return c["A"] * c["B"]


SPEC = ModelSpec(
    name="exp_law", parameters=(A, B), effects=("exp_law",), physical_range={"A": (0.0, np.inf), "B": (0.0, np.inf)},
    combinations=(Combination("A*B", ("A", "B"), _initial_modulus, unit="MPa", label="A·B"),),
    shape_parameters=("B",), transforms={"A": "log", "B": "logit"})


def exp_law_model(**_) -> Model:
    return Model([ExpLaw()], name="exp_law", spec=SPEC)


@pytest.fixture
def second_base():
    register_base(SPEC, exp_law_model)
    try:
        yield exp_law_model()
    finally:
        BASES.pop(SPEC.name, None)


def test_second_base_runs_fit_population_and_report(second_base, tmp_path):
    model = second_base
    strain = np.linspace(0.0, 0.3, 30)
    truths = {"e1": (0.010, 8.0), "e2": (0.012, 7.5), "e3": (0.009, 8.5)}
    data = tmp_path / "data"
    data.mkdir()
    for k, (sid, (a, b)) in enumerate(truths.items()):
        spec = synthetic_specimen(model, {"A": a, "B": b}, strain, 0.01, seed=k, relative=True, attrs={"id": sid})
        hbm.save_specimen(spec, data / f"{sid}.csv")

    # one fit: the collapsed tier integrates A out; the stored file names its base
    fit = hbm.fit_specimen(hbm.load_specimen(data / "e1.csv"), model=model, samples=200, restarts=1, seed=3,
                           progress=False, out=tmp_path / "e1.nc")
    assert fit.result.config["likelihood_tier"] == "collapsed"
    back = io.read_specimen_result(fit.path)
    assert back.base_model == "exp_law" and spec_of(back) is SPEC
    s = hbm.fit.summarize(back)
    assert set(s) == {"A", "B", "sigma", "A*B"}
    assert s["A*B"]["lower"] < 0.010 * 8.0 < s["A*B"]["upper"]   # the generating initial modulus

    # the whole workflow: fits, the population layer (no mixture: informed pooling), identifiability, report
    wres = run_workflow(data=str(data), out=str(tmp_path / "out"), model=model, workers=0, samples=100, restarts=0,
                        sobol=False, figures=False, hier_samples=100, hier_max_steps=5, hier_exact=None,
                        progress=False)
    assert sorted(wres.results) == ["e1", "e2", "e3"] and not wres.errors
    assert wres.hierarchical is not None and wres.hierarchical.attrs["mode"] == "informed"
    assert wres.manifolds == {}                                   # the made-up base has no manifold
    assert all(r.base_model == "exp_law" for r in wres.results.values())
    text = wres.report_path.read_text()
    assert "## Identifiable combinations (posterior mean [90% interval], MPa)" in text and "A*B" in text
    # none of the Spyrou base's sections or sentences (its manifold, combinations, transforms)
    assert "VOLF–T1" not in text and "(1−VOLF)·T1" not in text and "G = c·GF" not in text and "THETA" not in text


def test_spyrou_result_files_store_no_base_name(tmp_path):
    """The default base's files stay as they were: no new attribute."""
    model = hbm.spyrou_model()
    theta = dict(VOLF=0.9, EOPT=0.1, P1=0.13, T1=1.5, T2=9.3, THETA=59.9, GF=0.012, GM=0.009)
    spec = synthetic_specimen(model, theta, np.linspace(0, 0.4, 20), 0.002, seed=1)
    res = hbm.fit_specimen(spec, samples=40, restarts=0, progress=False, out=tmp_path / "s.nc")
    assert res.result.base_model is None and "base_model" not in io.read_attrs(res.path)
    assert spec_of(io.read_specimen_result(res.path)).name == "spyrou"


def test_spyrou_spec_combinations_are_its_linear_amplitude_columns():
    """The spec's combinations name the model's linear amplitude columns (hbm.model.linear), and compute
    what an independent formula of the Voigt structure gives."""
    from hbm.model.linear import structure_of

    model = hbm.spyrou_model()
    spec = model.spec
    assert sorted(c.column for c in spec.combinations) == sorted(structure_of(model).columns)
    rng = np.random.default_rng(0)
    theta = rng.uniform(model.bounds[:, 0], model.bounds[:, 1], (50, model.n_params))
    col = dict(zip(model.parameter_names, theta.T))
    got = spec.combination_values(col)
    c = theta[:, 0]  # the fraction, first in the table
    expect = [c * theta[:, 6] + (1 - c) * theta[:, 7], c * theta[:, 2], (1 - c) * theta[:, 3]]
    for (name, v), e in zip(got.items(), expect):
        np.testing.assert_allclose(v, e, rtol=1e-15, err_msg=name)
    assert spec_of(model + hbm.effects.make_effect("offset")) is spec
    assert spec_of(model.with_bounds(**{spec.manifold.x: (0.6, 0.9)})) is spec


def test_models_and_specs_pickle_for_worker_processes():
    """The detective's refit workers and dask pickle models: a registered base's spec travels by name."""
    import pickle

    model = hbm.spyrou_model() + hbm.effects.make_effect("offset")
    back = pickle.loads(pickle.dumps(model))
    assert back.spec is model.spec and back.parameter_names == model.parameter_names
    assert pickle.loads(pickle.dumps(SPEC)).name == "exp_law"   # unregistered: by value
