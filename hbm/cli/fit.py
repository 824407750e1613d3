"""``hbm fit SPECIMEN``: CMA-ES optima + TMCMC posterior (+ Sobol) of one specimen -> netCDF."""

from __future__ import annotations

import argparse
import contextlib
import warnings
from pathlib import Path

from ..errors import HbmWarning
from ..export.stability import fit_line as stability_line
from ..fit.specimen import fit_specimen, format_at_bounds
from ..io.identity import checkpoint_dir, fit_key, set_aside_checkpoints
from ..io import specimen_path
from ..workflow.run import DEFAULT_OUT
from ..data.plausibility import edges_suggest_units
from ..data.prepare import prepare_record
from ..runtime.files import file_lock, prepare_output_dir, prepare_output_file, remove_stale_temps
from ._common import NOISE_CHOICES, add_likelihood, n_noise_parameters
from ._common import (
    check_replaceable, add_max_evaluations, check_max_evaluations, add_model_arguments, add_record_arguments,
    add_seed, build_model,
    build_prior, plot_path, print_json, check_population_memory, check_sobol_memory, free_parameters,
    load_specimen_arg, n_points, non_negative_int, positive_int, power_of_two_or_zero, sample_size, sweep,
    value_range)

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
  hbm fit data/specimens/hawkins1994_rat.csv --fix EOPT=0.192 --samples 4000 --out hawkins.nc --force
  hbm fit calvo2010_rat2 --kernel manifold --bounds VOLF=0.5:0.75 --sweep VOLF:0.05
