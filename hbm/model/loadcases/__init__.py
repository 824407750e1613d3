"""Loading modes of one tissue: a registry of load cases, each solving the 3-D model (DESIGN.md §8).

Frame: f = fibre axis, c = cross-fibre in the specimen plane, n = the third direction.  Every mode is
one small class in one file, registered under the issue's vocabulary:

==================  =============================================================  ====================
mode (aliases)      deformation, free faces                                        observables
==================  =============================================================  ====================
``uniaxial_f``      load along f; c, n free: F = diag(λ, λ^-1/2, λ^-1/2)            stress = σ_ff,
(uniaxial)                                                                         strain_c, strain_n
``uniaxial_c``      load along c; f, n free: F = diag(λf, λ, 1/(λλf)), λf solved   stress = σ_cc,
(transverse,cross)                                                                 strain_f, strain_n
``planar_f_hold_c`` F = diag(λ, 1, 1/λ), n free                                    σ_ff, stress_2 = σ_cc
``planar_c_hold_f`` F = diag(1, λ, 1/λ), n free                                    σ_cc, stress_2 = σ_ff
``planar_c_hold_n`` F = diag(1/λ, λ, 1), f free                                    σ_cc, stress_2 = σ_nn
``biaxial_fc``      F = diag(λ1, λ2, 1/(λ1λ2)), n free (λ2 from strain_2)          σ_ff, stress_2 = σ_cc
``biaxial_cn``      F = diag(1/(λ1λ2), λ1, λ2), f free                             σ_cc, stress_2 = σ_nn
``shear_fc`` (fs)   F = I + γ·e_f⊗e_c                                              stress = σ_fc
``shear_cf`` (sf)   F = I + γ·e_c⊗e_f                                              stress = σ_cf
``shear_cn`` (sn)   F = I + γ·e_c⊗e_n                                              stress = σ_cn
==================  =============================================================  ====================

Stresses are Cauchy (MPa; :meth:`LoadCase.load_stretch` converts to nominal P = σ/λ), strains
engineering, negative strain is compression (the semi-confined modes I–III are the planar modes at
strain < 0).  :func:`predict_observables` is the one entry point; :func:`check_mode` refuses the thesis
form outside along-fibre tension.
"""

from __future__ import annotations

from typing import Mapping

import numpy as np

from ...errors import HbmError
from ..energy3d import Energy3D
from ..spyrou import model_form
from .base import LoadCase, Observable, PrescribedStretch, SimpleShear
from .registry import ALIASES, DEFAULT_LOAD_CASE, LOAD_CASES, get_load_case, is_load_case, register_load_case
# the built-in modes register themselves on import, in the order of the table above
from .uniaxial_f import UniaxialF
from .uniaxial_c import UniaxialC
from .planar_f_hold_c import PlanarFHoldC
from .planar_c_hold_f import PlanarCHoldF
from .planar_c_hold_n import PlanarCHoldN
from .biaxial_fc import BiaxialFC
from .biaxial_cn import BiaxialCN
from .shear_fc import ShearFC
from .shear_cf import ShearCF
from .shear_cn import ShearCN

__all__ = ["LoadCase", "Observable", "PrescribedStretch", "SimpleShear", "ALIASES", "DEFAULT_LOAD_CASE",
           "LOAD_CASES", "get_load_case", "is_load_case", "register_load_case", "check_mode", "predict_observables",
           "THESIS_FORM_REASON", "UniaxialF", "UniaxialC", "PlanarFHoldC", "PlanarCHoldF", "PlanarCHoldN",
           "BiaxialFC", "BiaxialCN", "ShearFC", "ShearCF", "ShearCN"]

#: why the thesis form is evaluated only along the fibres (DESIGN.md §8, "axial")
THESIS_FORM_REASON = (
    "the thesis form applies the collagen stress along the fibres only; read in 3-D it is not convex (its "
    "compressive tangent 3*mu + (1-c)*T1*T2*(3cos^2(theta) - 1)/2 is negative for all six shipped specimens) and "
    "has no traction-free state in cross-fibre tension, so it is defined in along-fibre tension only")


def check_mode(model_or_form, mode) -> None:
    """Refuse a (model form, mode) pair hbm cannot evaluate.

    Parameters
    ----------
    model_or_form : Model, Energy3D or str
        A model built on the Spyrou base, an energy, or the form name (``"thesis"``, ``"energy"``).
    mode : str or LoadCase
        A mode name or alias.

    Raises
    ------
    HbmError
        For an unknown mode, a model without the Spyrou collagen, or the thesis form in any mode but
        ``uniaxial_f`` (the message gives the reason and the way out, ``--form energy``).
    """
    case = get_load_case(mode)
    if isinstance(model_or_form, str):
        form = model_or_form
    elif isinstance(model_or_form, Energy3D):
        form = model_or_form.form
    else:
        form = model_form(model_or_form)
    if form is None:
        raise HbmError(f"mode {case.name}: the model has no Spyrou collagen, so hbm has no 3-D energy for it")
    if form == "thesis" and case.name != DEFAULT_LOAD_CASE:
        raise HbmError(f"mode {case.name} needs the energy form (--form energy): {THESIS_FORM_REASON}")


def predict_observables(energy: Energy3D, load_case, theta_mapping: Mapping[str, np.ndarray], strain,
                        strain_2=None) -> dict[str, np.ndarray]:
    """The model's prediction of every observable of one test.

    Parameters
    ----------
    energy : Energy3D
        The material (:func:`hbm.model.energy3d.energy_from_model` builds it from a model).
    load_case : str or LoadCase
        The mode (name or alias).
    theta_mapping : mapping
        Parameter name -> array ``(..., 1)`` (as :meth:`hbm.Model._params` builds) or scalar.
    strain : array_like (n_points,)
        The control: engineering strain along the load, or γ in simple shear.
    strain_2 : array_like (n_points,), optional
        The second control of biaxial modes (default: ``strain``).

    Returns
    -------
    dict
        Observable name -> array (..., n_points): Cauchy stresses (MPa), engineering strains.

    Raises
    ------
    HbmError
        For an unknown mode, the thesis form outside ``uniaxial_f``, a stretch ≤ 0, a non-finite
        control, or a lateral problem without a solution.
    """
    case = get_load_case(load_case)
    check_mode(energy, case)
    params = {k: np.asarray(v, dtype=float) for k, v in theta_mapping.items()}
    return case.solve(energy, params, strain, strain_2)
