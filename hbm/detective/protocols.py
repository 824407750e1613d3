"""What the specimen's protocol already contains, and the experiments that would reveal an effect.

Suggestions look at the file first (time column, strain rates, relaxation holds, unloading and
reloading, points near zero strain): an experiment the file already contains is not suggested
again -- it is named as present, and what would have to change (more points, less noise, a wider
range of rates, a longer hold) is said instead.
"""

from __future__ import annotations

from typing import Iterable

import numpy as np

__all__ = ["protocol_features", "experiments_for", "describe_protocol"]


def protocol_features(d) -> dict:
    """Features of a specimen's protocol.

    Returns
    -------
    dict
        ``time`` (has a time column), ``rates`` (distinct loading strain rates, 1/s, merged
        within a factor 3), ``hold`` (a relaxation hold: ≥ 3 points at constant strain with
        time running), ``unloading``, ``reload_beyond`` (reloading past the previous maximum),
        ``near_zero`` (points below 2 % strain), ``n_points``.
    """
    e = np.asarray(d.strain, float)
    t = None if d.time is None else np.asarray(d.time, float)
    seg = np.asarray(d.loading.history)    # one loading path: load, unload, reload, hold
    same = seg[1:] == seg[:-1]
    de = np.diff(e)
    feats = {"time": t is not None, "rates": [], "hold": False, "unloading": False, "reload_beyond": False,
             "near_zero": bool(np.min(np.abs(e)) < 0.02), "n_points": int(e.size)}
    feats["unloading"] = bool(np.any(same & (de < -1e-9)))
    if t is not None:
        dt = np.diff(t)
        load = same & (de > 1e-9) & (dt > 0)
        rates = np.sort(de[load] / dt[load])
        merged: list[float] = []
        for r in rates:
            if not merged or r > 3.0 * merged[-1]:
                merged.append(float(r))
        # one rate per cluster: the cluster's median
        feats["rates"] = [float(np.median(rates[(rates >= m) & (rates < 3.0 * m)])) for m in merged]
        flat = same & (np.abs(de) <= 1e-9) & (dt > 0)
        run = 0
        for f in flat:
            run = run + 1 if f else 0
            if run >= 2:
                feats["hold"] = True
                break
    if feats["unloading"]:
        # reloading beyond the previous maximum within a history
        for s in np.unique(seg):
            es = e[seg == s]
            peak = np.maximum.accumulate(es)
            went_down = np.flatnonzero(es < peak - 1e-9)
            if went_down.size and np.any(es[went_down[0]:] > peak[went_down[0]] + 1e-9):
                feats["reload_beyond"] = True
    return feats


def describe_protocol(f: dict) -> str:
    """One line: what the file contains."""
    parts = [f"{f['n_points']} points"]
    if f["time"]:
        parts.append(f"{len(f['rates'])} strain rate(s)" + (" (" + ", ".join(f"{r:.2g}/s" for r in f["rates"]) + ")"
                                                            if f["rates"] else ""))
    else:
        parts.append("no time column")
    parts.append("a relaxation hold" if f["hold"] else "no hold")
    parts.append(("unloading and reloading" + (" beyond the previous maximum" if f["reload_beyond"] else ""))
                 if f["unloading"] else "no unloading")
    return ", ".join(parts)


def _needs(effect: str, f: dict) -> tuple[list[str], list[str]]:
    """(what to add, what the file already has) to reveal ``effect``."""
    add, have = [], []
    if effect == "viscoelastic":
        if not f["time"]:
            add.append("a time column (the strain rate of each test)")
        if len(f["rates"]) >= 2 and max(f["rates"]) / min(f["rates"]) >= 9:
            have.append(f"{len(f['rates'])} strain rates")
        else:
            add.append("ramps at strain rates at least a decade apart (e.g. 0.01, 0.1, 1 %/s)")
        (have if f["hold"] else add).append("a relaxation hold" + ("" if f["hold"] else " of a few minutes"))
    elif effect == "damage":
        if f["reload_beyond"]:
            have.append("a load-unload-reload cycle beyond the previous maximum")
        else:
            add.append("a load-unload-reload cycle reloading beyond the previous maximum strain")
    elif effect == "offset":
        (have if f["near_zero"] else add).append("points at (near) zero strain, or an unloaded load-cell reading")
    elif effect in ("slack", "fiber_exponential"):
        add.append("the reference length pinned independently (stress-free length at minimal preload, or "
                   "sarcomere length to fix EOPT) and a densely sampled toe region")
    elif effect == "series_compliance":
        add.append("the tissue strain measured optically on the mid-belly (markers/DIC)")
    elif effect in ("recruitment", "dispersion"):
        add.append("imaging of collagen crimp and orientation (SHG microscopy) or off-axis/biaxial tests")
    return add, have


def experiments_for(effects: Iterable[str], f: dict) -> str:
    """The experiment that would reveal or separate ``effects``, given the file's protocol ``f``."""
    add: list[str] = []
    have: list[str] = []
    for e in effects:
        a, h = _needs(e, f)
        add += [x for x in a if x not in add]
        have += [x for x in h if x not in have]
    text = "; ".join(add) if add else ("more points or less noise with the same protocol (it already contains "
                                       "what reveals these effects)")
    if have:
        text += f" (the file already has {', '.join(have)})"
    return text
