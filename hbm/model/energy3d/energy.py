"""The Spyrou–Agoras–Danas strain energy in 3-D (DESIGN.md §8).

Fibre axis a0 = e1 = f, c = e2, n = e3; c = VOLF; μ = k_iso·G, G = c·GF + (1 − c)·GM; incompressible
(J = 1 by a pressure p); Voigt: one F for both phases::

    W(C) = μ/2·(I1 − 3) + c·P1/2·⟨λf − 1 − EOPT⟩₊² + (1 − c)·W_coll(C),     λf² = a0·C·a0

with W_coll the collagen's 3-D reading (``collagen3d``: :mod:`.cone` or :mod:`.gst`; the thesis form
uses :mod:`.axial`).  Stresses are analytic: S = 2·∂W/∂C, Kirchhoff τ = F·S·Fᵀ, Cauchy σ = τ − p·I
with p from the free face of each load case (:mod:`hbm.model.loadcases`).
"""

from __future__ import annotations

from typing import Mapping

import numpy as np

from ...errors import HbmError, SettingError
from ...runtime.validation import check_positive
from ..spec import register_energy
from ..spyrou import FORMS, NeoHookeanMatrix, model_form
from .axial import AxialCollagen
from .base import DEFAULT_COLLAGEN3D, CollagenReading, Sym, get_collagen_reading, is_zero


#: what the compiled kernel hard-codes: a subclass replacing one of these runs the numpy path
_KERNEL_LAWS = ("shear_modulus", "_fibre_energy", "_fibre_force", "_fibre_stiffness", "principal_numpy")
_KERNEL_READING_LAWS = ("rule", "principal", "_nodes", "segment_energy", "segment_force", "segment_stiffness")


