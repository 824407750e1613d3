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
``fiber-exp-pow-uncoupled``    N = 6 helical families at THETA to the axis, azimuths 0°, 60°, ... 300°
                               (mirror-symmetric, so uniaxial tension does not twist), each carrying
                               (1 − c)/N of the collagen: dΨ/dIn = ξ·(In − 1)^(β−1)·exp(α·(In − 1)^β).
                               hbm's dW_c/dλH = T1·(exp(T2·(λH − 1)) − 1) is not of this family: ξ, α, β
                               are fitted (least squares on the total uniaxial stress, relative) and the
                               card states the remaining error.

Cauchy fibre stresses are those of FEBio's documentation (the stress of each law as a function of
the fibre's squared stretch In); :mod:`hbm.export.verify` assembles them in 3-D.
"""

from __future__ import annotations

from dataclasses import dataclass, asdict

import numpy as np
from scipy.optimize import brentq, least_squares

from ..model.spec import Constituents, base_spec
from ..model.spyrou import helical_stretch

#: helical collagen families of the energy card (equally spaced azimuths over 360°)
N_FAMILIES = 6
#: toe exponents tried for the fibre law (FEBio requires >= 2; larger -> shorter, steeper toe); the
#: one with the smallest error over the tested range is written
FIBRE_BETAS = (3.0, 6.0, 12.0, 25.0, 50.0)
#: weight of the stretch beyond the tested range (up to 1.5x) in the collagen fit
EXTENSION_WEIGHT = 0.1
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
def pow_linear_cauchy(In, E, lam0, beta):
    """Cauchy stress magnitude of FEBio's ``fiber-pow-linear(-uncoupled)`` at squared stretch In."""
    In = np.asarray(In, float)
    if E <= 0:
        return np.zeros_like(In)
    I0 = lam0 * lam0
    ksi = E / 4.0 / (beta - 1.0) * I0 ** -1.5 * (I0 - 1.0) ** (2.0 - beta)
    b = ksi * (I0 - 1.0) ** (beta - 1.0) + E / 2.0 / np.sqrt(I0)
    x = np.maximum(In - 1.0, 0.0)
    toe = 2.0 * In * ksi * x ** (beta - 1.0)
    lin = 2.0 * b * In - E * np.sqrt(np.maximum(In, 0.0))
    return np.where(In < 1.0, 0.0, np.where(In < I0, toe, lin))


def exp_pow_cauchy(In, ksi, alpha, beta):
    """Cauchy stress magnitude of FEBio's ``fiber-exp-pow-uncoupled`` (mu = 0) at squared stretch In."""
    x = np.maximum(np.asarray(In, float) - 1.0, 0.0)
    return 2.0 * np.asarray(In, float) * ksi * x ** (beta - 1.0) * np.exp(np.minimum(alpha * x ** beta, 700.0))


def family_directions(theta_deg: float, n: int = N_FAMILIES) -> np.ndarray:
    """(n, 3) unit directions at ``theta_deg`` to the x axis (the muscle axis), azimuths 360°·k/n."""
    th = np.deg2rad(theta_deg)
    phi = 2.0 * np.pi * np.arange(n) / n
    return np.column_stack([np.full(n, np.cos(th)), -np.sin(th) * np.sin(phi), np.sin(th) * np.cos(phi)])


# ----------------------------------------------------------------------------- the energy card
@dataclass
class EnergyCard:
    """Parameters of the ``febio-energy`` card (MPa, dimensionless, degrees)."""

    c1: float
    k: float
    fibre_E: float
    fibre_lam0: float
    fibre_beta: float
    ksi: float          # per family
    alpha: float
    beta: float
    theta: float
    n_families: int
    fit_error: float    # max relative error of the 1-D mapping over the tested range
    fit_error_15: float  # the same over 1.5x the tested range

    def as_dict(self) -> dict:
        return asdict(self)

    def uniaxial_1d(self, lam) -> np.ndarray:
        """Uniaxial Cauchy stress of the card with λH from the kinematics (used for fitting only)."""
        lam = np.asarray(lam, float)
        s = 2.0 * self.c1 * (lam ** 2 - 1.0 / lam)
        s = s + pow_linear_cauchy(lam ** 2, self.fibre_E, self.fibre_lam0, self.fibre_beta)
        return s + _collagen_1d(lam, self.theta, self.n_families * self.ksi, self.alpha, self.beta)


