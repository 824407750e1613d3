"""``viscoelastic``: quasi-linear viscoelasticity (Fung) with a Prony-series relaxation function."""

from __future__ import annotations

import numpy as np

from ..errors import HbmError
from ..model.core import Effect, Parameter
from ._common import history_slices


class Viscoelastic(Effect):
    """Quasi-linear viscoelasticity (Fung 1981): the elastic stress σ_e(ε(t)) relaxes with a
    reduced relaxation function G::

        σ(t) = ∫₀ᵗ G(t − s) · dσ_e/ds ds,    G(t) = 1 − Σᵢ gᵢ·(1 − exp(−t/τᵢ))

    Evaluated along each loading history with the standard recursive (exponential
    integrator) update, exact when σ_e is piecewise linear in time between data points::

        σ = g∞·σ_e + Σᵢ hᵢ,   g∞ = 1 − Σᵢ gᵢ
        hᵢ(t_k) = e^{−Δt/τᵢ}·hᵢ(t_{k−1}) + gᵢ·Δσ_e·(τᵢ/Δt)·(1 − e^{−Δt/τᵢ})

    Each history starts from rest (hᵢ = gᵢ·σ_e at its first point, i.e. an instantaneous
    step there); tests whose time continues are one history (``state.loading.history``), so a
    relaxation hold or a reload remembers the ramp before it.  Requires the ``time`` column.
    A faster ramp gives a higher stress; during a hold the stress decays towards g∞·σ_e
    with time constants τᵢ.  gᵢ = 0 reproduces the elastic model exactly.

    Parameters
    ----------
    G1 : -, box [0, 0.9] (one term) or [0, 0.45] (two terms), null 0.
    LOGTAU1 : log10 s, box [−1, 3.5], null 1 (placeholder; irrelevant when G1 = 0).
        Passive muscle relaxes by 30–70 % with time constants from ~1 s to ~1000 s
        (Van Loocke M, Lyons CG, Simms CK 2008, J Biomech 41:1555–1566; Best TM et al. 1994,
        J Biomech 27:413–419).
    G2, LOGTAU2 : second Prony term when ``terms=2`` (null 0 / 2.5).

    Parameters of the constructor
    -----------------------------
    terms : {1, 2}
        Number of Prony terms.
    tau : float or sequence of float, optional
        Fix the time constant(s) in seconds instead of inferring LOGTAUᵢ.
    """

    name = "viscoelastic"
    stage = "history"
    strength = "G1"
    description = "quasi-linear viscoelasticity (Fung), Prony series, along each loading history"
    reference = "Fung YC (1981) Biomechanics: Mechanical Properties of Living Tissues, Springer"
    preserves_linearity = True  # a linear operator on the elastic stress: it filters each column
    # in every mode: the operator on the Kirchhoff stress tensor (J = 1) acts on each stress observable's own
    # history, and the traction-free conditions keep their elastic kinematics (hbm.model.modes_effects)
    modes = "stress_observables"
    #: index of the first Prony term (G1, LOGTAU1 ...); a further relaxation time (hbm.effects.relaxation) counts on
    first = 1
    parameters = (Parameter("G1", 0.0, 0.9, "-", "relaxing fraction of the Prony term 1", null=0.0),
                  Parameter("LOGTAU1", -1.0, 3.5, "log10 s", "log10 relaxation time of Prony term 1", null=1.0))

    def __init__(self, terms: int = 1, tau=None) -> None:
        if terms not in (1, 2):
            raise HbmError(f"viscoelastic: terms must be 1 or 2, got {terms!r}")
        taus = None if tau is None else [float(t) for t in np.atleast_1d(tau)]
        if taus is not None and (len(taus) != terms or not all(t > 0 for t in taus)):
            raise HbmError(f"viscoelastic: tau must be {terms} positive time constant(s) in s, got {tau!r}")
        self.terms, self.tau = terms, taus
        gmax = 0.9 if terms == 1 else 0.45
        params = []
        for i in range(self.first, self.first + terms):
            params.append(Parameter(f"G{i}", 0.0, gmax, "-", f"relaxing fraction of Prony term {i}", null=0.0))
            if taus is None:
                params.append(Parameter(f"LOGTAU{i}", -1.0, 3.5, "log10 s",
                                        f"log10 relaxation time of Prony term {i}", null=float(i)))
        self.parameters = tuple(params)

    def experiment(self, f):
        add, have = [], []
        if not f["time"]:
            add.append("a time column (the strain rate of each test)")
        if len(f["rates"]) >= 2 and max(f["rates"]) / min(f["rates"]) >= 9:
            have.append(f"{len(f['rates'])} strain rates")
        else:
            add.append("ramps at strain rates at least a decade apart (e.g. 0.01, 0.1, 1 %/s)")
        (have if f["hold"] else add).append("a relaxation hold" + ("" if f["hold"] else " of a few minutes"))
        return add, have

    def _taus(self, p):
        if self.tau is not None:
            return [np.asarray(t) for t in self.tau]
        return [10.0 ** p[f"LOGTAU{i}"] for i in range(self.first, self.first + self.terms)]

    def modify(self, state, p, stress):
        loading = state.loading
        if loading.time is None:
            raise HbmError("viscoelastic effect needs a 'time' column (s) in the specimen; this loading has none")
        g = [p[f"G{i}"] for i in range(self.first, self.first + self.terms)]  # (..., 1)
        taus = self._taus(p)
        shape = np.broadcast_shapes(stress.shape, *(x.shape for x in g), *(np.shape(t) for t in taus))
        stress = np.broadcast_to(stress, shape)
        ginf = 1.0 - sum(g)
        # (n,); 0 at the first point, and clipped where time restarts (unused there: new history)
        dt = np.maximum(np.diff(loading.time, prepend=loading.time[:1]), 0.0)
        ds = np.diff(stress, axis=-1, prepend=stress[..., :1])
        out = np.empty(shape)
        # per term: decay e_k = exp(-dt/tau) and increment gain f_k = (tau/dt)(1 - e_k) (-> 1 as dt -> 0)
        decay, gain = [], []
        for tau in taus:
            r = dt / tau
            e = np.exp(-r)
            decay.append(e)
            gain.append(np.where(r > 0, -np.expm1(-r) / np.where(r > 0, r, 1.0), 1.0))
        for sl in history_slices(loading):
            a = sl.start
            h = [gi[..., 0] * stress[..., a] for gi in g]
            out[..., a] = ginf[..., 0] * stress[..., a] + sum(h)
            for k in range(a + 1, sl.stop):
                for i in range(self.terms):
                    h[i] = decay[i][..., k] * h[i] + g[i][..., 0] * ds[..., k] * gain[i][..., k]
                out[..., k] = ginf[..., 0] * stress[..., k] + sum(h)
        return out
