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

The energy-consistent form (``spyrou_model(form="energy")``)
-------------------------------------------------------------
The thesis (eqs. 1.7, 1.8, 1.12, 1.14) applies the collagen's nominal stress, a function of the
helix stretch λH, along the fiber axis, multiplied by λ.  For θ above the magic angle
(54.7°, so everywhere in the box [55°, 60°]) λH > 1 also under axial *compression* (the
lateral expansion λ^−1/2 stretches the helix), and the thesis form then returns a tensile
stress: +0.53 MPa from the collagen at ε = −0.3 with VOLF = 0.9, T1 = 5, T2 = 10, THETA = 60.

The energy form derives the same constituents from one strain energy per unit reference
volume, incompressible, with traction-free lateral faces (transverse isotropy, lateral
stretches λ^−1/2)::

    W(λ) = k_iso·G/2·(λ² + 2/λ − 3)                       neo-Hookean matrix
         + c·P1/2·⟨λ − 1 − EOPT⟩₊²                         fibers: dW_f/dλ = P1·⟨ε − EOPT⟩₊
         + (1 − c)·W_c(λH(λ))                              helical collagen
    W_c(λH) = T1·(exp(T2·x) − 1 − T2·x)/T2,  x = ⟨λH − 1⟩₊,  so dW_c/dλH = T1·(exp(T2·x) − 1)

(W_c → T1·T2·x²/2 as T2 → 0, and W_c = 0 at T2 = 0, where the thesis collagen stress vanishes
too; :func:`collagen_energy` uses the series there).  The uniaxial Cauchy stress is
σ = λ·dW/dλ, with the chain rule through the helix stretch::

    σ = k_iso·G·(λ² − 1/λ) + λ·c·P1·⟨ε − EOPT⟩₊
      + λ·(1 − c)·T1·(exp(T2·x) − 1)·λH'(λ),     λH'(λ) = (cos²θ·λ − sin²θ/(2λ²))/λH

Matrix and fibers are unchanged; the collagen term gains the factor λH'(λ) (the projection of
the helix's stretch rate on the axis; the same σ11 − σ22 follows from the fibril's Cauchy
stress λH·W_c'·a⊗a with the helix averaged around the fiber).  Consequences:

* compression (λ < 1): wherever the collagen is taut, cos²θ·λ(λ + 1) < sin²θ, and since
  λ² ≤ (λ + 1)/2 for λ ≤ 1 this gives cos²θ·λ³ < sin²θ/2, i.e. λH' < 0.  The collagen then
  resists the lateral expansion and adds a *compressive* stress; with the matrix
  (G·(λ² − 1/λ) < 0) and slack fibers, σ < 0 for every ε < 0 when G > 0, and σ(0) = 0 exactly
  (λH − 1 is computed as ε·(cos²θ·(λ + 1) − sin²θ/λ)/(λH + 1), free of cancellation).
* tension (λ > λ*): 0 < λH' < cosθ, so the energy-form collagen stress is at most cosθ
  (0.57 at 55°, 0.5 at 60°) of the thesis value, and ~0.1 just past λ* at 60°.  Fits of the two
  forms to the same tension curve give different T1, T2 (the identifiable (1 − c)·T1 is not
  comparable between forms).

