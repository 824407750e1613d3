"""``hbm optimize``: CMA-ES point estimates (MAP / weighted least squares) and bound sweeps."""

from __future__ import annotations

import argparse

from ..likelihood.core import make_likelihood
from ..fit.optimization import optimize
from ._common import NOISE_CHOICES, n_noise_parameters
from ._common import (
    add_model_arguments, add_seed, build_model, build_prior, check_population_memory, format_table, integer,
    load_specimen_arg, positive_int, print_json, sweep, value_range)

DESCRIPTION = """\
Fit the model to one specimen with CMA-ES (the `cma` package) in the unit box of the free
parameters, with IPOP restarts (population doubled each restart).  Every restart's optimum
is kept and printed: on this non-identifiable model their spread is informative.

Objective: --objective map (default) minimises -log posterior = -log likelihood under the
--noise model with the noise parameters optimised too (uniform prior); --objective wls
minimises the thesis's weighted least squares Er (eq. 1.19, weights max(max|s|/10, |s_i|)).

--sweep VOLF:0.01 runs the thesis's bound sweep: VOLF's box is cut into consecutive windows of
width 0.01 and one (warm-started) optimisation is run in each; the optima trace the VOLF-T1
manifold, along which (1-VOLF)*T1 stays constant.

SPECIMEN is a CSV file or the id of data/specimens/<id>.csv.

examples:
  hbm optimize data/specimens/hawkins1994_rat.csv --fix EOPT=0.192 --restarts 4
  hbm optimize hawkins1994_rat --fix EOPT=0.192 --sweep VOLF:0.01 --json > sweep.json
"""


def register(subparsers) -> None:
    """Add the ``optimize`` subcommand."""
    p = subparsers.add_parser("optimize", help="CMA-ES point estimates, restarts and bound sweeps",
                              description=DESCRIPTION,
                              formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("specimen", metavar="SPECIMEN", help="specimen CSV file or id")
    p.add_argument("--restarts", type=positive_int, default=4, metavar="K", help="CMA-ES runs (IPOP), default 4")
    p.add_argument("--sweep", type=sweep, metavar="NAME:WIDTH", help="bound sweep, e.g. VOLF:0.01")
    add_model_arguments(p)
    p.add_argument("--noise", default="iid", choices=NOISE_CHOICES,
                   help="noise model of the likelihood (default iid)")
    p.add_argument("--sigma-bounds", type=value_range, metavar="LO:HI", help="box of the noise sd (or scale)")
    p.add_argument("--objective", default="map", choices=["map", "wls"], help="map (default) or wls")
    add_seed(p, "random seed (default 0)")
    p.add_argument("--popsize", type=integer(2), default=None, metavar="P",
                   help="initial CMA-ES population size (>= 2; default cma's 4 + 3 ln d)")
    p.add_argument("--maxfevals", type=positive_int, default=None, metavar="M",
                   help="evaluation budget per CMA-ES run")
    p.add_argument("--progress", action="store_true", help="progress bar on stderr")
    p.add_argument("--json", action="store_true", help="print one JSON object instead of a table")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    """Run the optimisation and print the optima."""
    model, fix, bounds = build_model(args)
    prior = build_prior(model, args)
    ds = load_specimen_arg(args.specimen, args.sl0, model)
    if args.popsize is not None:  # IPOP doubles the population at every restart
        largest = args.popsize * 2 ** (args.restarts - 1)
        check_population_memory(f"--popsize {args.popsize} with --restarts {args.restarts} (IPOP: up to {largest})",
                                largest, ds.n_points, model.n_params + n_noise_parameters(args.noise))
    sweep_spec = (args.sweep.name, args.sweep.width) if args.sweep else None
    lik = make_likelihood(model, ds, noise=args.noise, fix=fix, bounds=None if prior is not None else bounds,
                          sigma_bounds=args.sigma_bounds, prior=prior)
    res = optimize(lik, restarts=args.restarts, seed=args.seed, objective=args.objective, sweep=sweep_spec,
                   popsize=args.popsize, maxfevals=args.maxfevals, progress=args.progress)
    out = res.to_dict()
    out["specimen"] = ds.id
    out["noise"] = args.noise
    out["fixed"] = fix
    if args.json:
        print_json(out)
        return 0
    names = list(res.best["params"])
    key = "window" if sweep_spec else "restart"
    header = [key, "objective"] + names
    rows = []
    for o in res.optima:
        k = f"{o['window'][0]:.4g}-{o['window'][1]:.4g}" if sweep_spec else str(o["restart"])
        rows.append([k, f"{o['objective']:.6g}"] + [f"{o['params'][n]:.5g}" for n in names])
    print(f"specimen {out['specimen']}: {model.name}, noise={args.noise}, objective={args.objective}, "
          f"free={', '.join(res.names)}" + (f", fixed {fix}" if fix else ""))
    print(format_table(header, rows))
    b = res.best
    print(f"best: objective {b['objective']:.6g} (log-likelihood {b['log_likelihood']:.6g}); "
          f"{res.n_evaluations} evaluations in {res.wall_time:.1f} s")
    return 0
