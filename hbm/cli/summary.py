"""``hbm summary RESULT.nc [--csv]``: the parameter table of a fit, with units, for a spreadsheet."""

from __future__ import annotations

import argparse
import csv
import sys


from ..io.conventions import parameter_attrs, udunits
from ..fit.quality import combination_samples
from ..fit.specimen import chain_rhat, chains_line, summarize
from ..io import read_specimen_result
from ..model.spec import spec_of
from ._common import format_table

DESCRIPTION = """\
The posterior of a fit as a table: per parameter (and identifiable combination) its unit
(UDUNITS, "1" = dimensionless), mean, sd, 5 %, median and 95 % quantiles, and R-hat over the
posterior's chains (rank-normalised split R-hat; nan when the file holds one chain: the text
table's last line says why).  Marginal
summaries: a row of medians is not a parameter set the data support (use 'hbm export' for one).

examples:
  hbm summary results/specimens/calvo2010_rat1.nc
  hbm summary fit.nc --csv > fit.csv
"""

def register(subparsers) -> None:
    p = subparsers.add_parser("summary", help="parameter table (with units) of a fit, text or CSV",
                              description=DESCRIPTION, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("result", metavar="RESULT.nc", help="specimen result file (hbm fit / hbm run)")
    p.add_argument("--csv", action="store_true", help="CSV on stdout instead of a text table")
    p.set_defaults(func=run)


def rows(path) -> list[list[str]]:
    """Header + one row per parameter/combination."""
    return _rows(read_specimen_result(path))


def _rows(r) -> list[list[str]]:
    out = [["parameter", "units", "mean", "sd", "q05", "median", "q95", "r_hat"]]
    cols = r.as_dict()
    stats = summarize(r, prob=0.9)
    combos = combination_samples(r)
    combination_units = {c.name: udunits(c.unit) for c in spec_of(r).combinations}
    for name, s in stats.items():
        unit = combination_units.get(name) or parameter_attrs(name).get("units", "")
        rh = chain_rhat(r, cols[name] if name in cols else combos[name])
        out.append([name, unit] + [f"{s[k]:.6g}" for k in ("mean", "sd", "lower", "median", "upper")] + [f"{rh:.4f}"])
    return out


def run(args: argparse.Namespace) -> int:
    r = read_specimen_result(args.result)
    table = _rows(r)
    if args.csv:
        csv.writer(sys.stdout, lineterminator="\n").writerows(table)
    else:
        print(format_table(table[0], table[1:]))
        print(chains_line(r))
    return 0
