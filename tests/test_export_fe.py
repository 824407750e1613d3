"""A one-element finite-element solve (felupe, a test extra: GPL, never imported by hbm) of the
febio-energy card, against the independent uniaxial check of :mod:`hbm.export.verify`."""

import numpy as np
import pytest

from hbm.export import laws, verify
from hbm.export.source import NAMES
from hbm.model.spyrou import spyrou_model

fem = pytest.importorskip("felupe")

PARAMS = {"VOLF": 0.85, "EOPT": 0.08, "P1": 0.05, "T1": 6.0, "T2": 12.0, "THETA": 58.0, "GF": 0.02, "GM": 0.04}
#: the card hbm exports for PARAMS (energy form) fitted on strains 0..0.4
CARD = laws.energy_card(PARAMS, 1.0, (0.0, 0.4), lambda e: spyrou_model(form="energy").stress(
    e, np.array([PARAMS[n] for n in NAMES])))
#: bulk modulus of the three-field (u, p, J) element: 1e5 x the shear modulus keeps J - 1 ~ 1e-5
BULK = 1e5 * 2 * CARD.c1


class CardMaterial:
    """Isochoric energy of the card: c1·(Ī1 − 3) + Σ fibres Ψ(Īn), with dΨ/dIn from the laws'
    documented Cauchy stresses (s = 2·In·dΨ/dIn); hessian by central differences of the gradient."""

    def __init__(self, card):
        self.card = card
        self.dirs = [(np.array([1.0, 0, 0]), self._fibre)] + [
            (a, self._family) for a in laws.family_directions(card.theta, card.n_families)]
        self.x = [np.eye(3), np.zeros(0)]  # felupe reads the state-variable shape from x[-1]

    def _fibre(self, In):
        return laws.pow_linear_cauchy(In, self.card.fibre_E, self.card.fibre_lam0, self.card.fibre_beta) / (2 * In)

    def _family(self, In):
        return laws.exp_pow_cauchy(In, self.card.ksi, self.card.alpha, self.card.beta) / (2 * In)

    def _P(self, F):
        J = np.linalg.det(np.moveaxis(F, (0, 1), (-2, -1)))
        Finv_T = np.moveaxis(np.linalg.inv(np.moveaxis(F, (0, 1), (-2, -1))), (-2, -1), (1, 0))
        j23 = J ** (-2.0 / 3.0)
        I1 = np.einsum("ij...,ij...->...", F, F)
        P = 2 * self.card.c1 * j23 * (F - I1 / 3 * Finv_T)
        for a, dpsi in self.dirs:
            Fa = np.einsum("ij...,j->i...", F, a)
            In = np.einsum("i...,i...->...", Fa, Fa)
            w = dpsi(j23 * In)
            P = P + 2 * w * j23 * (np.einsum("i...,j->ij...", Fa, a) - In / 3 * Finv_T)
        return P

    def gradient(self, x):
        F, statevars = x[0], x[-1]
        return [self._P(F), statevars]

    def hessian(self, x):
        F = x[0]
        h = 1e-7
        A = np.zeros((3, 3, 3, 3) + F.shape[2:])
        for k in range(3):
            for m in range(3):
                Fp, Fm = F.copy(), F.copy()
                Fp[k, m] += h
                Fm[k, m] -= h
                A[:, :, k, m] = (self._P(Fp) - self._P(Fm)) / (2 * h)
        return [A]


def test_single_element_matches_independent_check():
    mesh = fem.Cube(n=2)  # one hexahedron, unit cube
    region = fem.RegionHexahedron(mesh)
    field = fem.FieldContainer([fem.Field(region, dim=3)])  # p and J: cell-wise, added by the solid body
    umat = CardMaterial(CARD)
    solid = fem.SolidBodyNearlyIncompressible(umat, field, bulk=BULK)
    boundaries = fem.dof.uniaxial(field, clamped=False, return_loadcase=False)
    strain = np.linspace(0.05, 0.45, 9)
    step = fem.Step(items=[solid], ramp={boundaries["move"]: strain}, boundaries=boundaries)
    job = fem.CharacteristicCurve(steps=[step], boundary=boundaries["move"])
    job.evaluate(tol=1e-10)
    force = np.array([y[0] for y in job.y])  # axial reaction on the unit face = nominal stress
    lam = 1 + strain
    # Cauchy stress = force / current area; current area = J/λ with J ~ 1 (measured on the element)
    u = field[0].values
    lat = 1 + u[:, 1].min()  # lateral stretch of the (homogeneously deformed) unit cube
    J = lam[-1] * lat * (1 + u[:, 2].min())
    assert abs(J - 1) < 1e-4
    fe = np.abs(force) * lam  # σ = P·λ (incompressible); the last J enters at 1e-4
    ref = verify.uniaxial_solve(verify.energy_card_stress(CARD), strain)
    print("felupe vs independent check: max relative difference", np.max(np.abs(fe / ref - 1)))
    np.testing.assert_allclose(fe, ref, rtol=1e-3)