class Energy3D:
    """The base model's strain energy with one collagen reading: W, S, principal τ and its tangent.

    Parameters
    ----------
    iso_factor : float
        k_iso: μ = k_iso·G (1 = traction-free uniaxial, 2/3 = the thesis's deviatoric reading).
    form : {"thesis", "energy"}
        The collagen form of the 1-D model (:func:`hbm.model.spyrou_model`).  ``"thesis"`` uses the
        axial reading, meaningful in along-fibre tension only.
    collagen3d : str, CollagenReading or None
        The energy form's 3-D reading of the collagen (a key of
        :data:`~hbm.model.energy3d.COLLAGEN_READINGS`: ``"cone"`` (default) or ``"gst"``, or a reading
        instance such as :class:`~hbm.model.energy3d.ConeFamilies` to measure a discretised card).  Not
        allowed with the thesis form, which has only its own reading.

    Attributes
    ----------
    iso_factor, form : as given
    collagen3d : str
        The reading in use (``"axial"`` for the thesis form): record it with any result.
    collagen : CollagenReading

    Notes
    -----
    Parameters are passed as the mapping ``name -> array`` of :meth:`hbm.Model._params` (``(..., 1)``),
    broadcast against the kinematic arrays (``(..., n_points)``); every method is vectorised over both.
    """

    def __init__(self, iso_factor: float = 1.0, form: str = "energy", collagen3d: str | None = None) -> None:
        self.iso_factor = check_positive(iso_factor, "iso_factor")
        if form not in FORMS:
            raise SettingError(f"form: expected one of {', '.join(FORMS)}, got {form!r}")
        self.form = form
        if form == "thesis":
            if collagen3d is not None:
                raise SettingError(f"collagen3d={collagen3d!r}: the 3-D reading of the collagen is an option of "
                                   "the energy form (--form energy); the thesis form has only its own, along the "
                                   "fibres")
            self.collagen = AxialCollagen()
        elif isinstance(collagen3d, CollagenReading):
            self.collagen = collagen3d
        else:
            self.collagen = get_collagen_reading(DEFAULT_COLLAGEN3D if collagen3d is None else collagen3d)
        self.collagen3d = self.collagen.name

    @property
    def kernel(self) -> int | None:
        """The compiled diagonal kernel's code for this reading (``kernel_code`` of its class, :mod:`.diagonal`),
        or ``None`` where the numpy path runs: a reading without one, or a subclass (of this class or of the
        reading) that replaces a law the kernel hard-codes (the fibres', the matrix's, the segments' or the
        quadrature)."""
        kind = type(self.collagen)
        owner = next((c for c in kind.__mro__ if "kernel_code" in c.__dict__), None)
        if owner is None or owner.kernel_code is None:
            return None
        if any(getattr(type(self), m) is not getattr(Energy3D, m) for m in _KERNEL_LAWS):
            return None
        if any(getattr(kind, m) is not getattr(owner, m) for m in _KERNEL_READING_LAWS):
            return None
        return owner.kernel_code

    @property
    def label(self) -> str:
        """``spyrou(form=..., collagen3d=...[, k_iso=...])``: the energy's identity for result keys."""
        k = "" if self.iso_factor == 1.0 else f", k_iso={self.iso_factor:.4g}"
        return f"spyrou(form={self.form}, collagen3d={self.collagen3d}{k})"

    def __repr__(self) -> str:
        return f"<Energy3D {self.label}>"

    # -- the constituents ---------------------------------------------------------------------
    def shear_modulus(self, p: Mapping[str, np.ndarray]) -> np.ndarray:
        """μ = k_iso·(c·GF + (1 − c)·GM) (MPa)."""
        c = p["VOLF"]
        return self.iso_factor * (c * p["GF"] + (1.0 - c) * p["GM"])

    @staticmethod
    def _fibre_energy(p, lf_minus_1):
        """W_f = c·P1/2·⟨λf − 1 − EOPT⟩₊²."""
        fib = np.maximum(lf_minus_1 - p["EOPT"], 0.0)
        return 0.5 * p["VOLF"] * p["P1"] * fib * fib

    @staticmethod
    def _fibre_force(p, lf_minus_1):
        """dW_f/dλf = c·P1·⟨λf − 1 − EOPT⟩₊ (the fibres' nominal stress times c)."""
        return p["VOLF"] * p["P1"] * np.maximum(lf_minus_1 - p["EOPT"], 0.0)

    @staticmethod
    def _fibre_stiffness(p, lf_minus_1):
        """d²W_f/dλf² = c·P1 where the fibres are taut (a subclass with another fibre law, such as an FE
        card's, replaces the three ``_fibre_*`` methods)."""
        return p["VOLF"] * p["P1"] * (lf_minus_1 > p["EOPT"])

    # -- energy and stresses --------------------------------------------------------------------
    def energy(self, p: Mapping[str, np.ndarray], D: Sym) -> np.ndarray:
        """W (MPa, per unit reference volume) at D = C − I (isochoric states are the user's to give).

        Raises
        ------
        HbmError
            For the thesis form, whose collagen is defined by a stress (:mod:`.axial`).
        """
        lf = np.sqrt(1.0 + np.asarray(D.ff, dtype=float))
        c = p["VOLF"]
        trace = D.ff + D.cc + D.nn
        return (0.5 * self.shear_modulus(p) * trace + self._fibre_energy(p, lf - 1.0)
                + (1.0 - c) * self.collagen.energy(p, D))

    def pk2(self, p: Mapping[str, np.ndarray], D: Sym) -> Sym:
        """Second Piola–Kirchhoff stress S = 2·∂W/∂C (MPa) at D = C − I, without the pressure."""
        d_f = np.asarray(D.ff, dtype=float)
        lf = np.sqrt(1.0 + d_f)
        mu = self.shear_modulus(p)
        coll = self.collagen.pk2(p, D)
        c = p["VOLF"]
        fibre = self._fibre_force(p, d_f / (lf + 1.0)) / lf
        out = []
        for k, v in enumerate(coll):
            part = 0.0 if is_zero(v) else (1.0 - c) * v
            if k < 3:
                part = part + mu
            if k == 0:
                part = part + fibre
            out.append(part)
        return Sym(*out)

    def kirchhoff(self, p: Mapping[str, np.ndarray], F: np.ndarray) -> np.ndarray:
        """Kirchhoff stress τ = F·S·Fᵀ (MPa) at any F (..., 3, 3) in the fibre frame, without the pressure
        (for an incompressible F the Cauchy stress is τ − p·I)."""
        F = np.asarray(F, dtype=float)
        D = Sym.from_matrix(np.swapaxes(F, -1, -2) @ F - np.eye(3))
        S = self.pk2(p, D).matrix()
        return F @ S @ np.swapaxes(F, -1, -2)

    def principal(self, p: Mapping[str, np.ndarray], e: tuple, tangent: bool = False):
        """Principal Kirchhoff stresses at F = diag(λf, λc, λn), up to an isotropic part.

        Parameters
        ----------
        p : mapping
            Parameters (name -> array).
        e : tuple of 3 arrays
            Log-stretches (ln λf, ln λc, ln λn).
        tangent : bool
            Also return c_ij = ∂τ_i/∂ln λ_j.

        Returns
        -------
        tau : tuple of 3 arrays
            τ_i − μ (MPa): the neo-Hookean's isotropic μ·I is left out, because the pressure of the
            incompressible solid absorbs it; every difference τ_i − τ_j, hence every Cauchy stress
            of a load case, is exact and free of that cancellation at small strains.
        c : tuple of tuples or None
            The symmetric tangent (MPa), ``None`` unless ``tangent``.

        Notes
        -----
        The cone and gst readings of this class run the compiled kernel of :mod:`.diagonal`;
        :meth:`principal_numpy` is the reference (and the path of every other reading or subclass).
        """
        code = self.kernel
        if code is not None:
            from .diagonal import principal_diagonal  # numba loads on first use, not with `hbm data check`
            return principal_diagonal(self, code, p, e, tangent)
        return self.principal_numpy(p, e, tangent)

    def principal_numpy(self, p: Mapping[str, np.ndarray], e: tuple, tangent: bool = False):
        """:meth:`principal` by numpy over the reading's quadrature (the reference of the compiled kernel)."""
        e = tuple(np.asarray(ei, dtype=float) for ei in e)
        d = tuple(np.expm1(2.0 * ei) for ei in e)
        mu = self.shear_modulus(p)
        ct, cc = self.collagen.principal(p, e, tangent)
        c = p["VOLF"]
        fibre = np.exp(e[0]) * self._fibre_force(p, np.expm1(e[0]))
        tau = (mu * d[0] + fibre + (1.0 - c) * ct[0], mu * d[1] + (1.0 - c) * ct[1], mu * d[2] + (1.0 - c) * ct[2])
        if not tangent:
            return tau, None
        lf, ones = np.exp(e[0]), np.ones_like(d[0])
        # d(λf·W_f')/d ln λf = λf·W_f' + λf²·W_f''
        fibre_k = fibre + lf * lf * self._fibre_stiffness(p, np.expm1(e[0]))
        rows = []
        for i in range(3):
            row = []
            for j in range(3):
                v = (1.0 - c) * cc[i][j]
                if i == j:
                    v = v + 2.0 * mu * (1.0 + d[i]) * ones
                if i == j == 0:
                    v = v + fibre_k
                row.append(v)
            rows.append(tuple(row))
        return tau, tuple(rows)


