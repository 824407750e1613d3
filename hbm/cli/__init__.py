"""The ``hbm`` command.  Each subcommand lives in its own module with ``register(subparsers)``."""

from __future__ import annotations

import argparse
import importlib
import sys

from .._version import __version__
from ..errors import HbmError

# subcommand modules, in the order shown by --help
COMMANDS = ["run", "fit", "optimize", "sobol", "diagnose", "predict", "data"]

DESCRIPTION = """\
hbm: Bayesian learning of skeletal-muscle model parameters across specimens.

Fits the Spyrou-Agoras-Danas microstructural model of passive muscle (fibers + ECM,
8 parameters VOLF EOPT P1 T1 T2 THETA GF GM plus noise) to uniaxial stress-strain curves.
"""


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="hbm", description=DESCRIPTION,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--version", action="version", version=f"hbm {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name in COMMANDS:
        importlib.import_module(f"{__name__}.{name}").register(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if not getattr(args, "func", None):
        parser.print_help()
        return 2
    try:
        return int(args.func(args) or 0)
    except HbmError as exc:
        print(f"hbm: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("hbm: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
