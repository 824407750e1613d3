"""``hbm simulate TESTS.csv --theta NAME=VALUE,... --out OUT.csv``: virtual experiments in every loading mode."""

from __future__ import annotations

import argparse
import json

from ..effects import resolve_effect
from ..fit.simulate import simulate_tests, write_simulation
from ..model import spyrou_model
from ..model.energy3d import COLLAGEN_READINGS
from ._common import add_data_arguments, add_form_argument, fix_item, load_specimen_arg

DESCRIPTION = """\
Predict every observable of every test of a specimen file with given parameters.

Each test is solved in its mode (the file's 'mode' column; uniaxial_f without it) with the model's
3-D energy and the collagen reading --collagen3d; the output holds the file's rows (engineering
strain, Cauchy stress in MPa, as loaded) plus <observable>_model columns (stress_model,
stress_2_model, strain_f_model ...; empty where a row's mode does not define the observable).
The thesis form is defined along the fibres only: other modes need --form energy.
--effect adds effects where they are defined in 3-D (viscoelastic relaxes every stress observable along
its own history, an offset per stress observable: S0, S0_2); others only along the fibres.
Cells of the measured columns may be empty: a file without measurements is a protocol.
"""


def theta_list(text: str) -> dict[str, float]:
    """``type=`` rule of ``--theta NAME=VALUE,...``: finite values, each name once."""
    out: dict[str, float] = {}
    for item in filter(None, (t.strip() for t in str(text).split(","))):
        name, value = fix_item(item)
        if name in out:
            raise argparse.ArgumentTypeError(f"{name} given twice")
        out[name] = value
    return out


def register(subparsers) -> None:
    """Add ``simulate`` to the ``hbm`` parser."""
    p = subparsers.add_parser("simulate", help="predict every observable of every test (virtual experiments)",
                              description=DESCRIPTION, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("tests", metavar="TESTS.csv", help="specimen file with the tests (a 'mode' column per test, or FILE:MODE for a "
                   "file without one)")
    p.add_argument("--theta", type=theta_list, action="append", required=True, metavar="NAME=VALUE,...",
                   help="every model parameter, e.g. VOLF=0.9,EOPT=0.18,...; repeatable")
    add_form_argument(p)
    p.add_argument("--effect", action="append", default=[], metavar="ID",
                   help="add an effect (library id or file.py:Class; repeatable); it acts per test where it is "
                        "defined in 3-D (viscoelastic: every stress observable's history; offset: S0, S0_2 ...) "
                        "and is refused elsewhere")
    p.add_argument("--collagen3d", choices=sorted(COLLAGEN_READINGS), default=None,
                   help="3-D reading of the collagen (energy form): default cone")
    p.add_argument("--out", required=True, metavar="OUT.csv", help="output CSV (written atomically)")
    add_data_arguments(p)
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    """Load, check (before any computation), simulate, write."""
    theta: dict[str, float] = {}
    for part in args.theta:
        theta.update(part)
    model = spyrou_model(form=args.form)
    if args.effect:
        model = model.with_effects(*[resolve_effect(e) for e in args.effect])
    spec = load_specimen_arg(args.tests, args.sl0)
    pred = simulate_tests(spec, theta, model=model, collagen3d=args.collagen3d)
    reading = args.collagen3d or ("cone" if args.form == "energy" else "axial")
    path = write_simulation(spec, pred, args.out, record={
        "simulated_model": f"{model.name}, collagen3d={reading}",
        "simulated_theta": json.dumps(theta)})  # every name checked against the model by simulate_tests
    modes = ", ".join(dict.fromkeys(t.load_case for t in spec.tests))
    print(f"{path}: {spec.n_points} rows, {len(spec.tests)} test(s) ({modes}); columns "
          f"{', '.join(pred)} (Cauchy stress in MPa, engineering strain; {model.name}, collagen3d={reading})")
    return 0
