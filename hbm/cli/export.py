"""``hbm export RESULT.nc --to FORMAT``: a verified FE material card from a posterior."""

from __future__ import annotations

import argparse
from pathlib import Path

from ..export import FORMATS, export
from ..export.registry import format_module
from ..export.source import parse_summary
from ..runtime.files import prepare_output_file
from ._common import print_json

DESCRIPTION = """\
Write a material card for an FE code from a fit (specimens/<id>.nc) or a population
(hierarchical.nc), verified on the way out: the card's law, re-implemented from its
documentation and solved in homogeneous incompressible uniaxial tension (lateral stretch by
root finding), is compared with hbm's curve on the tested strain range and on 1.5x it.  Exact
cards must agree within 0.5 %; approximate ones within the bound the card states.  The energy
cards (3-D materials) are also solved in every loading mode hbm predicts (cross-fibre tension,
planar, biaxial, simple shear; the tested strain range as each mode's control) against hbm's
cone reading, and state their deviation per mode.  Energy-form fits also get a Drucker
stability check (uniaxial, equibiaxial, planar).

formats:
  febio-uniaxial  Mooney-Rivlin + active fibre stress load curve (exact along the fibres; not an
                  energy, along-fibre uniaxial only)
  febio-energy    Mooney-Rivlin + fiber-pow-linear + N helical fiber-exp-linear families (energy
                  form only; a 3-D material: states its deviation from hbm per mode)
  febio-optimize  FEBio optimisation input: summary as start, 1-99 % posterior interval as bounds
  abaqus-marlow   *HYPERELASTIC, MARLOW with *UNIAXIAL TEST DATA (isotropic, exact in uniaxial
                  tension; along-fibre uniaxial only)
  abaqus-uanisohyper  UANISOHYPER_INV subroutine of the energy form (exact in uniaxial; a 3-D
                  material with N <= 24 families; needs gfortran here to compile and check it)
  csv, json       parameter draws / the summary's parameter set with units

summaries: median (the draw nearest the pointwise median curve), p05/p95 (pointwise quantile
curves of the posterior predictive; energy cards use the nearest draw), population (the
new-specimen predictive of hierarchical.nc), draws:N (csv/json).  Units: MPa, mm, N, s.

examples:
  hbm export results/specimens/calvo2010_rat1.nc --to febio-uniaxial
  hbm export fit.nc --to febio-energy --summary p95 --out muscle_p95.feb
  hbm export results/hierarchical.nc --to abaqus-marlow --summary population
"""


def register(subparsers) -> None:
    p = subparsers.add_parser("export", help="verified FE material card (FEBio, Abaqus) or parameter table",
                              description=DESCRIPTION, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("result", metavar="RESULT.nc", help="specimen result or hierarchical.nc")
    p.add_argument("--to", required=True, choices=list(FORMATS), metavar="FORMAT",
                   help="one of " + ", ".join(FORMATS))
    p.add_argument("--summary", default="median", metavar="S",
                   help="median (default), p05, p95, population or draws:N")
    p.add_argument("--out", metavar="FILE", help="output file (default: RESULT stem + _<format>_<summary> + suffix)")
    p.add_argument("--json", action="store_true", help="print the report (verification, stability) as JSON")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    """Check options and paths, export, print the verification."""
    parse_summary(args.summary)
    mod = format_module(args.to)
    res = Path(args.result)
    out = Path(args.out) if args.out else res.with_name(
        f"{res.stem}_{args.to}_{args.summary.replace(':', '')}{mod.SUFFIX}")
    prepare_output_file(out, "--out")
    rep = export(res, args.to, args.summary, out)
    if args.json:
        print_json(rep.to_json())
    else:
        print(rep.report())
    return 0
