"""The ``hbm`` command.  Each subcommand lives in its own module with ``register(subparsers)``.

A command loads only what it uses: the top-level parser lists every subcommand with its one-line
help from :data:`SUBCOMMANDS`, and only the invoked subcommand's module is imported and builds its
arguments (``hbm --version`` imports none of them, ``hbm data check`` neither the samplers nor
the detective nor matplotlib).

Error contract of :func:`main`: a bad option, bad input file, unwritable output, full disk or
a size that cannot fit in memory ends as ONE line ``hbm: error: ...`` on stderr naming the
option or file, exit status 2; Ctrl-C (or SIGTERM) at any moment ends as ``hbm: interrupted``,
exit status 130 (143), with temporary files removed and TMCMC checkpoints kept.  An unexpected
internal error is one line too (exit 1); ``HBM_DEBUG=1`` shows its traceback.
"""

from __future__ import annotations

import argparse
import atexit
import contextlib
import importlib
import json
import os
import signal
import sys
import threading
import warnings
from typing import Sequence

from .._version import __version__
from ..errors import HbmError, HbmWarning, SettingError
from ..runtime.process import restore_sigint
from ._parser import HbmArgumentParser

#: the subcommands in the order shown by ``hbm --help``: name -> (module of hbm.cli that registers
#: it, one-line help); a test keeps the help equal to the module's own
SUBCOMMANDS = {
    "run": ("run", "all specimens in parallel + hierarchical layer + report"),
    "fit": ("fit", "posterior (TMCMC) + optima (CMA-ES) of one specimen -> netCDF"),
    "optimize": ("optimize", "CMA-ES point estimates, restarts and bound sweeps"),
    "sobol": ("sobol", "Sobol sensitivity indices and relevance classes"),
    "diagnose": ("diagnose", "where does the model fail, which effect is missing"),
    "extend": ("diagnose", "add effects one at a time and show the error fall"),
    "predict": ("predict", "predictions from fitted specimens (organ-scale curves)"),
    "simulate": ("simulate", "predict every observable of every test (virtual experiments)"),
    "data": ("data", "specimen data utilities (check CSV files)"),
    "export": ("export", "verified FE material card (FEBio, Abaqus) or parameter table"),
    "summary": ("summary", "parameter table (with units) of a fit, text or CSV"),
}
# subcommand modules, in the order shown by --help
COMMANDS = list(dict.fromkeys(module for module, _ in SUBCOMMANDS.values()))

DESCRIPTION = """\
hbm: Bayesian learning of skeletal-muscle model parameters across specimens.

Fits the Spyrou-Agoras-Danas microstructural model of passive muscle (fibers + ECM,
8 parameters VOLF EOPT P1 T1 T2 THETA GF GM plus noise) to uniaxial stress-strain curves.
"""


