"""User-controlled priors: a box and a form ("uniform" or "loguniform") per parameter.

The thesis prior is uniform on the rat study's box (``model.bounds``).  A :class:`Prior`
replaces it, parameter by parameter, by any finite box -- narrower *or wider* -- and by a
log-uniform density where a parameter spans decades (P1, GF, GM, sigma).  It is read from TOML::

    [VOLF]
    lo = 0.3
    hi = 0.99
    [P1]
    lo = 1e-6
    hi = 1.0
    form = "loguniform"

Parameters not listed keep the model's box, uniform.  Noise parameters (``sigma``, ``rho``, ...)
may be listed too; the likelihood checks them against its noise model.

How a log-uniform prior is sampled: the samplers of hbm draw from a uniform prior on a box, so
:class:`hbm.likelihood.Likelihood` works in coordinates ``y`` with ``y = log θ`` for the
log-uniform parameters (``y = θ`` otherwise).  A uniform prior on ``[log lo, log hi]`` in ``y`` is
exactly the log-uniform prior on ``[lo, hi]`` in ``θ``, so the evidence
``Z = ∫ L(θ(y)) π_y(y) dy`` is unchanged by the transform and stays exact.
"""

from __future__ import annotations

import math
import os
import tomllib
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Iterable, Mapping

import numpy as np

from ..errors import HbmError

__all__ = ["FORMS", "PriorError", "ParameterPrior", "Prior", "load_prior", "resolve_prior"]

#: supported prior densities on a box
FORMS = ("uniform", "loguniform")
_KEYS = ("lo", "hi", "form")


class PriorError(HbmError, ValueError):
    """A prior specification (file, mapping or override) hbm cannot use."""


@dataclass(frozen=True)
class ParameterPrior:
    """Prior of one parameter: the box ``[lo, hi]`` and its density ``form``."""

    lo: float
    hi: float
    form: str = "uniform"

    @property
    def is_log(self) -> bool:
        return self.form == "loguniform"

    def to_dict(self) -> dict[str, Any]:
        return {"lo": float(self.lo), "hi": float(self.hi), "form": self.form}


def _fmt_box(lo: float, hi: float) -> str:
    return f"[{lo:g}, {hi:g}]"


def _check_entry(name: str, lo: Any, hi: Any, form: Any, where: str) -> ParameterPrior:
    """Validated :class:`ParameterPrior` (one-line :class:`PriorError` naming ``where`` and ``name``)."""
    if not isinstance(form, str) or form not in FORMS:
        raise PriorError(f"{where}: {name}: unknown form {form!r}; expected one of {', '.join(FORMS)}")
    try:
        lo_f, hi_f = float(lo), float(hi)
    except (TypeError, ValueError):
        raise PriorError(f"{where}: {name}: lo and hi must be numbers, got {lo!r} and {hi!r}") from None
    if not (math.isfinite(lo_f) and math.isfinite(hi_f)):
        raise PriorError(f"{where}: {name}: lo and hi must be finite, got {lo_f:g} and {hi_f:g}")
    if not lo_f < hi_f:
        raise PriorError(f"{where}: {name}: needs lo < hi, got lo={lo_f:g}, hi={hi_f:g}")
    if form == "loguniform" and lo_f <= 0:
        raise PriorError(f"{where}: {name}: a loguniform prior needs lo > 0, got lo={lo_f:g}")
    return ParameterPrior(lo_f, hi_f, form)


