"""Are a curve's stresses those of passive muscle?  Units judged from the physics.

A stress file in the wrong unit (kPa or Pa read as MPa) is caught by its *stiffness*, not by
one stress threshold: the stress per unit strain (secant modulus, Cauchy stress / engineering
strain) of passive skeletal muscle lies within :data:`PLAUSIBLE_MODULUS`, from single fibres
(tens of kPa) to whole muscle stretched far into its stiff range (a few MPa).  Checked twice:

* in the **toe**, at the loading point nearest 30 % of the peak's strain, and
* at the **peak** (largest |stress|).

Sources of the range (README, "Units and plausibility"): fibre, bundle, fascicle and whole
muscle passive moduli of rabbit muscles rise from tens of kPa (fibres) to hundreds of kPa and
beyond (whole muscle) -- Ward, Winters, O'Connor & Lieber (2020) *Front. Physiol.* 11:211;
human gracilis fibres and bundles, 1-60 kPa nominal stress up to 1.0 strain -- Smith et al.
(2011) *J. Physiol.* 589:2625 (data/measured); rat tibialis anterior, 0.1-0.3 MPa at 40-45 %
strain -- Calvo et al. (2010) *J. Biomech.* 43:318 (data/specimens).  The shipped curves span
14 kPa (fibre toe) to 0.6 MPa (rat peak secant); the range adds a factor of about 5 of margin on
both sides.

A curve whose fit needs parameters on *opposite* box edges at once (some at their floor, others
at their ceiling) is the other symptom of a unit or measure error (:func:`edges_suggest_units`).
"""

from __future__ import annotations

from typing import Any, Mapping, Sequence

import numpy as np

__all__ = ["PLAUSIBLE_MODULUS", "TOE_FRACTION", "secant_moduli", "implausible", "suggest_unit", "describe",
           "edges_suggest_units"]

#: plausible stress per unit strain of passive muscle, MPa (secant: Cauchy stress / strain)
PLAUSIBLE_MODULUS = (2e-3, 3.0)
#: the toe is judged at the loading point nearest this fraction of the peak's strain
TOE_FRACTION = 0.3


def secant_moduli(strain: np.ndarray, stress: np.ndarray) -> dict[str, tuple[float, float, int]]:
    """Stress per unit strain in the toe and at the peak: ``{"toe"|"peak": (modulus, strain, index)}``.

    ``peak``: the largest |stress| over the largest |strain| reached on its side (for a loading
    ramp the secant at the peak; for a flat or relaxing curve, whose peak may sit at a small
    strain by noise, it does not divide by that small strain).  ``toe``: the secant at the point
    nearest :data:`TOE_FRACTION` of that strain.  A part is left out where it is undefined (the
    peak at zero strain; no toe point strictly between zero and that strain).
    """
    e, s = np.asarray(strain, float), np.asarray(stress, float)
    out: dict[str, tuple[float, float, int]] = {}
    i = int(np.argmax(np.abs(s)))
    if e[i] == 0 or not np.isfinite(s[i]):
        return out
    side = np.sign(e) == np.sign(e[i])
    reach = float(np.max(np.abs(e[side])))
    out["peak"] = (abs(s[i]) / reach, float(np.sign(e[i]) * reach), i)
    same = side & (np.abs(e) < reach) & (e != 0)
    if same.any():
        cand = np.flatnonzero(same)
        j = int(cand[np.argmin(np.abs(np.abs(e[cand]) - TOE_FRACTION * reach))])
        out["toe"] = (abs(s[j] / e[j]), float(e[j]), j)
    return out


def implausible(strain: np.ndarray, stress: np.ndarray) -> tuple[str, str, float, float, int] | None:
    """The first part outside :data:`PLAUSIBLE_MODULUS`: ``(part, "stiff"|"soft", modulus, strain, index)``.

    Too stiff in the toe or at the peak, or too soft at the peak (a toe may be slack: stress
    near zero there is physics, not a unit).  None when plausible.
    """
    lo, hi = PLAUSIBLE_MODULUS
    moduli = secant_moduli(strain, stress)
    for part in ("peak", "toe"):
        if part in moduli and moduli[part][0] > hi:
            return (part, "stiff", *moduli[part])
    if "peak" in moduli and moduli["peak"][0] < lo:
        return ("peak", "soft", *moduli["peak"])
    return None


#: stress units per MPa (hbm.data reads these)
_UNITS = {"MPa": 1.0, "kPa": 1e3, "Pa": 1e6}


def suggest_unit(found: tuple[str, str, float, float, int], have: str = "MPa") -> str | None:
    """The unit that brings an implausible curve (:func:`implausible`, read in ``have``) back into
    the range: the first larger unit for a too stiff curve, a smaller one for a too soft one."""
    lo, hi = PLAUSIBLE_MODULUS
    units = list(_UNITS) if found[1] == "stiff" else list(reversed(_UNITS))
    for u in units:
        modulus = found[2] * _UNITS[have] / _UNITS[u]
        if u != have and lo <= modulus <= hi:
            return u
    return None


def describe(found: tuple[str, str, float, float, int]) -> str:
    """``"stress per unit strain at the peak 160 MPa (strain 0.3), above the plausible ..."``."""
    part, kind, modulus, strain, _ = found
    lo, hi = PLAUSIBLE_MODULUS
    where = "at the peak" if part == "peak" else "in the toe"
    side = "above" if kind == "stiff" else "below"
    return (f"stress per unit strain {where} {modulus:.3g} MPa (at strain {strain:.3g}), {side} the "
            f"{lo:g}-{hi:g} MPa range of passive muscle")


def edges_suggest_units(items: Sequence[Mapping[str, Any]], n_free: int) -> str | None:
    """A possible unit or measure error: the fit pushes parameters to opposite box edges at once.

    ``items``: :func:`hbm.fit.at_bounds` entries (``parameter``, ``side``).  Flagged when at least
    two parameters sit at a lower and two at an upper edge, together half of the ``n_free``
    free model parameters or more.
    """
    lower = [str(i["parameter"]) for i in items if i.get("side") == "lower"]
    upper = [str(i["parameter"]) for i in items if i.get("side") == "upper"]
    if len(lower) >= 2 and len(upper) >= 2 and len(lower) + len(upper) >= max(4, n_free / 2):
        return (f"{len(lower) + len(upper)} of {n_free} parameters at opposite edges of their box at once "
                f"(lower: {', '.join(lower)}; upper: {', '.join(upper)}): possibly a unit or stress-measure "
                "error in the file -- check '# units_stress:' and '# stress_measure:' before reading the "
                "parameters")
    return None
