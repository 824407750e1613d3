"""The exported laws: hbm parameters -> card parameters, and each card law's documented stress.

Two kinds of card:

*curve* cards (``febio-uniaxial``, ``abaqus-marlow``) tabulate hbm's stress against stretch;
*energy* cards (``febio-energy``) map hbm's energy form onto FEBio laws:

``Mooney-Rivlin``              c1 = k_iso·G/2, c2 = 0: σ = k_iso·G·(λ² − 1/λ) in uniaxial tension, exact.
``fiber-pow-linear-uncoupled`` along the axis.  Its documented Cauchy fibre stress is
                               2·In·ξ·(In − 1)^(β−1) for 1 ≤ In < λ0² (toe) and 2·b·In − E·√In beyond
                               (In = λ², ξ and b fixed by E, λ0, β).  With E = c·P1·(1 + EOPT) and λ0
                               the root of b = c·P1/2 the linear part equals hbm's λ·c·P1·(λ − 1 − EOPT)
                               exactly; only the toe [1, λ0] differs (hbm: 0 up to 1 + EOPT, then linear).
``uncoupled fiber-exp-linear``  N helical families at THETA to the axis, equally spaced azimuths
                               φ_k = 360°·(k + ½)/N (mirror-symmetric: no shear under diagonal F), each
                               carrying (1 − c)/N of the collagen.  Its documented Cauchy fibre stress
                               is c3·(exp(c4·(λ − 1)) − 1) for 1 ≤ λ < λ1, c5·λ + c6 beyond (continuous).
                               hbm's segment stress λ·W_c'(λ) = (1 − c)/N·T1·λ·(exp(T2·(λ − 1)) − 1)
                               is not of this family (the factor λ): c3, c4 are fitted, minimax relative
                               on the segment stretches every loading mode reaches (:func:`fit_segment_law`),
                               λ1 is the largest of them and c5 continues the slope there; the card states
                               the remaining error.  N follows from the measured deviation of N equally
                               spaced families from the exact azimuthal average (:mod:`hbm.export.modes`).

Cauchy fibre stresses are those of FEBio's documentation (the stress of each law as a function of
the fibre's squared stretch In); :mod:`hbm.export.verify` assembles them in 3-D.
"""

from __future__ import annotations

from dataclasses import dataclass, asdict

import numpy as np
from scipy.optimize import brentq, minimize_scalar
from scipy.special import expi

from ..model.spec import Constituents, base_spec
from ..model.spyrou import helical_stretch

#: toe exponents tried for the fibre law (FEBio requires >= 2; larger -> shorter, steeper toe); the
#: one with the smallest error over the tested range is written
FIBRE_BETAS = (3.0, 6.0, 12.0, 25.0, 50.0)
#: relative error allowed beyond the tested segment stretches (up to 1.5x the tested range), as a multiple
#: of the error inside them, in the collagen fit
EXTENSION_ALLOWANCE = 3.0
#: bulk modulus of the uncoupled mixture as a multiple of the initial shear modulus
BULK_FACTOR = 1000.0
#: relative-error floor: errors are |Δσ| / max(|σ_ref|, FLOOR·max|σ_ref|) over the range compared
FLOOR = 1e-3


def relative_error(card, ref) -> float:
    """Max |card − ref| / max(|ref|, FLOOR·max|ref|) (relative where the stress is not ~0)."""
    card, ref = np.asarray(card, float), np.asarray(ref, float)
    scale = np.maximum(np.abs(ref), FLOOR * max(np.max(np.abs(ref)), 1e-300))
    return float(np.max(np.abs(card - ref) / scale))


# ----------------------------------------------------------------------------- documented fibre laws
def _pow_linear(In, E, lam0, beta, toe, linear):
    """A function of ``fiber-pow-linear`` at squared stretch In: 0 below In = 1, ``toe(In, x, ξ)`` up to
    I0 = λ0² (x = In − 1), ``linear(In, ξ, b, I0)`` beyond, with ξ and b fixed by E, λ0, β."""
    In = np.asarray(In, float)
    if E <= 0:
        return np.zeros_like(In)
    I0 = lam0 * lam0
    ksi = E / 4.0 / (beta - 1.0) * I0 ** -1.5 * (I0 - 1.0) ** (2.0 - beta)
    b = ksi * (I0 - 1.0) ** (beta - 1.0) + E / 2.0 / np.sqrt(I0)
    x = np.maximum(In - 1.0, 0.0)
    return np.where(In < 1.0, 0.0, np.where(In < I0, toe(In, x, ksi), linear(In, ksi, b, I0)))


