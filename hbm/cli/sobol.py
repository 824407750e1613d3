"""``hbm sobol``: Sobol sensitivity indices (SALib) and the thesis's relevance classes."""

from __future__ import annotations

import argparse

from ..fit.sensitivity import sobol
from ._common import (
    add_model_arguments, add_seed, build_model, build_prior, check_sobol_memory, format_table, free_parameters,
    load_specimen_arg, power_of_two, print_json)

DESCRIPTION = """\
Sobol first-order (S1) and total (ST) indices, with bootstrap confidence half-widths, of a
scalar quantity of interest over the (narrowed) prior box, using SALib's Sobol' sampler
(N*(D+2) model evaluations, N a power of 2), plus the indices of the stress at every strain
point of the specimen (in --json output).

Quantity of interest (--qoi):
  integrated_stress  (default) Q = integral of stress |d strain| along the loading path of the
                     specimen's strain points (the strain-energy density for a monotonic ramp)
  log_integrated_stress
                     Q = log of the above: indices of relative change.  Use it when the stress
                     spans decades over the box (wide T2/THETA ranges): the estimator for the raw
                     energy then converges slowly (ST > 1 at N = 1024); hbm fit/run use this one
  misfit             Q = sum of squared residuals to the specimen's stress

Relevance (thesis Table 2.1) is classified on the total index ST: very important >= 0.8,
important 0.5-0.8, unimportant 0.3-0.5, irrelevant < 0.3.

example (the thesis's Hawkins analysis):
  hbm sobol hawkins1994_rat --fix EOPT=0.192 --bounds P1=0.0001:0.01 --bounds T1=0:0.3 \\
      --bounds T2=150:175 --n 1024
"""


def register(subparsers) -> None:
    """Add the ``sobol`` subcommand."""
    p = subparsers.add_parser("sobol", help="Sobol sensitivity indices and relevance classes",
                              description=DESCRIPTION,
                              formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("specimen", metavar="SPECIMEN", help="specimen CSV file or id")
    p.add_argument("--n", type=power_of_two, default=1024, metavar="N",
                   help="base sample size N, a power of 2 (default 1024)")
    add_model_arguments(p)
    p.add_argument("--qoi", default="integrated_stress",
                   choices=["integrated_stress", "log_integrated_stress", "misfit"],
                   help="scalar quantity of interest (default integrated_stress)")
    add_seed(p, "random seed (default 0)")
    p.add_argument("--no-per-point", action="store_true", help="skip the per-strain-point indices")
    p.add_argument("--json", action="store_true", help="print one JSON object instead of a table")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    """Compute and print the indices."""
    n = args.n
    model, fix, bounds = build_model(args)
    prior = build_prior(model, args)
    if prior is not None:  # Sobol varies each parameter uniformly over its (natural) prior box
        bounds = {n: (prior[n].lo, prior[n].hi) for n in model.parameter_names if n in prior}
    ds = load_specimen_arg(args.specimen, args.sl0, model)
    check_sobol_memory(f"--n {n}", n, len(free_parameters(model, fix)), model.n_params, ds.n_points)
    res = sobol(model, data=ds, bounds=bounds, fix=fix, n=n, qoi=args.qoi, seed=args.seed,
                per_point=not args.no_per_point)
    out = res.to_dict()
    out["specimen"] = ds.id
    out["fixed"] = fix
    if args.json:
        print_json(out)
        return 0
    rows = [[k, f"{res.S1[k]:.3f} ± {res.S1_conf[k]:.3f}", f"{res.ST[k]:.3f} ± {res.ST_conf[k]:.3f}",
             res.relevance[k]] for k in res.ranking]
    print(f"specimen {out['specimen']}: Sobol indices of {args.qoi}, N={n} "
          f"({res.n_evaluations} model evaluations, {res.wall_time:.1f} s)"
          + (f", fixed {fix}" if fix else ""))
    print(format_table(["parameter", "S1", "ST", "relevance (ST)"], rows))
    return 0
