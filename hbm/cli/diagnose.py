"""``hbm diagnose`` (where does the model fail, which effect is missing) and ``hbm extend``
(add effects one at a time and watch the error fall)."""

from __future__ import annotations

import argparse
import warnings

from ..data import input_line, input_summary
from ..detective import diagnose, extend
from ..detective.calibration import CALIBRATION_CHOICES
from ..detective.caveats import CORRELATED_CHOICES
from ..detective.rules import CALIBRATION_REPLICATES
from ..effects import applicable, resolve_effect
from ..errors import HbmWarning, SettingError
from ..likelihood.modes import is_multimode
from ..model import spyrou_model
from ..runtime.files import prepare_output_file
from ..settings import FitSettings, add_arguments
from ._common import (
    n_noise_parameters, add_data_arguments, add_fix, add_form_argument, check_fix_bounds, check_population_memory,
    load_specimens_arg, name_list, integer, non_negative_int, plot_path, positive_float, print_json, workers)
from ._diagnose_modes import add_modes_diagnose_arguments, run_modes_diagnosis

#: --samples default of diagnose/extend (hbm.diagnose's n_samples default)
DEFAULT_SAMPLES = 800
#: --max-time default (s): a 150-point three-rate record takes 4-9 minutes in full on a busy 2-core machine
DEFAULT_MAX_TIME = 300.0
#: what the shared settings mean for the diagnosis (where it differs from a fit)
HELPS = {
    "seed": "seed of every random step (default 0)",
    "samples": f"TMCMC population size per evidence run (default {DEFAULT_SAMPLES}; use fewer for slow models)",
    "noise": "force one noise model for every fit (default: chosen by evidence)",
    "tier": ("tier of every evidence run: full (default) samples every parameter; auto integrates the linear "
             "amplitudes exactly and samples only the nonlinear and noise parameters where the model and noise "
             "allow it and it is cheap (at most 3 amplitude columns); collapsed: wherever it applies, however dear "
             "(auto is not the default here: it tilts comparisons between a collapsible and a full-space candidate, "
             "see results/detective_validation.md). Models without linear amplitudes (damage, series compliance) "
             "and proportional noise always use the full likelihood; the tier of each fit is in the output"),
}


DIAGNOSE_DESCRIPTION = """\
Compare the model with a specimen, show where it fails and name the missing effect.

1. fits the model (CMA-ES, then TMCMC) with a noise model chosen by evidence (iid,
   proportional or AR(1); --noise forces one), cross-checked against a model-free noise
   estimate; a stress scale no passive muscle shows (e.g. kPa) is reported as a data problem;
2. finds strain windows where the smoothed standardised residual is significantly non-zero,
   under the fitted and under the model-free noise (family-wise 5 %), and the coverage;
3. screens every candidate effect and generic controls (bump, step, kink in strain, trend in
   time), refits the best, re-optimises the base from every refit (gains against the best base);
4. verdict: effect (Δlog Z > 5, explains the misfit like the best control and beats it;
   greedy: several effects, in order) | group (with the experiment that separates them) |
   unexplained (misfit in ε or t ∈ [a, b], with its shape) | data_problem (a unit, or rows
   that are not the tissue: the artefact screen names them before any fit; --drop-artefacts
   drops them, --noise student_t keeps them in a robust fit) | adequate (only without any sign
   of misfit).  Each statistic (window score, each shape's and candidate's likelihood gain,
   the noise disagreement) is judged against its own null on this file at family-wise 5 %
   (--calibration off: fixed thresholds).  --power adds the detection limit of every library
   effect.  A dense record is diagnosed as bin means of its readings (--reduce off: every row).

examples:
  hbm diagnose data/specimens/calvo_1.csv
  hbm diagnose spec.csv --candidates offset,damage --candidate my_effect.py:MyEffect --json
  hbm diagnose spec.csv --model offset --fix EOPT=0.12 --plot diagnosis.png
  hbm diagnose spec.csv --power          # what this protocol and noise could reveal
  hbm diagnose spec.csv --noise iid      # force white noise

A file with tests in several loading modes (a `mode` column; or lateral strains) is diagnosed across
modes instead (hbm.detective.modes): the joint fit in each collagen reading (cone, gst) with the
reading named by evidence (>= 3 nats and >= 3 SE), leave-one-mode-out predictions, lateral strains
of along-fibre tests against lambda^-1/2 (compressibility, transverse isotropy) and a verdict per
mode; the fits and diagnosis.json/.txt go to --out (default hbm-results/diagnoses/<id>):
  hbm diagnose porcine_ramps.csv --form energy --samples 400
"""

EXTEND_DESCRIPTION = """\
Refit with effects added one at a time (in the given order, or greedily with --auto until no
candidate passes the decision rule of `hbm diagnose`) and show the error fall: RMSE,
log-evidence ± SE and 90 % predictive coverage per step, the base model first.

examples:
  hbm extend spec.csv --add viscoelastic,offset --plot fall.png
  hbm extend spec.csv --auto --json
"""


