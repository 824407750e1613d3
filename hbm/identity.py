"""Result identity: one content key per result, over everything that determines it.

A finished result (or a checkpoint) is reused only when its key matches; otherwise it is
recomputed and the run says which part changed.  A key is the SHA-256 of named components,
each itself a hash, so a mismatch can be explained component by component:

``data``
    the loaded arrays (strain, stress, time, test as float64 bytes) and the attributes that
    change their meaning (id, units, stress measure, deformation input, reference sarcomere
    length, test labels);
``model``
    the model's name, its effects (id, class, options), parameter names and prior box;
``settings``
    everything else the fit depends on (sampler, optimiser and Sobol settings, noise model and
    box, fixed values, user prior, seed, package version), hashed by the caller.

Hashes are computed from canonical JSON (sorted keys, floats by ``repr``) and raw bytes, so
they are the same in every process and on every run.
"""

from __future__ import annotations

import hashlib
import json
from typing import Any, Mapping

import numpy as np

__all__ = ["MEANING_ATTRS", "data_key", "model_key", "settings_key", "content_key", "changed"]

#: dataset attributes that change what the arrays mean (hbm.data records its conversions here)
MEANING_ATTRS = ("id", "units_stress", "units_stress_original", "stress_measure", "stress_measure_original",
                 "deformation_input", "reference_sarcomere_length_um", "test_labels")


def _canonical(obj: Any) -> Any:
    """JSON-able, order-independent form (floats by repr, arrays as lists)."""
    if isinstance(obj, Mapping):
        return {str(k): _canonical(v) for k, v in sorted(obj.items(), key=lambda kv: str(kv[0]))}
    if isinstance(obj, (list, tuple)):
        return [_canonical(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return _canonical(obj.tolist())
    if isinstance(obj, (np.floating, float)):
        return repr(float(obj))
    if isinstance(obj, (np.integer, int, bool, str)) or obj is None:
        return obj.item() if isinstance(obj, np.generic) else obj
    return repr(obj)


def _sha(*parts: bytes) -> str:
    h = hashlib.sha256()
    for p in parts:
        h.update(len(p).to_bytes(8, "little"))  # length-prefixed: no ambiguity between parts
        h.update(p)
    return h.hexdigest()[:16]


def _json(obj: Any) -> bytes:
    return json.dumps(_canonical(obj), sort_keys=True, separators=(",", ":")).encode()


def data_key(ds) -> str:
    """Hash of a specimen Dataset: its arrays and the attributes that give them meaning."""
    names = getattr(ds, "data_vars", ds)
    arrays = [np.ascontiguousarray(np.asarray(ds[v], dtype=float)).tobytes() if v in names else b"-"
              for v in ("strain", "stress", "time", "test")]
    attrs = getattr(ds, "attrs", {}) or {}
    return _sha(*arrays, _json({k: attrs.get(k) for k in MEANING_ATTRS if k in attrs}))


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
