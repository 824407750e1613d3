"""Independent check of every exported card: its documented law, solved in homogeneous uniaxial tension.

Each card's Cauchy stress is assembled in 3-D from its law's documented form (not from hbm's
formula): incompressible, F = diag(λ, λ2, 1/(λ·λ2)), pressure from the lateral face 3, and the
lateral stretch λ2 found by root finding (brentq) so that the lateral face 2 is traction-free too
(σ22 = σ33).  The resulting σ11 is compared with hbm's curve over the tested strain range and
over 1.5x it.  An exact card must agree to :data:`EXACT_TOLERANCE` over the tested range; an
approximate card to the bound it states.
"""

from __future__ import annotations

from dataclasses import dataclass, asdict
from typing import Callable

import numpy as np
from scipy.optimize import brentq

from .laws import EnergyCard, cone_directions, pow_linear_cauchy, relative_error

#: max relative difference of an exact card over the tested range
EXACT_TOLERANCE = 5e-3
#: slack on an approximate card's stated bound (the bound is measured with the 1-D formula, the
#: check in 3-D; they differ by the root-finding tolerance only)
BOUND_SLACK = 1e-6


@dataclass
class Check:
    """Result of one verification."""

    format: str
    exact: bool
    error_tested: float      # max relative difference over the tested range
    error_extended: float    # over 1.5x the tested range
    bound: float             # what the card promises over the tested range
    passed: bool
    method: str

    def as_dict(self) -> dict:
        return asdict(self)


# ----------------------------------------------------------------------------- 3-D stress of each card
def _deviatoric_iso(c1: float, f: np.ndarray) -> np.ndarray:
    """Mooney-Rivlin (c2 = 0) extra stress 2·c1·B for F = diag(f) (incompressible)."""
    return 2.0 * c1 * f ** 2


def febio_card_stress(card: EnergyCard) -> Callable[[np.ndarray], np.ndarray]:
    """The febio-energy card's Cauchy stress without the pressure, ``T(F)`` for F (m, 3, 3) at J = 1:
    Mooney-Rivlin 2·c1·B plus, for each fibre direction a (the axis and the N families of
    :func:`.laws.cone_directions`), s/λ²·(F a)⊗(F a) with s the law's documented Cauchy stress at the
    fibre stretch λ = |F a| (``fiber-pow-linear`` along the axis, ``uncoupled fiber-exp-linear`` for the
    families)."""
    dirs = np.vstack([[1.0, 0.0, 0.0], cone_directions(card.theta, card.n_families)])

    def T(F):
        F = np.asarray(F, float)
        t = 2.0 * card.c1 * np.einsum("mij,mkj->mik", F, F)
        Fa = np.einsum("mij,kj->mki", F, dirs)
        In = np.einsum("mki,mki->mk", Fa, Fa)
        s = np.empty_like(In)
        s[:, 0] = pow_linear_cauchy(In[:, 0], card.fibre_E, card.fibre_lam0, card.fibre_beta)
        s[:, 1:] = card.family_stress(np.sqrt(In[:, 1:]))
        return t + np.einsum("mk,mki,mkj->mij", s / In, Fa, Fa)

    return T


def energy_card_stress(card: EnergyCard) -> Callable[[np.ndarray], np.ndarray]:
    """Diagonal extra stress T(f) of the febio-energy card at F = diag(f) (:func:`febio_card_stress`)."""
    T3 = febio_card_stress(card)
    return lambda f: np.diagonal(T3(np.diag(np.asarray(f, float))[None]), axis1=1, axis2=2)[0]


