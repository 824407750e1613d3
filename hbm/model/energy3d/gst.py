"""The gst reading of the helical collagen: one averaged stretch λH² = H:C (DESIGN.md §8)."""

from __future__ import annotations

import numpy as np

from .base import DirectionalCollagen, Sym, register_collagen_reading


@register_collagen_reading
class GstCollagen(DirectionalCollagen):
    """Generalised structure tensor: λH² = H:C with H = cos²θ·a0⊗a0 + ½·sin²θ·(I − a0⊗a0).

    The helix is replaced by one fibre-like element whose squared stretch is the azimuthal mean of
    the segments' squared stretches, W_coll = W_c(λH).  Along the fibres (λ2 = λ3) every segment has
    that stretch, so this reading equals the cone there; elsewhere it is softer, because the mean
    of l² hides the segments that go taut first.  Convex (λH is a norm of F·H^½).
    """

    name = "gst"
    description = "one averaged helix stretch, lambda_H^2 = H:C (generalised structure tensor)"
    kernel_code = 1     # hbm.model.energy3d.diagonal.GST

    def rule(self, D, theta_deg, need="tangent"):
        c2 = np.cos(np.deg2rad(theta_deg)) ** 2
        half = 0.5 * (1.0 - c2)
        N = Sym(c2[..., None], half[..., None], half[..., None])
        l2m1 = (c2 * D.ff + half * (D.cc + D.nn))[..., None]
        return N, np.ones_like(l2m1), l2m1
