"""``hbm fit SPECIMEN``: CMA-ES optima + TMCMC posterior (+ Sobol) of one specimen -> netCDF."""

from __future__ import annotations

import argparse
from pathlib import Path

from ..errors import HbmError
from ._common import add_model_arguments, build_model, load_specimen_arg, parse_range

DESCRIPTION = """\
Fit one specimen: CMA-ES optima (restarts and an optional bound sweep), the TMCMC posterior of
the model parameters and the noise with its log-evidence, the posterior predictive and optional
Sobol indices.  Writes an ArviZ-compatible netCDF (groups posterior, sample_stats,
log_likelihood, posterior_predictive, observed_data, optima, sobol; open it with
arviz.from_netcdf) and prints a summary: posterior mean, sd and 90% interval of every parameter
and of the identifiable combinations G = c*GF + (1-c)*GM, c*P1, (1-c)*T1 (c = VOLF), and the
log-evidence with its standard error.

examples:
  hbm fit calvo2010_rat1
  hbm fit data/specimens/hawkins1994_rat.csv --fix EOPT=0.192 --samples 4000 --out hawkins.nc
  hbm fit calvo2010_rat2 --kernel manifold --bounds VOLF=0.5:0.75 --sweep VOLF:0.05
"""


def register(subparsers) -> None:
    p = subparsers.add_parser("fit", help="posterior (TMCMC) + optima (CMA-ES) of one specimen -> netCDF",
                              description=DESCRIPTION, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("specimen", metavar="SPECIMEN", help="specimen CSV file or id in data/specimens")
    p.add_argument("--samples", type=int, default=2000, metavar="N", help="TMCMC population size (default 2000)")
    p.add_argument("--kernel", default="rw", choices=["rw", "manifold"],
                   help="TMCMC move: random walk (default) or gradient/Fisher-metric manifold MALA")
    p.add_argument("--noise", default="iid", choices=["iid", "weighted", "proportional", "ar1"],
                   help="noise model (default iid Gaussian with unknown sigma)")
    p.add_argument("--sigma-bounds", metavar="LO:HI", help="box of the noise sd (or scale)")
    add_model_arguments(p)
    p.add_argument("--restarts", type=int, default=4, metavar="K", help="CMA-ES restarts (0 = skip; default 4)")
    p.add_argument("--sweep", metavar="NAME:WIDTH", help="CMA-ES bound sweep tracing a manifold, e.g. VOLF:0.05")
    p.add_argument("--maxfevals", type=int, default=5000, metavar="M",
                   help="evaluation budget per CMA-ES run (default 5000)")
    p.add_argument("--sobol", type=int, default=0, metavar="N",
                   help="Sobol base sample size (power of 2; default 0 = skip)")
    p.add_argument("--seed", type=int, default=0, metavar="S", help="root seed (default 0)")
    p.add_argument("--out", metavar="FILE.nc", help="output file (default results/specimens/<id>.nc)")
    p.add_argument("--checkpoint-dir", metavar="DIR",
                   help="TMCMC checkpoint folder: an interrupted fit resumes from its last stage")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from ..fit import fit_specimen
    from ..io import specimen_path

    data = load_specimen_arg(args.specimen)
    model, fix, bounds = build_model(args)
    if args.samples < 4:
        raise HbmError(f"--samples must be >= 4, got {args.samples}")
    if args.restarts < 0:
        raise HbmError(f"--restarts must be >= 0, got {args.restarts}")
    if args.sobol and (args.sobol & (args.sobol - 1)):
        raise HbmError(f"--sobol must be a power of 2, got {args.sobol}")
    sid = str(data.attrs.get("id", Path(args.specimen).stem))
    out = Path(args.out) if args.out else specimen_path("results", sid)
    res = fit_specimen(data, model=model, samples=args.samples, kernel=args.kernel, noise=args.noise,
                       fix=fix or None, bounds=bounds or None, seed=args.seed, restarts=args.restarts,
                       sweep=args.sweep, sobol_n=args.sobol or None, checkpoint_dir=args.checkpoint_dir,
                       out=out, progress=not args.no_progress,
                       optimize_options={"maxfevals": args.maxfevals},
                       sigma_bounds=parse_range(args.sigma_bounds, "--sigma-bounds"))
    print(res.table())
    t = res.timings
    print("time: " + ", ".join(f"{k} {v:.2f} s" for k, v in t.items()))
    print(f"wrote {res.path}")
    return 0
