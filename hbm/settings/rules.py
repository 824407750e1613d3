"""ONE validation rule per kind of setting, shared by the command line and the Python API.

A :class:`Rule` checks a value given in Python (:meth:`Rule.check`: the value, converted, or
:class:`hbm.errors.SettingError` ``"<name>: expected <what>, got <value>"``) and parses the same
kind of value from a command-line word (:meth:`Rule.parse`, argparse's ``type=``: the value or
``argparse.ArgumentTypeError`` ``"expected <what>, got <text>"``), so a value the command refuses
is refused by the API too.  The settings records (:mod:`hbm.settings`) name one rule per field;
the commands' other options (:mod:`hbm.cli._common`) use the same rules.

The functions :func:`check_seed`, :func:`check_int`, :func:`check_positive`, :func:`check_workers`
and :func:`check_physical_bounds` are the API forms used across the package.
"""

from __future__ import annotations

import argparse
import math
import os
from numbers import Integral, Real
from typing import Any, Callable, Iterable, Mapping

from ..errors import SettingError

__all__ = ["SEED_LIMIT", "MAX_WORKERS_PER_CORE", "MIN_SAMPLES", "Rule", "IntRule", "RealRule", "ChoiceRule",
           "SEED", "WORKERS", "POSITIVE_INT", "NON_NEGATIVE_INT", "SAMPLE_SIZE", "POWER_OF_TWO",
           "POWER_OF_TWO_OR_ZERO", "FINITE", "POSITIVE", "RANGE", "RangeRule", "RegistryChoices", "check_seed", "check_int",
           "check_positive", "check_workers", "usable_cores", "check_physical_bounds"]

#: seeds are non-negative integers below 2**32 (numpy's legacy seeding inside cma and SALib)
SEED_LIMIT = 2 ** 32
#: worker processes of the embedded cluster per core: beyond that they only compete for the cores
#: (and each holds a copy of the model and its data)
MAX_WORKERS_PER_CORE = 4
#: the smallest population / draw count any command accepts (TMCMC populations of --samples and
#: --hier-samples, posterior draws of predict): a population covariance over the 9-16 parameters
#: of the base model plus effects needs more particles than parameters
MIN_SAMPLES = 20


def _type_error(text: str, expected: str) -> argparse.ArgumentTypeError:
    return argparse.ArgumentTypeError(f"expected {expected}, got {text!r}")


class Rule:
    """A kind of setting: what it expects, how a Python value is checked and a word parsed.

    Subclasses override :meth:`convert` (a Python value -> the setting's value, raising
    ``ValueError`` when it is not one) and, where a word is read differently, :meth:`from_text`.
    """

    expected: str = "a value"

    def convert(self, value: Any) -> Any:
        return value

    def from_text(self, text: str) -> Any:
        """A command-line word as a Python value before :meth:`convert` (default: the word)."""
        return str(text).strip()

    def check(self, value: Any, name: str) -> Any:
        """The checked value of setting ``name`` given in Python."""
        try:
            return self.convert(value)
        except (TypeError, ValueError):
            raise SettingError(f"{name}: expected {self.expected}, got {value!r}") from None

    def parse(self, text: str) -> Any:
        """argparse ``type=``: the checked value of a command-line word."""
        try:
            return self.convert(self.from_text(text))
        except (TypeError, ValueError):
            raise _type_error(text, self.expected) from None

    def __call__(self, text: str) -> Any:  # a rule is itself a valid argparse ``type=``
        return self.parse(text)


def _integer(value: Any) -> int:
    if isinstance(value, bool) or not isinstance(value, Integral):
        if isinstance(value, Real) and float(value).is_integer():
            return int(value)
        raise ValueError(value)
    return int(value)


class IntRule(Rule):
    """An integer >= ``minimum`` (a Python float with an integral value passes; a word must be an integer)."""

    def __init__(self, minimum: int, expected: str | None = None) -> None:
        self.minimum = int(minimum)
        self.expected = expected or f"an integer >= {minimum}"
        self.__name__ = f"integer>={minimum}"

    def from_text(self, text: str) -> int:
        return int(str(text).strip())

    def convert(self, value: Any) -> int:
        v = _integer(value)
        if v < self.minimum:
            raise ValueError(value)
        return v