def build_parser(words: Sequence[str] | None = None) -> argparse.ArgumentParser:
    """The ``hbm`` parser (errors: one line, see :class:`HbmArgumentParser`).

    Parameters
    ----------
    words : sequence of str, optional
        The command line about to be parsed: only its subcommand is imported and built in full,
        every other one is listed with its one-line help (so ``hbm --help`` shows them all and a
        mistyped name gets argparse's usual error).  ``None``: every subcommand in full.
    """
    parser = HbmArgumentParser(prog="hbm", description=DESCRIPTION,
                               formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--version", action="version", version=f"hbm {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    invoked = None if words is None else _invoked(words)
    wanted = set(COMMANDS) if words is None else {SUBCOMMANDS[invoked][0]} if invoked else set()
    for module in COMMANDS:
        if module in wanted:
            importlib.import_module(f"{__name__}.{module}").register(sub)
        else:
            for name, (owner, help_text) in SUBCOMMANDS.items():
                if owner == module:
                    sub.add_parser(name, help=help_text)
    parser.set_defaults(commands=list(sub.choices))
    return parser


def _invoked(words: Sequence[str]) -> str | None:
    """The subcommand named on the command line ``words`` (None: no known subcommand).

    The top-level options (``-h``, ``--version``) take no value, so the first word that is not
    an option is the subcommand; anything else is left to argparse (and its error message).
    """
    first = next((str(w) for w in words if not str(w).startswith("-")), None)
    return first if first in SUBCOMMANDS else None


class _Terminated(KeyboardInterrupt):
    """SIGTERM, raised like Ctrl-C so that ``finally`` blocks remove temporary files."""


def _raise_terminated(signum, frame):
    raise _Terminated()


def _exit_now(signum, frame):  # pragma: no cover - interpreter shutdown
    sys.stderr.write("hbm: interrupted\n")
    sys.stderr.flush()
    os._exit(130)


def _show_warning(message, category, filename, lineno, file=None, line=None) -> None:
    """hbm's own warnings (an assumption the user did not choose) as one ``hbm: warning:`` line."""
    if issubclass(category, HbmWarning):
        print(f"hbm: warning: {_one_line(message)}", file=sys.stderr)
    else:
        _DEFAULT_SHOWWARNING(message, category, filename, lineno, file, line)


_DEFAULT_SHOWWARNING = warnings.showwarning


def _one_line(text: str) -> str:
    return " ".join(str(text).split())


def _os_error(exc: OSError) -> str:
    reason = exc.strerror or str(exc) or type(exc).__name__
    names = [n for n in (exc.filename, exc.filename2) if n is not None]
    return f"{' -> '.join(map(str, names))}: {reason}" if names else reason


def main(argv: list[str] | None = None) -> int:
    """Run ``hbm ARGV`` (default ``sys.argv[1:]``) and return the exit status."""
    if argv is None and threading.current_thread() is threading.main_thread():  # the command's own process
        atexit.register(_ignore_late_interrupt)  # runs after the atexit handlers registered during the run
    try:
        return _main(argv)
    except KeyboardInterrupt as exc:  # Ctrl-C in the last moment: while an error or the ending is handled
        print("hbm: interrupted", file=sys.stderr)
        return 143 if isinstance(exc, _Terminated) else 130


def _ignore_late_interrupt() -> None:
    """Ignore Ctrl-C in the process's very last moments (after its atexit work).

    Python's finalisation puts a Python-level SIGINT handler back to the OS default, so a Ctrl-C
    then would kill the process by the signal (no message, exit -2) after everything was written
    and printed; an ignored signal stays ignored, and the process ends with its own status.
    """
    with contextlib.suppress(ValueError, OSError):
        signal.signal(signal.SIGINT, signal.SIG_IGN)


def _main(argv: list[str] | None) -> int:
    in_main_thread = threading.current_thread() is threading.main_thread()
    previous_term = signal.signal(signal.SIGTERM, _raise_terminated) if in_main_thread else None
    words = list(sys.argv[1:] if argv is None else argv)
    previous_show = warnings.showwarning
    warnings.showwarning = _show_warning
    try:
        parser = build_parser(words)  # imports the invoked command's module: still under the import guard
        if in_main_thread:
            # the import guard of hbm.runtime.process ends here, after the command's imports (a Ctrl-C that
            # interrupts an import as KeyboardInterrupt can end the process by SIGINT although caught)
            restore_sigint()
        args = parser.parse_args(argv)
        if not getattr(args, "func", None):
            raise SettingError(f"expected a command ({', '.join(args.commands)}); see hbm --help")
        return int(args.func(args) or 0)
    except HbmError as exc:
        if "--json" in words:  # --json promises exactly one JSON object on stdout, also on failure
            print(json.dumps({"error": _one_line(exc)}))
        print(f"hbm: error: {_one_line(exc)}", file=sys.stderr)
        return 2
    except KeyboardInterrupt as exc:
        print("hbm: interrupted", file=sys.stderr)
        return 143 if isinstance(exc, _Terminated) else 130
    except OSError as exc:  # permission, missing path, full disk from code that does not wrap it
        print(f"hbm: error: {_one_line(_os_error(exc))}", file=sys.stderr)
        return 2
    except MemoryError:
        print("hbm: error: out of memory; use smaller sizes (--samples, --n, --sobol-n)", file=sys.stderr)
        return 2
    except Exception as exc:
        if os.environ.get("HBM_DEBUG"):
            raise
        print(f"hbm: error: internal error {type(exc).__name__}: {_one_line(exc)} (HBM_DEBUG=1 shows the "
              "traceback; please report it)", file=sys.stderr)
        return 1
    finally:
        warnings.showwarning = previous_show
        if in_main_thread:
            signal.signal(signal.SIGTERM, signal.SIG_DFL if previous_term is None else previous_term)
            if argv is None and signal.getsignal(signal.SIGINT) is signal.default_int_handler:
                # the process ends now: Ctrl-C during interpreter shutdown (dask's atexit) stays one line
                signal.signal(signal.SIGINT, _exit_now)


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
