"""``damage``: Mullins-type softening on unloading and reloading below the previous maximum."""

from __future__ import annotations

import numpy as np

from ..model.core import Effect, Parameter
from ._common import history_slices


class Damage(Effect):
    """Mullins-type stress softening (pseudo-elastic, Ogden & Roxburgh 1999, simplified).

    With σ_e the stress entering the history stage and σ_max its running maximum along the
    loading history (``np.maximum.accumulate`` per history)::

        σ = η·σ_e,   η = 1 − d·(1 − σ_e/σ_max)   (η = 1 where σ_max ≤ 0)

    On primary loading σ_e = σ_max, η = 1: the virgin curve is untouched.  On unloading the
    stress drops below the loading curve (η < 1); reloading retraces the unloading path
    until the previous maximum is reached and then continues on the primary curve.  The
    stress σ_e plays the role of the strain-energy ratio ψ/ψ_max (both increase monotonically
    along a uniaxial path).  Needs the load–unload–reload segments in one loading history
    (a ``time`` column whose time continues between the tests).  d = 0 reproduces the
    elastic model exactly.

    Parameters
    ----------
    DMG : -, box [0, 0.9], null 0.
        Unloading curves of soft tissues lie 20–60 % below the loading curve at half the
        previous maximum (Peña E, Doblaré M 2009, Int J Solids Struct 46:1727–1735; Ogden RW,
        Roxburgh DG 1999, Proc R Soc Lond A 455:2861–2877).
    """

    name = "damage"
    stage = "history"
    parameters = (Parameter("DMG", 0.0, 0.9, "-", "Mullins softening at zero stress after a maximum", null=0.0),)
    strength = "DMG"
    description = "Mullins-type softening below the previous maximum (load-unload-reload)"
    reference = "Ogden RW, Roxburgh DG (1999) Proc R Soc Lond A 455:2861-2877"
    along_fibre_reason = ("its softening is driven by the running maximum of the along-fibre stress; a 3-D "
                          "damage variable (which energy, which components soften) is not modelled")

    def experiment(self, f):
        if f["reload_beyond"]:
            return [], ["a load-unload-reload cycle beyond the previous maximum"]
        return ["a load-unload-reload cycle reloading beyond the previous maximum strain"], []

    def modify(self, state, p, stress):
        d = p["DMG"]
        stress = np.broadcast_to(stress, np.broadcast_shapes(stress.shape, d.shape))
        smax = np.empty(stress.shape)
        for sl in history_slices(state.loading):
            smax[..., sl] = np.maximum.accumulate(stress[..., sl], axis=-1)
        pos = smax > 0
        ratio = np.where(pos, np.clip(stress / np.where(pos, smax, 1.0), 0.0, 1.0), 1.0)
        return stress * (1.0 - d * (1.0 - ratio))
