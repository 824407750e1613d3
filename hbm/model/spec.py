"""What a base model declares about itself: its vocabulary (:class:`ModelSpec`) and the registry of bases.

Every generic layer of hbm -- the population layer, identifiability, the report and the views,
fit quality, optimisation, the file conventions and the exports -- asks the spec of the model it
works with instead of naming the model's parameters:

* ``parameters``: the base's :class:`~hbm.model.core.Parameter` table (units, meanings, prior box)
  and ``physical_range`` (what the physics allows, whatever box a user chooses);
* ``combinations``: the identifiable combinations (:class:`Combination`: a name, how to compute it
  from named samples, the parameters it absorbs, the linear amplitude column it is, its unit)
  and ``shape_parameters``, the parameters a curve informs directly;
* ``transforms``: the population layer's transform of each parameter (log, logit, identity);
* ``fractions``: volume fractions (identify.py adds a log(1 − θ) feature for each);
* ``candidates``: named combinations :func:`hbm.identifiability.identify.candidate_combinations`
  checks explicitly;
* ``manifold``: the fraction–amplitude manifold (:class:`Manifold`) a bound sweep traces;
* ``mixture``: the roles of a fraction mixture (:class:`MixtureRoles`) behind the population
  layer's ``combinations`` pooling and its exact prior density (:mod:`hbm.identifiability.combinations`);
* ``export``: how FE cards read the parameters (:class:`ExportMap`); a 3-D energy plugs in there;
* ``effects``: the effect ids of the base.

A model carries its spec (``Model.spec``, kept through ``model + effect``, ``with_bounds`` and
``replacing``).  A result file is mapped back to its spec by the base's registered name
(:func:`spec_of`): files of the Spyrou base store no name (older files stay as they were), a
result of another base stores ``base_model``.  :func:`register_base` adds a base.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Callable, Mapping, Protocol

import numpy as np

from ..errors import HbmError
from .core import Parameter

__all__ = ["Combination", "Manifold", "MixtureRoles", "ExportMap", "Constituents", "ModelSpec", "BASES",
           "DEFAULT_BASE", "register_base", "base_spec", "spec_of", "sweep_parameter", "parameter_info"]


@dataclass(frozen=True)
class Combination:
    """An identifiable combination of parameters.

    Attributes
    ----------
    name : str
        Its name in every table, figure and result file.
    parameters : tuple of str
        The parameters it absorbs (all must be present to compute it).
    compute : callable
        ``compute(columns) -> array`` from a mapping ``name -> array`` of named samples.
    column : str or None
        The linear amplitude column it corresponds to (:mod:`hbm.model.linear`), if any.
    unit : str
        Its unit (hbm's spelling: ``"MPa"``, ``"-"``).
    compression_note : str or None
        Why it is the prior on data without tension (its term vanishes for ε ≤ 0), or None.
    """

    name: str
    parameters: tuple[str, ...]
    compute: Callable[[Mapping[str, np.ndarray]], np.ndarray]
    column: str | None = None
    unit: str = "-"
    compression_note: str | None = None
    #: how prose writes it (the report's sentences), default its name
    label: str = ""

    @property
    def text(self) -> str:
        return self.label or self.name


@dataclass(frozen=True)
class Manifold:
    """The fraction–amplitude manifold of a base: ``(1 − x)·y`` constant along it (thesis Appendix B).

    ``x`` is a volume fraction in (0, 1), ``y`` a positive amplitude; :mod:`hbm.identifiability.manifolds`
    fits it in the coordinates (−log(1 − x), log y), where a constant level is a straight line;
    ``level`` names the combination that is constant along it.  ``sweep_width`` is the width of the
    windows of the run's default bound sweep over ``x``.
    """

    x: str
    y: str
    level: str
    sweep_width: float = 0.07
    #: how prose writes the level (default its name)
    level_label: str = ""

    @property
    def level_text(self) -> str:
        return self.level_label or self.level


@dataclass(frozen=True)
class MixtureRoles:
    """The parameters of a fraction mixture by role (the Voigt structure of the identifiable combinations).

    With c the ``fraction``: the combinations are c·``fibre``, (1 − c)·``matrix`` and
    c·``shear[0]`` + (1 − c)·``shear[1]``; ``angle`` (optional) is a helix angle whose onset strain
    the combination coordinates use.  :mod:`hbm.identifiability.combinations` computes the exact
    prior density of these combinations under a uniform box on the five parameters.
    """

    fraction: str
    fibre: str
    matrix: str
    shear: tuple[str, str]
    angle: str | None = None
    #: names of the three combinations in the features' order: the shear mix, c·fibre, (1 − c)·matrix
    names: tuple[str, str, str] = ("G", "fibre", "matrix")

    @property
    def params(self) -> tuple[str, str, str, str, str]:
        """(fraction, fibre, matrix, shear modulus of phase c, of phase 1 − c)."""
        return (self.fraction, self.fibre, self.matrix, *self.shear)


@dataclass(frozen=True)
class Constituents:
    """What an FE card reads from one parameter set: the physical constituents of the material.

    Attributes
    ----------
    shear_modulus : float
        Effective small-strain shear modulus of the matrix (MPa), before a card's k_iso.
    fibre_amplitude : float
        Fibre stiffness: nominal stress per unit fibre strain beyond the onset (MPa).
    fibre_onset : float
        Engineering strain at which the fibres engage.
    collagen_amplitude : float
        Collagen stress scale (MPa).
    collagen_rate : float
        Exponential stiffening rate of the collagen.
    collagen_angle : float
        Helix angle of the collagen to the fibres (degrees).
    """

    shear_modulus: float
    fibre_amplitude: float
    fibre_onset: float
    collagen_amplitude: float
    collagen_rate: float
    collagen_angle: float


class ExportMap(Protocol):
    """How FE cards read a base's parameters (:mod:`hbm.export`).

    ``constituents(params)`` gives the material's constituents of a parameter set (a mapping
    ``name -> value``, or ``name -> array`` for many sets at once); ``kinks(params)`` the strains
    where the uniaxial curve has a corner (a tabulated card keeps them); ``energy(params, k_iso,
    l1, l2, l3)`` the strain energy at principal stretches (the 3-D energy of the base plugs in
    here: the stability check reads it through the map).
    """

    def constituents(self, params: Mapping[str, float]) -> Constituents: ...

    def kinks(self, params: Mapping[str, float]) -> list[float]: ...

    def energy(self, params: Mapping[str, np.ndarray], k_iso: float, l1, l2, l3) -> np.ndarray: ...


@dataclass(frozen=True)
class ModelSpec:
    """The vocabulary of a base model (module docstring)."""

    name: str
    parameters: tuple[Parameter, ...]
    effects: tuple[str, ...]
    physical_range: Mapping[str, tuple[float, float]] = field(default_factory=dict)
    combinations: tuple[Combination, ...] = ()
    shape_parameters: tuple[str, ...] = ()
    transforms: Mapping[str, str] = field(default_factory=dict)
    fractions: tuple[str, ...] = ()
    candidates: tuple[Combination, ...] = ()
    manifold: Manifold | None = None
    mixture: MixtureRoles | None = None
    export: Any = None
    #: shape parameters the population layer pools only when the posteriors inform them
    pooled_when_informed: tuple[str, ...] = ()
    #: the report's sentences about the base: ``"combinations"`` (what the data can identify, below the
    #: combinations table), ``"transforms"`` (why each transform, in the population section)
    texts: Mapping[str, str] = field(default_factory=dict)

    @property
    def pooled_shape(self) -> tuple[str, ...]:
        """The shape parameters the population layer always pools beside the combinations."""
        return tuple(p for p in self.shape_parameters if p not in self.pooled_when_informed)

    def __reduce_ex__(self, protocol):
        # a registered base travels by its name (worker processes, dask): one spec per base everywhere,
        # and its functions need not pickle; any other spec by value
        registered = BASES.get(self.name)
        if registered is not None and registered[0] is self:
            return base_spec, (self.name,)
        return super().__reduce_ex__(protocol)

    @property
    def parameter_names(self) -> tuple[str, ...]:
        return tuple(p.name for p in self.parameters)

    @property
    def combination_names(self) -> tuple[str, ...]:
        return tuple(c.name for c in self.combinations)

    def units(self) -> dict[str, str]:
        """Unit of every parameter and combination (hbm's spelling)."""
        return {**{p.name: p.unit for p in self.parameters}, **{c.name: c.unit for c in self.combinations}}

    def combination_values(self, columns: Mapping[str, np.ndarray]) -> dict[str, np.ndarray]:
        """The combinations (name -> array, spec order) of ``columns`` (name -> array); empty unless every
        parameter of every combination is there (a fixed one: the parameters are reported instead)."""
        if not all(p in columns for c in self.combinations for p in c.parameters):
            return {}
        return {c.name: np.asarray(c.compute(columns), float) for c in self.combinations}

    def quantities(self, names, theta) -> dict[str, np.ndarray]:
        """The combinations plus the shape parameters from rows (n, len(names)) of named parameters."""
        theta = np.asarray(theta, float)
        col = {n: theta[:, i] for i, n in enumerate(names)}
        out = self.combination_values(col)
        out.update({k: col[k] for k in self.shape_parameters if k in col})
        return out

    def transform(self, name: str) -> str:
        """The population transform of parameter ``name`` ("logit" for one the spec does not name)."""
        return self.transforms.get(name, "logit")


#: registered base models: name -> (spec, factory of the model)
BASES: dict[str, tuple[ModelSpec, Callable[..., Any]]] = {}
#: the base a result file without a ``base_model`` attribute was fitted with (every file before
#: the registry existed)
DEFAULT_BASE = "spyrou"


def register_base(spec: ModelSpec, factory: Callable[..., Any]) -> None:
    """Register a base model: its spec and a factory of the model (``factory(**options) -> Model``).

    An existing name is replaced.
    """
    BASES[spec.name] = (spec, factory)


def base_spec(name: str | None = None) -> ModelSpec:
    """The spec of the registered base ``name`` (default :data:`DEFAULT_BASE`)."""
    name = DEFAULT_BASE if name is None else str(name)
    try:
        return BASES[name][0]
    except KeyError:
        raise HbmError(f"unknown base model {name!r}; registered: {', '.join(sorted(BASES))}") from None


def spec_of(obj=None) -> ModelSpec:
    """The spec of a model (its ``spec``), of a result (its stored ``base_model``, the default base
    for files that store none) or of a registered name; the default base's for None."""
    if obj is None or isinstance(obj, str):
        return base_spec(obj)
    if isinstance(obj, ModelSpec):
        return obj
    spec = getattr(obj, "spec", None)
    if isinstance(spec, ModelSpec):
        return spec
    return base_spec(getattr(obj, "base_model", None))


def sweep_parameter(model) -> str | None:
    """The parameter of the run's default CMA-ES bound sweep: the fraction of the model's manifold, when
    the model has one and it is a parameter (None: no sweep)."""
    man = getattr(getattr(model, "spec", None), "manifold", None)
    return man.x if man is not None and man.x in getattr(model, "parameter_names", ()) else None


def parameter_info() -> dict[str, tuple[str, str]]:
    """``name -> (unit, meaning)`` of every parameter of every registered base."""
    return {p.name: (p.unit, p.meaning) for spec, _ in BASES.values() for p in spec.parameters}