def pow_linear_cauchy(In, E, lam0, beta):
    """Cauchy stress magnitude of FEBio's ``fiber-pow-linear(-uncoupled)`` at squared stretch In."""
    return _pow_linear(In, E, lam0, beta, lambda In, x, ksi: 2.0 * In * ksi * x ** (beta - 1.0),
                       lambda In, ksi, b, I0: 2.0 * b * In - E * np.sqrt(np.maximum(In, 0.0)))


def pow_linear_slope(In, E, lam0, beta):
    """d(Cauchy stress)/dIn of ``fiber-pow-linear`` (for the tangent of :mod:`.card_models`)."""
    def toe(In, x, ksi):
        return 2.0 * ksi * x ** (beta - 1.0) + 2.0 * In * ksi * (beta - 1.0) * x ** (beta - 2.0)

    def linear(In, ksi, b, I0):
        return 2.0 * b - E / (2.0 * np.sqrt(np.maximum(In, 1e-300)))

    return _pow_linear(In, E, lam0, beta, toe, linear)


def pow_linear_energy(In, E, lam0, beta):
    """Ψ(In) of ``fiber-pow-linear``: ξ/β·(In − 1)^β in the toe, Ψ(I0) + b·(In − I0) − E·(√In − λ0) beyond,
    0 below In = 1 (its Cauchy stress is 2·In·dΨ/dIn, :func:`pow_linear_cauchy`)."""
    return _pow_linear(In, E, lam0, beta, lambda In, x, ksi: ksi / beta * x ** beta,
                       lambda In, ksi, b, I0: (ksi / beta * (I0 - 1.0) ** beta + b * (In - I0)
                                               - E * (np.sqrt(np.maximum(In, 0.0)) - lam0)))


def exp_linear_cauchy(lam, c3, c4, c5, lam1):
    """Cauchy stress magnitude of FEBio's ``uncoupled fiber-exp-linear`` at fibre stretch ``lam``:
    0 below 1, c3·(exp(c4·(λ − 1)) − 1) up to λ1, c5·λ + c6 beyond with c6 = c3·(exp(c4·(λ1 − 1)) − 1) − c5·λ1."""
    lam = np.asarray(lam, float)
    c6 = c3 * np.expm1(c4 * (lam1 - 1.0)) - c5 * lam1
    expo = c3 * np.expm1(c4 * np.clip(lam - 1.0, 0.0, lam1 - 1.0))
    return np.where(lam < 1.0, 0.0, np.where(lam < lam1, expo, c5 * lam + c6))


def exp_linear_slope(lam, c3, c4, c5, lam1):
    """d(Cauchy stress)/dλ of ``uncoupled fiber-exp-linear``."""
    lam = np.asarray(lam, float)
    expo = c3 * c4 * np.exp(c4 * np.clip(lam - 1.0, 0.0, lam1 - 1.0))
    return np.where(lam < 1.0, 0.0, np.where(lam < lam1, expo, c5))


def exp_linear_energy(lam, c3, c4, c5, lam1):
    """Ψ(λ) = ∫₁^λ s(t)/t dt of ``uncoupled fiber-exp-linear`` (s its Cauchy stress, λ·dΨ/dλ = s): with
    Ei the exponential integral, c3·(e^(−c4)·(Ei(c4·λ) − Ei(c4)) − ln λ) up to λ1, then
    Ψ(λ1) + c5·(λ − λ1) + c6·ln(λ/λ1)."""
    lam = np.asarray(lam, float)

    def expo(x):
        x = np.maximum(x, 1.0)
        # e^(−c4)·(Ei(c4·x) − Ei(c4)) = ∫₁^x e^(c4(t−1))/t dt; expi of large arguments is finite to c4·x ~ 700
        return c3 * (np.exp(-c4) * (expi(c4 * x) - expi(c4)) - np.log(x)) if c4 > 0 else np.zeros_like(x)

    c6 = c3 * np.expm1(c4 * (lam1 - 1.0)) - c5 * lam1
    inner = expo(np.minimum(lam, lam1))
    outer = expo(np.asarray(lam1)) + c5 * (lam - lam1) + c6 * np.log(np.maximum(lam, lam1) / lam1)
    return np.where(lam < 1.0, 0.0, np.where(lam < lam1, inner, outer))


def cone_directions(theta_deg: float, n: int) -> np.ndarray:
    """(n, 3) unit directions at ``theta_deg`` to the x axis (the muscle axis f; y = c, z = n), azimuths
    φ_k = 360°·(k + ½)/n: (cos θ, sin θ·cos φ_k, sin θ·sin φ_k), the set of
    :class:`hbm.model.energy3d.ConeFamilies`.  Even n makes it symmetric under both mirrors of the
    c–n plane, so a diagonal F gives a diagonal stress (no shear coupling in the stretch modes)."""
    th = np.deg2rad(theta_deg)
    phi = 2.0 * np.pi * (np.arange(n) + 0.5) / n
    return np.column_stack([np.full(n, np.cos(th)), np.sin(th) * np.cos(phi), np.sin(th) * np.sin(phi)])