class _Seed(IntRule):
    """A seed: an integer from 0 to 2**32 - 1 (a numpy SeedSequence passes unchanged in Python)."""

    def __init__(self) -> None:
        super().__init__(0, f"a seed: an integer from 0 to {SEED_LIMIT - 1}")
        self.__name__ = "seed"

    def convert(self, value: Any) -> Any:
        if type(value).__name__ == "SeedSequence":
            return value
        v = super().convert(value)
        if v >= SEED_LIMIT:
            raise ValueError(value)
        return v


class _Workers(IntRule):
    """Worker processes of an embedded cluster: 0 (no dask) up to :data:`MAX_WORKERS_PER_CORE` per core."""

    def __init__(self) -> None:
        super().__init__(0)
        self.__name__ = "workers"

    def check(self, value: Any, name: str) -> int:
        v = super().check(value, name)
        cores = os.cpu_count() or 1
        cap = MAX_WORKERS_PER_CORE * cores
        if v > cap:
            raise SettingError(f"{name}: {v} worker processes on {cores} core(s); expected at most {cap} "
                               f"({MAX_WORKERS_PER_CORE} per core: more only compete for the cores and memory); "
                               "for a larger cluster connect to its scheduler (--scheduler / DASK_SCHEDULER_ADDRESS)")
        return v

    def parse(self, text: str) -> int:
        try:
            v = self.from_text(text)
        except ValueError:
            raise _type_error(text, self.expected) from None
        try:
            return self.check(v, "--workers")
        except SettingError as exc:
            raise argparse.ArgumentTypeError(str(exc).removeprefix("--workers: ")) from None


class _PowerOfTwo(IntRule):
    """A power of 2 >= 2 (a Sobol' sequence), or also 0 (skip)."""

    def __init__(self, zero: bool) -> None:
        self.zero = zero
        super().__init__(0, ("0 (skip) or a power of 2 >= 2 (e.g. 512, 1024)" if zero
                             else "a power of 2 >= 2 (e.g. 512, 1024)"))
        self.__name__ = "power_of_two_or_zero" if zero else "power_of_two"

    def convert(self, value: Any) -> int:
        v = _integer(value)
        if (v == 0 and self.zero) or (v >= 2 and not v & (v - 1)):
            return v
        raise ValueError(value)


class RealRule(Rule):
    """A finite number, optionally >= (``strict``: >) ``minimum``."""

    def __init__(self, minimum: float | None = None, *, strict: bool = False, expected: str | None = None) -> None:
        self.minimum, self.strict = minimum, strict
        self.expected = expected or ("a finite number" if minimum is None
                                     else f"a finite number {'>' if strict else '>='} {minimum:g}")
        self.__name__ = "number"

    def convert(self, value: Any) -> float:
        if isinstance(value, bool):
            raise ValueError(value)
        v = float(value)
        if not math.isfinite(v):
            raise ValueError(value)
        if self.minimum is not None and (v <= self.minimum if self.strict else v < self.minimum):
            raise ValueError(value)
        return v

    def parse(self, text: str) -> float:
        word = str(text).strip()
        try:
            v = float(word)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected {self.expected}; {word!r} is not a number") from None
        if not math.isfinite(v):
            raise argparse.ArgumentTypeError(f"expected {self.expected}; {word!r} is not finite")
        try:
            return self.convert(v)
        except ValueError:
            raise _type_error(text, self.expected) from None