def active_fibre_stress(c1: float, stretch: np.ndarray, stress: np.ndarray) -> Callable:
    """Diagonal extra stress of the febio-uniaxial card: Mooney-Rivlin + active fibre stress whose
    Cauchy value along the axis is the load curve, linear interpolation, extrapolated linearly."""
    x, y = np.asarray(stretch, float), np.asarray(stress, float)

    def stl(lam):
        if lam <= x[0]:
            return y[0] + (lam - x[0]) * (y[1] - y[0]) / (x[1] - x[0])
        if lam >= x[-1]:
            return y[-1] + (lam - x[-1]) * (y[-1] - y[-2]) / (x[-1] - x[-2])
        return float(np.interp(lam, x, y))

    def T(f):
        t = _deviatoric_iso(c1, f)
        t[0] += stl(f[0])
        return t

    return T


def marlow_stress(strain: np.ndarray, nominal: np.ndarray) -> Callable:
    """Diagonal extra stress of an isotropic Marlow solid built from uniaxial (nominal) test data.

    Marlow's energy depends on Ī1 only and reproduces the test: W(Ī1(λ)) = ∫₁^λ T dλ with
    Ī1(λ) = λ² + 2/λ and T the data interpolated linearly, so dW/dĪ1 = T(λ)/(2·(λ − 1/λ²)) at the
    tension stretch λ ≥ 1 of that Ī1 (found by root finding); σ = 2·W'(Ī1)·B.
    """
    lam_t = 1.0 + np.asarray(strain, float)
    t = np.asarray(nominal, float)
    keep = lam_t >= 1.0  # the tension branch defines W(Ī1)
    lam_t, t = lam_t[keep], t[keep]
    slope0 = (t[1] - t[0]) / (lam_t[1] - lam_t[0])

    def dW(I1):
        if I1 - 3.0 < 1e-12:
            return slope0 / 6.0  # T ~ T'(1)(λ − 1), λ − 1/λ² ~ 3(λ − 1)
        lam = brentq(lambda x: x * x + 2.0 / x - I1, 1.0, max(2.0, np.sqrt(I1)), xtol=1e-15, rtol=1e-15)
        return float(np.interp(lam, lam_t, t)) / (2.0 * (lam - lam ** -2))

    def T(f):
        return 2.0 * dW(float(np.sum(f ** 2))) * f ** 2

    return T


def uniaxial_solve(T: Callable, strain: np.ndarray) -> np.ndarray:
    """σ11 of the incompressible solid with extra stress T in uniaxial tension along x.

    For each λ = 1 + ε the lateral stretch λ2 is the root of T22 − T33 = 0 with λ3 = 1/(λ·λ2)
    (brentq on a bracket around λ^−1/2); σ11 = T11 − T33 (pressure from face 3).
    """
    out = np.empty(len(strain))
    for i, e in enumerate(np.asarray(strain, float)):
        lam = 1.0 + e
        if abs(e) < 1e-14:
            out[i] = 0.0
            continue

        def g(l2):
            t = T(np.array([lam, l2, 1.0 / (lam * l2)]))
            return t[1] - t[2]

        mid = lam ** -0.5
        a, b = mid * 0.7, mid / 0.7
        if g(a) * g(b) > 0:  # no sign change: the symmetric state (g is 0 there by symmetry)
            l2 = mid
        else:
            l2 = brentq(g, a, b, xtol=1e-15, rtol=1e-15)
        t = T(np.array([lam, l2, 1.0 / (lam * l2)]))
        out[i] = t[0] - t[2]
    return out


def compare(fmt: str, T: Callable, strain, ref, tested_mask, exact: bool, bound: float, method: str) -> Check:
    """Solve the card's law and compare with ``ref`` (hbm's curve) on the tested and 1.5x range."""
    card = uniaxial_solve(T, strain)
    e_t = relative_error(card[tested_mask], np.asarray(ref)[tested_mask])
    e_x = relative_error(card, ref)
    limit = EXACT_TOLERANCE if exact else bound + BOUND_SLACK
    return Check(format=fmt, exact=exact, error_tested=e_t, error_extended=e_x,
                 bound=EXACT_TOLERANCE if exact else bound, passed=bool(e_t <= limit), method=method)
