"""hbm's own evaluation of what an energy card is: the card's laws on hbm's 3-D machinery.

Every energy card is evaluated twice in every loading mode (:mod:`.modes`): re-implemented from its
documentation and solved independently (:mod:`.verify`, :mod:`.abaqus_uanisohyper`), and here, by
:class:`hbm.model.energy3d.Energy3D` and the load cases' solvers with the card's discretised laws in
place of the exact ones.  The second gives the deviation the card *states*; the first must agree with it.

* ``abaqus-uanisohyper``: hbm's own laws on N equally spaced families,
  ``Energy3D(collagen3d=ConeFamilies(N))`` (:func:`family_energy`);
* ``febio-energy``: :class:`CardEnergy`, the FEBio laws (Mooney-Rivlin, ``fiber-pow-linear`` along the
  axis, N ``uncoupled fiber-exp-linear`` families) in the energy's fibre and segment hooks.
"""

from __future__ import annotations

import numpy as np

from ..model.energy3d import ConeFamilies, Energy3D
from .laws import (EnergyCard, exp_linear_cauchy, exp_linear_energy, exp_linear_slope, pow_linear_cauchy,
                   pow_linear_energy, pow_linear_slope)


def family_energy(k_iso: float, n: int) -> Energy3D:
    """hbm's energy form with the exact segment law on ``n`` equally spaced families (the azimuths of
    :func:`hbm.export.laws.cone_directions`): the Abaqus card, and the family share of any card."""
    return Energy3D(k_iso, "energy", ConeFamilies(n))


class ExpLinearFamilies(ConeFamilies):
    """N equally spaced families carrying FEBio's ``uncoupled fiber-exp-linear`` law.

    Parameters
    ----------
    card : EnergyCard
        c3, c4, c5, lam1 per family and N.
    collagen_volume : float
        1 − c: the energy scales the reading by it, the card's families already carry it.
    """

    def __init__(self, card: EnergyCard, collagen_volume: float) -> None:
        super().__init__(card.n_families)
        self.name = f"febio-exp-linear({self.n})"
        self._law = (card.c3, card.c4, card.c5, card.lam1)
        # per unit collagen volume, summed over the families (the rule's weights are 1/N)
        self._scale = self.n / float(collagen_volume)

    def segment_energy(self, l, t1, t2):
        return self._scale * exp_linear_energy(l, *self._law)

    def segment_force(self, x, t1, t2):
        lam = 1.0 + x
        return self._scale * exp_linear_cauchy(lam, *self._law) / lam

    def segment_stiffness(self, x, t1, t2):
        # x = ⟨l − 1⟩₊: a slack segment (x = 0) has no stiffness, though the law's slope at l = 1⁺ is c3·c4
        lam = 1.0 + x
        k = exp_linear_slope(lam, *self._law) / lam - exp_linear_cauchy(lam, *self._law) / lam ** 2
        return self._scale * np.where(x > 0, k, 0.0)


class CardEnergy(Energy3D):
    """The ``febio-energy`` card as an :class:`Energy3D`: Mooney-Rivlin c1 = μ/2 (the neo-Hookean matrix
    of hbm, unchanged), ``fiber-pow-linear`` along the axis, :class:`ExpLinearFamilies` collagen.

    Parameters
    ----------
    card : EnergyCard
    k_iso : float
        The fit's iso factor (μ = k_iso·G = 2·c1).
    collagen_volume : float
        1 − c of the card's parameter set.
    """

    def __init__(self, card: EnergyCard, k_iso: float, collagen_volume: float) -> None:
        super().__init__(k_iso, "energy", ExpLinearFamilies(card, collagen_volume))
        self._fibre = (card.fibre_E, card.fibre_lam0, card.fibre_beta)

    def _fibre_energy(self, p, lf_minus_1):
        lam = 1.0 + np.asarray(lf_minus_1, float)
        return pow_linear_energy(lam * lam, *self._fibre)

    def _fibre_force(self, p, lf_minus_1):
        # dΨ/dλ = (Cauchy stress)/λ
        lam = 1.0 + np.asarray(lf_minus_1, float)
        return pow_linear_cauchy(lam * lam, *self._fibre) / lam

    def _fibre_stiffness(self, p, lf_minus_1):
        lam = 1.0 + np.asarray(lf_minus_1, float)
        return 2.0 * pow_linear_slope(lam * lam, *self._fibre) - pow_linear_cauchy(lam * lam, *self._fibre) / lam ** 2
