"""``febio-energy``: the energy form as FEBio laws (Mooney-Rivlin + power-linear fibre + helical families).

Only for ``form="energy"`` results: the thesis form is not derived from a strain energy (its
collagen turns tensile under compression), so no hyperelastic card can reproduce it; use
``febio-uniaxial`` or ``abaqus-marlow`` for those.  The mapping and its approximations are in
:mod:`hbm.export.laws`; the card states its measured error over the tested range.
"""

from __future__ import annotations

import xml.etree.ElementTree as ET

from ..errors import HbmError
from . import verify
from ._xml import provenance_lines, sub, to_text, vec
from .laws import energy_card, family_directions
from .registry import Written

DESCRIPTION = ("FEBio uncoupled solid mixture: Mooney-Rivlin + fiber-pow-linear-uncoupled (axis) + "
               "fiber-exp-pow-uncoupled helical families (energy form of the Spyrou model)")
SUFFIX = ".feb"
VALID = ("3-D hyperelastic (an energy): any homogeneous or FE loading; calibrated in uniaxial tension "
         "along the fibres only, so other modes are the model's prediction, not data")


def require_energy(src) -> None:
    if src.form != "energy":
        raise HbmError(f"{src.path}: fitted with the thesis form, which is not derived from a strain energy "
                       "(its collagen stress turns tensile under axial compression), so no hyperelastic card "
                       "reproduces it; refit with --form energy, or export --to febio-uniaxial / abaqus-marlow")


def make_card(src):
    require_energy(src)
    return energy_card(src.constituents(), src.k_iso, src.strain_range, src.stress, src.curve_strain)


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
    if card.ksi > 0:
        for a in family_directions(card.theta, card.n_families):
            h = sub(m, "solid", type="fiber-exp-pow-uncoupled")
            sub(h, "ksi", card.ksi)
            sub(h, "alpha", card.alpha)
            sub(h, "beta", card.beta)
            sub(h, "mu", 0.0)
            sub(h, "fiber", vec(a), type="vector")
            sub(h, "k", 0.0)
    return root


def check(src, card) -> verify.Check:
    return verify.compare("febio-energy", verify.energy_card_stress(card), src.curve_strain,
                          src.stress(src.curve_strain), src.tested_mask(), False, card.fit_error,
                          "documented FEBio fibre/matrix stresses, 3-D incompressible, lateral stretch by "
                          "root finding")


def write(src) -> Written:
    card = make_card(src)
    chk = check(src, card)
    lines = provenance_lines(src, DESCRIPTION, VALID, [chk])
    lines.append(f"approximation: the card differs from hbm's energy form by at most {card.fit_error:.3g} "
                 f"(relative) on the tested range, {card.fit_error_15:.3g} on 1.5x it (fibre toe below "
                 f"lam0 = {card.fibre_lam0:.6g} and the exp-pow fit of the collagen)")
    lines.append(f"{card.n_families} helical families at THETA = {card.theta:.6g} deg to x, azimuths 360/"
                 f"{card.n_families} apart, each with (1 - VOLF)/{card.n_families} of the collagen")
    if src.summary in ("p05", "p95"):
        lines.append(f"{src.summary}: the card is the posterior draw nearest the {src.summary} curve "
                     f"(max gap {src.nearest_gap:.3g} relative)")
    return Written(text=to_text(build(card), lines), checks=[chk], card=card.as_dict())
