"""The settings of one specimen's fit (:class:`FitSettings`) and the stored ``config`` of its result
(:class:`FitRecord`).

:func:`hbm.fit.fit_specimen` takes a :class:`FitSettings` (or its fields as keywords); ``hbm fit``
builds its options from the declarations below, ``hbm run`` inherits them
(:class:`hbm.settings.RunSettings`), the result key hashes :meth:`FitSettings.record` and the
result file stores :meth:`FitRecord.to_attrs`.

Renamed concepts keep their stored names (the table: :mod:`hbm.settings`); the tier a fit *used* is
stored as ``likelihood_tier``, its reason as ``likelihood_note`` (:class:`FitRecord`).
"""

from __future__ import annotations

import importlib
from dataclasses import dataclass, field
from typing import Any, ClassVar, Mapping, NamedTuple

from ..errors import SettingError
from .fields import Settings, canonical, record, setting
from .rules import (
    NON_NEGATIVE_INT, POSITIVE_INT, POWER_OF_TWO_OR_ZERO, RANGE, SAMPLE_SIZE, SEED, ChoiceRule, RealRule, Rule,
    _type_error)

__all__ = ["FitSettings", "FitRecord", "Sweep", "SWEEP", "RUN_SWEEP", "registry", "MOVE_RULE", "NOISE_RULE", "TIER_RULE"]


def registry(module: str, attribute: str):
    """The names of a registry, read when asked: ``attribute`` of ``module`` (a dict's keys, a
    tuple, or a function returning names).  The settings name registries by module so that they
    import none of them (the model and the samplers import the settings' rules)."""
    def names() -> tuple[str, ...]:
        value = getattr(importlib.import_module(module), attribute)
        return tuple(value() if callable(value) else value)

    names.__name__ = attribute
    return names


#: the moves of :data:`hbm.samplers.moves.MOVES`, the noise models of :mod:`hbm.likelihood.noise`
#: and the likelihood tiers of :data:`hbm.likelihood.collapsed.TIERS`
MOVE_RULE = ChoiceRule(registry("hbm.samplers.moves", "MOVES"), "TMCMC move")
NOISE_RULE = ChoiceRule(registry("hbm.likelihood.noise", "noise_model_names"), "noise model")
TIER_RULE = ChoiceRule(registry("hbm.likelihood.collapsed.likelihood", "TIERS"), "likelihood tier")


class Sweep(NamedTuple):
    """A parsed ``--sweep NAME:WIDTH`` (``text``: as given)."""

    name: str
    width: float
    text: str


class _SweepRule(Rule):
    """A CMA-ES bound sweep ``NAME:WIDTH`` (WIDTH > 0), or (name, width) in Python; ``none``/``off``
    on the command line: no sweep.  A Python value keeps its form (string or pair): the result key
    hashes it as given."""

    expected = "NAME:WIDTH with WIDTH > 0, e.g. VOLF:0.05 (or none)"

    def __init__(self, auto: bool = False) -> None:
        self.auto = auto   # "auto": the model's manifold sweep, resolved when the model is known
        self.__name__ = "sweep"

    @staticmethod
    def split(value: Any) -> tuple[str, float]:
        if isinstance(value, (tuple, list)):
            name, width = value[0], value[1]
        else:
            name, sep, width = str(value).partition(":")
            if not sep:
                raise ValueError(value)
        name, width = str(name).strip(), float(width)
        if not name or any(c.isspace() for c in name) or "," in name or not width > 0:
            raise ValueError(value)
        return name, width

    def convert(self, value: Any) -> Any:
        if self.auto and value == "auto":
            return value
        if isinstance(value, Sweep):  # a parsed option: the pair (the text where the run keeps it)
            return value.text if self.auto else (value.name, value.width)
        name, width = self.split(value)
        return (name, width) if isinstance(value, (tuple, list)) else str(value)

    def parse(self, text: str) -> Sweep | str | None:
        if str(text).strip().lower() in ("none", "off", ""):
            return None
        if self.auto and str(text).strip() == "auto":
            return "auto"
        name, sep, width = str(text).partition(":")
        if not sep:
            raise _type_error(text, self.expected)
        w = RealRule().parse(width) if width.strip() else None
        try:
            name, w = self.split((name, w))
        except (TypeError, ValueError):
            raise _type_error(text, self.expected) from None
        return Sweep(name, w, str(text).strip())

    def check(self, value: Any, name: str) -> Any:
        try:
            return self.convert(value)
        except (TypeError, ValueError):
            raise SettingError(f"{name}: expected PARAM:WIDTH (e.g. VOLF:0.05) with WIDTH > 0, got {value!r}") \
                from None


