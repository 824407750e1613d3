"""``offset``: constant stress offset (load-cell zero error)."""

from __future__ import annotations

from ..model.core import Effect, Parameter


def offset_experiment(self, f):
    """Both placements of the offset show at zero strain."""
    item = "points at (near) zero strain, or an unloaded load-cell reading"
    return ([], [item]) if f["near_zero"] else ([item], [])


class Offset(Effect):
    """Constant stress offset added to the output, σ → σ + S0.

    A load cell zeroed with the specimen under a small preload (or drifting) shifts the
    whole curve by a constant.  It is the only candidate visible at ε → 0, where every
    physical contribution vanishes, so it is unique (DESIGN.md §2).

    Parameters
    ----------
    S0 : MPa, box [−0.02, 0.02], null 0.
        Typical load-cell zero errors of soft-tissue rigs are ~1–10 kPa for peak stresses of
        ~0.1 MPa (e.g. Van Loocke M, Lyons CG, Simms CK 2006, J Biomech 39:2999–3009 report
        preload/zeroing of a few kPa).
    """

    name = "offset"
    stage = "output"
    parameters = (Parameter("S0", -0.02, 0.02, "MPa", "constant stress offset (load-cell zero)", null=0.0),)
    strength = "S0"
    description = "constant stress offset (load-cell zero error)"
    reference = "Van Loocke M, Lyons CG, Simms CK (2006) J Biomech 39:2999-3009"
    experiment = offset_experiment
    linear_parameters = ("S0",)  # a constant column added after the history stage
    # one load-cell zero per measured force: S0 on `stress`, S0_2 on `stress_2` (hbm.model.modes_effects)
    modes = "stress_observables"
    per_observable = True

    def modify(self, state, p, stress):
        return stress + p["S0"]
