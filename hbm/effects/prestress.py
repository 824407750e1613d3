"""``prestress``: a constant stress carried by the tissue (the offset's placement before history)."""

from __future__ import annotations

import numpy as np

from ..model.core import Effect, Parameter
from .offset import offset_experiment


class Prestress(Effect):
    """A constant stress carried by the tissue itself, added at the elastic stage, σ_e → σ_e + S0.

    A specimen mounted under a small preload, or with residual stresses from excision, carries
    a stress at zero applied strain that *belongs to the tissue*: it relaxes with it under a
    viscoelastic (history) effect and softens with it under damage, unlike a load-cell zero
    error (``offset``), which is added to the measured output after them.  Without a history
    effect the two are the same model; with one, a pre-stress decays towards g∞·S0 during a
    slow ramp or a hold while a load-cell offset stays put.  It is declared a placement of
    ``offset`` (``placement_of``): the detective screens the two as one candidate named
    ``offset`` and, where a history effect makes them differ, refits both and keeps the one
    the evidence prefers.

    Parameters
    ----------
    S0 : MPa, box [−0.02, 0.02], null 0 (the range of ``offset``).
        Preloads of a few kPa are usual in soft-tissue rigs (Van Loocke M, Lyons CG, Simms CK
        2006, J Biomech 39:2999–3009).
    """

    name = "prestress"
    stage = "elastic"
    placement_of = "offset"
    parameters = (Parameter("S0", -0.02, 0.02, "MPa", "constant stress carried by the tissue (pre-stress)",
                            null=0.0),)
    strength = "S0"
    description = "constant stress carried by the tissue (pre-stress; relaxes/softens with it)"
    reference = "Van Loocke M, Lyons CG, Simms CK (2006) J Biomech 39:2999-3009"
    experiment = offset_experiment
    linear_parameters = ("S0",)  # a constant column, filtered by a history effect after it
    along_fibre_reason = ("a stress carried by the tissue is a stress tensor whose components and convection "
                          "under other deformations hbm does not model; a load-cell zero is 'offset', defined "
                          "per stress observable")

    def stress(self, state, p):
        s0 = p["S0"]
        return np.broadcast_to(s0, np.broadcast_shapes(s0.shape, state.eps.shape)).copy()

    def stress_jacobian(self, state, p):
        return {"S0": np.ones(np.broadcast_shapes(p["S0"].shape, state.eps.shape))}
