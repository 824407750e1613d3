"""Commands load what they use (issue 38 item 3): ``import hbm`` and the ``hbm`` parser import no heavy
module, ``hbm --version`` no numerical library, ``hbm data check`` neither the samplers' statistics
nor the detective, cma, matplotlib, ArviZ or dask.

Checked by the modules a fresh interpreter holds afterwards (``sys.modules``), not by seconds: the
check cannot fail because the machine is busy.  ``workflows/benchmarks/command_latency.py`` measures
the seconds.
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import subprocess
import sys
from pathlib import Path

import pytest

import hbm
from hbm import cli

ROOT = Path(__file__).resolve().parents[1]
SHIPPED = ROOT / "data" / "specimens" / "calvo2010_rat1.csv"

#: never loaded by `import hbm`, the parser, `hbm --version` or `hbm data check`
HEAVY = ("matplotlib", "cma", "arviz", "dask", "distributed", "scipy.stats", "SALib", "hbm.detective",
         "hbm.samplers.hierarchical", "hbm.population")
#: not loaded by `hbm --version` either: it prints a string
NUMERICAL = ("numpy", "scipy", "numba", "xarray", "pandas", "netCDF4")


def _loaded_after(code: str) -> dict:
    """Run ``code`` in a fresh interpreter (this checkout first on the path); the modules it loaded."""
    probe = (f"import sys, json\n{code}\n"
             f"print(json.dumps(sorted(m for m in {HEAVY + NUMERICAL!r} if m in sys.modules)))\n")
    env = dict(os.environ, PYTHONPATH=str(ROOT), HBM_DEBUG="")
    res = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, cwd=ROOT, env=env,
                         timeout=300)
    assert res.returncode == 0, res.stderr
    return set(json.loads(res.stdout.strip().splitlines()[-1]))


def test_import_hbm_and_the_parser_load_no_heavy_module():
    loaded = _loaded_after("import hbm\nimport hbm.cli\nparser = hbm.cli.build_parser([])")
    assert not loaded & set(HEAVY + NUMERICAL), loaded


def test_version_loads_no_numerical_library():
    loaded = _loaded_after("from hbm.cli import main\ntry:\n    main(['--version'])\nexcept SystemExit as e:\n"
                           "    assert e.code == 0")
    assert not loaded & set(HEAVY + NUMERICAL), loaded


def test_data_check_loads_neither_samplers_nor_detective():
    loaded = _loaded_after(f"from hbm.cli import main\nassert main(['data', 'check', {str(SHIPPED)!r}]) == 0")
    assert "numpy" in loaded  # the probe saw the command's imports (it reads the file with numpy)
    assert not loaded & set(HEAVY), loaded


def test_summary_loads_neither_the_optimiser_nor_the_samplers_statistics(tmp_path):
    """``hbm summary`` reads a stored fit: no cma, scipy.stats (about 0.4 s of it: R-hat ranks with numpy),
    matplotlib or the detective."""
    from test_export import _result

    fit = _result(tmp_path, name="summary_probe")
    loaded = _loaded_after(f"from hbm.cli import main\nassert main(['summary', {str(fit)!r}]) == 0")
    assert "xarray" in loaded  # the probe saw the command read the file
    assert not loaded & {"cma", "scipy.stats", "matplotlib", "hbm.detective", "hbm.samplers.hierarchical"}, loaded


def test_fit_parser_loads_no_plotting_or_detective():
    """Building ``hbm fit``'s options (as ``hbm fit --help`` does) needs neither matplotlib nor the detective."""
    loaded = _loaded_after("import hbm.cli\nhbm.cli.build_parser(['fit', '--help'])")
    assert not loaded & {"matplotlib", "hbm.detective", "hbm.samplers.hierarchical", "dask", "arviz", "SALib"}


# ------------------------------------------------------------------ the light table and the full parser agree
def _subcommands(parser: argparse.ArgumentParser) -> argparse._SubParsersAction:
    return next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))


def test_subcommand_table_matches_the_modules():
    """The one-line help shown by ``hbm --help`` is each module's own, in the modules' order."""
    full = _subcommands(cli.build_parser())
    assert [(a.dest, a.help) for a in full._choices_actions] == [
        (name, help_text) for name, (_, help_text) in cli.SUBCOMMANDS.items()]
    for name in cli.SUBCOMMANDS:  # built alone, each command has its full options and help
        only = _subcommands(cli.build_parser([name]))
        assert only.choices[name].format_help() == full.choices[name].format_help()


@pytest.mark.parametrize("words", [[], ["--version"], ["data", "check", "x.csv"], ["extend", "x"], ["nosuch"]])
def test_top_level_help_is_the_same_whatever_was_built(words):
    assert cli.build_parser(words).format_help() == cli.build_parser().format_help()


def test_unknown_command_keeps_the_argparse_error(capsys):
    assert cli.main(["fitt", "x"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("hbm: error: argument COMMAND: invalid choice: 'fitt' (choose from ") and "'summary'" in err


# ------------------------------------------------------------------ the lazy public names
@pytest.mark.parametrize("package", ["hbm", "hbm.io", "hbm.samplers", "hbm.fit", "hbm.workflow"])
def test_every_public_name_resolves(package):
    mod = __import__(package, fromlist=["__all__"])
    for name in mod.__all__:
        namespace: dict = {}
        exec(f"from {package} import {name}", namespace)  # noqa: S102 - the statement users write
        assert namespace[name] is getattr(mod, name)
        assert name in dir(mod)
    with pytest.raises(AttributeError, match="no_such_name"):
        getattr(mod, "no_such_name")


def test_lazy_names_are_the_defining_modules_objects():
    from hbm.fit.specimen import fit_specimen
    from hbm.samplers.tmcmc import tmcmc
    assert hbm.fit_specimen is fit_specimen and hbm.tmcmc is tmcmc and hbm.fit.fit_specimen is fit_specimen


def test_ctrl_c_guard_lasts_until_main_takes_over():
    """In the command's process the import guard (one line, exit 130) covers ``import hbm``, ``import
    hbm.cli`` and -- inside ``main`` -- the invoked command's imports, without a gap; ``main`` then ends it.
    (A Ctrl-C that interrupts an import as KeyboardInterrupt could end the process by SIGINT, exit -2.)"""
    code = ("import signal, sys\nsys.argv[0] = 'hbm'  # what the console script's process looks like\n"
            "import hbm, hbm.cli\nguarded = signal.getsignal(signal.SIGINT) is not signal.default_int_handler\n"
            "try:\n    hbm.cli.main(['--version'])\nexcept SystemExit:\n    pass\n"
            "print(guarded, signal.getsignal(signal.SIGINT) is signal.default_int_handler)")
    res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT, timeout=120,
                         env=dict(os.environ, PYTHONPATH=str(ROOT)), preexec_fn=lambda: signal.signal(
                             signal.SIGINT, signal.SIG_DFL))
    assert res.stdout.split()[-2:] == ["True", "True"], (res.stdout, res.stderr)
