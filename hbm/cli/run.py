"""``hbm run``: the whole multi-specimen workflow (dask-parallel fits, hierarchical layer, report)."""

from __future__ import annotations

import argparse

from ..errors import HbmError
from ._common import add_model_arguments, build_model

DESCRIPTION = """\
For every specimen CSV in --data: CMA-ES optima with a VOLF bound sweep (the VOLF-T1
manifold), the TMCMC posterior with log-evidence, and Sobol indices, in parallel on dask
(one task per specimen).  Then the hierarchical Bayesian layer (a Gaussian population over the identifiable
combinations, hyper-evidence, updated individuals, a new specimen's predictive), identifiable
combinations, manifold splines, figures and a Markdown report.

Outputs in --out:
  specimens/<id>.nc   per-specimen ArviZ-compatible netCDF (arviz.from_netcdf)
  hierarchical.nc     hyper-posterior (mu_<P>, sd_<P>), updated individuals, new-specimen predictive
  manifolds.nc        VOLF-T1 manifold splines
  figures/*.png       corner, predictive, Sobol per specimen; manifolds, forest, hyper-posterior
  report.md           tables, population estimates, specimen variability, timings
  run.json            settings and timings
  organ/              with --geometry: organ-scale predictions (see 'hbm predict organ -h')

Re-running skips specimens whose result file is complete (same settings) and resumes
interrupted ones from <out>/checkpoints/.  Results do not depend on --workers.
Parallelism: an embedded dask LocalCluster with --workers processes (default: all cores), or an
existing cluster with --scheduler ADDRESS (or DASK_SCHEDULER_ADDRESS); for SLURM/PBS see
workflows/hpc_slurm.py (dask-jobqueue, pip install 'hbm[hpc]').  --workers 0 runs serially
without dask.

examples:
  hbm run
  hbm run --quick --workers 2 --out /tmp/smoke
  hbm run --samples 5000 --kernel manifold --scheduler tcp://10.0.0.5:8786
  hbm run --geometry data/geometry/fusiform.toml
"""


