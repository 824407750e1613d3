"""Result identity: one content key per result, over everything that determines it.

A finished result (or a checkpoint) is reused only when its key matches; otherwise it is
recomputed and the run says which part changed.  A key is the SHA-256 of named components,
each itself a hash, so a mismatch can be explained component by component:

``data``
    the specimen (:class:`hbm.data.Specimen`): its arrays (strain, stress, time, test as float64
    bytes) and the attributes that change their meaning (id, units, stress measure, deformation
    input, reference sarcomere length, test labels); further measured series and load cases
    other than along-fibre tension enter only when present (:meth:`~hbm.data.Specimen.key_extras`),
    so the key of a stress-only along-fibre specimen is the one hbm always computed;
``model``
    the model's name, its effects (id, class, options), parameter names and prior box;
``settings``
    everything else the fit depends on (sampler, optimiser and Sobol settings, noise model and
    box, fixed values, user prior, seed, package version): for a fit,
    :meth:`hbm.settings.FitSettings.record` of the very settings :func:`hbm.fit.fit_specimen`
    runs with -- ONE record, so a new setting is keyed where it is declared.

:func:`fit_key` is the key of results AND checkpoints of ``hbm fit`` and ``hbm run``: a
checkpoint of other data, model or settings is never resumed.

Hashes are computed from canonical JSON (sorted keys, floats by ``repr``) and raw bytes, so
they are the same in every process and on every run.
"""

from __future__ import annotations

import hashlib
import json
from pathlib import Path
from typing import Any, Mapping

import numpy as np

from ..data.specimen import as_specimen
from ..settings.fields import canonical

__all__ = ["MEANING_ATTRS", "data_key", "model_key", "settings_key", "content_key", "changed",
           "fit_key", "checkpoint_dir", "set_aside_checkpoints"]

#: dataset attributes that change what the arrays mean (hbm.data records its conversions here)
MEANING_ATTRS = ("id", "units_stress", "units_stress_original", "stress_measure", "stress_measure_original",
                 "deformation_input", "reference_sarcomere_length_um", "test_labels", "stress_input",
                 "cross_section_mm2", "conversion_steps", "dropped_rows", "reduction")


def _sha(*parts: bytes) -> str:
    h = hashlib.sha256()
    for p in parts:
        h.update(len(p).to_bytes(8, "little"))  # length-prefixed: no ambiguity between parts
        h.update(p)
    return h.hexdigest()[:16]


def _json(obj: Any) -> bytes:
    return json.dumps(canonical(obj), sort_keys=True, separators=(",", ":")).encode()


def data_key(data) -> str:
    """Hash of a specimen (a :class:`~hbm.data.Specimen`, or a Dataset converted to one): its arrays,
    the attributes that give them meaning, and its further series and load cases when it has any."""
    spec = as_specimen(data)
    stress = spec.observed.get("stress")
    arrays = [b"-" if a is None else np.ascontiguousarray(a, dtype=float).tobytes()
              for a in (spec.strain, None if stress is None else stress.values, spec.time, spec.test)]
    attrs = spec.attrs
    parts = [*arrays, _json({k: attrs.get(k) for k in MEANING_ATTRS if k in attrs})]
    extras = spec.key_extras()
    if extras:  # only when present: the key of a stress-only along-fibre specimen is unchanged
        parts.append(_json(extras))
    return _sha(*parts)


def _effect_description(e) -> dict:
    options = {k: v for k, v in vars(e).items() if not k.startswith("_")} if hasattr(e, "__dict__") else {}
    return {"name": getattr(e, "name", type(e).__name__),
            "class": f"{type(e).__module__}.{type(e).__qualname__}", "options": options}


def model_key(model) -> str:
    """Hash of a model: name, effects (id, class, options), parameter names and prior box."""
    return _sha(_json({"name": getattr(model, "name", type(model).__name__),
                       # explicit, so the key does not rely on the name spelling out the form
                       "form": getattr(model, "form", None),
                       "effects": [_effect_description(e) for e in getattr(model, "effects", ())],
                       "parameters": list(getattr(model, "parameter_names", ())),
                       "bounds": np.asarray(getattr(model, "bounds", []), float)}))


def settings_key(settings: Mapping[str, Any]) -> str:
    """Hash of a settings mapping (canonical JSON)."""
    return _sha(_json(settings))


def content_key(components: Mapping[str, str]) -> str:
    """The key of a result from its named component hashes."""
    return _sha(_json(dict(components)))


def changed(stored: Mapping[str, str] | None, new: Mapping[str, str]) -> list[str]:
    """Names of the components that differ (all of them when nothing was stored)."""
    if not stored:
        return list(new)
    return [k for k in new if stored.get(k) != new[k]] + [k for k in stored if k not in new]


def fit_key(data, model, settings, extra: Mapping[str, Any] | None = None) -> tuple[str, dict[str, str]]:
    """The content key of a fit of ``data`` with ``model`` and ``settings`` (a
    :class:`~hbm.settings.FitSettings`, whose :meth:`~hbm.settings.FitSettings.record` is hashed, with
    ``extra``: settings of a fit path that FitSettings does not hold, e.g. the collagen reading of a fit
    across loading modes).

    Returns
    -------
    key : str
    parts : dict
        Its components ``data``, ``model``, ``settings`` (for :func:`changed`).
    """
    parts = {"data": data_key(data), "model": model_key(model),
             "settings": settings_key(settings.record(**dict(extra or {})))}
    return content_key(parts), parts


def checkpoint_dir(root: str | Path, specimen_id: str, key: str) -> Path:
    """The checkpoint folder of one keyed fit: ``<root>/<id>-<key>`` (the file inside is ``<id>.npz``)."""
    return Path(root) / f"{specimen_id}-{key}"


def set_aside_checkpoints(root: str | Path, current: Mapping[str, Path]) -> list[Path]:
    """Checkpoints in ``root`` of the specimens of ``current`` ({id: keyed folder}) made under
    another key (other data, model or settings), or unkeyed (``<root>/<id>.npz``, older hbm).

    They are left on disk untouched and never resumed; the caller says so in one notice.
    """
    root = Path(root)
    other: list[Path] = []
    for sid, folder in current.items():
        old = [p for p in root.glob(f"{sid}-*/{sid}.npz") if p.parent.name[len(sid) + 1:].isalnum()
               and p.parent != Path(folder)]
        other += sorted(old) + [p for p in [root / f"{sid}.npz"] if p.is_file()]
    return other

