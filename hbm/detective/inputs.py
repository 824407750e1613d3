"""The detective's inputs: the specimen's arrays, the current model and the candidate effects."""

from __future__ import annotations

import math
import os
import warnings
from dataclasses import dataclass

import numpy as np

from ..data import STRESS_UNITS, Specimen, as_specimen, load_specimen
from ..data.reduction import bin_counts
from ..effects import REGISTRY, family, load_effect, make_effect
from ..errors import HbmError, HbmWarning
from ..model.core import Effect, Loading, Model
from ..model.modes_effects import added_effects as model_added_effects
from ..model.spyrou import spyrou_model
from ..data.plausibility import describe, implausible, suggest_unit
from .rules import FEW_POINTS, MIN_POINTS

__all__ = ["SpecimenData", "as_data", "unit_anomaly", "resolve_effect", "resolve_model", "resolve_candidates", "added_effects"]


@dataclass(frozen=True, slots=True)
class SpecimenData:
    """A specimen as the detective uses it: flat arrays plus the sampling structure."""

    ds: Specimen                 # the specimen itself (likelihoods are built from it)
    strain: np.ndarray
    stress: np.ndarray
    time: np.ndarray | None
    test: np.ndarray | None
    segment: np.ndarray          # id of contiguous sampling segments (tests / histories)
    ar_first: np.ndarray         # True where the likelihood's AR(1) noise restarts (history starts)
    loading: Loading
    name: str
    #: a reduced dense record: the readings' worth of each bin mean (hbm.data.reduction), else None
    counts: np.ndarray | None = None


def as_data(data) -> SpecimenData:
    """Check a specimen (a Dataset is converted, a path loaded) and return its :class:`SpecimenData`."""
    if isinstance(data, (str, os.PathLike)):
        data = load_specimen(data)
    try:
        spec = as_specimen(data)
    except HbmError as exc:
        raise HbmError(f"diagnose: {exc}") from None
    if not spec.has_stress:
        raise HbmError(f"diagnose: {spec.id}: data must have variables 'strain' and 'stress'")
    stress = spec.stress
    strain, time, test = spec.strain, spec.time, spec.test
    if strain.size != stress.size or strain.size < MIN_POINTS:
        raise HbmError(f"diagnose: need >= {MIN_POINTS} points with matching strain/stress, "
                       f"got {strain.size}/{stress.size}")
    if strain.size < FEW_POINTS:
        warnings.warn(f"diagnose: only {strain.size} points; misfit windows and effect evidence have little "
                      f"power below {FEW_POINTS} points (an 'adequate' verdict is weak evidence)", HbmWarning,
                      stacklevel=2)
    if not (np.all(np.isfinite(strain)) and np.all(np.isfinite(stress))):
        raise HbmError("diagnose: strain/stress contain non-finite values")
    loading = spec.loading
    starts = np.zeros(strain.size, bool)
    starts[0] = True
    if test is not None:
        starts[1:] |= test[1:] != test[:-1]
    starts |= loading.history_starts
    segment = np.cumsum(starts) - 1
    return SpecimenData(spec, strain, stress, time, test, segment, loading.history_starts.copy(), loading, spec.id,
                        bin_counts(spec))


def unit_anomaly(d: SpecimenData) -> str | None:
    """A stiffness no passive muscle shows: the file is probably in other units.

    The loader's check (:mod:`hbm.data.plausibility`: stress per unit strain in the toe and at the
    peak against passive muscle), reported as a data problem with the unit that would bring the
    curve back, not analysed as physics.
    """
    found = implausible(d.strain, d.stress)
    if found is None:
        return None
    unit = suggest_unit(found)
    fix = (f"the file is probably in {unit}, not MPa -- divide by 1e{int(round(math.log10(STRESS_UNITS[unit])))}"
           if unit in ("kPa", "Pa") else "wrong units, stress measure or column?")
    return f"{describe(found)}: {fix}; a data problem, not missing physics"


def resolve_effect(c) -> Effect:
    """An Effect from an instance, an Effect subclass, a library id or ``"path.py:ClassName"``."""
    if isinstance(c, Effect):
        return c
    if isinstance(c, type) and issubclass(c, Effect):
        return c()
    if isinstance(c, str):
        if ":" in c and (c.split(":")[0].endswith(".py")):
            return load_effect(c)
        if c not in REGISTRY:
            raise HbmError(f"unknown effect {c!r}; known effects: {', '.join(sorted(REGISTRY))} "
                           "(or path.py:ClassName for your own)")
        return make_effect(c)
    raise HbmError(f"a candidate must be an effect id, 'path.py:ClassName' or an hbm.Effect, got {c!r}")


def resolve_model(model) -> Model:
    """The current model: ``None``/``"base"``, ``"EFFECT,..."``, a list of effects or a Model."""
    if model is None:
        return spyrou_model()
    if isinstance(model, Model):
        return model
    if isinstance(model, str):
        parts = [p.strip() for p in model.split(",") if p.strip()]
        parts = [p for p in parts if p != "base"]
        return spyrou_model().with_effects(*[resolve_effect(p) for p in parts]) if parts else spyrou_model()
    if isinstance(model, (list, tuple)):
        return spyrou_model().with_effects(*[resolve_effect(p) for p in model])
    raise HbmError(f"model must be None, 'base', 'EFFECT,...', a list of effects or an hbm.Model, got {model!r}")


def resolve_candidates(candidates, model: Model) -> list[Effect]:
    """The candidate effects to screen, without those already in ``model``, duplicates and
    other placements of a listed effect (or of one in ``model``)."""
    if candidates is None or (isinstance(candidates, str) and candidates == "all"):
        effs = [resolve_effect(k) for k in REGISTRY]
    else:
        if isinstance(candidates, (str, Effect)):
            candidates = [candidates] if isinstance(candidates, Effect) or ":" in candidates \
                else [c for c in candidates.split(",") if c.strip()]
        effs = []
        for c in candidates:
            if isinstance(c, str) and c.strip() == "all":
                effs += [resolve_effect(k) for k in REGISTRY]
            else:
                effs.append(resolve_effect(c.strip() if isinstance(c, str) else c))
    # another placement of an effect is the same candidate (``Effect.placement_of``): the refit
    # tries the placements where the model makes them differ, so screen each family once, by
    # the effect the family is named after when it is listed
    have = {family(e) for e in model.effects} | set(model.effect_names)
    heads = {e.name for e in effs}
    out, seen = [], set()
    for e in effs:
        fam = family(e)
        if e.name in have or fam in have or fam in seen or (fam != e.name and fam in heads):
            continue
        seen.add(fam)
        out.append(e)
    return out


def added_effects(model: Model) -> list[str]:
    """Names of the effects of ``model`` beyond the Spyrou base (what reports call the model)."""
    return [e.name for e in model_added_effects(model)]
