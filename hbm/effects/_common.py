"""Shared helpers of the effect library (collagen kernel, per-history slicing)."""

from __future__ import annotations

import numpy as np

from ..model.core import Loading
from ..model.spyrou import helical_stretch

# same guard as the base model: keeps exp finite for any parameter box
EXP_CLIP = 700.0


def collagen_excess(lam: np.ndarray, theta_deg) -> np.ndarray:
    """x = ⟨λH − 1⟩₊, the helical collagen stretch beyond straightening."""
    return np.maximum(helical_stretch(lam, theta_deg) - 1.0, 0.0)


def collagen_kernel(x: np.ndarray, t2) -> np.ndarray:
    """exp(T2·x) − 1 for x ≥ 0 (0 where x = 0), exponent clipped."""
    return np.expm1(np.minimum(t2 * x, EXP_CLIP))


def needs(text: str):
    """An :meth:`hbm.Effect.experiment` that always asks for the same experiment ``text``."""
    def experiment(self, f):
        return [text], []
    return experiment


#: the experiments shared by look-alike effects (DESIGN.md §2)
REFERENCE_LENGTH = ("the reference length pinned independently (stress-free length at minimal preload, or "
                    "sarcomere length to fix EOPT) and a densely sampled toe region")
COLLAGEN_IMAGING = "imaging of collagen crimp and orientation (SHG microscopy) or off-axis/biaxial tests"


def history_slices(loading: Loading) -> list[slice]:
    """Slices of the point axis, one per loading history (points in order)."""
    starts = np.flatnonzero(loading.history_starts).tolist() + [loading.n_points]
    return [slice(a, b) for a, b in zip(starts[:-1], starts[1:])]
