"""Load cases: the vocabulary each loading mode declares, and the two families of solvers.

A load case is one homogeneous test of an incompressible specimen in the fibre frame (f = fibre
axis, c = cross-fibre in the specimen plane, n = the third direction; DESIGN.md §8).  It declares
what generic layers need (names, control, observables with units) and solves the model for them::

    solve(energy, params, strain, strain_2=None) -> {observable: ndarray (..., n_points)}

``params`` is the mapping ``name -> array (..., 1)`` of :meth:`hbm.Model._params`, ``strain`` the
control (n_points,).  Stresses are Cauchy (MPa), strains engineering; negative strain is compression.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Mapping

import numpy as np

from ...errors import HbmError
from ..energy3d import Energy3D, Sym

#: index of each fibre-frame axis
AXIS = {"f": 0, "c": 1, "n": 2}


@dataclass(frozen=True)
class Observable:
    """One quantity a load case predicts.

    Attributes
    ----------
    name : str
        Column name (``stress``, ``stress_2``, ``strain_f`` ...).
    unit : str
        UDUNITS unit (``MPa`` or ``1``).
    long_name : str
        What it is, in words.
    axis : str or None
        For a normal stress: the fibre-frame axis it acts along (its nominal value is σ/λ_axis);
        ``None`` for shear stresses (nominal = Cauchy in simple shear) and strains.
    """

    name: str
    unit: str
    long_name: str
    axis: str | None = None

    @property
    def is_stress(self) -> bool:
        return self.unit == "MPa"


def lateral_strain(axis: str, mode: str) -> Observable:
    return Observable(f"strain_{axis}", "1", f"engineering strain along {axis} (traction-free face) in {mode}")


class LoadCase:
    """Base class of a load case (one small subclass per mode, registered by name).

    Class attributes
    ----------------
    name : str
        The ``mode`` value (e.g. ``"uniaxial_c"``).
    aliases : tuple of str
        Other accepted spellings.
    control : {"stretch", "shear"}
        What ``strain`` is: an engineering strain along the load, or the amount of shear γ.
    description : str
        One line: the deformation, which faces are free.
    observables : tuple of Observable
        What :meth:`solve` returns (``stress`` first).
    inputs : tuple of str
        Control columns: ``("strain",)`` or ``("strain", "strain_2")`` (biaxial; ``strain_2`` equal to
        ``strain`` when absent).
    """

    name: str = ""
    aliases: tuple[str, ...] = ()
    control: str = "stretch"
    description: str = ""
    observables: tuple[Observable, ...] = ()
    inputs: tuple[str, ...] = ("strain",)

    def solve(self, energy: Energy3D, params: Mapping[str, np.ndarray], strain, strain_2=None
              ) -> dict[str, np.ndarray]:
        """The prediction of every observable, each (..., n_points)."""
        raise NotImplementedError

    @property
    def observable_names(self) -> tuple[str, ...]:
        return tuple(o.name for o in self.observables)

    def observable(self, name: str) -> Observable:
        for o in self.observables:
            if o.name == name:
                return o
        raise HbmError(f"mode {self.name}: no observable {name!r}; it predicts {', '.join(self.observable_names)}")

    # -- inputs -------------------------------------------------------------------------------------
    def controls(self, strain, strain_2=None) -> tuple[np.ndarray, np.ndarray | None]:
        """The checked control arrays (n_points,): ``strain`` and ``strain_2`` (for two-input modes,
        ``strain`` where absent or NaN).  :class:`HbmError` for a non-finite value or a stretch ≤ 0."""
        s = _checked(self, "strain", strain)
        if "strain_2" not in self.inputs:
            if strain_2 is not None:
                raise HbmError(f"mode {self.name}: takes one control (strain), got strain_2 as well")
            return s, None
        if strain_2 is None:
            return s, s
        s2 = np.asarray(strain_2, dtype=float)
        if s2.shape != s.shape:
            raise HbmError(f"mode {self.name}: strain_2 has shape {s2.shape}, strain {s.shape}")
        return s, _checked(self, "strain_2", np.where(np.isnan(s2), s, s2))

    def load_stretch(self, observable: str, strain, strain_2=None) -> np.ndarray:
        """The stretch along a stress observable's axis (n_points,), to convert between Cauchy and nominal
        stress (P = σ/λ along the load in stretch modes; 1 in simple shear, where P = σ)."""
        obs = self.observable(observable)
        if not obs.is_stress:
            raise HbmError(f"mode {self.name}: {observable} is a strain, not a stress")
        s, s2 = self.controls(strain, strain_2)
        if obs.axis is None:
            return np.ones_like(s)
        return np.exp(self.prescribed_log_stretch(obs.axis, s, s2))

    def prescribed_log_stretch(self, axis: str, strain: np.ndarray, strain_2: np.ndarray | None) -> np.ndarray:
        """ln λ along ``axis`` where the mode prescribes it."""
        raise HbmError(f"mode {self.name}: the stretch along {axis} is not prescribed")

    def __repr__(self) -> str:
        return f"<load case {self.name}: {self.description}>"


def _checked(case: LoadCase, what: str, values) -> np.ndarray:
    a = np.asarray(values, dtype=float)
    if a.ndim != 1:
        raise HbmError(f"mode {case.name}: {what} must be 1-D (n_points,), got shape {a.shape}")
    if not np.all(np.isfinite(a)):
        i = int(np.flatnonzero(~np.isfinite(a))[0])
        raise HbmError(f"mode {case.name}: {what} must be finite, got {a[i]} at point {i}")
    if case.control == "stretch" and np.any(a <= -1.0):
        i = int(np.argmin(a))
        raise HbmError(f"mode {case.name}: {what} must be > -1 (a stretch > 0), got {a[i]:.6g} at point {i}")
    return a


def full_shape(params: Mapping[str, np.ndarray], n_points: int) -> tuple[int, ...]:
    """(..., n_points): the broadcast of the parameters (..., 1) against the points."""
    return np.broadcast_shapes(*(np.shape(v) for v in params.values()), (n_points,))


def fill(value, shape) -> np.ndarray:
    """``value`` as a fresh float array of ``shape``."""
    return np.array(np.broadcast_to(value, shape), dtype=float)


def normal_stress(name: str, axis: str, role: str) -> Observable:
    return Observable(name, "MPa", f"Cauchy stress sigma_{axis}{axis} ({role})", axis)


class PrescribedStretch(LoadCase):
    """A mode with a diagonal F given by the controls (J = 1) and one traction-free face that sets p.

    Subclasses give :meth:`log_stretches` (ln λ along f, c, n), ``free`` (the axis of the free face)
    and ``stress_axes`` (observable -> axis), or ``axes = (loaded, second)`` with ``roles`` (the words
    for ``stress`` and ``stress_2``), from which the free face and the observables follow.
    σ_aa = τ_aa − τ_free,free in closed form.
    """

    free: str = "n"
    stress_axes: dict[str, str] = {}
    axes: tuple[str, str] | None = None
    roles: tuple[str, str] = ("", "")

    def __init_subclass__(cls, **kw):
        super().__init_subclass__(**kw)
        if cls.axes is not None and "axes" in cls.__dict__:
            loaded, second = cls.axes
            cls.free = ({"f", "c", "n"} - {loaded, second}).pop()
            cls.stress_axes = {"stress": loaded, "stress_2": second}
            cls.observables = tuple(normal_stress(k, a, r) for (k, a), r in zip(cls.stress_axes.items(), cls.roles))

    def log_stretches(self, strain: np.ndarray, strain_2: np.ndarray | None) -> tuple[np.ndarray, ...]:
        raise NotImplementedError

    def prescribed_log_stretch(self, axis, strain, strain_2):
        if axis == self.free:
            return super().prescribed_log_stretch(axis, strain, strain_2)
        return self.log_stretches(strain, strain_2)[AXIS[axis]]

    def solve(self, energy, params, strain, strain_2=None):
        s, s2 = self.controls(strain, strain_2)
        e = self.log_stretches(s, s2)
        tau, _ = energy.principal(params, e)
        shape = full_shape(params, s.size)
        p = tau[AXIS[self.free]]
        return {name: fill(tau[AXIS[axis]] - p, shape) for name, axis in self.stress_axes.items()}


class Planar(PrescribedStretch):
    """Planar (pure-shear) test, ``axes = (loaded, held)``: stretch λ along ``loaded``, ``held`` kept at
    1, the third face traction-free (its stretch 1/λ).  ``stress`` = σ along the load, ``stress_2`` = σ on the
    held faces.  At strain < 0: semi-confined compression."""

    roles = ("along the load", "on the held faces")

    def log_stretches(self, strain, strain_2):
        e = np.log1p(strain)
        out = [np.zeros_like(e)] * 3
        out[AXIS[self.axes[0]]], out[AXIS[self.free]] = e, -e
        return tuple(out)


class Biaxial(PrescribedStretch):
    """Biaxial test, ``axes = (first, second)``: λ1 = 1 + strain along the first, λ2 = 1 + strain_2 along
    the second (λ1 when strain_2 is absent: equibiaxial), the third face traction-free
    (its stretch 1/(λ1·λ2)).  ``stress`` = σ along the first axis, ``stress_2`` = σ along the second."""

    roles = ("along strain", "along strain_2")
    inputs = ("strain", "strain_2")

    def log_stretches(self, strain, strain_2):
        out = [None] * 3
        e1, e2 = np.log1p(strain), np.log1p(strain_2)
        out[AXIS[self.axes[0]]], out[AXIS[self.axes[1]]], out[AXIS[self.free]] = e1, e2, -(e1 + e2)
        return tuple(out)


class SimpleShear(LoadCase):
    """Simple shear F = I + γ·e_X⊗e_Y (displacement along X, varying along Y), J = 1.

    C − I has D_XY = γ and D_YY = γ², and σ_XY = τ_XY = S_XY + γ·S_YY does not depend on the
    pressure.  ``strain`` is γ (any sign: σ_XY is odd in γ).
    """

    control = "shear"
    X: str = "f"
    Y: str = "c"

    def __init_subclass__(cls, **kw):
        super().__init_subclass__(**kw)
        cls.observables = (Observable("stress", "MPa", f"Cauchy shear stress sigma_{cls.X}{cls.Y}"),)

    def solve(self, energy, params, strain, strain_2=None):
        g, _ = self.controls(strain, strain_2)
        x, y = AXIS[self.X], AXIS[self.Y]
        S = energy.pk2(params, Sym.from_components({(x, y): g, (y, y): g * g}))
        return {"stress": fill(S.get(x, y) + g * S.get(y, y), full_shape(params, g.size))}