def fit_segment_law(t2: float, y_tested: float, y_max: float) -> tuple[float, float, float, float]:
    """Fit ``c·(exp(k·y) − 1)`` to the segment stress (1 + y)·(exp(T2·y) − 1) (per unit amplitude), minimax
    relative on the segment excess y = λ − 1 in (0, ``y_max``], the part beyond ``y_tested`` allowed
    :data:`EXTENSION_ALLOWANCE` times the error.

    Returns
    -------
    c, k : float
        The exp-linear coefficients per unit amplitude (c3 = amplitude·c, c4 = k).
    error_tested, error_all : float
        Max relative error on (0, y_tested] and on (0, y_max].

    Notes
    -----
    A positive sum of such terms does no better (measured with a linear programme over a grid of k:
    the optimum is one term), because (1 + y)·exp(T2·y) is not a positive mixture of exponentials.
    The error grows with the range (equal weights, T2 from 2.5 to 162): 0.6-1.4 % up to y = 0.3, 1.7-3.4 %
    up to y = 0.66.
    """
    y_max = max(float(y_max), 1e-6)
    y_tested = min(max(float(y_tested), 1e-6), y_max)
    y = np.unique(np.concatenate([np.geomspace(1e-4 * y_max, y_max, 200), np.linspace(0.0, y_max, 201)[1:]]))
    target = (1.0 + y) * np.expm1(t2 * y)
    w = np.where(y <= y_tested * (1 + 1e-12), 1.0, EXTENSION_ALLOWANCE)

    def best_c(k):
        r = np.expm1(k * y) / target
        lo, hi = float(np.min(1.0 / r)), float(np.max(1.0 / r))
        res = minimize_scalar(lambda c: np.max(np.abs(c * r - 1.0) / w), bounds=(lo, hi), method="bounded",
                              options={"xatol": 1e-12 * hi})
        return float(res.x), float(res.fun)

    ks = np.linspace(max(t2 - 10.0, 1e-3), t2 + 10.0, 201)
    errs = [best_c(k)[1] for k in ks]
    i = int(np.argmin(errs))
    res = minimize_scalar(lambda k: best_c(k)[1], bounds=(ks[max(i - 1, 0)], ks[min(i + 1, ks.size - 1)]),
                          method="bounded", options={"xatol": 1e-10 * (1.0 + t2)})
    k = float(res.x)
    c = best_c(k)[0]
    rel = np.abs(c * np.expm1(k * y) / target - 1.0)
    return c, k, float(np.max(rel[y <= y_tested * (1 + 1e-12)])), float(np.max(rel))


# ----------------------------------------------------------------------------- the energy card
@dataclass
class EnergyCard:
    """Parameters of the ``febio-energy`` card (MPa, dimensionless, degrees)."""

    c1: float
    k: float
    fibre_E: float
    fibre_lam0: float
    fibre_beta: float
    c3: float            # per family (uncoupled fiber-exp-linear)
    c4: float
    c5: float
    lam1: float          # the largest segment stretch fitted (1.5x the tested range, every mode)
    theta: float
    n_families: int
    law_error: float     # max relative error of a family's stress on the segment stretches of the tested range
    law_error_15: float  # the same up to lam1
    fit_error: float     # max relative error of the 1-D mapping over the tested range (along the fibres)
    fit_error_15: float  # the same over 1.5x the tested range

    def as_dict(self) -> dict:
        return asdict(self)

    def family_stress(self, lam) -> np.ndarray:
        """Cauchy stress of one collagen family at its stretch ``lam`` (the documented law)."""
        return exp_linear_cauchy(lam, self.c3, self.c4, self.c5, self.lam1)

    def uniaxial_1d(self, lam) -> np.ndarray:
        """Uniaxial Cauchy stress of the card with λH from the kinematics (every family at λH)."""
        lam = np.asarray(lam, float)
        s = 2.0 * self.c1 * (lam ** 2 - 1.0 / lam)
        s = s + pow_linear_cauchy(lam ** 2, self.fibre_E, self.fibre_lam0, self.fibre_beta)
        if self.c3 <= 0:
            return s
        lh = helical_stretch(lam, self.theta)
        c2 = np.cos(np.deg2rad(self.theta)) ** 2
        dlh = (c2 * lam - (1.0 - c2) / (2.0 * lam * lam)) / lh
        # σ = λ·dW/dλ, W = N·Ψ(λH), λH·dΨ/dλH = the family's Cauchy stress
        return s + lam * self.n_families * self.family_stress(lh) / lh * dlh