def _add_common(p: argparse.ArgumentParser) -> None:
    p.add_argument("specimen", metavar="SPECIMEN", nargs="+",
                   help="specimen CSV file or id in data/specimens; FILE:MODE gives a file without a mode column its loading mode "
                        "(e.g. along.csv:uniaxial_f across.csv:uniaxial_c); several files are one specimen's tests")
    p.add_argument("--model", type=name_list, default=["base"], metavar="base|EFFECT,...",
                   help="current model: 'base' (Spyrou) or base plus comma-separated effects (default base)")
    add_fix(p, "EOPT=0.12")
    add_form_argument(p)
    add_data_arguments(p)
    # the settings diagnose shares with a fit, declared once in hbm.settings.FitSettings; --max-evaluations
    # is per evidence run (the population shrinks to what it affords, then a hard cap)
    add_arguments(p, FitSettings, ("seed", "samples", "max_evaluations", "noise", "tier",
                                       "reduce", "artefacts"),
                  defaults={"samples": None, "noise": None, "tier": "full"}, helps=HELPS)
    p.add_argument("--json", action="store_true", help="print exactly one JSON object on stdout")
    p.add_argument("--plot", type=plot_path, metavar="FILE", default=None,
                   help="write the figure (PNG/PDF/SVG/...; into an existing folder)")
    p.add_argument("--progress", action="store_true", default=True,
                   help="progress lines on stderr as the diagnosis goes (the default)")
    p.add_argument("--no-progress", dest="progress", action="store_false", help="no progress lines")
    p.add_argument("--max-time", type=positive_float, default=DEFAULT_MAX_TIME, metavar="SECONDS",
                   help=f"wall seconds after which no new fit is started (default {DEFAULT_MAX_TIME:.0f}); the "
                        "verdict so far, with the candidates not yet decided and why, is written (text, JSON, "
                        "figure) and the command exits 0")
    p.add_argument("--workers", type=workers, default=None, metavar="K",
                   help="processes the candidate refits of a round run in (default: the usable cores; 0 or 1: "
                        "all in this process); the results do not depend on it")
    p.add_argument("--correlated", choices=CORRELATED_CHOICES, default="auto",
                   help="correlated residuals are noise (AR(1) offered) or model error (not offered); auto "
                        "(default): model error on curves marked digitised or group mean ('# digitised: yes', "
                        "'# kind: group mean', or those words in the provenance) or without noise at the "
                        "model-free scale, noise otherwise")


def register(subparsers) -> None:
    """Register ``diagnose`` and ``extend``."""
    p = subparsers.add_parser("diagnose", help="where does the model fail, which effect is missing",
                              description=DIAGNOSE_DESCRIPTION,
                              formatter_class=argparse.RawDescriptionHelpFormatter)
    _add_common(p)
    p.add_argument("--candidates", type=name_list, default=["all"], metavar="all|none|EFFECT,...",
                   help="library effects to screen (default all)")
    p.add_argument("--candidate", action="append", default=[], metavar="PATH.py:ClassName",
                   help="a user-written effect to screen as well; repeatable")
    p.add_argument("--top", type=non_negative_int, default=3, metavar="K",
                   help="physical candidates refitted (default 3)")
    p.add_argument("--power", action="store_true",
                   help="also report the detection limit of every library effect on this protocol and noise")
    p.add_argument("--calibration", choices=list(CALIBRATION_CHOICES), default="on",
                   help="on (default): each statistic of the verdict is judged against its own null -- the fitted "
                        "model with its fitted noise simulated on this file's design -- at family-wise 5 %% and "
                        "reported with its calibrated p-value; off: the fixed thresholds (10 nats for a shape "
                        "alone, 5 for a named effect); the output says which was used")
    p.add_argument("--replicates", type=integer(40, "an integer >= 40"), default=CALIBRATION_REPLICATES, metavar="N",
                   help=f"null replicates per round of the calibration (default {CALIBRATION_REPLICATES}; "
                        "a p-value's resolution is 1/(N+1))")
    add_modes_diagnose_arguments(p)
    p.set_defaults(func=run_diagnose)

    q = subparsers.add_parser("extend", help="add effects one at a time and show the error fall",
                              description=EXTEND_DESCRIPTION,
                              formatter_class=argparse.RawDescriptionHelpFormatter)
    _add_common(q)
    q.add_argument("--add", type=name_list, default=[], metavar="EFFECT[,EFFECT...]",
                   help="effects to add in this order (library ids or PATH.py:ClassName)")
    q.add_argument("--auto", action="store_true",
                   help="greedy: keep adding the effect `diagnose` names until none passes")
    q.set_defaults(func=run_extend)


def _model_effects(args) -> list[str]:
    """--model as a list of effect specs ('base' is the Spyrou model itself)."""
    return [m for m in args.model if m != "base"]