Difference in tension, |σ_energy − σ_thesis| / σ_thesis, at each specimen's generating parameters
(data/specimens/*.csv) over its strain range [0, ε_max].  Both forms coincide below the collagen
onset ε* = λ* − 1 (0.303 at 60°); beyond it the difference grows with the collagen's share of the
stress, so it is largest at ε_max::

    specimen          THETA    T2   ε_max   max rel. diff (at ε_max)   collagen share at ε_max
    calvo2010_rat1    60      9.3   0.44    0.35                       0.42
    calvo2010_rat2    60     16     0.42    0.44                       0.52
    calvo2010_rat3    60      2.5   0.40    0.63                       0.74
    calvo2010_rat4    60     14     0.43    0.33                       0.40
    calvo2010_rat5    60     24     0.45    0.40                       0.49
    hawkins1994_rat   59.8  162     0.42    0.75                       0.91

Over the prior box (20,000 uniform draws; ε* runs from 0.013 at 55° to 0.303 at 60°)::

    ε         0.02   0.05   0.1    0.2    0.3    0.4    0.5    0.7    1.0
    median    0      0      0      0.78   0.80   0.77   0.73   0.67   0.60
    90 %      0      0.69   0.91   0.88   0.85   0.82   0.78   0.71   0.64
    max       0.98   0.97   0.94   0.91   0.89   0.84   0.80   0.73   0.65

The thesis form is the one the thesis's results were obtained with and stays the default; the
energy form is the one to use for data with compressive strains (:func:`compression_check`).
"""

from __future__ import annotations

import math

from typing import Mapping

import numpy as np

from ..errors import HbmError
from ..settings.rules import check_positive
from .core import Effect, Loading, Model, Parameter, State
from .spec import Combination, Constituents, Manifold, MixtureRoles, ModelSpec, principal_energy, register_base

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
#: what the physics allows, whatever box a user chooses: a volume fraction in [0, 1], an angle
#: between 0 and 90 degrees to the fibres, non-negative moduli, rates and scales, a fibre strain
#: above -1 (a stretch above 0)
PHYSICAL_RANGE = {"VOLF": (0.0, 1.0), "EOPT": (-1.0, math.inf), "P1": (0.0, math.inf), "T1": (0.0, math.inf),
                  "T2": (0.0, math.inf), "THETA": (0.0, 90.0), "GF": (0.0, math.inf), "GM": (0.0, math.inf)}


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


def unit_contribution(effect: Effect, state: State, p: Mapping[str, np.ndarray], **values: float) -> np.ndarray:
    """``effect.stress`` with some parameters replaced by constants: the unit-amplitude curve
    of a linear structure through the effect's own (hot-path) stress, e.g. the collagen at
    VOLF = 0, T1 = 1 is λ·(exp(T2·(λH − 1)) − 1)."""
    q = dict(p)
    for name, v in values.items():
        q[name] = np.full_like(np.asarray(p[name], dtype=float), v)
    return effect.stress(state, q)


class NeoHookeanMatrix(Effect):
    """Isotropic neo-Hookean part of both phases: k_iso·(c·GF + (1−c)·GM)·(λ² − 1/λ)."""

    name = "matrix"
    stage = "elastic"
    parameters = (VOLF, GF, GM)
    description = "neo-Hookean matrix of fibers and ECM (Voigt average of the shear moduli)"

    linear_parameters = ("GF", "GM")

    def __init__(self, iso_factor: float = 1.0) -> None:
        self.iso_factor = float(iso_factor)

    def amplitude_coefficients(self, p):
        return {"GF": ("G", p["VOLF"]), "GM": ("G", 1.0 - p["VOLF"])}

    def unit_stress(self, state, p):
        return {"G": unit_contribution(self, state, p, GF=1.0, GM=1.0)}

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
    linear_parameters = ("P1",)

    def amplitude_coefficients(self, p):
        return {"P1": ("VOLF*P1", p["VOLF"])}

    def unit_stress(self, state, p):
        return {"VOLF*P1": unit_contribution(self, state, p, VOLF=1.0, P1=1.0)}

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


class CollagenAmplitude:
    """Linear structure of the collagen and of its corrections (recruitment, dispersion): each
    contribution is (1 − c)·T1 times a shape, so T1 feeds the column (1-VOLF)*T1 with weight 1 − c
    and the unit curve is the effect's own stress at VOLF = 0, T1 = 1.  Mix in before
    :class:`~hbm.model.core.Effect`."""

    linear_parameters = ("T1",)

    def amplitude_coefficients(self, p):
        return {"T1": ("(1-VOLF)*T1", 1.0 - p["VOLF"])}

    def unit_stress(self, state, p):
        return {"(1-VOLF)*T1": unit_contribution(self, state, p, VOLF=0.0, T1=1.0)}


class HelicalCollagen(CollagenAmplitude, Effect):
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


def collagen_energy(lh, t1, t2):
    """Strain energy of the helical collagen per unit volume, W_c(λH) (MPa).

    W_c = T1·(exp(T2·x) − 1 − T2·x)/T2 with x = ⟨λH − 1⟩₊, so that dW_c/dλH is the thesis's
    nominal collagen stress T1·(exp(T2·x) − 1) (eq. 1.14).  For z = T2·x < 1e-3 the series
    T1·x·(z/2 + z²/6 + z³/24 + z⁴/120) replaces the quotient, whose cancellation would grow
    as 1/z (relative error < 1e-12 on both sides of the switch); it also gives the limit
    W_c = 0 at T2 = 0 instead of 0/0.

    Parameters
    ----------
    lh : array_like
        Helix stretch λH.
    t1, t2 : array_like
        T1 (MPa) and T2 (-), broadcast against ``lh``.

    Returns
    -------
    ndarray
        W_c (MPa, energy per unit reference volume).
    """
    lh, t1, t2 = np.broadcast_arrays(*(np.asarray(a, dtype=float) for a in (lh, t1, t2)))
    x = np.maximum(lh - 1.0, 0.0)
    z = np.minimum(t2 * x, _EXP_CLIP)
    small = z < 1e-3
    zs = np.where(small, z, 0.0)
    series = x * zs * (0.5 + zs * (1.0 / 6.0 + zs * (1.0 / 24.0 + zs / 120.0)))
    quotient = (np.expm1(z) - z) / np.where(small, 1.0, t2)  # t2 > 0 wherever z >= 1e-3
    return t1 * np.where(small, series, quotient)


def _helix_excess(lam, eps, c2):
    """(λH, λH − 1) with λH − 1 = ε·(cos²θ·(λ + 1) − sin²θ/λ)/(λH + 1): exact 0 at ε = 0."""
    d = eps * (c2 * (lam + 1.0) - (1.0 - c2) / lam)  # λH² − 1, factored to avoid cancellation
    lh = np.sqrt(1.0 + d)
    return lh, d / (lh + 1.0)


class EnergyHelicalCollagen(HelicalCollagen):
    """Helical collagen derived from a strain energy: λ·(1−c)·T1·(exp(T2·x) − 1)·λH'(λ).

    x = ⟨λH − 1⟩₊ and λH'(λ) = (cos²θ·λ − sin²θ/(2λ²))/λH (module docstring).  A variant of
    :class:`HelicalCollagen` (same name ``"collagen"``, stage and parameters, which it inherits)
    that replaces it in ``spyrou_model(form="energy")``.  Compressive (or zero) under axial
    compression, at most cosθ times the thesis stress in tension.
    """

    description = "exponential helical collagen of the ECM from a strain energy (traction-free lateral faces)"

    @staticmethod
    def _energy_parts(state, p):
        lam = state.lam
        c2 = np.cos(np.deg2rad(p["THETA"])) ** 2
        lh, x = _helix_excess(lam, state.eps, c2)
        np.maximum(x, 0.0, out=x)
        e = np.expm1(np.minimum(p["T2"] * x, _EXP_CLIP))
        num = c2 * lam - (1.0 - c2) / (2.0 * lam * lam)  # λH·λH'(λ)
        return lam, c2, lh, x, e, num

    def stress(self, state, p):
        # hot path: the quantities of _energy_parts computed in place, the λ-only factors kept
        # on the strain axis (n_points,);
        # λH² − 1 = cos²θ·(λ + 1 + 1/λ)·ε − ε/λ and λH·λH' = cos²θ·(λ + 1/(2λ²)) − 1/(2λ²)
        lam, eps = state.lam, state.eps
        c2 = np.cos(np.deg2rad(p["THETA"])) ** 2
        inv = 1.0 / lam
        d = c2 * ((lam + 1.0 + inv) * eps)
        d -= eps * inv
        lh = d + 1.0
        np.sqrt(lh, out=lh)
        d /= lh + 1.0  # λH − 1
        np.maximum(d, 0.0, out=d)
        d *= p["T2"]
        np.minimum(d, _EXP_CLIP, out=d)
        np.expm1(d, out=d)
        half = 0.5 * inv * inv
        num = c2 * (lam + half)
        num -= half
        d *= num
        d /= lh
        d *= (1.0 - p["VOLF"]) * p["T1"]
        d *= lam
        return d

    def stress_jacobian(self, state, p):
        lam, c2, lh, x, e, num = self._energy_parts(state, p)
        c, t1, t2 = p["VOLF"], p["T1"], p["T2"]
        th = np.deg2rad(p["THETA"])
        dlh_dl = num / lh
        scale = lam * (1.0 - c) * t1
        # per radian: dcos²θ = −sin2θ; dλH/dθ = sinθcosθ·(1/λ − λ²)/λH as for HelicalCollagen
        s2t = np.sin(2.0 * th)
        dlh_dth = 0.5 * s2t * (1.0 / lam - lam * lam) / lh
        dnum_dth = -s2t * (lam + 1.0 / (2.0 * lam * lam))
        dd_dth = dnum_dth / lh - num * dlh_dth / (lh * lh)  # d(λH')/dθ
        on = (x > 0).astype(float)
        return {
            "VOLF": -lam * t1 * e * dlh_dl,
            "T1": lam * (1.0 - c) * e * dlh_dl,
            "T2": scale * (e + 1.0) * x * dlh_dl,
            "THETA": scale * ((e + 1.0) * t2 * on * dlh_dth * dlh_dl + e * dd_dth) * (np.pi / 180.0),
        }


#: Forms of the collagen term: the thesis's (eqs. 1.7, 1.12, 1.14) and the strain-energy one.
FORMS: tuple[str, ...] = ("thesis", "energy")


def _check_form(form: str) -> str:
    if form not in FORMS:
        raise HbmError(f"unknown model form {form!r}; choose one of {', '.join(FORMS)}")
    return form


def spyrou_model(iso_factor: float = 1.0, form: str = "thesis") -> Model:
    """The base Spyrou–Agoras–Danas model with its 8 parameters.

    Parameters
    ----------
    iso_factor : float
        k_iso multiplying the neo-Hookean term: 1 (traction-free uniaxial, default) or 2/3
        (the thesis's deviatoric 33 component).
    form : {"thesis", "energy"}
        ``"thesis"`` (default): the collagen stress of thesis eqs. 1.7–1.14
        (:class:`HelicalCollagen`), tensile under axial compression.  ``"energy"``: the
        collagen derived from a strain energy (:class:`EnergyHelicalCollagen`), compressive
        under compression; use it for data with compressive strains (:func:`compression_check`).

    Returns
    -------
    Model
        Parameters ``("VOLF","EOPT","P1","T1","T2","THETA","GF","GM")`` with the prior box of
        thesis Table 1.1 (T1 in [0, 20], T2 in [0, 200]).

    Raises
    ------
    HbmError
        For an unknown ``form``; :class:`~hbm.errors.SettingError` for an ``iso_factor`` that is
        not a finite number > 0 (the rule of ``--iso-factor``).
    """
    iso_factor = check_positive(iso_factor, "iso_factor")
    collagen = HelicalCollagen() if _check_form(form) == "thesis" else EnergyHelicalCollagen()
    effects = (NeoHookeanMatrix(iso_factor), PassiveFibers(), collagen)
    name = "spyrou" if iso_factor == 1.0 else f"spyrou(k_iso={iso_factor:.4g})"
    if form == "energy":
        name = "spyrou(form=energy)" if iso_factor == 1.0 else f"spyrou(k_iso={iso_factor:.4g}, form=energy)"
    return Model(effects, parameters=BASE_PARAMETERS, name=name, spec=SPEC)


#: A point is compressive when its strain is below −COMPRESSION_STRAIN.
COMPRESSION_STRAIN = 0.01
#: The first points of each loading history that are exempt (a tension test's pre-load offset).
COMPRESSION_LEAD = 3


def compression_check(strain, form: str = "thesis", *, time=None, test=None,
                      name: str | None = None) -> str | None:
    """Whether data are substantially compressive for the thesis form; a message if so.

    A point is *compressive* when its strain is below −0.01 (``COMPRESSION_STRAIN``).  The
    first 3 points (``COMPRESSION_LEAD``) of each loading history are exempt, so a tension test
    that starts at a slightly negative strain passes.  The data are *substantially
    compressive* when more than 3 of the remaining points, or more than 10 % of all points,
    are compressive.  The thesis form turns tensile under axial compression (module
    docstring); the energy form does not, so it always passes.

    Parameters
    ----------
    strain : array_like (n_points,) or Loading
        Engineering strain of the specimen (a :class:`Loading` carries its histories).
    form : {"thesis", "energy"}
        Form of the model the data are meant for.
    time, test : array_like (n_points,), optional
        Time and test ids that split the points into loading histories (as in :class:`Loading`).
    name : str, optional
        Specimen name to start the message with.

    Returns
    -------
    str or None
        ``None`` when the data are fine for ``form``; otherwise a one-line message that names
        the energy option.

    Raises
    ------
    HbmError
        For an unknown ``form``.
    """
    _check_form(form)
    loading = strain if isinstance(strain, Loading) else Loading(np.asarray(strain, dtype=float), time, test)
    eps = loading.strain
    if form == "energy" or eps.size == 0:
        return None
    # position of each point within its loading history (0, 1, 2, ...)
    starts = np.flatnonzero(loading.history_starts)
    rank = np.arange(eps.size) - starts[loading.history]
    compressive = (eps < -COMPRESSION_STRAIN) & (rank >= COMPRESSION_LEAD)
    n_c = int(compressive.sum())
    if n_c <= COMPRESSION_LEAD and n_c <= 0.1 * eps.size:
        return None
    who = f"{name}: " if name else ""
    return (f"{who}{n_c} of {eps.size} points are compressive (strain < -{COMPRESSION_STRAIN:g}, min "
            f"{eps.min():.3g}) and the thesis form of the Spyrou model turns tensile under axial "
            f"compression; use the energy-consistent form (spyrou_model(form='energy'), --form energy)")


def model_form(model: Model) -> str | None:
    """``"thesis"`` or ``"energy"``: the collagen form of a model built on the Spyrou collagen,
    ``None`` for a model without it (then no compression check applies)."""
    # duck-typed models (a user's own object with .stress) have no effects list: no check
    kinds = [e for e in getattr(model, "effects", ()) if isinstance(e, HelicalCollagen)]
    if not kinds:
        return None
    return "energy" if any(isinstance(e, EnergyHelicalCollagen) for e in kinds) else "thesis"


#: Effect ids of the base model, in model order (the detective's removal test and the organ
#: report ask for them by these names).
BASE_EFFECTS: tuple[str, ...] = ("matrix", "fibers", "collagen")


class SpyrouExport:
    """How FE cards read the Spyrou parameters (:class:`~hbm.model.spec.ExportMap`): the matrix's
    shear modulus G = c·GF + (1 − c)·GM, the fibres' c·P1 beyond EOPT, the collagen's (1 − c)·T1,
    T2 and helix angle THETA (c = VOLF)."""

    def constituents(self, p: Mapping[str, float]) -> Constituents:
        c = p["VOLF"]
        return Constituents(shear_modulus=c * p["GF"] + (1 - c) * p["GM"], fibre_amplitude=c * p["P1"],
                            fibre_onset=p["EOPT"], collagen_amplitude=(1 - c) * p["T1"], collagen_rate=p["T2"],
                            collagen_angle=p["THETA"])

    def kinks(self, p: Mapping[str, float]) -> list[float]:
        """Zero strain (above the magic angle the helix is also taut under compression, so the collagen
        stress has a kink there), the fibre onset EOPT and the collagen onset λ* − 1."""
        return [0.0, p["EOPT"], float(collagen_onset_stretch(p["THETA"])) - 1.0]

    def energy(self, p: Mapping[str, np.ndarray], k_iso: float, l1, l2, l3) -> np.ndarray:
        """W (MPa) of the energy form, incompressible, fibres along x, at principal stretches (m,)::

            W = k_iso·G/2·(I1 − 3) + c·P1/2·⟨λf − 1 − EOPT⟩₊² + (1 − c)·⟨W_c(λH(φ))⟩_φ

        with the helical collagen averaged exactly over its azimuth φ around the fibre (the cone
        reading of :class:`hbm.model.energy3d.Energy3D`; in uniaxial tension every azimuth has the λH
        of the uniaxial formula).  ``p``: parameter columns (n, 1); returns (n, m)."""
        # registered by hbm.model.energy3d, which builds on this module's laws
        return principal_energy(SPEC.name)(p, k_iso, l1, l2, l3)


# the combinations from named columns (module-level functions: a spec pickles)
def _shear(c):
    return c["VOLF"] * c["GF"] + (1 - c["VOLF"]) * c["GM"]


def _fibres(c):
    return c["VOLF"] * c["P1"]


def _collagen(c):
    return (1 - c["VOLF"]) * c["T1"]


def _collagen_named(c):  # identify.py's candidates: the same products, written as they always were
    return (1.0 - c["VOLF"]) * c["T1"]


def _collagen_rate(c):
    return (1.0 - c["VOLF"]) * c["T1"] * c["T2"]


def _shear_named(c):
    return c["VOLF"] * c["GF"] + (1.0 - c["VOLF"]) * c["GM"]


#: The vocabulary of the Spyrou base (:class:`~hbm.model.spec.ModelSpec`).  The combinations a
#: uniaxial curve identifies (DESIGN.md §1): G = c·GF + (1−c)·GM, A_f = c·P1, A_m = (1−c)·T1, with
#: the shape parameters T2, THETA, EOPT.  Population transforms: log for strictly positive moduli
#: spanning decades (P1, GF, GM: a log-normal population, sd reads as a relative spread); logit on
#: the box for bounded fractions/scales (VOLF, EOPT, T1, T2: no truncation needed); identity
#: (truncated normal) for THETA, whose posteriors pile up against the 60° edge: logit would stretch
#: that pile-up into a tail many units wide, far wider than the population, and the importance ESS
#: collapses (measured: 10% ESS 2-3 of 500 vs 9-190).
SPEC = ModelSpec(
    name="spyrou", parameters=BASE_PARAMETERS, effects=BASE_EFFECTS, physical_range=PHYSICAL_RANGE,
    combinations=(
        Combination("G", ("VOLF", "GF", "GM"), _shear, column="G", unit="MPa", label="G = VOLF·GF + (1−VOLF)·GM"),
        Combination("VOLF*P1", ("VOLF", "P1"), _fibres, column="VOLF*P1", unit="MPa", label="VOLF·P1",
                    compression_note="the fibre term is identically zero for ε ≤ 0 (compression data)"),
        Combination("(1-VOLF)*T1", ("VOLF", "T1"), _collagen, column="(1-VOLF)*T1", unit="MPa",
                    label="(1−VOLF)·T1")),
    shape_parameters=("T2", "THETA", "EOPT"),
    transforms={"VOLF": "logit", "EOPT": "logit", "P1": "log", "T1": "logit", "T2": "logit", "THETA": "identity",
                "GF": "log", "GM": "log"},
    fractions=("VOLF",),
    # checked by name in identify.py: when the collagen works in its near-linear regime (small
    # T2·(λ − 1)) only (1−c)·T1·T2 is learnable, not (1−c)·T1 itself
    candidates=(
        Combination("(1-VOLF)*T1", ("VOLF", "T1"), _collagen_named),
        Combination("(1-VOLF)*T1*T2", ("VOLF", "T1", "T2"), _collagen_rate),
        Combination("VOLF*P1", ("VOLF", "P1"), _fibres),
        Combination("VOLF*GF+(1-VOLF)*GM", ("VOLF", "GF", "GM"), _shear_named)),
    manifold=Manifold("VOLF", "T1", "(1-VOLF)*T1", sweep_width=0.07, level_label="(1−VOLF)·T1"),
    mixture=MixtureRoles("VOLF", "P1", "T1", ("GF", "GM"), angle="THETA", names=("G", "VOLF*P1", "(1-VOLF)*T1")),
    export=SpyrouExport(),
    pooled_when_informed=("EOPT",),
    texts={"combinations": ("Uniaxial data can at best identify G = c·GF + (1−c)·GM, c·P1 and (1−c)·T1 (c = VOLF); "
                            "the individual parameters slide along manifolds. When the collagen works in its "
                            "near-linear range (small T2·(λH − 1) over the tested strains) only (1−c)·T1·T2 is "
                            "learnt and (1−c)·T1 trades off against T2: see each specimen's identified "
                            "combinations above."),
           # why hbm.identifiability.modes finds null directions in every set of homogeneous tests
           "modes_structural": ("This is structural, not a matter of which tests were run: under the Voigt mixture "
                                "(one F for both phases) the volume fraction VOLF enters the energy only through the "
                                "phase amplitudes VOLF·P1 and (1−VOLF)·T1 and the mixed shear modulus "
                                "VOLF·GF + (1−VOLF)·GM, so no homogeneous test in any loading mode separates VOLF "
                                "from P1 and T1, or GF from GM."),
           "transforms": ("log for positive moduli spanning decades, logit on the prior box for bounded quantities, "
                          "identity (truncated to the box) for THETA whose posteriors pile up at 60°")})

register_base(SPEC, spyrou_model)

#: The combinations a uniaxial curve identifies -- the names used in every table, figure and result file.
COMBINATIONS: tuple[str, ...] = SPEC.combination_names

#: Shape parameters that a curve informs directly, reported beside the combinations.
SHAPE_PARAMETERS: tuple[str, ...] = SPEC.shape_parameters


def identifiable_combinations(names, theta) -> dict[str, np.ndarray]:
    """G = c·GF + (1−c)·GM, A_f = c·P1 and A_m = (1−c)·T1 from a theta array (..., n_params)."""
    theta = np.asarray(theta, dtype=float)
    return SPEC.combination_values({n: theta[..., i] for i, n in enumerate(names)})

