"""``csv``: parameter draws (or the summary's parameter set) with units, for forward-UQ tools.

Comment lines (``#``) carry the provenance; the header row names each column with its unit,
``NAME [unit]`` (UDUNITS; "1" = dimensionless).  ``--summary draws:N`` writes N posterior draws,
any other summary the one parameter set it selects (:mod:`hbm.export.source`).
"""

from __future__ import annotations

import numpy as np

from .registry import Written

DESCRIPTION = "CSV of parameter draws or the summary's parameter set, with units"
SUFFIX = ".csv"


def rows(src) -> np.ndarray:
    return src.draws if src.summary.startswith("draws") else src.theta[None, :]


def write(src) -> Written:
    lines = [f"# {k}: {v}" for k, v in src.provenance().items()]
    lines += [f"# {n}" for n in src.notes]
    lines.append(",".join(f"{n} [{src.units[n]}]" for n in src.names))
    lines += [",".join(f"{x:.10g}" for x in r) for r in rows(src)]
    return Written(text="\n".join(lines) + "\n", card={"rows": int(rows(src).shape[0])})