def _prepare(args, extra: list[str]):
    """Every check before the first fit: effects resolve (also user files), --fix names, sizes,
    the figure's folder.  ``extra``: effect specs added on top of --model (extend --add).

    Returns the specimen, the keyword arguments shared by diagnose and extend, and the model of --model.
    """
    effects = [resolve_effect(e) for e in _model_effects(args)]
    base = spyrou_model(form=args.form)
    model = base.with_effects(*effects) if effects else base
    have = set(model.effect_names)
    grown = model
    for spec in extra:
        effect = resolve_effect(spec)
        name = effect.name
        if name in have:
            raise SettingError(f"--add {spec}: effect {name!r} is already in the model "
                               f"({', '.join(model.effect_names)}); expected a new effect")
        if not applicable(effect, grown):
            raise SettingError(f"--add {spec}: effect {name!r} goes beside {', '.join(effect.requires)}; expected "
                               "it after that in the list (e.g. --add viscoelastic,viscoelastic_2)")
        have.add(name)
        grown = grown.with_effects(effect)
    check_fix_bounds(model, dict(args.fix), {})
    ds = load_specimens_arg(args.specimen, args.sl0, model)
    samples = args.samples or DEFAULT_SAMPLES
    check_population_memory(f"--samples {samples}", samples, ds.n_points,
                            model.n_params + len(extra) + n_noise_parameters(args.noise))  # None: the largest model
    if args.plot is not None:
        prepare_output_file(args.plot, "--plot")
    if args.max_evaluations is not None:  # the record's rule: the budget pays for the population at least
        FitSettings.from_args(args, samples=samples, noise=None, tier=args.tier)
    kw = {"model": model if args.form != "thesis" else ",".join(args.model), "fix": dict(args.fix), "seed": args.seed,
          "progress": args.progress, "noise": args.noise, "correlated": args.correlated, "max_time": args.max_time,
          "tier": args.tier, "workers": args.workers, "reduce": args.reduce or "auto",
          "artefacts": args.artefacts or "flag"}
    if args.samples is not None:
        kw["n_samples"] = args.samples
    if args.max_evaluations is not None:
        kw["max_evaluations"] = args.max_evaluations
    return ds, kw, model


def _candidates(args) -> list[str]:
    """--candidates (all | none | ids) plus --candidate files, each resolved now: an unknown id or
    a user file that does not load fails before the base fit, not after it."""
    lib = args.candidates
    out: list = [] if lib == ["none"] else list(lib)
    out += list(args.candidate or [])
    for spec in out:
        if spec != "all":
            resolve_effect(spec)
    if not out:
        raise SettingError("--candidates/--candidate: nothing to screen")
    return out


def _print_input(ds) -> None:
    """The loader's conversions first: every stress below is Cauchy, MPa, in strain."""
    line = input_line(input_summary(ds))
    if line:
        print(line)


def run_diagnose(args) -> int:
    """Check everything, then diagnose and print (or plot) the verdict."""
    candidates = _candidates(args)
    ds, kw, model = _prepare(args, [])
    if is_multimode(ds):  # tests in several loading modes: the detective across modes (hbm.detective.modes)
        return run_modes_diagnosis(args, ds, args.samples or DEFAULT_SAMPLES, model)
    if args.out is not None or args.force:
        warnings.warn(f"{ds.id}: --out/--force are for files with tests in several loading modes; an along-fibre "
                      "diagnosis writes no result file (ignored)", HbmWarning, stacklevel=1)
    dg = diagnose(ds, candidates=candidates, top=args.top, power=args.power, calibration=args.calibration,
                  replicates=args.replicates, **kw)
    if args.plot:
        dg.plot(args.plot)
    ds = dg.data.ds          # the record as diagnosed (a dense one reduced, artefact rows dropped on request)
    if args.json:
        print_json({**dg.to_dict(), "input": input_summary(ds)})
    else:
        _print_input(ds)
        print(dg.summary())
        if args.plot:
            print(f"figure: {args.plot}")
    return 0


def run_extend(args) -> int:
    """Check everything, then refit with the effects added and print the table."""
    adds = list(args.add)
    if not adds and not args.auto:
        raise SettingError("extend: give --add EFFECT[,EFFECT...] or --auto")
    ds, kw, _ = _prepare(args, adds)
    ext = extend(ds, add=adds, auto=args.auto, **kw)
    if args.plot:
        ext.plot(args.plot)
    ds = ext.data.ds          # the record as fitted
    if args.json:
        print_json({**ext.to_dict(), "input": input_summary(ds)})
    else:
        _print_input(ds)
        print(ext.table())
        for dcs in ext.decisions:
            print(f"auto: model {'+'.join(dcs['model'])}: {dcs['verdict']} — {dcs['message']}")
        if args.plot:
            print(f"figure: {args.plot}")
    return 0