def register(subparsers) -> None:
    p = subparsers.add_parser("run", help="all specimens in parallel + hierarchical layer + report",
                              description=DESCRIPTION, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--data", default="data/specimens", metavar="DIR",
                   help="folder of specimen CSV files (default data/specimens)")
    p.add_argument("--out", default="results", metavar="DIR", help="output folder (default results)")
    p.add_argument("--samples", type=int, default=2000, metavar="N", help="TMCMC population size (default 2000)")
    p.add_argument("--kernel", default="rw", choices=["rw", "manifold"], help="TMCMC move kernel (default rw)")
    p.add_argument("--noise", default="iid", choices=["iid", "weighted", "proportional", "ar1"],
                   help="noise model (default iid)")
    add_model_arguments(p)
    p.add_argument("--workers", type=int, default=None, metavar="K",
                   help="dask worker processes of the embedded cluster (default: all cores; 0 = no dask)")
    p.add_argument("--scheduler", metavar="ADDRESS", help="existing dask scheduler, e.g. tcp://host:8786")
    p.add_argument("--seed", type=int, default=0, metavar="S", help="root seed (default 0)")
    p.add_argument("--restarts", type=int, default=3, metavar="K", help="CMA-ES restarts per specimen (default 3)")
    p.add_argument("--sweep", default="VOLF:0.07", metavar="NAME:WIDTH",
                   help="CMA-ES bound sweep tracing the VOLF-T1 manifold (default VOLF:0.07, 7 windows; "
                        "'none' to skip)")
    p.add_argument("--maxfevals", type=int, default=3000, metavar="M",
                   help="evaluation budget per CMA-ES run (default 3000)")
    p.add_argument("--sobol-n", type=int, default=1024, metavar="N", help="Sobol base sample size (default 1024)")
    p.add_argument("--no-sobol", action="store_true", help="skip Sobol indices")
    p.add_argument("--hier-samples", type=int, default=1000, metavar="N",
                   help="TMCMC population over the hyperparameters (default 1000)")
    p.add_argument("--pool", metavar="auto|combinations|informed|all|P1,P2,...", default="auto",
                   help="what gets a population distribution: 'combinations' = the identifiable combinations "
                        "log G, log VOLF*P1, log (1-VOLF)*T1 with T2, THETA (and EOPT when informed); "
                        "'informed' = the model parameters whose posterior sd (transformed space) is below 2/3 "
                        "of the prior's in at least half of the specimens; 'all' = every model parameter; or a "
                        "list of parameters. 'auto' (default): combinations for the base model with VOLF, P1, "
                        "T1, GF, GM, T2, THETA free, informed otherwise")
    p.add_argument("--hier-estimator", choices=("raw", "kernel"), default="raw",
                   help="estimator of p(d_i|psi): raw importance ratios (default, unbiased) or kernel-smoothed "
                        "ratios (O(h^2) bias, robust when the population is narrower than a posterior)")
    p.add_argument("--no-hierarchical", action="store_true", help="skip the hierarchical layer")
    p.add_argument("--no-figures", action="store_true", help="skip figures")
    p.add_argument("--retries", type=int, default=1, metavar="R", help="dask retries per specimen task (default 1)")
    p.add_argument("--quick", action="store_true",
                   help="smoke run: N<=500, 2 restarts, sweep VOLF:0.1, Sobol N 128, 500 hyper samples")
    p.add_argument("--no-progress", action="store_true", help="no progress bars")
    p.add_argument("--geometry", metavar="FILE.toml",
                   help="also predict a fusiform muscle's force-elongation curves (hbm predict organ) into "
                        "<out>/organ and add them to the report")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from ..workflow import RunConfig, run_workflow

    model, fix, bounds = build_model(args)
    if args.workers is not None and args.workers < 0:
        raise HbmError(f"--workers must be >= 0, got {args.workers}")
    if args.sobol_n & (args.sobol_n - 1):
        raise HbmError(f"--sobol-n must be a power of 2, got {args.sobol_n}")
    sweep = None if str(args.sweep).lower() in ("none", "", "off") else args.sweep
    hooks = []
    if getattr(args, "geometry", None):
        from ..organ_report import organ_report_hook

        # the geometry is read now, so a bad file fails before hours of fitting
        hooks.append(organ_report_hook(args.geometry, model=model, seed=args.seed, figures=not args.no_figures))
    cfg = RunConfig(data=args.data, out=args.out, samples=args.samples, kernel=args.kernel, noise=args.noise,
                    workers=args.workers, scheduler=args.scheduler, seed=args.seed, sobol=not args.no_sobol,
                    sobol_n=args.sobol_n, restarts=args.restarts, sweep=sweep, maxfevals=args.maxfevals,
                    fix=fix or None, bounds=bounds or None, hierarchical=not args.no_hierarchical,
                    hier_samples=args.hier_samples, figures=not args.no_figures, progress=not args.no_progress,
                    retries=args.retries, quick=args.quick,
                    hier_estimator=args.hier_estimator,
                    hier_pooled=(args.pool if args.pool in ("auto", "combinations", "informed", "all")
                                 else [x.strip() for x in args.pool.split(",") if x.strip()] or "auto"))
    is_base = model.effect_names == ("matrix", "fibers", "collagen") and model.name == "spyrou"
    res = run_workflow(cfg, model=None if is_base else model, extra_sections=hooks)
    print(f"{len(res.results)} specimens fitted ({len(res.skipped)} reused), "
          f"{len(res.errors)} failed; report: {res.report_path}")
    t = res.timings
    print("time: " + ", ".join(f"{k} {t[k]:.1f} s" for k in ("specimens_wall", "hierarchical", "figures", "organ",
                                                              "total") if k in t))
    for hook in hooks:
        pred = getattr(hook, "prediction", None)
        if pred is None:
            print("organ prediction FAILED (see the report's organ section)")
            return 1
        print(f"organ prediction: {pred.path}")
    return 1 if res.errors else 0
