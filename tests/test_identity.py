"""Result identity (hbm.io.identity): a finished result or checkpoint is reused only when its data,
model and settings are those of the rerun; the run says what changed (issue 14)."""

from __future__ import annotations

import numpy as np
import pytest
import xarray as xr
from hypothesis import given, settings
from hypothesis import strategies as st

from hbm.io import identity
from hbm import io
from hbm.data import save_specimen, synthetic_specimen
from hbm.effects import make_effect
from hbm.model import spyrou_model
from hbm.workflow import RunConfig, run_workflow

THETA = dict(VOLF=0.9, EOPT=0.1, P1=0.13, T1=1.5, T2=9.3, THETA=59.9, GF=0.012, GM=0.009)


def _ds(n=20, **attrs):
    eps = np.linspace(0.0, 0.4, n)
    return xr.Dataset({"strain": ("point", eps), "stress": ("point", 0.1 * eps ** 2)}, attrs={"id": "a", **attrs})


@settings(max_examples=60, deadline=None, derandomize=True)
@given(i=st.integers(0, 19), delta=st.floats(1e-12, 1.0), which=st.sampled_from(["strain", "stress"]))
def test_data_key_changes_with_any_value(i, delta, which):
    a = _ds()
    b = a.copy(deep=True)
    b[which].values[i] += delta
    assert identity.data_key(a) == identity.data_key(a.copy(deep=True))
    assert identity.data_key(a) != identity.data_key(b)


def test_data_key_sees_meaning_attributes_only():
    a = _ds()
    assert identity.data_key(a) != identity.data_key(_ds(units_stress_original="kPa"))
    assert identity.data_key(a) != identity.data_key(_ds(reference_sarcomere_length_um="2.1"))
    assert identity.data_key(a) == identity.data_key(_ds(source="another comment"))


def test_model_key_distinguishes_models():
    keys = {identity.model_key(m) for m in (spyrou_model(), spyrou_model(iso_factor=2 / 3),
                                            spyrou_model(form="energy"), spyrou_model().with_effects(make_effect("offset")))}
    assert len(keys) == 4
    assert identity.model_key(spyrou_model()) == identity.model_key(spyrou_model())


def test_model_key_sees_form_attribute_and_box():
    class M:  # a model whose name does not spell out its form or box
        name, effects, parameter_names = "m", (), ("A",)

        def __init__(self, form, hi):
            self.form, self.bounds = form, [[0.0, hi]]

    assert identity.model_key(M("thesis", 1.0)) == identity.model_key(M("thesis", 1.0))
    assert identity.model_key(M("thesis", 1.0)) != identity.model_key(M("energy", 1.0))
    assert identity.model_key(M("thesis", 1.0)) != identity.model_key(M("thesis", 1.0 + 1e-12))


def test_changed_names_the_parts():
    old = {"data": "1", "model": "2", "settings": "3"}
    assert identity.changed(old, {**old, "data": "x"}) == ["data"]
    assert identity.changed(None, old) == ["data", "model", "settings"]


@pytest.fixture
def folder(tmp_path):
    data = tmp_path / "data"
    data.mkdir()
    model = spyrou_model()
    for k, sid in enumerate(("s1", "s2")):
        ds = synthetic_specimen(model, THETA, np.linspace(0, 0.4, 16), 0.002, seed=k)
        ds = ds.with_attrs(id=sid)
        save_specimen(ds, data / f"{sid}.csv")
    return tmp_path


def _run(folder, capsys, **kw):
    cfg = dict(data=str(folder / "data"), out=str(folder / "out"), samples=60, restarts=0, sweep=None, sobol=False,
               hier_samples=60, hier_max_steps=3, hier_extend=1.0, figures=False, workers=0, progress=True)
    cfg.update(kw)
    wres = run_workflow(RunConfig(**cfg))
    return wres, capsys.readouterr().err