class Prior:
    """Per-parameter prior boxes and forms (parameters not listed: the model's box, uniform).

    Parameters
    ----------
    entries : mapping
        ``{name: ParameterPrior | (lo, hi) | (lo, hi, form) | {"lo", "hi", "form"}}``.
    source : str
        Named in error messages (a file name, ``"--bounds"`` ...).

    Raises
    ------
    PriorError
        lo >= hi, non-finite values, an unknown form or key, loguniform with lo <= 0.
    """

    def __init__(self, entries: Mapping[str, Any] | None = None, *, source: str = "prior") -> None:
        self.source = str(source)
        self.entries: dict[str, ParameterPrior] = {}
        for name, spec in dict(entries or {}).items():
            self.entries[str(name)] = self._entry(str(name), spec)

    def _entry(self, name: str, spec: Any) -> ParameterPrior:
        if isinstance(spec, ParameterPrior):
            return _check_entry(name, spec.lo, spec.hi, spec.form, self.source)
        if isinstance(spec, Mapping):
            unknown = [k for k in spec if k not in _KEYS]
            if unknown:
                raise PriorError(f"{self.source}: {name}: unknown key(s) {', '.join(map(str, unknown))}; "
                                 f"expected {', '.join(_KEYS)}")
            missing = [k for k in ("lo", "hi") if k not in spec]
            if missing:
                raise PriorError(f"{self.source}: {name}: missing {' and '.join(missing)}")
            return _check_entry(name, spec["lo"], spec["hi"], spec.get("form", "uniform"), self.source)
        if isinstance(spec, (tuple, list)) and len(spec) in (2, 3):
            return _check_entry(name, spec[0], spec[1], spec[2] if len(spec) == 3 else "uniform", self.source)
        raise PriorError(f"{self.source}: {name}: expected a table with lo, hi[, form], got {spec!r}")

    # -- construction ----------------------------------------------------------------------
    @classmethod
    def from_model(cls, model) -> "Prior":
        """The thesis prior: uniform on the model's box, every model parameter listed."""
        return cls({n: (lo, hi) for n, (lo, hi) in zip(model.parameter_names, np.asarray(model.bounds, float))},
                   source="model")

    @classmethod
    def from_toml(cls, path: str | os.PathLike) -> "Prior":
        """Read a TOML file with one table per parameter (keys ``lo``, ``hi``, optional ``form``).

        Raises
        ------
        PriorError
            Missing/unreadable file, TOML syntax error, bad entries.
        """
        path = Path(path)
        try:
            text = path.read_bytes()
        except OSError as exc:
            raise PriorError(f"{path}: cannot read prior file ({exc.strerror or exc})") from None
        try:
            doc = tomllib.loads(text.decode("utf-8"))
        except (tomllib.TOMLDecodeError, UnicodeDecodeError) as exc:
            raise PriorError(f"{path}: not a valid TOML prior file ({exc})") from None
        bad = [k for k, v in doc.items() if not isinstance(v, Mapping)]
        if bad:
            raise PriorError(f"{path}: {bad[0]}: expected a table [{bad[0]}] with lo, hi[, form]")
        if not doc:  # an empty file is a mistake (wrong path, unsaved editor), not "the default box"
            raise PriorError(f"{path}: no parameter table; expected e.g. [VOLF] lo = 0.5, hi = 0.9")
        return cls(doc, source=str(path))

    @classmethod
    def from_dict(cls, d: Mapping[str, Any] | None, *, source: str = "prior") -> "Prior":
        """Inverse of :meth:`to_dict` (also accepts ``(lo, hi[, form])`` tuples)."""
        return cls(d or {}, source=source)

    def override(self, bounds: Mapping[str, tuple[float, float]] | None, *, source: str = "bounds") -> "Prior":
        """A copy whose boxes are replaced by ``bounds`` (may widen as well as narrow; forms kept)."""
        new = Prior(self.entries, source=self.source)
        for name, (lo, hi) in dict(bounds or {}).items():
            form = self.entries[name].form if name in self.entries else "uniform"
            new.entries[str(name)] = _check_entry(str(name), lo, hi, form, source)
        return new

    # -- queries -----------------------------------------------------------------------------
    def __contains__(self, name: str) -> bool:
        return name in self.entries

    def __getitem__(self, name: str) -> ParameterPrior:
        return self.entries[name]

    def __iter__(self):
        return iter(self.entries)

    def __len__(self) -> int:
        return len(self.entries)

    def __eq__(self, other: object) -> bool:
        return isinstance(other, Prior) and self.entries == other.entries

    def __repr__(self) -> str:
        return "Prior(" + ", ".join(f"{n}={p.form}{_fmt_box(p.lo, p.hi)}" for n, p in self.entries.items()) + ")"

    @property
    def is_uniform(self) -> bool:
        """True when no parameter is loguniform."""
        return not any(p.is_log for p in self.entries.values())

    def check_names(self, names: Iterable[str], *, what: str = "the model") -> None:
        """:class:`PriorError` naming the unknown parameters, if any entry is not in ``names``."""
        names = list(names)
        unknown = [n for n in self.entries if n not in names]
        if unknown:
            raise PriorError(f"{self.source}: unknown parameter(s) {', '.join(unknown)}; "
                             f"{what} has {', '.join(names)}")

    def to_dict(self) -> dict[str, dict[str, Any]]:
        """JSON-able ``{name: {"lo", "hi", "form"}}``."""
        return {n: p.to_dict() for n, p in self.entries.items()}

    def departures(self, model) -> list[str]:
        """How this prior differs from the thesis box of ``model`` (one item per parameter).

        E.g. ``"THETA [55, 60] -> [40, 70]"``, ``"P1 [0.0001, 0.1] -> loguniform [1e-06, 1]"``.
        Noise parameters (no thesis box) are not compared.
        """
        out = []
        box = np.asarray(model.bounds, float)
        for i, n in enumerate(model.parameter_names):
            if n not in self.entries:
                continue
            p = self.entries[n]
            a, b = float(box[i, 0]), float(box[i, 1])
            if p.lo == a and p.hi == b and not p.is_log:
                continue
            new = ("loguniform " if p.is_log else "") + _fmt_box(p.lo, p.hi)
            out.append(f"{n} {_fmt_box(a, b)} -> {new}")
        return out

    def notice(self, model) -> str | None:
        """One line ``"prior departs from the thesis box: ..."``, or None when it does not."""
        dep = self.departures(model)
        return "prior departs from the thesis box: " + "; ".join(dep) if dep else None