def _fibre_lam0(on: float, beta: float) -> float:
    """λ0 with b = E/(2·on) (linear branch equal to hbm's), i.e. on·((λ0²−1)/(2(β−1)λ0³) + 1/λ0) = 1."""
    def h(l0):
        return on * ((l0 * l0 - 1.0) / (2.0 * (beta - 1.0) * l0 ** 3) + 1.0 / l0) - 1.0

    lo = max(on, 1.0 + 1e-6)
    if h(lo) <= 0:  # EOPT ~ 0: no toe to place; the shortest toe FEBio's range allows
        return 1.0 + 1e-3
    return float(brentq(h, lo, 10.0, xtol=1e-14))


def energy_card(p, k_iso: float, strain_range, hbm_stress, n_families: int,
                segment_stretch: tuple[float, float], check_strain=None) -> EnergyCard:
    """Map hbm's energy-form parameters ``p`` onto the FEBio energy card.

    Parameters
    ----------
    p : Constituents or dict
        What the card reads (:class:`hbm.model.spec.Constituents`), or the base parameters by name
        (read through the default base's export map).
    k_iso : float
    strain_range : (lo, hi)
        Tested engineering-strain range (along the fibres).
    hbm_stress : callable
        strain -> hbm's Cauchy stress of ``p`` along the fibres (for the fibre toe and the stated errors).
    n_families : int
        Collagen families (azimuths of :func:`cone_directions`).
    segment_stretch : (float, float)
        The largest helix-segment stretch every loading mode reaches on the tested range and on 1.5x it
        (:func:`hbm.export.modes.segment_stretch`): the collagen law is fitted up to these.
    check_strain : array, optional
        Strain grid (1.5x the tested range) on which the stated errors are measured (default 301 points).
    """
    k = p if isinstance(p, Constituents) else base_spec().export.constituents(p)
    c1 = k_iso * k.shear_modulus / 2.0
    cp1, on = k.fibre_amplitude, 1.0 + k.fibre_onset
    E = cp1 * on
    lo, hi = strain_range
    eps = np.linspace(lo, hi, 201)
    eps15 = np.linspace(1.5 * lo, 1.5 * hi, 301)
    target = hbm_stress(eps)
    l_t, l_x = (float(v) for v in segment_stretch)
    card = EnergyCard(c1=c1, k=BULK_FACTOR * 2.0 * c1, fibre_E=E, fibre_lam0=1.0 + 1e-3, fibre_beta=2.0,
                      c3=0.0, c4=0.0, c5=0.0, lam1=max(l_x, 1.0), theta=float(k.collagen_angle),
                      n_families=int(n_families), law_error=0.0, law_error_15=0.0, fit_error=0.0, fit_error_15=0.0)
    if E > 0:
        best, fibre_hbm = np.inf, (1.0 + eps) * cp1 * np.maximum(eps - k.fibre_onset, 0.0)
        for fb in FIBRE_BETAS:  # the toe shape: a 1-D choice among a few exponents
            l0 = _fibre_lam0(on, fb)
            # total stress with only the fibre law changed: its error relative to the total
            err = relative_error(target - fibre_hbm + pow_linear_cauchy((1.0 + eps) ** 2, E, l0, fb), target)
            if err < best:
                best, card.fibre_beta, card.fibre_lam0 = err, fb, l0
    amp, t2 = k.collagen_amplitude / card.n_families, k.collagen_rate
    if amp > 0 and t2 > 0 and l_x > 1.0:
        cc, card.c4, card.law_error, card.law_error_15 = fit_segment_law(t2, l_t - 1.0, l_x - 1.0)
        card.c3 = amp * cc
        # beyond the fitted stretches the family stiffens linearly with the slope it has there (FEBio's
        # linear branch, continuous with it): the card is verified up to lam1 only
        card.c5 = card.c3 * card.c4 * float(np.exp(card.c4 * (l_x - 1.0)))
    # the stated errors on the grid the verification uses (check_strain), tested part and all of it
    chk = np.asarray(check_strain if check_strain is not None else eps15, float)
    ref = hbm_stress(chk)
    tested = (chk >= lo - 1e-12) & (chk <= hi + 1e-12)
    card.fit_error = relative_error(card.uniaxial_1d(1.0 + chk[tested]), ref[tested])
    card.fit_error_15 = relative_error(card.uniaxial_1d(1.0 + chk), ref)
    return card