def _collagen_1d(lam, theta, ksi_total, alpha, beta):
    """σ of the families in uniaxial tension: λ·dW/dλ = λ·(dΨ/dIn·2λH)·λH'(λ) summed over families."""
    if ksi_total <= 0:
        return np.zeros_like(lam)
    lh = helical_stretch(lam, theta)
    c2 = np.cos(np.deg2rad(theta)) ** 2
    dlh = (c2 * lam - (1.0 - c2) / (2.0 * lam * lam)) / lh
    # exp_pow_cauchy = 2·In·Ψ' -> dΨ/dλH = 2·λH·Ψ' = exp_pow_cauchy / λH
    return lam * exp_pow_cauchy(lh * lh, ksi_total, alpha, beta) / lh * dlh


def _fibre_lam0(on: float, beta: float) -> float:
    """λ0 with b = E/(2·on) (linear branch equal to hbm's), i.e. on·((λ0²−1)/(2(β−1)λ0³) + 1/λ0) = 1."""
    def h(l0):
        return on * ((l0 * l0 - 1.0) / (2.0 * (beta - 1.0) * l0 ** 3) + 1.0 / l0) - 1.0

    lo = max(on, 1.0 + 1e-6)
    if h(lo) <= 0:  # EOPT ~ 0: no toe to place; the shortest toe FEBio's range allows
        return 1.0 + 1e-3
    return float(brentq(h, lo, 10.0, xtol=1e-14))


def energy_card(p, k_iso: float, strain_range, hbm_stress, check_strain=None) -> EnergyCard:
    """Map hbm's energy-form parameters ``p`` onto the FEBio energy card.

    Parameters
    ----------
    p : Constituents or dict
        What the card reads (:class:`hbm.model.spec.Constituents`), or the base parameters by name
        (read through the default base's export map).
    k_iso : float
    strain_range : (lo, hi)
        Tested engineering-strain range; the collagen is fitted there.
    hbm_stress : callable
        strain -> hbm's Cauchy stress of ``p`` (the target).
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
    target, target15 = hbm_stress(eps), hbm_stress(eps15)
    card = EnergyCard(c1=c1, k=BULK_FACTOR * 2.0 * c1, fibre_E=E, fibre_lam0=1.0 + 1e-3, fibre_beta=2.0,
                      ksi=0.0, alpha=0.0, beta=2.0, theta=float(k.collagen_angle), n_families=N_FAMILIES,
                      fit_error=0.0, fit_error_15=0.0)
    if E > 0:
        best, fibre_hbm = np.inf, (1.0 + eps) * cp1 * np.maximum(eps - k.fibre_onset, 0.0)
        for fb in FIBRE_BETAS:  # the toe shape: a 1-D choice among a few exponents
            l0 = _fibre_lam0(on, fb)
            # total stress with only the fibre law changed: its error relative to the total
            err = relative_error(target - fibre_hbm + pow_linear_cauchy((1.0 + eps) ** 2, E, l0, fb), target)
            if err < best:
                best, card.fibre_beta, card.fibre_lam0 = err, fb, l0
    am, t2 = k.collagen_amplitude, k.collagen_rate
    lh_max = float(np.max(helical_stretch(1.0 + eps15, k.collagen_angle)))
    if am > 0 and t2 > 0 and lh_max > 1.0:
        # fitted on 1.5x the tested range, the extension weighted EXTENSION_WEIGHT: the tested range
        # decides, the extension keeps the exponential from running away just past it
        ext = (eps15 > hi) | (eps15 < lo)
        e_all = np.concatenate([eps, eps15[ext]])
        t_all = np.concatenate([target, target15[ext]])
        w = np.concatenate([np.ones(eps.size), np.full(int(ext.sum()), EXTENSION_WEIGHT)])
        base = card.uniaxial_1d(1.0 + e_all)
        scale = np.maximum(np.abs(t_all), FLOOR * np.max(np.abs(target))) / w
        x_max = max(lh_max - 1.0, 1e-6)

        def resid(z):
            ks, al, be = np.exp(z[0]), np.exp(z[1]), 2.0 + np.exp(z[2])
            return (base + _collagen_1d(1.0 + e_all, card.theta, ks, al, be) - t_all) / scale

        z0 = np.log([am * t2 / 4.0, max(t2 / (8.0 * x_max), 1e-3), 1e-2])
        sol = least_squares(resid, z0, method="trf", x_scale=1.0, max_nfev=400)
        card.ksi = float(np.exp(sol.x[0])) / N_FAMILIES
        card.alpha, card.beta = float(np.exp(sol.x[1])), float(2.0 + np.exp(sol.x[2]))
    # the stated errors on the grid the verification uses (check_strain), tested part and all of it
    chk = np.asarray(check_strain if check_strain is not None else eps15, float)
    ref = hbm_stress(chk)
    tested = (chk >= lo - 1e-12) & (chk <= hi + 1e-12)
    card.fit_error = relative_error(card.uniaxial_1d(1.0 + chk[tested]), ref[tested])
    card.fit_error_15 = relative_error(card.uniaxial_1d(1.0 + chk), ref)
    return card