def load_prior(spec: "Prior | str | os.PathLike | Mapping[str, Any] | None") -> Prior | None:
    """A :class:`Prior` from a Prior, a TOML path or a mapping; None stays None."""
    if spec is None or isinstance(spec, Prior):
        return spec
    if isinstance(spec, (str, os.PathLike)):
        return Prior.from_toml(spec)
    if isinstance(spec, Mapping):
        return Prior.from_dict(spec)
    raise PriorError(f"prior: expected a Prior, a TOML file path or a mapping, got {type(spec).__name__}")


def resolve_prior(model, prior: "Prior | str | os.PathLike | Mapping[str, Any] | None" = None,
                  bounds: Mapping[str, tuple[float, float]] | None = None) -> Prior:
    """The prior a fit uses: the model's box, then ``prior`` (file/mapping), then ``bounds`` overrides.

    ``bounds`` may widen the box (unlike ``make_likelihood(bounds=...)``, which only narrows);
    :meth:`Prior.notice` says how the result departs from the thesis box.

    Parameters
    ----------
    model : Model
    prior : Prior, path to a TOML file, mapping or None
    bounds : {name: (lo, hi)}, optional
        Box overrides of model parameters (``--bounds NAME=LO:HI``); the form is kept.

    Returns
    -------
    Prior
        Every model parameter listed, plus any noise parameter the prior names.

    Raises
    ------
    PriorError
        Unknown model parameters in ``bounds``; bad entries.
    """
    base = Prior.from_model(model)
    user = load_prior(prior)
    if user is not None:
        base = Prior({**base.entries, **user.entries}, source=user.source)
    if bounds:
        Prior(bounds, source="bounds").check_names(model.parameter_names)
        base = base.override(bounds)
    return base