def energy_from_model(model, collagen3d: str | None = None) -> Energy3D:
    """The 3-D energy of a model built on the Spyrou base (:func:`hbm.model.spyrou_model`).

    Parameters
    ----------
    model : Model
        Its collagen effect gives the form, its matrix effect the iso factor.  Effects beyond the
        base model are not part of the energy (the caller applies them per test where they are
        defined in 3-D).
    collagen3d : str, optional
        The energy form's collagen reading (default ``"cone"``); not allowed with the thesis form.

    Returns
    -------
    Energy3D

    Raises
    ------
    HbmError
        When the model has no Spyrou collagen or matrix.
    """
    form = model_form(model)
    matrix = [e for e in getattr(model, "effects", ()) if isinstance(e, NeoHookeanMatrix)]
    if form is None or not matrix:
        raise HbmError(f"model {getattr(model, 'name', model)!r}: a 3-D energy exists only for the Spyrou base "
                       "model (its matrix and collagen effects)")
    return Energy3D(matrix[0].iso_factor, form, collagen3d)


def _spyrou_principal_energy(p, k_iso: float, l1, l2, l3) -> np.ndarray:
    """The Spyrou base's export energy (:meth:`hbm.model.spyrou.SpyrouExport.energy`): the energy form
    with the cone reading at principal stretches (m,), parameter columns (n, 1) -> (n, m)."""
    D = Sym(*(np.asarray(v, float) ** 2 - 1.0 for v in (l1, l2, l3)))
    return Energy3D(k_iso, "energy", "cone").energy(p, D)


register_energy("spyrou", _spyrou_principal_energy)
