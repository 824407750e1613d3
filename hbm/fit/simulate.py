"""Virtual experiments: the model's prediction of every observable of every test of a file (issue 35, item 3).

``hbm simulate TESTS.csv --theta NAME=VALUE,... --out OUT.csv`` and :func:`simulate_tests` answer "what does
this material do in shear (across the fibres, biaxially ...)?" before the test is run: each test is solved
in its mode (:mod:`hbm.model.loadcases`) with the model's 3-D energy, and every observable the mode defines
is written as ``<observable>_model`` next to the file's rows (NaN, an empty cell, where a row's mode does
not define it).  Stresses are Cauchy in MPa, strains engineering -- the loaded specimen's convention.
"""

from __future__ import annotations

from pathlib import Path
from typing import Mapping

import numpy as np

from ..data.specimen import Specimen, as_specimen
from ..data.writer import save_specimen
from ..errors import SettingError
from ..model.core import Model
from ..model.energy3d import energy_from_model
from ..model.loadcases import check_mode, get_load_case
from ..model.modes_effects import ModeEffects

__all__ = ["simulate_tests", "write_simulation", "MODEL_SUFFIX"]

#: suffix of a predicted column
MODEL_SUFFIX = "_model"


def _theta_row(model: Model, theta: Mapping[str, float]) -> np.ndarray:
    missing = [n for n in model.parameter_names if n not in theta]
    unknown = [n for n in theta if n not in model.parameter_names]
    if missing or unknown:
        raise SettingError(f"--theta: expected a value for every parameter ({', '.join(model.parameter_names)}); "
                           + (f"missing {', '.join(missing)}" if missing else "")
                           + ("; " if missing and unknown else "") + (f"unknown {', '.join(unknown)}" if unknown else ""))
    row = np.array([float(theta[n]) for n in model.parameter_names])
    lo, hi = model.bounds[:, 0], model.bounds[:, 1]
    bad = [f"{n}={v:g} (box [{a:g}, {b:g}])" for n, v, a, b in zip(model.parameter_names, row, lo, hi)
           if not (np.isfinite(v) and a <= v <= b)]
    if bad:
        raise SettingError(f"--theta: outside the model's box: {', '.join(bad)}")
    return row


def simulate_tests(data, theta: Mapping[str, float], *, model: Model, collagen3d: str | None = None
                   ) -> dict[str, np.ndarray]:
    """The model's value of every observable of every test, per row of the specimen.

    Parameters
    ----------
    data : Specimen or xarray.Dataset
        The tests (their modes, controls; measured values are not needed).
    theta : mapping
        A value for every model parameter (natural units).
    model : Model
        The base model (:func:`hbm.spyrou_model`), possibly with effects (they act per test where they are
        defined in 3-D, :mod:`hbm.model.modes_effects`); the thesis form only where every test is
        ``uniaxial_f``.
    collagen3d : {"cone", "gst"}, optional
        The collagen's 3-D reading (default cone; not with the thesis form).

    Returns
    -------
    dict
        ``<observable>_model`` -> array (n_points,), NaN in the rows of modes that do not define it.

    Raises
    ------
    HbmError
        A missing or out-of-box parameter, the thesis form outside ``uniaxial_f`` (with the reason), an
        unknown reading, an effect in a mode where it is not defined -- all before any computation.
    """
    spec = as_specimen(data)
    energy = energy_from_model(model, collagen3d)
    for t in spec.tests:
        check_mode(energy, t.load_case)
    tests = [(t, get_load_case(t.load_case)) for t in spec.tests]
    try:  # effects beyond the base act per test where they are defined in 3-D; refused elsewhere
        effects = ModeEffects(model, spec.loading, tests, [(t, o) for t, c in tests for o in c.observable_names])
    except SettingError as exc:
        raise SettingError(f"simulate: {exc}") from None
    preds = effects.solve(energy, _theta_row(effects.model, theta)[None, :], spec.strain_2)
    out: dict[str, np.ndarray] = {}
    for t, _ in tests:
        for name, v in preds[t.id].items():
            col = out.setdefault(name + MODEL_SUFFIX, np.full(spec.n_points, np.nan))
            col[t.rows] = np.reshape(v, -1)
    return out


def write_simulation(data, predictions: Mapping[str, np.ndarray], path: str | Path, *,
                     record: Mapping[str, str] | None = None) -> Path:
    """Write the specimen's rows (Cauchy MPa, engineering strain) with the predicted columns, atomically.

    ``record``: extra ``# key: value`` lines (the parameters, form and reading used).
    """
    spec: Specimen = as_specimen(data)
    attrs = {**spec.attrs, **dict(record or {})}
    out = Specimen(spec.id, spec.strain, spec.time, spec.test, spec.observed, attrs, spec.tests, spec.strain_2)
    for name, values in predictions.items():
        unit = "MPa" if name.startswith("stress") else "-"
        out = out.with_series(name, values, unit, f"model prediction of {name[: -len(MODEL_SUFFIX)]}")
    return save_specimen(out, path)