SWEEP = _SweepRule()
#: the run's sweep: also "auto" (the model's manifold abscissa), kept as text
RUN_SWEEP = _SweepRule(auto=True)


@record
class FitSettings(Settings):
    """The settings of one specimen's fit: everything :func:`hbm.fit.fit_specimen` takes besides
    the data, the model, paths and progress display.

    Attributes (see each field's help; ``hbm fit -h`` lists them with their flags)
    """

    samples: int = setting(2000, rule=SAMPLE_SIZE, flag="--samples", metavar="N",
                           help="TMCMC population size N, the posterior draws stored (default {default})")
    move: str = setting("rw", rule=MOVE_RULE, flag="--move", aliases=("--kernel",), old_names=("kernel",),
                        stored="kernel",
                        help="TMCMC move: rw = random walk (default {default}), manifold = gradient/Fisher-metric "
                             "manifold MALA, or any registered move")
    noise: str = setting("iid", rule=NOISE_RULE, flag="--noise",
                         help="noise model (default {default}: iid Gaussian with unknown sigma)")
    tier: str = setting("auto", rule=TIER_RULE, flag="--tier", aliases=("--likelihood",), old_names=("likelihood",),
                        stored="likelihood",
                        help="likelihood tier: auto = integrate the linear amplitudes exactly and sample only the "
                             "nonlinear and noise parameters where the model and noise allow it, else the full "
                             "likelihood; collapsed = require that; full = sample every parameter (default {default})")
    fix: dict | None = setting(None, help="parameters held fixed {name: value} (checked against the model)")
    bounds: dict | None = setting(None, help="narrowed prior boxes {name: (lo, hi)} (checked against the model)")
    seed: Any = setting(0, rule=SEED, flag="--seed", metavar="S",
                        help="root seed; the phases get spawned children (default {default})")
    restarts: int = setting(4, rule=NON_NEGATIVE_INT, flag="--restarts", metavar="K",
                            help="CMA-ES restarts (0 = skip; default {default})")
    sweep: Any = setting(None, rule=SWEEP, flag="--sweep", metavar="NAME:WIDTH",
                         help="CMA-ES bound sweep tracing a manifold, e.g. NAME:0.05 over a fraction NAME (default: none)")
    sobol_n: int | None = setting(None, rule=POWER_OF_TWO_OR_ZERO, flag="--sobol-n", aliases=("--sobol",),
                                  metavar="N", help="Sobol base sample size, a power of 2 (0 = skip; default {default})")
    maxfevals: int | None = setting(None, rule=POSITIVE_INT, flag="--maxfevals", metavar="M",
                                    stored="optimize_options.maxfevals",
                                    help="evaluation budget per CMA-ES run (default {default})")
    optimize_options: dict | None = setting(None, help="further keyword arguments of hbm.fit.optimization.optimize")
    sigma_bounds: Any = setting(None, rule=RANGE, flag="--sigma-bounds", metavar="LO:HI",
                                help="box of the noise sd (or scale)")
    tmcmc_options: dict | None = setting(None, help="further keyword arguments of hbm.samplers.tmcmc")
    max_evaluations: int | None = setting(None, rule=POSITIVE_INT, flag="--max-evaluations", metavar="M",
                                          help="cap on TMCMC likelihood evaluations including the initial N (default: "
                                               "no cap); a binding cap gives a cruder posterior and evidence, flagged "
                                               "in the result")
    prior: Any = setting(None, help="user prior (hbm.likelihood.prior.Prior, TOML path or mapping)")

    def __post_init__(self) -> None:
        super().__post_init__()
        if self.sobol_n == 0:  # 0 = skip, as None
            object.__setattr__(self, "sobol_n", None)
        for name in ("fix", "bounds", "optimize_options", "tmcmc_options"):
            value = getattr(self, name)
            if value is not None and not isinstance(value, Mapping):
                raise SettingError(f"{name}: expected a mapping, got {value!r}")
        self._normalise()
        self._check_budget()

    def _normalise(self) -> None:
        """Settings that follow from others (a subclass's hook; nothing at the fit level)."""

    def _check_budget(self) -> None:
        if self.max_evaluations is not None and self.max_evaluations < self.samples:
            raise SettingError(f"max_evaluations {self.max_evaluations}: expected at least the TMCMC population "
                               f"size {self.samples} (the initial population alone costs N evaluations)")

    # -- what the fit runs with ----------------------------------------------------------------
    @property
    def sweep_pair(self) -> tuple[str, float] | None:
        """The sweep as (parameter, width), whatever form it was given in."""
        return None if self.sweep is None else SWEEP.split(self.sweep)

    def cma_options(self) -> dict:
        """Keyword arguments of every CMA-ES run: the 5000-evaluation default, ``maxfevals``, then
        ``optimize_options``."""
        out = {"maxfevals": 5000}
        if self.maxfevals is not None:
            out["maxfevals"] = int(self.maxfevals)
        out.update(dict(self.optimize_options or {}))
        return out

    def stored_optimize_options(self) -> dict | None:
        """``optimize_options`` as stored and keyed (``maxfevals`` folded in), None when unset."""
        out = dict(self.optimize_options or {})
        if self.maxfevals is not None:
            out = {"maxfevals": int(self.maxfevals), **out}
        return out or None

    def record(self, **extra: Any) -> dict:
        """The settings that key the result and its checkpoints, in canonical JSON form (floats by
        repr; module docstring: stored names; ``maxfevals`` keyed inside ``optimize_options``)."""
        out = super().record(**extra)
        out.pop("optimize_options.maxfevals", None)
        opts = self.stored_optimize_options()
        if opts is not None:
            out["optimize_options"] = opts
        return {k: canonical(v) for k, v in out.items()}


