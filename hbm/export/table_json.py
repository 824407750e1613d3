"""``json``: parameter draws or the summary's parameter set, marginal summaries, units and provenance."""

from __future__ import annotations

import json

import numpy as np

from .registry import Written
from .table_csv import rows

DESCRIPTION = "JSON of parameter draws or the summary's parameter set, marginal quantiles, units"
SUFFIX = ".json"


def write(src) -> Written:
    q = np.quantile(src.draws, [0.01, 0.05, 0.5, 0.95, 0.99], axis=0)
    names, units = src.names, src.units
    obj = {"provenance": src.provenance(), "notes": list(src.notes),
           "units": {n: units[n] for n in names},
           "parameters": [dict(zip(names, map(float, r))) for r in rows(src)],
           "marginals": {n: {"q01": float(q[0, i]), "q05": float(q[1, i]), "median": float(q[2, i]),
                             "q95": float(q[3, i]), "q99": float(q[4, i])} for i, n in enumerate(names)},
           "marginals_note": "marginal quantiles of each parameter over the draws; a vector of them is not a "
                             "parameter set the data support"}
    return Written(text=json.dumps(obj, indent=1) + "\n", card={"rows": len(obj["parameters"])})
