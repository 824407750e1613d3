"""``febio-uniaxial``: Mooney-Rivlin matrix + an active fibre stress tabulating hbm's fibre + collagen stress.

An ``uncoupled solid mixture`` of ``Mooney-Rivlin`` (c1 = k_iso·G/2, c2 = 0) and an ``uncoupled
active fiber stress`` along the muscle axis (global x) with smax = 1 MPa, activation 1 and the
load curve ``stl`` = hbm's stress minus the matrix's, tabulated against the axial stretch over
1.5x the tested range.  In homogeneous uniaxial tension along the fibres the total stress is
hbm's curve (any summary, either model form); it is *not* an energy: transverse, shear or
multiaxial loading is outside its validity.
"""

from __future__ import annotations

import xml.etree.ElementTree as ET

import numpy as np

from . import verify
from ._xml import provenance_lines, sub, to_text, vec
from .laws import BULK_FACTOR
from .registry import Written

DESCRIPTION = "FEBio uncoupled solid mixture: Mooney-Rivlin + active fibre stress load curve (exact along the fibres)"
SUFFIX = ".feb"
VALID = ("homogeneous uniaxial tension/compression along the fibres within the tabulated stretch range; "
         "NOT an energy: invalid for transverse, shear or multiaxial loading")


def card(src) -> tuple[float, np.ndarray, np.ndarray]:
    """(c1, stretch, fibre stress) of the card: the tabulated stress is hbm's minus the matrix's."""
    c1 = src.k_iso * src.constituents().shear_modulus / 2.0
    strain, stress = src.table()
    lam = 1.0 + strain
    return c1, lam, stress - 2.0 * c1 * (lam ** 2 - 1.0 / lam)


def build(src) -> ET.Element:
    c1, lam, s = card(src)
    root = ET.Element("febio_spec", version="4.0")
    mats = sub(root, "Material")
    m = sub(mats, "material", id=1, name="muscle", type="uncoupled solid mixture")
    sub(m, "k", BULK_FACTOR * 2.0 * c1)
    mr = sub(m, "solid", type="Mooney-Rivlin")
    sub(mr, "c1", c1)
    sub(mr, "c2", 0.0)
    sub(mr, "k", 0.0)
    af = sub(m, "solid", type="uncoupled active fiber stress")
    sub(af, "smax", 1.0)
    sub(af, "activation", 1.0)
    stl = sub(af, "stl", type="point")
    sub(stl, "interpolate", "linear")
    sub(stl, "extend", "extrapolate")
    pts = sub(stl, "points")
    for x, y in zip(lam, s):
        sub(pts, "pt", f"{x:.10g},{y:.10g}")
    ax = sub(af, "mat_axis", type="vector")
    sub(ax, "a", vec((1, 0, 0)))
    sub(ax, "d", vec((0, 1, 0)))
    sub(af, "k", 0.0)
    return root


def check(src) -> verify.Check:
    c1, lam, s = card(src)
    strain, ref = src.reference()
    return verify.compare("febio-uniaxial", verify.active_fibre_stress(c1, lam, s), strain,
                          ref, src.in_tested(strain), True, verify.EXACT_TOLERANCE,
                          "Mooney-Rivlin + active fibre stress (linear load curve), 3-D incompressible, "
                          "lateral stretch by root finding")


def write(src) -> Written:
    chk = check(src)
    lines = provenance_lines(src, DESCRIPTION, VALID, [chk])
    lines.append(f"bulk modulus k = {BULK_FACTOR:g} x initial shear modulus (near-incompressible penalty)")
    return Written(text=to_text(build(src), lines), checks=[chk],
                   card={"c1": card(src)[0], "smax": 1.0, "points": int(src.table()[0].size)})