@dataclass(frozen=True)
class FitRecord:
    """The ``config`` attribute of a specimen result: the fit's settings and what the fit did.

    Every reader of a stored config reads it through :meth:`from_attrs` (files of every hbm
    version; missing entries at their defaults).  Stored keys: the settings' (``samples``,
    ``kernel``, ``noise``, ``fix``, ``bounds``, ``restarts``, ``sweep``, ``sobol_n``,
    ``optimize_options``, ``sigma_bounds``, ``tmcmc_options`` -- with ``max_evaluations`` inside --,
    ``prior``), then ``seeds``, ``n_evaluations``, ``n_stages``, ``likelihood_tier`` (the tier
    used), ``likelihood_note`` (why), ``source_file``, ``input`` (the loader's conversions),
    ``collapsed`` (the collapsed tier's record), ``seed_spawn_key``, ``settings_hash`` and
    ``identity`` (the result key and its components), and any extra entries.
    """

    settings: FitSettings
    seeds: Mapping[str, int] = field(default_factory=dict)
    n_evaluations: int | None = None
    n_stages: int | None = None
    tier_used: str = "full"
    tier_note: str = ""
    source_file: str = ""
    input: str = ""
    collapsed: Mapping[str, Any] | None = None
    seed_spawn_key: tuple[int, ...] | None = None
    settings_hash: str | None = None
    identity: Mapping[str, str] | None = None
    extra: Mapping[str, Any] = field(default_factory=dict)

    #: outcome field -> stored key
    OUTCOMES: ClassVar[dict[str, str]] = {"seeds": "seeds", "n_evaluations": "n_evaluations", "n_stages": "n_stages",
                "tier_used": "likelihood_tier", "tier_note": "likelihood_note", "source_file": "source_file",
                "input": "input", "collapsed": "collapsed", "seed_spawn_key": "seed_spawn_key",
                "settings_hash": "settings_hash", "identity": "identity"}
    #: stored when empty too (older files: a bare key); the rest only when set
    ALWAYS: ClassVar[tuple[str, ...]] = ("seeds", "n_evaluations", "n_stages", "tier_used", "tier_note", "source_file")

    def to_attrs(self) -> dict:
        """The stored ``config`` (today's layout, key for key)."""
        s = self.settings
        opts = dict(s.tmcmc_options or {})
        if s.max_evaluations is not None:
            opts["max_evaluations"] = int(s.max_evaluations)
        sweep = s.sweep_pair
        out: dict[str, Any] = {
            "samples": int(s.samples), "kernel": s.move, "noise": s.noise, "fix": dict(s.fix or {}) or None,
            "bounds": {k: list(map(float, v)) for k, v in (s.bounds or {}).items()} or None,
            "restarts": int(s.restarts or 0), "sweep": list(sweep) if sweep else None,
            "sobol_n": int(s.sobol_n or 0), "optimize_options": s.stored_optimize_options(),
            "sigma_bounds": list(map(float, s.sigma_bounds)) if s.sigma_bounds is not None else None,
            "tmcmc_options": {k: v for k, v in opts.items() if k != "gradient_fim"} or None}
        for name, key in self.OUTCOMES.items():
            value = getattr(self, name)
            if name in self.ALWAYS or value:
                out[key] = list(value) if name == "seed_spawn_key" else value
        if s.prior is not None:
            out["prior"] = s.prior.to_dict() if hasattr(s.prior, "to_dict") else s.prior
        out.update(dict(self.extra))
        return out

    @classmethod
    def from_attrs(cls, config: Mapping[str, Any] | None) -> "FitRecord":
        """The record of a stored ``config`` (an empty mapping gives the defaults)."""
        c = dict(config or {})
        opts = dict(c.get("tmcmc_options") or {})
        budget = opts.pop("max_evaluations", None)
        cma = dict(c.get("optimize_options") or {})
        maxfevals = cma.pop("maxfevals", None)
        # what was stored, unchecked: a file may name a move or noise model not registered here
        settings = FitSettings.stored(
            samples=int(c.get("samples", FitSettings.default("samples"))), move=c.get("kernel", "rw"),
            noise=c.get("noise", "iid"), fix=c.get("fix"), bounds=c.get("bounds"), restarts=c.get("restarts", 0),
            sweep=tuple(c["sweep"]) if c.get("sweep") else None, sobol_n=c.get("sobol_n") or None,
            maxfevals=maxfevals, optimize_options=cma or None,
            sigma_bounds=tuple(c["sigma_bounds"]) if c.get("sigma_bounds") else None, tmcmc_options=opts or None,
            max_evaluations=budget, prior=c.get("prior"))
        known = set(cls.OUTCOMES.values()) | {"samples", "kernel", "noise", "fix", "bounds", "restarts", "sweep",
                                               "sobol_n", "optimize_options", "sigma_bounds", "tmcmc_options",
                                               "prior"}
        outcome = {name: c[key] for name, key in cls.OUTCOMES.items() if key in c}
        if "seed_spawn_key" in outcome:
            outcome["seed_spawn_key"] = tuple(outcome["seed_spawn_key"])
        return cls(settings=settings, extra={k: v for k, v in c.items() if k not in known}, **outcome)

