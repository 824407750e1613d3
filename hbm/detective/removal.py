"""Removal test: is each base part (matrix, fibers, collagen) needed by the data?

The opposite question to the candidates': the model without one part is refitted (CMA-ES from
the full model's optimum, the same noise model) and compared by a Laplace evidence in the
removed parameters (the nested comparison of :func:`.refits.evidence_gains`, reversed).  A part
whose removal does not lower the evidence is reported: the data do not need it (its parameters
are then unidentified, and their posteriors are the prior box).
"""

from __future__ import annotations

import numpy as np

from ..model.core import Model
from ..model.spec import spec_of
from .fitting import FitInterrupted, Fitter, cma_maximise, laplace_occam
from .results import FitSummary

__all__ = ["removal_test"]


def removal_test(base: FitSummary, fitter: Fitter, seed: int) -> list[dict]:
    """For each base part of ``base.model``: Δlog Z of removing it (≥ 0: not needed).

    Returns
    -------
    list of dict
        ``part``, ``removed`` (parameters that disappear), ``delta_log_evidence`` (removal minus
        full model; Laplace in the removed parameters), ``delta_max_log_likelihood`` and
        ``needed`` (False when the removal does not lower the evidence); a part whose parameters
        other parts read cannot be removed and is left out.
    """
    model = base.model
    out = []
    full = dict(zip(base.names, base.theta_max))
    parts = [p for p in spec_of(model).effects if p in model.effect_names]
    for k, part in enumerate(parts):
        effects = [e for e in model.effects if e.name != part]
        try:
            reduced = Model(effects, name=f"{model.name} without {part}")
        except ValueError:   # another part reads its parameters: not removable alone
            continue
        removed = [n for n in model.parameter_names if n not in reduced.parameter_names]
        fix = {n: v for n, v in (fitter.fix or {}).items() if n in reduced.parameter_names}
        lik = fitter.likelihood(reduced, base.noise, fix=fix)
        b = np.asarray(lik.bounds, float)
        x0 = np.clip([full.get(n, 0.5 * (lo + hi)) for n, (lo, hi) in zip(lik.names, b)], b[:, 0], b[:, 1])
        try:
            x, f = cma_maximise(fitter.guard(lik), [x0], 0.05, seed + 7 * k, maxfevals=1200)
        except FitInterrupted:
            fitter.skip("the removal test of " + ", ".join(parts[k:]), "interrupted at --max-time: whether the "
                        "data need these parts is not known")
            break
        occ = laplace_occam(base.likelihood, base.theta_max, base.names, removed, base.samples)
        dl = float(f - base.max_log_likelihood)
        dz = dl - occ    # removing the parameters gives back their Occam factor (≤ 0)
        out.append({"part": part, "removed": removed, "delta_max_log_likelihood": dl,
                    "delta_log_evidence": float(dz), "needed": bool(dz < 0.0)})
        fitter.log(f"removal of {part}: Δlog Z {dz:+.1f} ({'needed' if dz < 0 else 'NOT needed'})")
    return out
