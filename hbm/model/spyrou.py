"""The Spyrou–Agoras–Danas Voigt model of passive skeletal muscle in uniaxial tension.

Uniaxial, incompressible tension along the fibers (thesis Chapter 1; DESIGN.md §1).  With
λ = 1 + ε and c = VOLF the Cauchy stress along the fibers is the sum of three effects::

    matrix    k_iso · G · (λ² − 1/λ),        G = c·GF + (1 − c)·GM
    fibers    λ · c · P1 · ⟨ε − EOPT⟩₊
    collagen  λ · (1 − c) · T1 · (exp(T2·(λH − 1)) − 1)  for λH > 1, else 0
              λH = sqrt(cos²θ·λ² + sin²θ/λ),  θ = THETA (degrees)

``k_iso = 1`` is the traction-free uniaxial result (σ33 − σ11 of the neo-Hookean phase);
``k_iso = 2/3`` is the thesis read literally (deviatoric 33 component only).  Neither has been
checked against the 2017 paper of Spyrou et al.; the default is 1.

Only G, c·P1 and (1 − c)·T1 are learnable from a uniaxial curve (with EOPT, T2, THETA): the
VOLF–T1 "manifold" of the thesis is the line (1 − c)·T1 = const.
"""

from __future__ import annotations

from typing import Mapping

import numpy as np

from .core import Effect, Model, Parameter, State

# exp(709) is the largest finite double; T2 up to 200 with λ up to 3 stays far below, but a
# user can widen the box, so the exponent is clipped to keep the model finite everywhere.
_EXP_CLIP = 700.0

VOLF = Parameter("VOLF", 0.5, 0.99, "-", "fiber volume fraction c")
EOPT = Parameter("EOPT", 0.0, 0.2, "-", "fiber strain at which passive fiber stress starts")
P1 = Parameter("P1", 1e-4, 0.5, "MPa", "passive fiber modulus (nominal stress per unit strain)")
T1 = Parameter("T1", 0.0, 20.0, "MPa", "collagen stress scale of the ECM")
T2 = Parameter("T2", 0.0, 200.0, "-", "collagen exponential stiffening rate")
THETA = Parameter("THETA", 55.0, 60.0, "deg", "helix angle of ECM collagen to the fibers")
GF = Parameter("GF", 1e-4, 0.1, "MPa", "shear modulus of the fiber phase")
GM = Parameter("GM", 1e-4, 0.1, "MPa", "shear modulus of the ECM phase")

BASE_PARAMETERS = (VOLF, EOPT, P1, T1, T2, THETA, GF, GM)


def collagen_onset_stretch(theta_deg):
    """Stretch λ* at which the helical collagen starts to carry load, λH(λ*) = 1.

    λ* = (−1 + sqrt(1 + 4·tan²θ)) / 2 (the nontrivial root of cos²θ·λ³ − λ + sin²θ = 0).
    """
    t = np.tan(np.deg2rad(theta_deg))
    return (-1.0 + np.sqrt(1.0 + 4.0 * t * t)) / 2.0


def helical_stretch(lam, theta_deg):
    """Stretch of the helical collagen, λH = sqrt(cos²θ·λ² + sin²θ/λ)."""
    th = np.deg2rad(theta_deg)
    c2 = np.cos(th) ** 2
    return np.sqrt(c2 * lam * lam + (1.0 - c2) / lam)


class NeoHookeanMatrix(Effect):
    """Isotropic neo-Hookean part of both phases: k_iso·(c·GF + (1−c)·GM)·(λ² − 1/λ)."""

    name = "matrix"
    stage = "elastic"
    parameters = (VOLF, GF, GM)
    description = "neo-Hookean matrix of fibers and ECM (Voigt average of the shear moduli)"

    def __init__(self, iso_factor: float = 1.0) -> None:
        self.iso_factor = float(iso_factor)

    def stress(self, state: State, p: Mapping[str, np.ndarray]) -> np.ndarray:
        c = p["VOLF"]
        return self.iso_factor * (c * p["GF"] + (1.0 - c) * p["GM"]) * state.neo_hookean

    def stress_jacobian(self, state, p):
        c, f = p["VOLF"], self.iso_factor * state.neo_hookean
        return {"VOLF": (p["GF"] - p["GM"]) * f, "GF": c * f, "GM": (1.0 - c) * f}


class PassiveFibers(Effect):
    """Linear passive fibers: λ·c·P1·⟨ε − EOPT⟩₊ (thesis eq. 1.11 with eqs. 1.7, 1.9)."""

    name = "fibers"
    stage = "elastic"
    parameters = (VOLF, EOPT, P1)
    description = "linear passive myofibers beyond the optimal strain EOPT"

    def stress(self, state, p):
        f = state.eps - p["EOPT"]
        np.maximum(f, 0.0, out=f)
        f *= p["VOLF"] * p["P1"]
        f *= state.lam
        return f

    def stress_jacobian(self, state, p):
        lam, c, p1 = state.lam, p["VOLF"], p["P1"]
        ramp = np.maximum(state.eps - p["EOPT"], 0.0)
        on = (state.eps > p["EOPT"]).astype(float)
        return {"VOLF": lam * p1 * ramp, "P1": lam * c * ramp, "EOPT": -lam * c * p1 * on}


