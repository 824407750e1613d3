"""``hbm diagnose`` (where does the model fail, which effect is missing) and ``hbm extend``
(add effects one at a time and watch the error fall)."""

from __future__ import annotations

import argparse

from ..errors import HbmError
from ._common import load_specimen_arg, parse_fix, print_json

DIAGNOSE_DESCRIPTION = """\
Compare the model with a specimen, show where it fails and name the missing effect.

1. fits the model (CMA-ES, then TMCMC) with a noise model chosen from the data (iid,
   proportional or AR(1), by BIC), cross-checked against a model-free noise estimate;
2. finds strain windows where the smoothed standardised residual is significantly non-zero
   (family-wise 5 %, correlated noise accounted for) and the predictive coverage;
3. screens every candidate effect by a projected score test, refits the best few plus a
   generic local-misfit control, each at its own best noise model (Δlog-evidence ± SE);
4. verdict: adequate | effect (Δlog Z > 5, beats the runner-up, parameter away from null) |
   group (confusable effects, with the experiment that separates them) | unexplained
   (misfit in ε ∈ [a, b] that only the non-physical control explains).

examples:
  hbm diagnose data/specimens/calvo_1.csv
  hbm diagnose spec.csv --candidates offset,damage --candidate my_effect.py:MyEffect --json
  hbm diagnose spec.csv --model offset --fix EOPT=0.12 --plot diagnosis.png
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
    p.add_argument("specimen", metavar="SPECIMEN", help="specimen CSV path or id in data/specimens/")
    p.add_argument("--model", default="base", metavar="base|EFFECT,...",
                   help="current model: 'base' (Spyrou) or base plus comma-separated effects (default base)")
    p.add_argument("--fix", action="append", default=[], metavar="NAME=VALUE",
                   help="hold a parameter fixed, e.g. --fix EOPT=0.12; repeatable")
    p.add_argument("--seed", type=int, default=0, metavar="S", help="seed of every random step (default 0)")
    p.add_argument("--samples", type=int, default=None, metavar="N",
                   help="TMCMC population size per evidence run (default 800; shrinks for slow models)")
    p.add_argument("--json", action="store_true", help="print exactly one JSON object on stdout")
    p.add_argument("--plot", metavar="FILE", default=None, help="write the figure (PNG/PDF/SVG)")
    p.add_argument("--progress", action="store_true", help="progress lines on stderr")


def register(subparsers) -> None:
    """Register ``diagnose`` and ``extend``."""
    p = subparsers.add_parser("diagnose", help="where does the model fail, which effect is missing",
                              description=DIAGNOSE_DESCRIPTION,
                              formatter_class=argparse.RawDescriptionHelpFormatter)
    _add_common(p)
    p.add_argument("--candidates", default="all", metavar="all|EFFECT,...",
                   help="library effects to screen (default all)")
    p.add_argument("--candidate", action="append", default=[], metavar="PATH.py:ClassName",
                   help="a user-written effect to screen as well; repeatable")
    p.add_argument("--top", type=int, default=3, metavar="K", help="physical candidates refitted (default 3)")
    p.set_defaults(func=run_diagnose)

    q = subparsers.add_parser("extend", help="add effects one at a time and show the error fall",
                              description=EXTEND_DESCRIPTION,
                              formatter_class=argparse.RawDescriptionHelpFormatter)
    _add_common(q)
    q.add_argument("--add", default="", metavar="EFFECT[,EFFECT...]",
                   help="effects to add in this order (library ids or PATH.py:ClassName)")
    q.add_argument("--auto", action="store_true",
                   help="greedy: keep adding the effect `diagnose` names until none passes")
    q.set_defaults(func=run_extend)


def _split(text: str) -> list[str]:
    return [t.strip() for t in (text or "").split(",") if t.strip()]


def _candidates(args) -> object:
    lib = args.candidates.strip() if args.candidates else "all"
    out: list = [] if lib == "none" else (["all"] if lib == "all" else _split(lib))
    out += list(args.candidate or [])
    if not out:
        raise HbmError("--candidates/--candidate: nothing to screen")
    return out


def _kw(args) -> dict:
    kw = {"model": args.model, "fix": parse_fix(args.fix), "seed": args.seed, "progress": args.progress}
    if args.samples is not None:
        if args.samples < 50:
            raise HbmError(f"--samples {args.samples}: expected an integer >= 50")
        kw["n_samples"] = args.samples
    return kw


def run_diagnose(args) -> int:
    from ..detective import diagnose

    if args.top < 0:
        raise HbmError(f"--top {args.top}: expected an integer >= 0")
    ds = load_specimen_arg(args.specimen)
    dg = diagnose(ds, candidates=_candidates(args), top=args.top, **_kw(args))
    if args.plot:
        dg.plot(args.plot)
    if args.json:
        print_json(dg.to_dict())
    else:
        print(dg.summary())
        if args.plot:
            print(f"figure: {args.plot}")
    return 0


def run_extend(args) -> int:
    from ..detective import extend

    adds = _split(args.add)
    if not adds and not args.auto:
        raise HbmError("extend: give --add EFFECT[,EFFECT...] or --auto")
    ds = load_specimen_arg(args.specimen)
    ext = extend(ds, add=adds, auto=args.auto, **_kw(args))
    if args.plot:
        ext.plot(args.plot)
    if args.json:
        print_json(ext.to_dict())
    else:
        print(ext.table())
        for dcs in ext.decisions:
            print(f"auto: model {'+'.join(dcs['model'])}: {dcs['verdict']} — {dcs['message']}")
        if args.plot:
            print(f"figure: {args.plot}")
    return 0
