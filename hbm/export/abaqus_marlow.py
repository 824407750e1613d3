"""``abaqus-marlow``: ``*HYPERELASTIC, MARLOW`` with ``*UNIAXIAL TEST DATA`` (nominal stress, nominal strain).

Marlow's isotropic energy W(Ī1) reproduces the tabulated uniaxial test exactly (between the
points, up to Abaqus's interpolation).  Isotropic and fully incompressible (no volumetric data):
valid for quick 1-D-like models loaded in uniaxial tension along one direction; it knows nothing
of the fibre direction.
"""

from __future__ import annotations

import numpy as np

from . import verify
from .modes import SCOPE_ALONG
from .registry import Written

DESCRIPTION = "Abaqus *HYPERELASTIC, MARLOW with *UNIAXIAL TEST DATA (isotropic, exact in uniaxial tension)"
SUFFIX = ".inp"
VALID = ("uniaxial tension within the tabulated strain range; isotropic (no fibre direction), fully "
         "incompressible (Abaqus/Standard); shear, biaxial and compressive states are Marlow's isotropic "
         "extrapolation, not hbm's model")


def table(src) -> tuple[np.ndarray, np.ndarray]:
    """(nominal strain, nominal stress) of the tension part of the curve."""
    strain, stress = src.table()
    keep = strain >= 0
    e = strain[keep]
    return e, stress[keep] / (1.0 + e)


def check(src) -> verify.Check:
    e, t = table(src)
    strain, ref = src.reference()
    tension = strain >= 0
    return verify.compare("abaqus-marlow", verify.marlow_stress(e, t), strain[tension],
                          ref[tension], src.in_tested(strain[tension]), True, verify.EXACT_TOLERANCE,
                          "Marlow W(I1) integrated from the table, 3-D incompressible, lateral stretch by "
                          "root finding (tension part)")


def write(src) -> Written:
    chk = check(src)
    e, t = table(src)
    head = ["** hbm export: " + DESCRIPTION]
    head += [f"** {k}: {v}" for k, v in src.provenance().items()]
    head += [f"** valid for: {VALID}",
             f"** check ({chk.method}): max relative difference to hbm {chk.error_tested:.3g} on the tested "
             f"range, {chk.error_extended:.3g} on 1.5x it; tolerance {chk.bound:.3g}: "
             f"{'passed' if chk.passed else 'FAILED'}"]
    head += [f"** {n}" for n in src.notes]
    body = ["*MATERIAL, NAME=MUSCLE", "*HYPERELASTIC, MARLOW", "*UNIAXIAL TEST DATA",
            "** nominal stress (MPa), nominal strain"]
    body += [f"{s:.10g}, {x:.10g}" for x, s in zip(e[1:], t[1:])]  # the origin (0, 0) is implied
    return Written(text="\n".join(head + body) + "\n", checks=[chk], card={"points": int(e.size - 1)},
                   scope=SCOPE_ALONG)
