"""The linear structure of a model: stress = X(φ)·A with amplitudes A linear in some parameters.

Given the nonlinear parameters φ (VOLF, EOPT, T2, THETA for the base model, plus the shape
parameters of added effects), the base stress is a sum of three unit-amplitude columns times
the amplitudes

    G = c·GF + (1 − c)·GM,    VOLF*P1 = c·P1,    (1-VOLF)*T1 = (1 − c)·T1      (c = VOLF)

and the non-identifiable ridge of the full posterior is exactly the direction these amplitudes
leave free (DESIGN.md §7).  A fit can integrate the amplitudes out in closed form and sample φ
only (:mod:`hbm.likelihood.collapsed`); this module says whether a model has that structure and builds
its pieces:

* ``columns`` — the amplitude columns; ``amplitude_parameters`` — the original parameters that
  feed them, each exactly one column with a coefficient wᵢ(φ): A_j = Σ_{i ∈ j} wᵢ·aᵢ;
* ``basis(loading, theta)`` — X(φ), (..., n_points, n_columns), from one pass through the
  model: kinematics that do not depend on the stress (slack), unit curves of the elastic
  effects, history effects that are linear operators (quasi-linear viscoelasticity filters
  each column), additive output columns (a load-cell offset).

Effects declare the structure (:attr:`hbm.Effect.linear_parameters`,
:attr:`hbm.Effect.preserves_linearity`); a model with an effect that does not (damage, a
compliant series element, a user's undeclared effect) has no structure and is fitted in the
full parameter space.  :meth:`LinearStructure.verify` checks a declaration numerically: the
stress of the model and X(φ)·A at random points of the prior box.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Mapping

import numpy as np

from ..errors import HbmError
from .core import Effect, Loading, Model, State

__all__ = ["LinearStructure", "structure_of", "why_not_linear"]


def _no_elastic(eps: np.ndarray) -> np.ndarray:  # pragma: no cover - guarded by preserves_linearity
    raise HbmError("an effect declared preserves_linearity but its strain map evaluated the stress")


def why_not_linear(model: Model) -> str | None:
    """Why ``model`` has no linear structure (one sentence), or ``None`` if it has one."""
    amplitude: dict[str, str] = {}   # parameter -> the effect that declares it linear
    for e in model.effects:
        if e.stage in ("elastic", "output") and e.linear_parameters:
            unknown = [a for a in e.linear_parameters if a not in _effect_parameters(e)]
            if unknown:
                return f"effect {e.name!r} declares linear parameters {unknown} it does not have or use"
            for a in e.linear_parameters:
                amplitude.setdefault(a, e.name)
        elif e.stage in ("kinematics", "history", "output") and e.preserves_linearity:
            continue
        elif e.stage == "elastic":
            return f"effect {e.name!r} does not declare the parameters its stress is linear in"
        else:
            what = "its strain map may depend on the stress" if e.stage == "kinematics" else \
                "it is not declared a linear operator on the stress"
            return f"effect {e.name!r} ({e.stage} stage): {what}"
    if not amplitude:
        return "no effect declares linear parameters"
    for e in model.effects:
        nonlinear_use = [a for a in _effect_parameters(e) if a in amplitude and a not in e.linear_parameters]
        if nonlinear_use:
            return (f"effect {e.name!r} reads {nonlinear_use} without declaring them linear "
                    f"(declared linear by {amplitude[nonlinear_use[0]]!r})")
    return None


def _effect_parameters(e: Effect) -> tuple[str, ...]:
    """Every parameter an effect owns or reads."""
    return tuple(q.name for q in e.parameters) + tuple(e.uses)


@dataclass(frozen=True)
class LinearStructure:
    """The amplitude columns of a model; build with :func:`structure_of`.

    Attributes
    ----------
    model : Model
    columns : tuple of str
        Amplitude columns in order (``"G"``, ``"VOLF*P1"``, ``"(1-VOLF)*T1"``, ...).
    amplitude_parameters : tuple of str
        The original parameters feeding the columns, in model order.
    column_of : dict
        Amplitude parameter -> its column.
    nonlinear_parameters : tuple of str
        Every other model parameter (φ), in model order.
    """

    model: Model
    columns: tuple[str, ...]
    amplitude_parameters: tuple[str, ...]
    column_of: Mapping[str, str]
    nonlinear_parameters: tuple[str, ...]
    _owner: Mapping[str, Effect] = field(repr=False)

    @property
    def n_columns(self) -> int:
        return len(self.columns)

    def column_index(self) -> np.ndarray:
        """(n_amplitude_parameters,) column number of each amplitude parameter."""
        return np.array([self.columns.index(self.column_of[a]) for a in self.amplitude_parameters], dtype=int)

    def coefficients(self, theta) -> np.ndarray:
        """wᵢ(φ), (..., n_amplitude_parameters): column j's amplitude is Σ_{i in j} wᵢ·aᵢ.

        ``theta`` is a full parameter array (..., model.n_params); amplitude entries are ignored."""
        p = self.model._params(theta)
        shape = np.asarray(theta).shape[:-1]
        out = np.empty(shape + (len(self.amplitude_parameters),))
        for i, a in enumerate(self.amplitude_parameters):
            _, w = self._owner[a].amplitude_coefficients(p)[a]
            out[..., i] = np.broadcast_to(np.asarray(w, dtype=float), shape + (1,))[..., 0]
        return out

    def amplitudes(self, theta) -> np.ndarray:
        """A(θ), (..., n_columns), from a full parameter array."""
        theta = np.asarray(theta, dtype=float)
        a = theta[..., [self.model.index(n) for n in self.amplitude_parameters]]
        terms = self.coefficients(theta) * a
        out = np.zeros(theta.shape[:-1] + (self.n_columns,))
        for i, j in enumerate(self.column_index()):
            out[..., j] += terms[..., i]
        return out

    def basis(self, loading: Loading | np.ndarray, theta, time=None, test=None) -> np.ndarray:
        """X(φ), (..., n_points, n_columns): the stress of unit amplitudes at the φ of ``theta``.

        One pass through the model, vectorised over the leading axes of ``theta`` (a full
        parameter array; its amplitude entries are ignored)."""
        model = self.model
        loading = model._loading(loading, time, test)
        theta = np.asarray(theta, dtype=float)
        p = model._params(theta)
        state = State(loading.strain, loading)
        for e in model.effects:
            if e.stage == "kinematics":
                state = state.with_strain(e.strain(state, p, _no_elastic))
        shape = theta.shape[:-1]
        # the column axis sits before the points so that history effects see (..., k, n) and
        # their parameters broadcast as (..., 1, 1)
        x = np.zeros(shape + (self.n_columns, loading.n_points))
        pk = {k: v[..., None, :] for k, v in p.items()}
        for stage in ("elastic", "history", "output"):
            for e in model.effects:
                if e.stage != stage:
                    continue
                if stage == "elastic" or (stage == "output" and e.linear_parameters):
                    for col, u in e.unit_stress(state, p).items():
                        x[..., self.columns.index(col), :] += u
                else:
                    x = e.modify(state, pk, x)
        return np.swapaxes(x, -1, -2)

    def stress(self, loading, theta, time=None, test=None) -> np.ndarray:
        """X(φ)·A(θ), (..., n_points): equals ``model.stress`` for a valid structure."""
        x = self.basis(loading, theta, time, test)
        return np.einsum("...nk,...k->...n", x, self.amplitudes(theta))

    def verify(self, loading, rng: np.random.Generator, *, n: int = 8, rtol: float = 1e-8,
               time=None, test=None) -> float:
        """Check the declared structure at ``n`` random points of the prior box.

        Returns the largest error of X(φ)·A against ``model.stress`` relative to the largest
        stress magnitude of that point, and raises :class:`HbmError` above ``rtol`` (the
        model is then not linear in its declared amplitudes: fit it with the full likelihood).
        """
        model = self.model
        loading = model._loading(loading, time, test)
        b = model.bounds
        theta = b[:, 0] + rng.random((n, model.n_params)) * (b[:, 1] - b[:, 0])
        ref = model.stress(loading, theta)
        err = np.abs(self.stress(loading, theta) - ref).max(axis=-1)
        rel = float(np.max(err / np.maximum(np.abs(ref).max(axis=-1), 1e-300)))
        # two effects feeding one column must agree on the coefficient of a shared parameter
        p = model._params(theta)
        for e in (e for e in model.effects if e.linear_parameters):
            for a, (col, w) in e.amplitude_coefficients(p).items():
                col0, w0 = self._owner[a].amplitude_coefficients(p)[a]
                if col != col0 or not np.allclose(w, w0, rtol=1e-12, atol=0.0):
                    raise HbmError(f"effects {e.name!r} and {self._owner[a].name!r} map {a} to different "
                                   f"amplitude columns or coefficients ({col!r} vs {col0!r})")
        if not np.isfinite(rel) or rel > rtol:
            raise HbmError(f"model {model.name!r} is not linear in its declared amplitudes "
                           f"{list(self.amplitude_parameters)}: X(φ)·A differs from the stress by {rel:.3g} "
                           "(relative) at a random point of the prior box; fit it with the full likelihood")
        return rel


def structure_of(model: Model) -> LinearStructure | None:
    """The linear structure of ``model``, or ``None`` (:func:`why_not_linear` says why)."""
    if why_not_linear(model) is not None:
        return None
    owner: dict[str, Effect] = {}
    columns: list[str] = []
    probe = model._params(model.bounds.mean(axis=1))  # column names do not depend on values
    for e in model.effects:
        if not e.linear_parameters:
            continue
        for a, (col, _) in e.amplitude_coefficients(probe).items():
            owner.setdefault(a, e)
            if col not in columns:
                columns.append(col)
    names = model.parameter_names
    amp = tuple(n for n in names if n in owner)
    column_of = {a: owner[a].amplitude_coefficients(probe)[a][0] for a in amp}
    return LinearStructure(model=model, columns=tuple(columns), amplitude_parameters=amp, column_of=column_of,
                           nonlinear_parameters=tuple(n for n in names if n not in owner), _owner=owner)