class HelicalCollagen(Effect):
    """ECM collagen wound at THETA: λ·(1−c)·T1·(exp(T2·(λH−1)) − 1) for λH > 1 (eqs. 1.12–1.14)."""

    name = "collagen"
    stage = "elastic"
    parameters = (VOLF, T1, T2, THETA)
    description = "exponential helical collagen of the ECM, engaged beyond the onset stretch"

    @staticmethod
    def _parts(state, p):
        lam = state.lam
        lh = helical_stretch(lam, p["THETA"])
        x = np.maximum(lh - 1.0, 0.0)  # zero where the collagen is slack
        e = np.exp(np.minimum(p["T2"] * x, _EXP_CLIP))
        return lam, lh, x, e

    def stress(self, state, p):
        # hot path (called for every particle of every MCMC step): in-place, expm1,
        # λH² = cos²θ·(λ² − 1/λ) + 1/λ reuses the cached neo-Hookean factor
        c2 = np.cos(np.deg2rad(p["THETA"])) ** 2
        x = c2 * state.neo_hookean
        x += 1.0 / state.lam
        np.sqrt(x, out=x)
        x -= 1.0
        np.maximum(x, 0.0, out=x)
        x *= p["T2"]
        np.minimum(x, _EXP_CLIP, out=x)
        np.expm1(x, out=x)
        x *= (1.0 - p["VOLF"]) * p["T1"]
        x *= state.lam
        return x

    def stress_jacobian(self, state, p):
        lam, lh, x, e = self._parts(state, p)
        c, t1, t2 = p["VOLF"], p["T1"], p["T2"]
        th = np.deg2rad(p["THETA"])
        on = (x > 0).astype(float)
        # dλH/dθ (per degree) = sinθ·cosθ·(1/λ − λ²)/λH · π/180
        dlh = np.sin(th) * np.cos(th) * (1.0 / lam - lam * lam) / lh * (np.pi / 180.0)
        return {
            "VOLF": -lam * t1 * (e - 1.0),
            "T1": lam * (1.0 - c) * (e - 1.0),
            "T2": lam * (1.0 - c) * t1 * e * x,
            "THETA": lam * (1.0 - c) * t1 * e * t2 * dlh * on,
        }


def spyrou_model(iso_factor: float = 1.0) -> Model:
    """The base Spyrou–Agoras–Danas model with its 8 parameters.

    Parameters
    ----------
    iso_factor : float
        k_iso multiplying the neo-Hookean term: 1 (traction-free uniaxial, default) or 2/3
        (the thesis's deviatoric 33 component).

    Returns
    -------
    Model
        Parameters ``("VOLF","EOPT","P1","T1","T2","THETA","GF","GM")`` with the prior box of
        thesis Table 1.1 (T1 in [0, 20], T2 in [0, 200]).
    """
    effects = (NeoHookeanMatrix(iso_factor), PassiveFibers(), HelicalCollagen())
    name = "spyrou" if iso_factor == 1.0 else f"spyrou(k_iso={iso_factor:.4g})"
    return Model(effects, parameters=BASE_PARAMETERS, name=name)


#: Effect ids of the base model, in model order (the detective's removal test and the organ
#: report ask for them by these names).
BASE_EFFECTS: tuple[str, ...] = ("matrix", "fibers", "collagen")

#: The combinations a uniaxial curve identifies (DESIGN.md §1): G = c·GF + (1−c)·GM, A_f = c·P1,
#: A_m = (1−c)·T1 -- the names used in every table, figure and result file.
COMBINATIONS: tuple[str, ...] = ("G", "VOLF*P1", "(1-VOLF)*T1")

#: Shape parameters that a curve informs directly, reported beside the combinations.
SHAPE_PARAMETERS: tuple[str, ...] = ("T2", "THETA", "EOPT")


def identifiable_combinations(names, theta) -> dict[str, np.ndarray]:
    """G = c·GF + (1−c)·GM, A_f = c·P1 and A_m = (1−c)·T1 from a theta array (..., n_params)."""
    theta = np.asarray(theta, dtype=float)
    col = {n: theta[..., i] for i, n in enumerate(names)}
    c = col["VOLF"]
    return {
        "G": c * col["GF"] + (1 - c) * col["GM"],
        "VOLF*P1": c * col["P1"],
        "(1-VOLF)*T1": (1 - c) * col["T1"],
    }
