"""``slack``: reference-length error — the tissue is stress-free until the slack is taken up."""

from __future__ import annotations

import numpy as np

from ..model.core import Effect, Parameter
from ._common import REFERENCE_LENGTH, needs


class Slack(Effect):
    """Reference-length (slack) error: the measured strain is relative to a length that is
    too short by a fraction s of the true stress-free length.

    Tissue strain from the applied (measured) strain ε::

        ε_t = max((1 + ε)/(1 + s) − 1, min(ε, 0)) = max((ε − s)/(1 + s), min(ε, 0)),   s = SLACK ≥ 0

    For 0 ≤ ε ≤ s the specimen is slack (ε_t = 0, no compression of the tissue); beyond, the
    curve is the base curve shifted right and slightly stretched.  Applied strains below 0
    pass through unchanged, so s = 0 reproduces the base model exactly for every ε.

    Parameters
    ----------
    SLACK : -, box [0, 0.1], null 0.
        Slack of a few percent of the gauge length is common when the reference length is set
        at a force threshold on a crimped/curved specimen (e.g. Hawkins & Bey 1994 set the
        zero at a preload; Calvo et al. 2010 report a preload-defined reference).

    Notes
    -----
    Looks like exponential fiber stiffening (both reshape the toe); pinning EOPT separates
    them only partly (DESIGN.md §2).  Reference: Hawkins D, Bey M (1994) J Biomech 27:1223.
    """

    name = "slack"
    stage = "kinematics"
    parameters = (Parameter("SLACK", 0.0, 0.1, "-", "slack: fraction of the stress-free length not taken up",
                            null=0.0),)
    strength = "SLACK"
    description = "reference-length error: stress-free until the slack is taken up"
    reference = "Hawkins D, Bey M (1994) J Biomech 27:1223-1235"
    experiment = needs(REFERENCE_LENGTH)
    preserves_linearity = True  # the strain map does not depend on the stress

    def strain(self, state, p, elastic):
        eps = state.eps
        s = p["SLACK"]
        shifted = (eps - s) / (1.0 + s)  # = (1+ε)/(1+s) − 1, exact (= ε) at s = 0
        return np.maximum(shifted, np.minimum(eps, 0.0))
