"""``febio-energy``: the energy form as FEBio laws (Mooney-Rivlin + power-linear fibre + helical families).

Only for ``form="energy"`` results: the thesis form is not derived from a strain energy (its
collagen turns tensile under compression), so no hyperelastic card can reproduce it; use
``febio-uniaxial`` or ``abaqus-marlow`` for those.  The mapping and its approximations are in
:mod:`hbm.export.laws`: N ``uncoupled fiber-exp-linear`` families on the cone stand for hbm's cone
reading (DESIGN.md §8), their law fitted on the helix-segment stretches every loading mode reaches.
The card is verified along the fibres (:mod:`.verify`) and in every loading mode (:mod:`.modes`), and
states its measured deviations; N is the smallest of :data:`N_LADDER` whose N-family deviation is
within :data:`hbm.export.modes.FAMILY_TARGET` (FEBio evaluates each family separately: cost ∝ N).
"""

from __future__ import annotations

import xml.etree.ElementTree as ET

from ..errors import HbmError
from . import modes, verify
from ._xml import provenance_lines, sub, to_text, vec
from .card_models import CardEnergy
from .laws import cone_directions, energy_card
from .registry import Written

DESCRIPTION = ("FEBio uncoupled solid mixture: Mooney-Rivlin + fiber-pow-linear-uncoupled (axis) + "
               "uncoupled fiber-exp-linear helical families (energy form of the Spyrou model, cone reading)")
SUFFIX = ".feb"
VALID = ("3-D hyperelastic (an energy; hbm's cone reading with N collagen families): any homogeneous or FE "
         "loading within the deviations stated below and the family stretch lambda1; calibrated in uniaxial "
         "tension along the fibres only, so other modes are the model's prediction, not data")
#: collagen families offered, smallest first (the first within the family target is written)
N_LADDER = (12, 24, 48, 96)
COST = "FEBio evaluates one fibre material per family (cost and card size grow linearly with N)"
METHOD = ("documented FEBio fibre/matrix stresses, 3-D incompressible, lateral stretch by root finding")


def require_energy(src) -> None:
    if src.form != "energy":
        raise HbmError(f"{src.path}: fitted with the thesis form, which is not derived from a strain energy "
                       "(its collagen stress turns tensile under axial compression), so no hyperelastic card "
                       "reproduces it; refit with --form energy, or export --to febio-uniaxial / abaqus-marlow")


def make_card(src):
    """(the card, the family deviations measured for the N tried)."""
    require_energy(src)
    n, seen = modes.choose_families(src, N_LADDER)
    card = energy_card(src.constituents(), src.k_iso, src.strain_range, src.stress, n, modes.segment_stretch(src),
                       src.curve_strain)
    return card, seen


def build(card) -> ET.Element:
    root = ET.Element("febio_spec", version="4.0")
    mats = sub(root, "Material")
    m = sub(mats, "material", id=1, name="muscle", type="uncoupled solid mixture")
    sub(m, "k", card.k)
    mr = sub(m, "solid", type="Mooney-Rivlin")
    sub(mr, "c1", card.c1)
    sub(mr, "c2", 0.0)
    sub(mr, "k", 0.0)
    if card.fibre_E > 0:
        f = sub(m, "solid", type="fiber-pow-linear-uncoupled")
        sub(f, "E", card.fibre_E)
        sub(f, "beta", card.fibre_beta)
        sub(f, "lam0", card.fibre_lam0)
        sub(f, "fiber", vec((1, 0, 0)), type="vector")
        sub(f, "k", 0.0)
    if card.c3 > 0:
        for a in cone_directions(card.theta, card.n_families):
            h = sub(m, "solid", type="uncoupled fiber-exp-linear")
            sub(h, "c3", card.c3)
            sub(h, "c4", card.c4)
            sub(h, "c5", card.c5)
            sub(h, "lambda", card.lam1)
            sub(h, "fiber", vec(a), type="vector")
            sub(h, "k", 0.0)
    return root


def check(src, card) -> verify.Check:
    return verify.compare("febio-energy", verify.energy_card_stress(card), src.curve_strain,
                          src.stress(src.curve_strain), src.tested_mask(), False, card.fit_error, METHOD)


def check_modes(src, card) -> list[modes.ModeCheck]:
    """The card in every loading mode: its FEBio laws solved here against hbm's evaluation of them."""
    volume = 1.0 - src.params()[src.spec.mixture.fraction]  # the collagen's share, as Energy3D applies it
    return modes.check_card("febio-energy", verify.febio_card_stress(card), src,
                            CardEnergy(card, src.k_iso, volume), card.n_families, METHOD)


def write(src) -> Written:
    card, seen = make_card(src)
    chk = check(src, card)
    every = check_modes(src, card)
    lines = provenance_lines(src, DESCRIPTION, VALID, [chk])
    lines.append(f"approximation: along the fibres the card differs from hbm's energy form by at most "
                 f"{card.fit_error:.3g} (relative) on the tested range, {card.fit_error_15:.3g} on 1.5x it (fibre "
                 f"toe below lam0 = {card.fibre_lam0:.6g} and the exp-linear fit of the collagen)")
    if card.c3 > 0:
        lines.append(f"{card.n_families} helical families at THETA = {card.theta:.6g} deg to x, azimuths 360/"
                     f"{card.n_families} apart starting at 180/{card.n_families}, each with (1 - VOLF)/"
                     f"{card.n_families} of the collagen; the family law differs from hbm's segment law by at most "
                     f"{card.law_error:.3g} (relative) up to the segment stretch of the tested range, "
                     f"{card.law_error_15:.3g} up to lambda1 = {card.lam1:.6g} (1.5x), linear beyond")
    else:
        lines.append("no collagen families: the collagen amplitude of this parameter set is 0")
    tradeoff = modes.tradeoff_line("febio-energy", card.n_families, seen, COST)
    lines += modes.header_lines(every, tradeoff)
    if src.summary in ("p05", "p95"):
        lines.append(f"{src.summary}: the card is the posterior draw nearest the {src.summary} curve "
                     f"(max gap {src.nearest_gap:.3g} relative)")
    return Written(text=to_text(build(card), lines), checks=[chk], card=card.as_dict(), notes=[tradeoff],
                   modes=every, scope=modes.SCOPE_3D)
