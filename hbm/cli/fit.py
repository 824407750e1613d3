"""``hbm fit SPECIMEN``: CMA-ES optima + TMCMC posterior (+ Sobol) of one specimen -> netCDF."""

from __future__ import annotations

import argparse
import contextlib
import warnings
from pathlib import Path

from .. import plots  # hbm.plots.fit (matplotlib) loads when a figure is drawn
from ..errors import HbmWarning
from ..export.stability import fit_line as stability_line
from ..fit.specimen import fit_specimen, format_at_bounds
from ..io.identity import checkpoint_dir, fit_key, set_aside_checkpoints
from ..io import specimen_path
from ..settings import DEFAULT_OUT
from ..data.plausibility import edges_suggest_units
from ..data.prepare import prepare_record
from ..runtime.files import file_lock, prepare_output_dir, prepare_output_file, remove_stale_temps
from ..settings import FitSettings, add_arguments
from ..likelihood.modes import is_multimode
from ._common import n_noise_parameters
from ._modes import add_modes_arguments, check_modes_settings, modes_record, run_modes
from ._common import (
    check_replaceable, add_model_arguments, build_model, build_prior, plot_path, print_json,
    check_population_memory, check_sobol_memory, free_parameters, load_specimens_arg)

#: the FitSettings that are options of ``hbm fit`` (fix, bounds and prior come with the model's options)
FIT_OPTIONS = ("samples", "move", "noise", "sigma_bounds", "tier", "restarts", "sweep", "maxfevals", "max_evaluations",
               "sobol_n", "seed", "reduce", "artefacts")
#: this command's defaults where they differ from FitSettings'
FIT_DEFAULTS = {"maxfevals": 5000, "sobol_n": 0}

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
  hbm fit calvo2010_rat2 --move manifold --bounds VOLF=0.5:0.75 --sweep VOLF:0.05
  hbm fit along.csv:uniaxial_f across.csv:uniaxial_c --form energy --collagen3d gst
"""


def register(subparsers) -> None:
    p = subparsers.add_parser("fit", help="posterior (TMCMC) + optima (CMA-ES) of one specimen -> netCDF",
                              description=DESCRIPTION, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("specimen", metavar="SPECIMEN", nargs="+",
                   help="specimen CSV file or id in data/specimens; FILE:MODE gives a file without a mode column its loading mode "
                        "(e.g. along.csv:uniaxial_f across.csv:uniaxial_c); several files are one specimen's tests")
    # the fit's settings, declared once in hbm.settings.FitSettings (flags, rules, choices from the registries)
    add_arguments(p, FitSettings, FIT_OPTIONS, defaults=FIT_DEFAULTS)
    add_model_arguments(p)
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
    add_modes_arguments(p)
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    """Check settings, sizes and paths, then fit and print the summary."""
    model, fix, bounds = build_model(args)
    prior = build_prior(model, args)
    # the one settings record: it runs the fit and keys its result and checkpoint
    settings = FitSettings.from_args(args, fix=fix or None, bounds=None if prior is not None else (bounds or None),
                                     prior=prior)
    data = load_specimens_arg(args.specimen, args.sl0, model)
    multimode = is_multimode(data)  # tests in several loading modes: the joint fit of hbm.fit.modes
    extra = None
    if multimode:
        check_modes_settings(settings, FIT_DEFAULTS)
        extra = modes_record(args)
    else:
        # the record as fitted (a dense one reduced, artefact rows dropped on request): the figure and the
        # quality lines compare the fit with it
        data = prepare_record(data, reduce=settings.reduce or "auto", artefacts=settings.artefacts or "flag").data
        points = data.n_points
        check_population_memory(f"--samples {settings.samples}", settings.samples, points,
                                model.n_params + n_noise_parameters(settings.noise))
        if settings.sobol_n:
            check_sobol_memory(f"--sobol-n {settings.sobol_n}", settings.sobol_n, len(free_parameters(model, fix)),
                               model.n_params, points)
    sid = data.id
    out = Path(args.out) if args.out else specimen_path(DEFAULT_OUT, sid)
    checked = prepare_output_file(out, "--out")
    figure = None if args.no_plot else (args.plot or out.with_suffix(".png"))
    if figure is not None:
        prepare_output_file(figure, "--plot")
    # the content key of this fit (data, model, settings): keys its checkpoint and is stored with the result
    key, parts = fit_key(data, model, settings, extra)
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
        identity = {"settings_hash": key, "identity": parts}
        if multimode:
            return run_modes(args, model, fix, bounds, prior, settings, data, out, figure, _figure_modes,
                             checkpoint_dir=ckdir, config_extra=identity)
        res = fit_specimen(data, model=model, settings=settings, checkpoint_dir=ckdir, out=out,
                           progress=not args.no_progress, config_extra=identity)
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
        plots.fit.fit_plot(res, data, path=figure)


def _figure_modes(fit, figure) -> None:
    """The figure of a fit across modes: one panel per test in its own axes."""
    plots.fit.modes_plot(fit, path=figure)


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