class RangeRule(Rule):
    """``LO:HI`` with finite LO < HI (a pair in Python)."""

    def __init__(self, expected: str = "LO:HI with finite LO < HI") -> None:
        self.expected = expected
        self._number = RealRule(expected=expected)   # a bad half is named against the whole LO:HI
        self.__name__ = "value_range"

    def convert(self, value: Any) -> tuple[float, float]:
        a, b = (FINITE.convert(x) for x in value)
        if not a < b:
            raise ValueError(value)
        return a, b

    def parse(self, text: str) -> tuple[float, float]:
        lo, sep, hi = str(text).partition(":")
        if not sep:
            raise _type_error(text, self.expected)
        a, b = self._number.parse(lo), self._number.parse(hi)
        if not a < b:
            raise _type_error(text, self.expected)
        return a, b


class RegistryChoices:
    """argparse ``choices`` read from a registry whenever argparse looks (help, checks, errors).

    A move, noise model or tier registered after the parser was built (a plug-in, a test) is a
    valid choice and appears in ``--help`` without editing any command.
    """

    def __init__(self, names: Callable[[], Iterable[str]]):
        self._names = names

    def __iter__(self):
        return iter(tuple(self._names()))

    def __contains__(self, value) -> bool:
        return value in tuple(self._names())

    def __len__(self) -> int:
        return len(tuple(self._names()))


class ChoiceRule(Rule):
    """One of the names of a registry (read when checked: a registered name is valid at once)."""

    def __init__(self, names: Callable[[], Iterable[str]], what: str) -> None:
        self.choices = RegistryChoices(names)
        self.what = what

    @property
    def expected(self) -> str:  # type: ignore[override]
        return f"a {self.what}: one of {', '.join(self.choices)}"

    def convert(self, value: Any) -> str:
        if not isinstance(value, str) or value not in self.choices:
            raise ValueError(value)
        return value


SEED = _Seed()
WORKERS = _Workers()
#: counts: positive (budgets, sizes) and non-negative (restarts, retries, workers)
POSITIVE_INT = IntRule(1)
NON_NEGATIVE_INT = IntRule(0)
#: TMCMC population sizes and posterior draw counts, the same minimum everywhere
SAMPLE_SIZE = IntRule(MIN_SAMPLES, f"a sample size >= {MIN_SAMPLES}")
POWER_OF_TWO = _PowerOfTwo(zero=False)
POWER_OF_TWO_OR_ZERO = _PowerOfTwo(zero=True)
FINITE = RealRule()
POSITIVE = RealRule(0.0, strict=True)
RANGE = RangeRule()


# ----------------------------------------------------------------------------- API forms
def check_seed(value: Any, name: str = "seed") -> int:
    """A seed: an integer from 0 to 2**32 - 1 (a numpy SeedSequence passes unchanged)."""
    return SEED.check(value, name)


def check_int(value: Any, name: str, minimum: int) -> int:
    """A count: an integer >= ``minimum``."""
    return IntRule(minimum).check(value, name)


def check_positive(value: Any, name: str) -> float:
    """A finite number > 0."""
    return POSITIVE.check(value, name)


def check_workers(value: Any, name: str = "workers") -> int:
    """Worker processes of an embedded cluster: 0 (no dask) up to MAX_WORKERS_PER_CORE per core."""
    return WORKERS.check(value, name)


def usable_cores() -> int:
    """Cores this process may run on (its CPU affinity where the OS tells it, else the count)."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:      # (not on macOS / Windows)
        return os.cpu_count() or 1


def check_physical_bounds(bounds: Mapping[str, Any] | None, ranges: Mapping[str, tuple[float, float]],
                          name: str = "bounds") -> None:
    """A prior box ``{parameter: (lo, hi)}`` inside what the physics allows (``ranges``, e.g. the
    physical ranges of the model's spec)."""
    for p, box in (bounds or {}).items():
        if p not in ranges:
            continue
        lo, hi = (float(b) for b in box)
        a, b = ranges[p]
        if not (a <= lo and hi <= b):
            allowed = f"[{a:g}, {b:g}]" if math.isfinite(b) else f">= {a:g}"
            raise SettingError(f"{name} {p}={lo:g}:{hi:g}: outside what {p} can physically be ({allowed}); "
                               f"expected a box inside it")