def test_reuse_only_what_did_not_change(folder, capsys, monkeypatch):
    w1, _ = _run(folder, capsys)
    assert w1.skipped == []
    h1 = (folder / "out" / "hierarchical.nc").read_bytes()
    s2 = (folder / "out" / "specimens" / "s2.nc").read_bytes()

    # unchanged rerun: both specimens and the hierarchical layer reused, bytes untouched
    w2, err = _run(folder, capsys)
    assert sorted(w2.skipped) == ["s1", "s2"]
    assert "hierarchical layer: reused" in err
    assert (folder / "out" / "hierarchical.nc").read_bytes() == h1

    # the same specimens and settings under another built-in rule of the layer (here the joint sampler's
    # pooling count): the layer is computed again, the specimens are reused
    import hbm.workflow.run as run_module
    rules = run_module.layer_rules()
    monkeypatch.setattr(run_module, "layer_rules",
                        lambda: {**rules, "joint_pool_informed": rules["joint_pool_informed"] + 1})
    w_rule, err = _run(folder, capsys)
    assert sorted(w_rule.skipped) == ["s1", "s2"] and "hierarchical layer: reused" not in err
    monkeypatch.undo()

    # one stress value edited: that specimen refits ("data changed"), the other is reused
    csv = folder / "data" / "s1.csv"
    lines = csv.read_text().splitlines()
    k = next(i for i, ln in enumerate(lines) if ln and ln[0].isdigit()) + 5
    cells = lines[k].split(",")
    cells[1] = repr(float(cells[1]) + 0.01)
    lines[k] = ",".join(cells)
    csv.write_text("\n".join(lines) + "\n")
    w3, err = _run(folder, capsys)
    assert w3.skipped == ["s2"] and "s1: data changed -- refitting" in err
    assert (folder / "out" / "specimens" / "s2.nc").read_bytes() == s2
    assert "hierarchical layer: reused" not in err  # s1 changed, so the population is recomputed

    # another model (iso factor): every specimen refits, the reason is the model
    w5 = run_workflow(RunConfig(data=str(folder / "data"), out=str(folder / "out"), samples=60, restarts=0,
                                sweep=None, sobol=False, hierarchical=False, figures=False, workers=0, progress=True),
                      model=spyrou_model(iso_factor=2 / 3))
    err = capsys.readouterr().err
    assert w5.skipped == [] and "s1: model changed -- refitting" in err and "s2: model changed -- refitting" in err
    assert io.read_specimen_result(folder / "out" / "specimens" / "s1.nc").samples.shape[0] == 60


def test_checkpoint_of_other_data_is_not_resumed(folder, capsys):
    _run(folder, capsys, hierarchical=False)
    out = folder / "out"
    old_key = io.read_attrs(out / "specimens" / "s1.nc")["config"]["settings_hash"]
    # an interrupted run: no finished file, a checkpoint under the old key (garbage: resuming it would fail)
    (out / "specimens" / "s1.nc").unlink()
    stale = out / "checkpoints" / f"s1-{old_key}" / "s1.npz"
    stale.parent.mkdir(parents=True, exist_ok=True)
    stale.write_bytes(b"not a checkpoint of these data")
    csv = folder / "data" / "s1.csv"
    lines = csv.read_text().splitlines()
    k = next(i for i, ln in enumerate(lines) if ln and ln[0].isdigit()) + 3
    cells = lines[k].split(",")
    cells[1] = repr(float(cells[1]) * 1.5 + 1e-3)
    lines[k] = ",".join(cells)
    csv.write_text("\n".join(lines) + "\n")
    w, err = _run(folder, capsys, hierarchical=False)
    assert "resuming" not in err and w.errors == {} and w.skipped == ["s2"]
    new_key = io.read_attrs(out / "specimens" / "s1.nc")["config"]["settings_hash"]
    assert new_key != old_key and stale.read_bytes() == b"not a checkpoint of these data"
