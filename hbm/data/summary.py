"""What a loaded specimen is: its loading path, provenance, group, and a one-paragraph input summary."""

from __future__ import annotations


import json


import re


from typing import Mapping

from ..errors import DataError
from ..model.core import Loading


from .columns import GROUP_KEY, _KEY_RE
from .specimen import Specimen, as_specimen


# ---------------------------------------------------------------------------------------
# helpers for consumers
# ---------------------------------------------------------------------------------------
def specimen_loading(data) -> Loading:
    """The :class:`hbm.Loading` of a specimen or protocol (:attr:`Specimen.loading`; a Dataset is
    converted, a Loading returned as it is)."""
    if isinstance(data, Loading):
        return data
    return as_specimen(data).loading


def provenance(ds: Specimen) -> str:
    """``"synthetic"``, ``"measured"`` or ``"unknown"`` from the ``provenance``/``source`` metadata."""
    prov = str(ds.attrs.get("provenance", "")).strip().lower()
    word = prov.split(maxsplit=1)[0] if prov else ""
    if word in ("synthetic", "measured"):  # "measured (group mean of ...)" -> "measured"
        return word
    if prov:
        return prov
    source = str(ds.attrs.get("source", "")).lower()
    if "synthetic" in source:
        return "synthetic"
    return "measured" if source else "unknown"


def specimen_groups(datasets: Mapping[str, Specimen], key: str | None = None) -> dict[str, str] | None:
    """Each specimen's group from its metadata: ``{id: group name}``, or None for ungrouped data.

    Parameters
    ----------
    datasets : mapping id -> Specimen
        Loaded specimens (:func:`load_specimens`).
    key : str, optional
        Metadata key to group by (``--group-by``: e.g. ``species``, ``muscle``, ``protocol``).
        None: the ``# group:`` lines, if any specimen has one; a single group then means
        ungrouped data (None).

    Raises
    ------
    DataError
        A specimen without the key (or an empty value) when others have it or ``key`` is given,
        or a given ``key`` whose values name a single group.
    """
    explicit = key is not None
    key = GROUP_KEY if key is None else re.sub(r"\s+", "_", str(key).strip())
    if explicit and not _KEY_RE.match(key):
        raise DataError(f"group key {key!r} is not a metadata key (letters, digits, _ . -)")
    values = {sid: str(ds.attrs.get(key, "")).strip() for sid, ds in datasets.items()}
    if not explicit and not any(values.values()):
        return None
    lacking = sorted(sid for sid, v in values.items() if not v)
    if lacking:
        shown = ", ".join(lacking[:5]) + (f" (+{len(lacking) - 5} more)" if len(lacking) > 5 else "")
        raise DataError(f"grouping by {key!r}: specimen{'s' if len(lacking) > 1 else ''} {shown} "
                        f"{'have' if len(lacking) > 1 else 'has'} no '# {key}: NAME' metadata line, expected one in "
                        "every specimen file")
    names = sorted(set(values.values()))
    if len(names) < 2:
        if not explicit:
            return None
        raise DataError(f"grouping by {key!r}: every specimen has {key} {names[0]!r}, expected at least two "
                        "groups (drop --group-by for one population)")
    return dict(sorted(values.items()))


def input_line(summary: str, where: str = "below") -> str:
    """The one line a command prints first about :func:`input_summary` (``""`` when nothing was converted)."""
    return f"input converted: {summary} (stresses {where} are Cauchy, MPa)" if summary else ""


def input_summary(ds: Specimen) -> str:
    """What the loader converted, from the attributes; ``""`` when the file held strain and MPa.

    Examples: ``"stress kPa->MPa, nominal->Cauchy; strain from sarcomere_length_um (SL0 2.0 um)"``,
    ``"tests labelled load, unload, reload"``.
    """
    a = ds.attrs
    parts = []
    stress = []
    if a.get("units_stress_original"):
        stress.append(f"{a['units_stress_original']}->{a.get('units_stress', 'MPa')}")
    if a.get("stress_measure_original"):
        stress.append(f"{a['stress_measure_original']}->Cauchy")
    if stress:
        parts.append("stress " + ", ".join(stress))
    deformation = a.get("deformation_input")
    if deformation:
        ref = a.get("reference_sarcomere_length_um")
        parts.append(f"strain from {deformation}" + (f" (SL0 {ref} um)" if ref and "sarcomere" in deformation
                                                     else ""))
    if a.get("test_labels"):
        try:
            labels = ", ".join(map(str, json.loads(a["test_labels"])))
        except (TypeError, ValueError):
            labels = str(a["test_labels"])
        parts.append(f"tests labelled {labels}")
    return "; ".join(parts)


