"""Shared helpers of the ``hbm`` subcommands: ONE validation rule per kind of setting, specimen
loading, model building, JSON output.

Every option value is checked when the command line is parsed (the ``type=`` functions and
actions below), every check that needs the model (parameter names, free parameters, sweeps,
pools) and every output path and memory estimate right after, before any computation starts.
Each failure is one line ``hbm: error: ...`` naming the option and what was expected, exit
status 2 (:class:`HbmArgumentParser` for parse errors, :class:`hbm.errors.HbmError` otherwise).
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import warnings
from pathlib import Path
from typing import Any, Iterable, Mapping, Sequence

import numpy as np

from ..data import Specimen, load_specimen
from ..data.modes import combine_tests
from ..model.loadcases import is_load_case
from ..effects import resolve_effect
from ..errors import DataError, HbmError, HbmWarning, OutputError, SettingError
from ..io.identity import changed
from .. import io, plots  # io.read_attrs, plots.supported_formats at use: xarray, matplotlib only if needed
from ..likelihood.prior import Prior, resolve_prior
from ..model import FORMS, compression_check, model_form, spyrou_model
from ..likelihood.noise import get_noise, noise_model_names
from ..model.spec import spec_of
from ..runtime.memory import format_bytes, require_memory
from ..settings.fit import NOISE_RULE, RUN_SWEEP, SWEEP, FitRecord, Sweep
from ._parser import HbmArgumentParser  # noqa: F401  (the subcommands' parser class, kept importable here)
from ..settings.rules import (
    FINITE, MIN_SAMPLES, NON_NEGATIVE_INT, POSITIVE, POSITIVE_INT, POWER_OF_TWO, POWER_OF_TWO_OR_ZERO, SAMPLE_SIZE,
    SEED, SEED_LIMIT, WORKERS, IntRule, RangeRule, RealRule, _type_error, check_physical_bounds)


#: ``--noise`` choices of every command: the registered noise models (:mod:`hbm.likelihood.noise`)
NOISE_CHOICES = NOISE_RULE.choices


def n_noise_parameters(noise: str | None) -> int:
    """Number of parameters of the registered noise model ``noise`` (appended to the model's);
    ``None`` (the command chooses the noise model): the largest registered one."""
    if noise is None:
        return max(len(get_noise(name).names) for name in noise_model_names())
    return len(get_noise(noise).names)


SPECIMEN_FOLDER = Path("data") / "specimens"
#: the shipped specimens of this checkout (an editable install), for ids given outside it
SHIPPED_FOLDER = Path(__file__).resolve().parents[2] / "data" / "specimens"
_FLOAT = 8  # bytes per float64


# ----------------------------------------------------------------------- value rules (type=)
# ONE rule per kind (hbm.settings.rules): a rule is argparse's type= and the API's check alike


def integer(minimum: int, expected: str | None = None) -> IntRule:
    """``type=`` rule: an integer >= ``minimum``."""
    return IntRule(minimum, expected)


#: counts: positive (budgets, sizes) and non-negative (restarts, retries, workers)
positive_int = POSITIVE_INT
non_negative_int = NON_NEGATIVE_INT
#: TMCMC population sizes and posterior draw counts, the same minimum everywhere
sample_size = SAMPLE_SIZE
#: ``--seed`` and ``--workers``: the API's rules (:func:`hbm.settings.rules.check_seed`, ``check_workers``)
seed = SEED
workers = WORKERS
#: Sobol base sample sizes: a power of 2 >= 2 (Sobol' sequence), or also 0 for "skip"
power_of_two = POWER_OF_TWO
power_of_two_or_zero = POWER_OF_TWO_OR_ZERO


def real(minimum: float | None = None, *, strict: bool = False) -> RealRule:
    """``type=`` rule: a finite number, optionally >= (``strict``: >) ``minimum``."""
    return RealRule(minimum, strict=strict)


finite_float = FINITE
positive_float = POSITIVE


def _name(text: str, expected: str) -> str:
    name = text.strip()
    if not name or any(c.isspace() for c in name) or "," in name:
        raise _type_error(text, expected)
    return name


def name_list(text: str) -> list[str]:
    """``type=`` rule of comma-separated name lists (effects, pooled parameters): non-empty, no repeats."""
    expected = "comma-separated names without repeats, e.g. offset,damage"
    names = [t.strip() for t in str(text).split(",")]
    if not all(names):
        raise _type_error(text, expected)
    repeated = sorted({n for n in names if names.count(n) > 1})
    if repeated:
        raise argparse.ArgumentTypeError(f"{', '.join(repeated)} given twice in {text!r}, expected each name once")
    return names


def fix_item(text: str) -> tuple[str, float]:
    """``type=`` rule of ``--fix NAME=VALUE``."""
    expected = "NAME=VALUE with a finite number, e.g. EOPT=0.192"
    name, sep, value = str(text).partition("=")
    if not sep:
        raise _type_error(text, expected)
    return _name(name, expected), RealRule(expected=expected).parse(value)


def bounds_item(text: str) -> tuple[str, tuple[float, float]]:
    """``type=`` rule of ``--bounds NAME=LO:HI``."""
    expected = "NAME=LO:HI with finite LO < HI, e.g. VOLF=0.5:0.75"
    name, sep, rng = str(text).partition("=")
    if not sep:
        raise _type_error(text, expected)
    return _name(name, expected), value_range(rng, expected)


def value_range(text: str, expected: str = "LO:HI with finite LO < HI") -> tuple[float, float]:
    """``type=`` rule of ``LO:HI`` ranges (``--sigma-bounds``, the box of ``--bounds``)."""
    return RangeRule(expected).parse(text)


#: ``type=`` rule of ``--sweep NAME:WIDTH`` (WIDTH > 0); ``none``/``off`` -> None; the run's also ``auto``
sweep = SWEEP
run_sweep = RUN_SWEEP


def plot_path(text: str) -> Path:
    """``type=`` rule of figure paths: an existing folder and a format matplotlib can write."""
    path = Path(text).expanduser()
    if not path.parent.is_dir():
        raise argparse.ArgumentTypeError(f"{text!r}: no folder {path.parent}, expected an existing folder")
    if path.is_dir():
        raise argparse.ArgumentTypeError(f"{text!r} is a folder, expected a file name")
    fmt = path.suffix.lstrip(".").lower() or "png"
    formats = plots.supported_formats()
    if fmt not in formats:
        raise argparse.ArgumentTypeError(f"{text!r}: cannot write .{fmt} figures, expected one of "
                                         f"{', '.join('.' + f for f in formats)}")
    return path


class UniqueNames(argparse.Action):
    """Repeatable ``NAME=...`` option collected into a dict; a NAME given twice is refused."""

    def __call__(self, parser, namespace, values, option_string=None):
        name, value = values
        current = dict(getattr(namespace, self.dest, None) or {})
        if name in current:
            parser.error(f"argument {option_string}: {name} given twice, expected each parameter once")
        current[name] = value
        setattr(namespace, self.dest, current)


# ----------------------------------------------------------------------- shared options
def add_seed(parser: argparse.ArgumentParser, help_text: str = "root seed (default 0)") -> None:
    """``--seed S`` with the shared rule (commands without a settings record)."""
    parser.add_argument("--seed", type=SEED, default=0, metavar="S", help=help_text)


def add_fix(parser: argparse.ArgumentParser, example: str = "EOPT=0.192") -> None:
    """``--fix NAME=VALUE`` (repeatable, each name once)."""
    parser.add_argument("--fix", action=UniqueNames, type=fix_item, default={}, metavar="NAME=VALUE",
                        help=f"hold a parameter fixed, e.g. --fix {example}; repeatable")


def add_data_arguments(parser: argparse.ArgumentParser) -> None:
    """--sl0, shared by every command that reads specimen files."""
    parser.add_argument("--sl0", type=real(0.0, strict=True), default=None, metavar="UM",
                        help="reference sarcomere length in µm for files with a sarcomere_length_um column "
                             "(strain = SL/SL0 - 1; a file's '# reference_sarcomere_length_um:' line must agree)")


def add_form_argument(parser: argparse.ArgumentParser) -> None:
    """--form thesis|energy: the collagen form of the Spyrou model."""
    parser.add_argument("--form", choices=list(FORMS), default="thesis",
                        help="collagen form: 'thesis' (default; eqs. 1.7-1.14, tension only) or 'energy' "
                             "(derived from a strain energy with free lateral faces; compressive under "
                             "compression: use it for compression tests)")


def add_model_arguments(parser: argparse.ArgumentParser) -> None:
    """--effect / --iso-factor / --form / --fix / --bounds / --sl0, shared by commands that build a model."""
    parser.add_argument("--effect", action="append", default=[], metavar="ID",
                        help="add an effect to the base model (library id or file.py:Class); repeatable")
    parser.add_argument("--iso-factor", type=positive_float, default=1.0, metavar="K",
                        help="k_iso of the neo-Hookean term: 1 (default) or 2/3 (thesis literal)")
    add_form_argument(parser)
    add_data_arguments(parser)
    add_fix(parser)
    parser.add_argument("--bounds", action=UniqueNames, type=bounds_item, default={}, metavar="NAME=LO:HI",
                        help="a parameter's prior box, e.g. --bounds VOLF=0.5:0.75 (may also widen the "
                             "thesis box, with a notice); repeatable")
    parser.add_argument("--prior", type=prior_file, default=None, metavar="FILE.toml",
                        help="prior per parameter: [NAME] lo = .., hi = .., form = 'uniform'|'loguniform' "
                             "(--bounds override its boxes); stored in every result file")


# ----------------------------------------------------------------------- checks needing the model
def check_names(model, names: Iterable[str], option: str) -> None:
    """Raise a one-line error if some names are not parameters of ``model``."""
    bad = [n for n in names if n not in model.parameter_names]
    if bad:
        raise SettingError(f"{option}: unknown parameter(s) {', '.join(bad)}; expected one of "
                           f"{', '.join(model.parameter_names)}")


def prior_file(text: str) -> Prior:
    """``--prior FILE.toml``: read and checked at parse time (:meth:`hbm.likelihood.prior.Prior.from_toml`)."""
    try:
        return Prior.from_toml(text)
    except HbmError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None


def check_fix_bounds(model, fix: dict, bounds: dict, prior: Prior | None = None) -> None:
    """--fix / --bounds / --prior against the model: known names, fixed values inside their box
    (the prior's, after --bounds), and at least one parameter left free."""
    check_names(model, fix, "--fix")
    check_names(model, bounds, "--bounds")
    check_physical_bounds(bounds, spec_of(model).physical_range, "--bounds")
    box = {n: tuple(model.bounds[i]) for i, n in enumerate(model.parameter_names)}
    if prior is not None:
        box.update({n: (prior[n].lo, prior[n].hi) for n in model.parameter_names if n in prior})
    box.update(bounds)
    for k, v in fix.items():
        a, b = box[k]
        if not a <= v <= b:
            raise SettingError(f"--fix {k}={v:g}: expected a value inside the box [{a:g}, {b:g}]")
    if len(fix) >= model.n_params:
        raise SettingError(f"--fix: all {model.n_params} model parameters are fixed, expected at least one free "
                           "parameter to learn")


def free_parameters(model, fix: dict) -> list[str]:
    """The model parameters not held by --fix."""
    return [n for n in model.parameter_names if n not in fix]


def check_sweep(model, fix: dict, spec: Sweep | str | None, option: str = "--sweep") -> None:
    """A sweep must run over a free parameter of the model ("auto": the model's own, resolved later)."""
    if spec is not None and spec != "auto" and spec.name not in free_parameters(model, fix):
        what = "is fixed by --fix" if spec.name in fix else "is not a model parameter"
        raise SettingError(f"{option} {spec.text}: {spec.name} {what}; expected NAME:WIDTH with NAME a free model "
                           f"parameter ({', '.join(free_parameters(model, fix))}) or {option} none")


def build_model(args: argparse.Namespace):
    """Base Spyrou model plus ``--effect`` effects, with --fix/--bounds (and --sweep) checked."""
    model = spyrou_model(iso_factor=float(getattr(args, "iso_factor", 1.0)), form=getattr(args, "form", "thesis"))
    effects = list(getattr(args, "effect", []) or [])
    if effects:
        model = model.with_effects(*[resolve_effect(e) for e in effects])
    fix = dict(getattr(args, "fix", None) or {})
    bounds = dict(getattr(args, "bounds", None) or {})
    check_fix_bounds(model, fix, bounds, getattr(args, "prior", None))
    check_sweep(model, fix, getattr(args, "sweep", None))
    return model, fix, bounds


def build_prior(model, args: argparse.Namespace) -> Prior | None:
    """The prior of a run: the thesis box, then ``--prior``, then ``--bounds`` (which may widen).

    ``None`` when neither option departs from the thesis box (the default path, bitwise as
    before); otherwise a one-line :class:`~hbm.errors.HbmWarning` says how the prior departs.
    """
    file, bounds = getattr(args, "prior", None), dict(getattr(args, "bounds", None) or {})
    if file is None and not bounds:
        return None
    if file is None and all(n in model.parameter_names and
                            model.bounds[model.index(n)][0] <= lo and hi <= model.bounds[model.index(n)][1]
                            for n, (lo, hi) in bounds.items()):
        return None  # only narrowing --bounds: the likelihood's own narrowing, as before
    prior = resolve_prior(model, file, bounds)
    notice = prior.notice(model)
    if notice:
        warnings.warn(notice, HbmWarning, stacklevel=2)
    return prior


def check_domain(model, specimen: Specimen) -> None:
    """Refuse substantially compressive data for the thesis form (it turns tensile there)."""
    if model_form(model) == "thesis":
        msg = compression_check(specimen.loading, "thesis", name=specimen.id)
        if msg is not None:
            raise DataError(msg)


def split_mode(spec: str) -> tuple[str, str | None]:
    """``FILE:MODE`` -> (FILE, MODE) when MODE is a loading mode or alias (:data:`hbm.model.loadcases.LOAD_CASES`)
    and ``spec`` itself is no existing path; anything else -> (spec, None) (a Windows drive, a colon in a name)."""
    head, sep, tail = spec.rpartition(":")
    if sep and head and not Path(spec).exists() and is_load_case(tail.strip()):
        return head, tail.strip()
    return spec, None


def load_specimen_arg(spec: str, sl0: float | None = None, model=None) -> Specimen:
    """A SPECIMEN argument -> :class:`~hbm.data.Specimen`: a CSV path, or an id of ``data/specimens/<id>.csv``,
    optionally with ``:MODE``, the loading mode of every test of a file without a ``mode`` column.

    ``sl0``: reference sarcomere length (``--sl0``); ``model``: checked against the data's
    domain (:func:`check_domain`) before any computation.
    """
    spec, mode = split_mode(spec)
    path = Path(spec)
    candidate = SPECIMEN_FOLDER / f"{spec}.csv"
    if not candidate.exists() and (SHIPPED_FOLDER / f"{spec}.csv").exists():
        candidate = SHIPPED_FOLDER / f"{spec}.csv"  # an id of a shipped specimen, from another folder
    if path.exists():
        ds = load_specimen(path, sl0=sl0, mode=mode)
    elif path.suffix.lower() == ".csv" or len(path.parts) > 1:
        raise HbmError(f"specimen {spec!r}: no such file (expected a CSV path or a specimen id)")
    elif candidate.exists():
        ds = load_specimen(candidate, sl0=sl0, mode=mode)
    else:
        ds = None
    if ds is not None:
        if model is not None:
            check_domain(model, ds)
        return ds
    raise HbmError(f"specimen {spec!r}: no such file, and no {candidate} (expected a CSV path or a "
                   "specimen id)")


def load_specimens_arg(specs: Sequence[str], sl0: float | None = None, model=None) -> Specimen:
    """Several SPECIMEN arguments (``FILE[:MODE]``, one file per direction as labs share them) -> one specimen
    whose tests are all the files' tests in order (:func:`hbm.data.modes.combine_tests`; id ``a+b``); one
    argument -> :func:`load_specimen_arg`."""
    parts = [load_specimen_arg(s, sl0, model) for s in specs]
    if len(parts) == 1:
        return parts[0]
    ids = [p.id for p in parts]
    if len(set(ids)) < len(ids):
        raise HbmError(f"SPECIMEN: {', '.join(specs)} name the same specimen twice ({ids}); expected distinct files")
    try:
        return combine_tests([(p, None) for p in parts], "+".join(ids))
    except DataError as exc:
        raise DataError(f"SPECIMEN: {exc}") from None


# ----------------------------------------------------------------------- memory estimates
def check_population_memory(setting: str, n: int, points: int, n_params: int) -> None:
    """A population of ``n`` parameter sets evaluated at ``points`` strain points holds at least
    an (n, points) stress array and the (n, n_params) population: refuse what cannot fit.
    ``setting`` names the option and value, e.g. ``"--samples 5000"``."""
    need = float(n) * (points + n_params) * _FLOAT
    require_memory(need, setting, f"{n} parameter sets x ({points} strain points + {n_params} parameters) x 8 bytes")


def check_sobol_memory(setting: str, n: int, n_free: int, n_params: int, points: int) -> None:
    """Sobol: N*(D+2) parameter sets, their stress at every point and the sample matrices."""
    rows = float(n) * (n_free + 2)
    need = rows * (points + n_params + n_free) * _FLOAT
    require_memory(need, setting, f"N*(D+2) = {rows:.0f} model evaluations x "
                   f"{points + n_params + n_free} values x 8 bytes")


# ----------------------------------------------------------------------- output
def check_replaceable(path: Path, parts: Mapping[str, str], option: str) -> None:
    """Refuse to replace ``path`` unless it is absent or a result of the same content (``parts``,
    :func:`hbm.io.identity.fit_key`).

    A result of another specimen, other data, another model or other settings -- or a file that
    is no hbm result at all -- is kept: :class:`~hbm.errors.OutputError` names what differs and
    the way out (``--force`` or another ``option``).
    """
    path = Path(path)
    if not path.exists():
        return
    attrs = io.read_attrs(path)
    config = attrs.get("config") if isinstance(attrs.get("config"), dict) else {}
    stored = FitRecord.from_attrs(config).identity
    stored = stored if isinstance(stored, dict) else None
    if "specimen_id" not in attrs:
        what = "a file that is not an hbm result"
    elif stored is None:
        what = f"a result of {attrs['specimen_id']} without a content key (an older hbm)"
    else:
        diff = changed(stored, parts)
        if not diff:
            return
        what = f"a result of {attrs['specimen_id']} with other {', '.join(diff)}"
    raise OutputError(f"{option} {path} holds {what}; pass --force to replace it, or choose another {option}")


def _jsonable(obj: Any) -> Any:
    """Convert numpy scalars/arrays and non-finite floats (-> null) for strict JSON."""
    if isinstance(obj, dict):
        return {str(k): _jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_jsonable(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return _jsonable(obj.tolist())
    if isinstance(obj, (np.bool_, bool)):
        return bool(obj)
    if isinstance(obj, (np.integer, int)):
        return int(obj)
    if isinstance(obj, (np.floating, float)):
        v = float(obj)
        return v if math.isfinite(v) else None
    return obj


def print_json(obj: Any, file=None) -> None:
    """Print exactly one strict JSON object (NaN/inf -> null) on stdout."""
    print(json.dumps(_jsonable(obj), indent=2, allow_nan=False), file=file or sys.stdout)


def format_table(header: Sequence[str], rows: Sequence[Sequence[str]]) -> str:
    """Plain left/right aligned text table (first column left-aligned)."""
    widths = [max(len(str(x)) for x in col) for col in zip(header, *rows)]
    def line(r):
        return "  ".join(str(x).ljust(w) if i == 0 else str(x).rjust(w) for i, (x, w) in enumerate(zip(r, widths)))
    return "\n".join([line(header), "  ".join("-" * w for w in widths)] + [line(r) for r in rows])


__all__ = ["HbmArgumentParser", "MIN_SAMPLES", "SEED_LIMIT", "integer", "positive_int", "non_negative_int",
           "sample_size", "seed", "workers", "power_of_two", "power_of_two_or_zero", "real", "finite_float",
           "positive_float",
           "name_list", "fix_item", "bounds_item", "value_range", "Sweep", "sweep", "plot_path", "UniqueNames",
           "add_seed", "add_fix", "NOISE_CHOICES", "n_noise_parameters", "add_model_arguments", "check_names", "check_fix_bounds", "free_parameters",
           "check_sweep", "build_model", "load_specimen_arg", "load_specimens_arg", "split_mode", "check_population_memory",
           "check_sobol_memory", "check_replaceable", "print_json", "format_table", "format_bytes"]