"""


def register(subparsers) -> None:
    p = subparsers.add_parser("fit", help="posterior (TMCMC) + optima (CMA-ES) of one specimen -> netCDF",
                              description=DESCRIPTION, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("specimen", metavar="SPECIMEN", help="specimen CSV file or id in data/specimens")
    p.add_argument("--samples", type=sample_size, default=2000, metavar="N",
                   help="TMCMC population size (default 2000)")
    p.add_argument("--kernel", default="rw", choices=["rw", "manifold"],
                   help="TMCMC move: random walk (default) or gradient/Fisher-metric manifold MALA")
    p.add_argument("--noise", default="iid", choices=NOISE_CHOICES,
                   help="noise model (default iid Gaussian with unknown sigma)")
    p.add_argument("--sigma-bounds", type=value_range, metavar="LO:HI", help="box of the noise sd (or scale)")
    add_model_arguments(p)
    add_record_arguments(p)
    add_likelihood(p, ("auto", "collapsed", "full"))
    p.add_argument("--restarts", type=non_negative_int, default=4, metavar="K",
                   help="CMA-ES restarts (0 = skip; default 4)")
    p.add_argument("--sweep", type=sweep, metavar="NAME:WIDTH",
                   help="CMA-ES bound sweep tracing a manifold, e.g. VOLF:0.05")
    p.add_argument("--maxfevals", type=positive_int, default=5000, metavar="M",
                   help="evaluation budget per CMA-ES run (default 5000)")
    add_max_evaluations(p)
    p.add_argument("--sobol", type=power_of_two_or_zero, default=0, metavar="N",
                   help="Sobol base sample size (power of 2; default 0 = skip)")
    add_seed(p)
    p.add_argument("--out", metavar="FILE.nc", help="output file (default hbm-results/specimens/<id>.nc); a "
                   "result of other content there (another specimen, data, model or settings) is refused "
                   "unless --force")
    p.add_argument("--force", action="store_true", help="replace a result of other content at --out")
    p.add_argument("--checkpoint-dir", metavar="DIR",
                   help="TMCMC checkpoint folder: an interrupted fit resumes from its last stage")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.add_argument("--json", action="store_true",
                   help="print one JSON object (rmse, rmse_rel, coverage90, log_evidence(_se), map, "
                        "combinations, at_bounds, ...) instead of the text report")
    p.add_argument("--plot", type=plot_path, default=None, metavar="FILE",
                   help="figure of data, best-fit curve and 90%% band (default: next to --out, .png)")
    p.add_argument("--no-plot", action="store_true", help="no figure")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    """Check settings, sizes and paths, then fit and print the summary."""
    model, fix, bounds = build_model(args)
    prior = build_prior(model, args)
    # the record as fitted (a dense one reduced, artefact rows dropped on request): the figure and the
    # quality lines compare the fit with it
    data = prepare_record(load_specimen_arg(args.specimen, args.sl0, model), reduce=args.reduce or "auto",
                          artefacts=args.artefacts or "flag").data
    points = n_points(data)
    check_population_memory(f"--samples {args.samples}", args.samples, points,
                            model.n_params + n_noise_parameters(args.noise))
    if args.sobol:
        check_sobol_memory(f"--sobol {args.sobol}", args.sobol, len(free_parameters(model, fix)), model.n_params,
                           points)
    sid = str(data.attrs.get("id", Path(args.specimen).stem))
    out = Path(args.out) if args.out else specimen_path(DEFAULT_OUT, sid)
    checked = prepare_output_file(out, "--out")
    figure = None if args.no_plot else (args.plot or out.with_suffix(".png"))
    if figure is not None:
        prepare_output_file(figure, "--plot")
    options = {"samples": args.samples, "kernel": args.kernel, "noise": args.noise, "fix": fix or None,
               "bounds": None if prior is not None else (bounds or None), "prior": prior, "seed": args.seed,
               "restarts": args.restarts, "sweep": (args.sweep.name, args.sweep.width) if args.sweep else None,
               "sobol_n": args.sobol or None, "optimize_options": {"maxfevals": args.maxfevals},
               "sigma_bounds": args.sigma_bounds,
               "max_evaluations": check_max_evaluations(args.max_evaluations, args.samples),
               "likelihood": args.likelihood, "reduce": args.reduce, "artefacts": args.artefacts}
    # the content key of this fit (data, model, settings): keys its checkpoint and is stored with the result
    key, parts = fit_key(data, model, options)
    with contextlib.ExitStack() as held:
        # the one writer rule: this fit's files are written (and their temp files swept) only
        # under their locks; a second writer of the same file is refused at once
        held.enter_context(file_lock(checked, "--out"))
        if not args.force:
            check_replaceable(checked, parts, "--out")
        if figure is not None:
            held.enter_context(file_lock(figure, "--plot"))
            remove_stale_temps(figure.parent, recursive=False, target=figure.name)  # a killed figure write
        remove_stale_temps(checked.parent, recursive=False, target=out.name)  # of this file, left by a killed fit
        ckdir = None
        if args.checkpoint_dir is not None:
            root = prepare_output_dir(args.checkpoint_dir, "--checkpoint-dir")
            ckdir = checkpoint_dir(root, sid, key)
            held.enter_context(file_lock(ckdir.parent / f"{ckdir.name}.npz", "--checkpoint-dir"))
            remove_stale_temps(ckdir, recursive=False, target=f"{sid}.npz")
            other = set_aside_checkpoints(root, {sid: ckdir})
            if other:
                warnings.warn(f"--checkpoint-dir: {len(other)} checkpoint(s) of {sid} made with other data, model or "
                              f"settings set aside (not resumed): {', '.join(str(p) for p in other)}", HbmWarning,
                              stacklevel=1)
        res = fit_specimen(data, model=model, checkpoint_dir=ckdir, out=out, progress=not args.no_progress,
                           config_extra={"settings_hash": key, "identity": parts}, **options)
        _figure(res, data, figure)
    return _print(args, res, figure)


def _figure(res, data, figure) -> None:
    """Box-edge warnings and the figure (under the output locks)."""
    items = res.quality(data)["at_bounds"]
    for item in items:
        line = format_at_bounds([item])[0].removeprefix("warning: ")
        warnings.warn(f"{res.result.specimen_id}: {line}", HbmWarning, stacklevel=1)
    units = edges_suggest_units(items, len(res.likelihood.model_names))
    if units is not None:
        warnings.warn(f"{res.result.specimen_id}: {units}", HbmWarning, stacklevel=1)
    if figure is not None:
        from ..plots.fit import fit_plot  # matplotlib is heavy: only when a figure is drawn
        fit_plot(res, data, path=figure)


def _print(args, res, figure) -> int:
    """The summary on stdout (text or JSON)."""
    if args.json:
        print_json(res.to_json())
        return 0
    print(res.report())
    print(stability_line(res.result))
    t = res.timings
    print("time: " + ", ".join(f"{k} {v:.2f} s" for k, v in t.items()))
    print(f"wrote {res.path}" + (f" and {figure}" if figure is not None else ""))
    return 0
