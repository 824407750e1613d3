"""Composable constitutive model: parameters, physical effects, loading, and the Model.

A :class:`Model` is an ordered collection of :class:`Effect` objects.  Evaluation of the
uniaxial Cauchy stress runs in four stages, each effect taking part in exactly one:

``"kinematics"``
    maps the applied (grip) strain to the tissue strain, e.g. slack or a compliant
    series element.  Signature ``strain(state, p, elastic) -> eps``.
``"elastic"``
    adds a stress contribution that depends on the current tissue strain only
    (neo-Hookean matrix, passive fibers, collagen).  Signature ``stress(state, p) -> s``.
``"history"``
    transforms the elastic stress along the loading history of each test
    (viscoelasticity, damage).  Signature ``modify(state, p, stress) -> stress``.
``"output"``
    transforms the final stress (e.g. a load-cell offset).  Same signature as history.

Parameters are passed to effects as a mapping ``name -> array`` shaped ``(..., 1)`` so that
they broadcast against the strain axis ``(..., n_points)``.  Nothing here loops over samples.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from typing import Callable, Mapping, Sequence

import numpy as np

STAGES = ("kinematics", "elastic", "history", "output")


@dataclass(frozen=True)
class Parameter:
    """One model parameter: its prior box, unit, meaning and null value.

    Parameters
    ----------
    name : str
        Identifier used in tables, on the command line and in netCDF files.
    lower, upper : float
        Closed prior box.
    unit : str
        Physical unit (``"-"`` for dimensionless).
    meaning : str
        One-line description.
    null : float or None
        Value at which the owning effect vanishes (``None`` for base-model parameters).
    """

    name: str
    lower: float
    upper: float
    unit: str = "-"
    meaning: str = ""
    null: float | None = None

    def __post_init__(self) -> None:
        if not (np.isfinite(self.lower) and np.isfinite(self.upper) and self.lower < self.upper):
            raise ValueError(f"parameter {self.name}: need finite lower < upper, got [{self.lower}, {self.upper}]")


@dataclass(frozen=True)
class Loading:
    """The loading path of a specimen: applied strain with optional time and test ids.

    ``history`` numbers the independent loading histories.  Consecutive points belong to the
    same history unless the time restarts (decreases) or, when no time is given, the test id
    changes.  History-dependent effects evaluate each history along its own path; tests whose
    time continues (load, unload, reload, hold) are segments of one history.
    """

    strain: np.ndarray
    time: np.ndarray | None = None
    test: np.ndarray | None = None
    history: np.ndarray = field(init=False, repr=False)

    def __post_init__(self) -> None:
        strain = np.asarray(self.strain, dtype=float)
        if strain.ndim != 1:
            raise ValueError(f"strain must be 1-D (n_points,), got shape {strain.shape}")
        object.__setattr__(self, "strain", strain)
        n = strain.size
        time = None if self.time is None else np.asarray(self.time, dtype=float)
        test = None if self.test is None else np.asarray(self.test)
        for name, arr in (("time", time), ("test", test)):
            if arr is not None and arr.shape != (n,):
                raise ValueError(f"{name} must have shape ({n},) like strain, got {arr.shape}")
        object.__setattr__(self, "time", time)
        object.__setattr__(self, "test", test)
        starts = np.zeros(n, dtype=bool)
        if n:
            starts[0] = True
        if time is not None and n > 1:
            starts[1:] |= np.diff(time) < 0
        elif test is not None and n > 1:
            starts[1:] |= test[1:] != test[:-1]
        object.__setattr__(self, "history", np.cumsum(starts) - 1)

    @property
    def n_points(self) -> int:
        return self.strain.size

    @property
    def history_starts(self) -> np.ndarray:
        """Boolean mask (n_points,): True where a new loading history begins."""
        starts = np.zeros(self.n_points, dtype=bool)
        if self.n_points:
            starts[0] = True
            starts[1:] = self.history[1:] != self.history[:-1]
        return starts


class State:
    """Kinematic state handed to effects: tissue strain (..., n_points) plus the loading."""

    __slots__ = ("eps", "loading", "_cache")

    def __init__(self, eps: np.ndarray, loading: Loading) -> None:
        self.eps = eps
        self.loading = loading
        self._cache: dict[str, np.ndarray] = {}

    @property
    def lam(self) -> np.ndarray:
        """Stretch along the fibers, λ = 1 + ε."""
        if "lam" not in self._cache:
            self._cache["lam"] = 1.0 + self.eps
        return self._cache["lam"]

    @property
    def neo_hookean(self) -> np.ndarray:
        """λ² − 1/λ, the incompressible neo-Hookean uniaxial kinematic factor."""
        if "nh" not in self._cache:
            lam = self.lam
            self._cache["nh"] = lam * lam - 1.0 / lam
        return self._cache["nh"]

    def with_strain(self, eps: np.ndarray) -> "State":
        return State(eps, self.loading)


class Effect:
    """Base class of a physical effect (override the hook of the effect's ``stage``).

    Class attributes
    ----------------
    name : str
        Short id (``"offset"``, ``"viscoelastic"`` ...).
    parameters : tuple of Parameter
        Parameters the effect introduces.  Effects may also *read* parameters declared by
        other effects of the model (e.g. ``VOLF``) by listing their names in ``uses``.
    uses : tuple of str
        Names of parameters owned by other effects that this effect reads.
    stage : str
        One of ``"kinematics"``, ``"elastic"``, ``"history"``, ``"output"``.
    description : str
        One line for tables and reports.
    strength : str, tuple of str or None
        The parameter(s) whose null value switches the effect off (amplitude-like), as
        opposed to parameters that only shape it (time constants, centres, widths).  The
        missing-physics detective (:mod:`hbm.detective`) names an effect only when these
        parameters move away from their null, and quotes their intervals.  ``None``: the
        detective takes the parameters whose null sits on a bound or at zero.
    placement_of : str or None
        The id of another effect of which this one is a second *placement*: the same
        parameters acting at another stage (a pre-stress carried by the tissue is the
        load-cell offset moved before the history stage).  The two give identical stresses
        unless an effect between their stages is present; the detective screens them as one
        candidate and refits both placements only where they differ.

    linear_parameters : tuple of str
        Declares the effect's contribution *linear and homogeneous* in these parameters
        (elastic and output stages): ``Σᵢ aᵢ·wᵢ(φ)·uᵢ(state, φ)`` with unit curves uᵢ and
        coefficients wᵢ that depend only on the other parameters φ.  Fitting then integrates
        these amplitudes out exactly (:mod:`hbm.model.linear`); hbm verifies the declaration
        numerically before using it.  Override :meth:`amplitude_coefficients` and
        :meth:`unit_stress` to group parameters into one amplitude column (e.g. GF and GM
        into G); by default each parameter is its own column with coefficient 1 and unit
        curve the contribution at that parameter = 1.
    preserves_linearity : bool
        Kinematics stage: the strain map does not depend on the stress (slack does, a
        compliant series element does not).  History/output stages: ``modify`` is a linear
        operator on the stress (quasi-linear viscoelasticity is, Mullins damage is not).
    modes, per_observable, along_fibre_reason
        Where the effect is defined beyond along-fibre tension (issue 35): :meth:`in_mode` answers per
        (mode, observable) from them; :mod:`hbm.model.modes_effects` applies or refuses accordingly.

    The detective also needs a ``null`` on every parameter of a candidate effect: the
    candidate is screened and refitted starting from the base model with the effect at its
    nulls (``Model.null_theta``).

    Examples
    --------
    >>> import hbm
    >>> class Offset(hbm.Effect):
    ...     name = "my_offset"
    ...     stage = "output"
    ...     parameters = (hbm.Parameter("S0", -0.01, 0.01, "MPa", "zero offset", null=0.0),)
    ...     def modify(self, state, p, stress):
    ...         return stress + p["S0"]
    >>> model = hbm.spyrou_model() + Offset()
    >>> model.parameter_names[-1]
    'S0'
    """

    name: str = "effect"
    parameters: tuple[Parameter, ...] = ()
    uses: tuple[str, ...] = ()
    stage: str = "elastic"
    description: str = ""
    strength: str | tuple[str, ...] | None = None
    placement_of: str | None = None
    linear_parameters: tuple[str, ...] = ()
    preserves_linearity: bool = False
    #: where the effect is defined beyond the 1-D along-fibre path (issue 35; :mod:`hbm.model.modes_effects`):
    #: ``"along_fibre"`` -- only uniaxial_f's ``stress``, refused in every other (mode, observable) with
    #: :attr:`along_fibre_reason`; ``"stress_observables"`` -- a history/output operator on every stress
    #: observable of every mode (strains, being kinematic, pass untouched)
    modes: str = "along_fibre"
    #: ``modes == "stress_observables"``: the parameters repeat per stress observable beyond ``stress``
    #: (``S0`` -> ``S0_2`` for ``stress_2``: one load-cell zero per measured force)
    per_observable: bool = False
    #: why an ``"along_fibre"`` effect has no 3-D form (quoted when it is refused in another mode)
    along_fibre_reason: str = ("it is written on the 1-D along-fibre strain path and hbm has no 3-D form of it "
                               "(no stress tensor, no lateral kinematics)")

    # -- hooks (override the one of your stage) ---------------------------------------
    def strain(self, state: State, p: Mapping[str, np.ndarray],
               elastic: Callable[[np.ndarray], np.ndarray]) -> np.ndarray:
        """Kinematics stage: tissue strain from ``state.eps`` (the applied strain)."""
        raise NotImplementedError

    def stress(self, state: State, p: Mapping[str, np.ndarray]) -> np.ndarray:
        """Elastic stage: additive Cauchy stress contribution (MPa), shape (..., n_points)."""
        raise NotImplementedError

    def modify(self, state: State, p: Mapping[str, np.ndarray], stress: np.ndarray) -> np.ndarray:
        """History/output stage: return the transformed stress."""
        raise NotImplementedError

    def stress_jacobian(self, state: State, p: Mapping[str, np.ndarray]) -> dict[str, np.ndarray] | None:
        """Optional analytic derivatives of the elastic contribution w.r.t. parameters.

        Returns a mapping ``parameter name -> d(contribution)/d(parameter)`` broadcastable to
        (..., n_points), covering every parameter the contribution depends on, or ``None``
        when not available (the model then falls back to central finite differences).
        """
        return None

    def amplitude_coefficients(self, p: Mapping[str, np.ndarray]) -> dict[str, tuple[str, np.ndarray | float]]:
        """Linear structure: ``parameter -> (amplitude column, coefficient wᵢ(φ))`` for every
        parameter of :attr:`linear_parameters`.  Default: each parameter its own column, w = 1."""
        return {a: (a, 1.0) for a in self.linear_parameters}

    def unit_stress(self, state: State, p: Mapping[str, np.ndarray]) -> dict[str, np.ndarray]:
        """Linear structure: ``amplitude column -> unit curve`` (..., n_points) at the φ of ``p``.

        The contribution of column j is ``(Σᵢ wᵢ·aᵢ)·u_j``.  Default: the contribution with
        that column's parameter set to 1 and the other linear parameters to 0 (elastic stage:
        :meth:`stress`; output stage: what :meth:`modify` adds to a zero stress)."""
        out: dict[str, np.ndarray] = {}
        for a in self.linear_parameters:
            q = dict(p)
            for b in self.linear_parameters:
                q[b] = np.full_like(np.asarray(p[b], dtype=float), 1.0 if b == a else 0.0)
            if self.stage == "elastic":
                out[a] = self.stress(state, q)
            else:
                out[a] = self.modify(state, q, np.zeros_like(state.eps, dtype=float))
        return out

    def experiment(self, protocol: Mapping[str, object]) -> tuple[list[str], list[str]]:
        """The experiment that would reveal this effect: ``(what to add, what the file already has)``.

        ``protocol`` is :func:`hbm.detective.protocols.protocol_features` of the specimen (keys
        ``time``, ``rates``, ``hold``, ``unloading``, ``reload_beyond``, ``near_zero``,
        ``n_points``).  The detective quotes it when it names or groups the effect.  Override it
        in your effect; the default says that hbm knows no protocol for it rather than
        claiming the file already contains one."""
        return ([f"an experiment that isolates {self.name!r} (hbm knows no protocol for this effect; "
                 "describe one in its experiment() method)"], [])

    def in_mode(self, mode: str, observable: str, is_stress: bool) -> str:
        """How the effect takes part in the prediction of ``observable`` in loading mode ``mode``.

        Returns ``"acts"`` (it transforms that prediction), ``"passes"`` (defined there, leaves it as it is:
        a stress operator on a kinematic strain) or, where the effect is not defined, the reason (a
        sentence; the caller refuses the pair with it).  The default follows :attr:`modes`; override it
        for another scope."""
        if self.modes == "stress_observables":
            return "acts" if is_stress else "passes"
        if mode == "uniaxial_f" and observable == "stress":
            return "acts"
        return self.along_fibre_reason

    # -- conveniences -------------------------------------------------------------------
    @property
    def null_values(self) -> dict[str, float]:
        """Parameter values at which this effect vanishes."""
        return {q.name: q.null for q in self.parameters if q.null is not None}

    def __repr__(self) -> str:
        return f"<Effect {self.name} ({self.stage}): {', '.join(q.name for q in self.parameters)}>"


def _check_effect(effect: Effect) -> None:
    if not isinstance(effect, Effect):
        raise TypeError(f"expected an hbm.Effect instance, got {type(effect).__name__}")
    if effect.stage not in STAGES:
        raise ValueError(f"effect {effect.name!r}: stage must be one of {STAGES}, got {effect.stage!r}")
    hook = {"kinematics": "strain", "elastic": "stress", "history": "modify", "output": "modify"}[effect.stage]
    if getattr(type(effect), hook) is getattr(Effect, hook):
        raise TypeError(f"effect {effect.name!r} (stage {effect.stage!r}) must implement {hook}()")


class Model:
    """A constitutive model built from effects, with a parameter table.

    Parameters
    ----------
    effects : sequence of Effect
        Evaluated by stage (kinematics, elastic, history, output), in the given order
        within a stage.
    parameters : sequence of Parameter, optional
        Explicit order of (some of) the parameters; the remaining parameters of the effects
        follow in the order the effects declare them.
    name : str
        Label used in reports.
    spec : ModelSpec, optional
        The vocabulary of the base model (:mod:`hbm.model.spec`: combinations, transforms,
        manifold, export map ...), kept through ``model + effect``, :meth:`with_bounds` and
        :meth:`replacing`; None for a model built from effects without a declared base.
    """

    def __init__(self, effects: Sequence[Effect], parameters: Sequence[Parameter] | None = None,
                 name: str = "model", spec=None) -> None:
        effects = tuple(effects)
        for e in effects:
            _check_effect(e)
        names = [e.name for e in effects]
        if len(set(names)) != len(names):
            raise ValueError(f"duplicate effect names in model: {names}")
        table: dict[str, Parameter] = {}
        for q in list(parameters or ()) + [q for e in effects for q in e.parameters]:
            if q.name in table and table[q.name] != q:
                if parameters and q.name in {x.name for x in parameters}:
                    continue  # the explicit table wins (e.g. narrowed bounds)
                raise ValueError(f"parameter {q.name!r} declared twice with different definitions")
            table.setdefault(q.name, q)
        for e in effects:
            missing = [u for u in e.uses if u not in table]
            if missing:
                raise ValueError(f"effect {e.name!r} uses parameters {missing} that no effect declares")
        self.effects = effects
        self.parameters: tuple[Parameter, ...] = tuple(table.values())
        self.name = name
        self.spec = spec
        self._index = {q.name: i for i, q in enumerate(self.parameters)}

    # -- parameter table --------------------------------------------------------------
    @property
    def parameter_names(self) -> tuple[str, ...]:
        return tuple(q.name for q in self.parameters)

    @property
    def n_params(self) -> int:
        return len(self.parameters)

    @property
    def bounds(self) -> np.ndarray:
        """Prior box, float array (n_params, 2)."""
        return np.array([[q.lower, q.upper] for q in self.parameters], dtype=float)

    @property
    def units(self) -> dict[str, str]:
        return {q.name: q.unit for q in self.parameters}

    @property
    def meanings(self) -> dict[str, str]:
        return {q.name: q.meaning for q in self.parameters}

    @property
    def effect_names(self) -> tuple[str, ...]:
        return tuple(e.name for e in self.effects)

    def index(self, name: str) -> int:
        """Column of parameter ``name`` in theta."""
        try:
            return self._index[name]
        except KeyError:
            raise KeyError(f"unknown parameter {name!r}; the model has {self.parameter_names}") from None

    def null_theta(self, base: np.ndarray | Mapping[str, float]) -> np.ndarray:
        """Full theta from base values plus every added effect at its null value."""
        if isinstance(base, Mapping):
            out = np.full(self.n_params, np.nan)
            for k, v in base.items():
                out[self.index(k)] = v
        else:
            base = np.asarray(base, dtype=float)
            out = np.full(base.shape[:-1] + (self.n_params,), np.nan)
            out[..., : base.shape[-1]] = base
        for e in self.effects:
            for k, v in e.null_values.items():
                i = self.index(k)
                out[..., i] = np.where(np.isnan(out[..., i]), v, out[..., i])
        if np.isnan(out).any():
            raise ValueError("null_theta: some parameters have neither a value nor a null value")
        return out

    def table(self) -> str:
        """Human-readable parameter table."""
        rows = [f"{'name':<10}{'lower':>10}{'upper':>10}  {'unit':<6} meaning"]
        for q in self.parameters:
            rows.append(f"{q.name:<10}{q.lower:>10.4g}{q.upper:>10.4g}  {q.unit:<6} {q.meaning}")
        return "\n".join(rows)

    # -- composition --------------------------------------------------------------------
    def with_effects(self, *effects: Effect) -> "Model":
        """A new model with ``effects`` added; their parameters are appended to the table."""
        extra = [e for e in effects]
        name = self.name + "+" + "+".join(e.name for e in extra) if extra else self.name
        return Model(self.effects + tuple(extra), parameters=self.parameters, name=name, spec=self.spec)

    def replacing(self, old: str, new: Effect) -> "Model":
        """A new model with effect ``old`` replaced by ``new`` in its place (``new`` may declare
        parameters of the same names, e.g. another placement of ``old``; the order of the
        parameter table is kept)."""
        if old not in self.effect_names:
            raise ValueError(f"replacing: no effect {old!r} in the model {self.effect_names}")
        mine = {q.name: q for q in new.parameters}
        gone = {q.name for e in self.effects if e.name == old for q in e.parameters} - set(mine)
        effects = [new if e.name == old else e for e in self.effects]
        parameters = [mine.get(q.name, q) for q in self.parameters if q.name not in gone]
        parts = self.name.split("+")   # the label's part, not a substring of another effect's id
        return Model(effects, parameters=parameters, name="+".join(new.name if x == old else x for x in parts),
                     spec=self.spec)

    def __add__(self, other: Effect) -> "Model":
        if isinstance(other, Effect):
            return self.with_effects(other)
        if isinstance(other, (list, tuple)):
            return self.with_effects(*other)
        return NotImplemented

    def with_bounds(self, **bounds: tuple[float, float]) -> "Model":
        """A copy with narrowed/changed prior bounds, e.g. ``with_bounds(VOLF=(0.5, 0.75))``."""
        table = []
        for q in self.parameters:
            if q.name in bounds:
                lo, hi = bounds[q.name]
                q = dataclasses.replace(q, lower=float(lo), upper=float(hi))
            table.append(q)
        unknown = set(bounds) - set(self.parameter_names)
        if unknown:
            raise KeyError(f"unknown parameters {sorted(unknown)}; the model has {self.parameter_names}")
        return Model(self.effects, parameters=table, name=self.name, spec=self.spec)

    # -- evaluation ---------------------------------------------------------------------
    def _params(self, theta: np.ndarray) -> dict[str, np.ndarray]:
        theta = np.asarray(theta, dtype=float)
        if theta.shape[-1] != self.n_params:
            raise ValueError(
                f"theta has {theta.shape[-1]} columns, the model has {self.n_params} parameters "
                f"{self.parameter_names}")
        return {q.name: theta[..., i, None] for i, q in enumerate(self.parameters)}

    @staticmethod
    def _loading(strain, time, test) -> Loading:
        if isinstance(strain, Loading):
            return strain
        return Loading(np.asarray(strain, dtype=float), time, test)

    def _elastic(self, p: Mapping[str, np.ndarray], loading: Loading) -> Callable[[np.ndarray], np.ndarray]:
        elastic = [e for e in self.effects if e.stage == "elastic"]

        shape_p = np.broadcast_shapes(*(v.shape for v in p.values()))

        def f(eps: np.ndarray) -> np.ndarray:
            state = State(eps, loading)
            shape = np.broadcast_shapes(eps.shape, shape_p)
            total = None
            for e in elastic:
                s = e.stress(state, p)
                if total is None and (s is eps or any(s is v for v in state._cache.values())):
                    s = s.copy()  # never accumulate into the cached kinematics
                # first contribution is fresh memory owned by us: accumulate in place after it
                total = s if total is None else np.add(total, s, out=total if total.shape == shape else None)
            if total is None:
                return np.zeros(shape)
            if total.shape != shape:
                total = np.broadcast_to(total, shape).copy()
            return total

        return f

    def stress(self, strain, theta, time=None, test=None) -> np.ndarray:
        """Cauchy stress (MPa) along the fibers.

        Parameters
        ----------
        strain : array (n_points,) or Loading
            Applied engineering strain.
        theta : array (..., n_params)
            Parameter values, columns in the order of :attr:`parameter_names`.
        time, test : array (n_points,), optional
            Time (s) and test ids; only history-dependent effects read them.

        Returns
        -------
        ndarray (..., n_points)
        """
        loading = self._loading(strain, time, test)
        p = self._params(theta)
        elastic = self._elastic(p, loading)
        # the strain stays 1-D (n_points,) until an effect needs it per sample: broadcasting
        # against the (..., 1) parameters then costs one pass instead of materialising copies
        state = State(loading.strain, loading)
        for e in self.effects:
            if e.stage == "kinematics":
                state = state.with_strain(e.strain(state, p, elastic))
        s = elastic(state.eps)
        for stage in ("history", "output"):
            for e in self.effects:
                if e.stage == stage:
                    s = e.modify(state, p, s)
        return s

    def __call__(self, strain, theta, time=None, test=None) -> np.ndarray:
        return self.stress(strain, theta, time, test)

    @property
    def has_analytic_jacobian(self) -> bool:
        return all(e.stage == "elastic" and type(e).stress_jacobian is not Effect.stress_jacobian
                   for e in self.effects)

    def stress_jacobian(self, strain, theta, time=None, test=None, *, fd_step: float = 1e-6) -> np.ndarray:
        """d stress / d theta, shape (..., n_points, n_params).

        Analytic when every effect provides :meth:`Effect.stress_jacobian`; otherwise central
        finite differences with step ``fd_step`` times the prior width, evaluated in one
        vectorised batch.
        """
        loading = self._loading(strain, time, test)
        theta = np.asarray(theta, dtype=float)
        if self.has_analytic_jacobian:
            p = self._params(theta)
            state = State(loading.strain, loading)
            jac = np.zeros(theta.shape[:-1] + (loading.n_points, self.n_params))
            for e in self.effects:
                d = e.stress_jacobian(state, p)
                if d is None:  # pragma: no cover - guarded by has_analytic_jacobian
                    break
                for k, v in d.items():
                    jac[..., self.index(k)] += v  # broadcasts (n_points,) or (..., n_points)
            else:
                return jac
        h = fd_step * (self.bounds[:, 1] - self.bounds[:, 0])
        eye = np.eye(self.n_params) * h
        pert = np.concatenate([theta[..., None, :] + eye, theta[..., None, :] - eye], axis=-2)
        s = self.stress(loading, pert)  # (..., 2d, n)
        d = self.n_params
        return np.swapaxes((s[..., :d, :] - s[..., d:, :]) / (2 * h[:, None]), -1, -2)

    def __repr__(self) -> str:
        return f"<Model {self.name}: {', '.join(self.parameter_names)}>"

