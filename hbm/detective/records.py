"""The record a diagnosis looks at: artefact rows named before any fit, a dense record reduced.

:func:`prepare` runs :func:`hbm.data.prepare.prepare_record` on the specimen: rows the artefact
screen flags are dropped when asked (``artefacts="drop"``, recorded in the dataset and the
result), otherwise they make the verdict a ``data_problem`` naming them and the fix -- unless the
noise model was chosen robust on purpose (``--noise student_t``): then the diagnosis runs on the
rows as they are and a caveat names them.  A dense record is diagnosed as its bin means
(:mod:`hbm.data.reduction`), each with its variance.
"""

from __future__ import annotations

import numpy as np

from ..data import input_summary
from ..data.prepare import Prepared, prepare_record
from ..likelihood.noise import get_noise
from .inputs import SpecimenData, as_data
from .noise_check import model_free_noise

__all__ = ["prepare", "artefact_problem", "artefact_caveats", "record_noise", "record_dict"]


def prepare(data, reduce: str = "auto", artefacts: str = "flag") -> tuple[SpecimenData, Prepared, list[str]]:
    """The specimen as the diagnosis sees it, what was done to it and the progress lines saying so."""
    d = as_data(data)
    prep = prepare_record(d.ds, reduce=reduce, artefacts=artefacts)
    if prep.data is not d.ds:
        d = as_data(prep.data)
    notes = []
    if prep.artefacts:
        notes.append(f"artefact screen: {prep.artefact_text()}")
    if prep.dropped or prep.reduced:
        notes.append(f"record: {input_summary(prep.data)}")
    return d, prep, notes


def _robust(noise: str | None) -> bool:
    return noise is not None and get_noise(noise).robust


def artefact_problem(prep: Prepared, noise: str | None) -> str | None:
    """The data_problem of rows that are not the tissue, with the fix (None: none, or kept on purpose
    under a robust noise model)."""
    if not prep.artefacts or _robust(noise):
        return None
    n = sum(len(a.rows) for a in prep.artefacts)
    return (f"{n} row{'s' if n > 1 else ''} that {'are' if n > 1 else 'is'} not the tissue: {prep.artefact_text()}; "
            "a data problem, named before any fit -- drop them (hbm diagnose --drop-artefacts; Python "
            "artefacts='drop'; recorded in the result) or fit robustly (--noise student_t), then diagnose again")


def artefact_caveats(prep: Prepared, noise: str | None) -> list[dict]:
    """The caveat of artefact rows kept under a robust noise model (empty otherwise)."""
    if not prep.artefacts or not _robust(noise):
        return []
    return [{"kind": "artefacts", "text": f"rows flagged as artefacts are kept, down-weighted by the heavy-tailed "
             f"{noise} noise: {prep.artefact_text()}"}]


def record_noise(d: SpecimenData) -> dict:
    """The model-free noise estimate of the record: of one raw reading for bin means (each mean's
    sd is σ/√count), of a row otherwise (:func:`.noise_check.model_free_noise`)."""
    if d.counts is None:
        return model_free_noise(d.stress, d.segment)
    return model_free_noise(d.stress, d.segment, scale=1.0 / np.sqrt(d.counts))


def record_dict(prep: Prepared) -> dict | None:
    """What the diagnosis's JSON says about the record (None for a record taken as it is)."""
    if not (prep.artefacts or prep.dropped or prep.reduced):
        return None
    return {"artefacts": [a.to_dict(prep.lines) for a in prep.artefacts],
            "dropped": [a.to_dict(prep.lines) for a in prep.dropped],
            "reduced": bool(prep.reduced), "summary": input_summary(prep.data)}
