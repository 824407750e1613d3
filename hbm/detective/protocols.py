"""What the specimen's protocol already contains, and the experiments that would reveal an effect.

Suggestions look at the file first (time column, strain rates, relaxation holds, unloading and
reloading, points near zero strain): an experiment the file already contains is not suggested
again -- it is named as present, and what would have to change (more points, less noise, a wider
range of rates, a longer hold) is said instead.
"""

from __future__ import annotations

from typing import Iterable

import numpy as np

from ..effects import REGISTRY
from ..model.core import Effect

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


def _needs(effect: Effect | str, f: dict) -> tuple[list[str], list[str]]:
    """(what to add, what the file already has) to reveal ``effect``: the effect's own
    :meth:`hbm.Effect.experiment`; a library id is looked up in the registry."""
    if isinstance(effect, str):
        cls = REGISTRY.get(effect)
        if cls is None:
            return Effect.experiment(_Named(effect), f)
        effect = cls()
    return effect.experiment(f)


class _Named:
    """Stands in for an effect known only by its id (a user's effect named in a result)."""

    def __init__(self, name: str) -> None:
        self.name = name


def experiments_for(effects: Iterable[Effect | str], f: dict) -> str:
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
