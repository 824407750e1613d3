"""What a diagnosis will cost, and what it left undecided when stopped (``--max-time``).

* :func:`cost_estimate` -- before the first fit: one timed batch of likelihood evaluations of the
  base model and of every candidate model, times the evaluations a fit is expected to make
  (CMA-ES per noise model + the TMCMC stages), summed over the fits a diagnosis usually runs;
* :func:`stop_record` -- after a stop: the verdict so far, the steps not run and why.

The refits of a round run in ``fitter.workers`` forked processes (one refit each, all started
from the same base fit), so a round's refits cost about their sum over the workers.
"""

from __future__ import annotations

import time as _time
from typing import Sequence

import numpy as np

from ..model.core import Effect, Model
from .fitting import Fitter
from .rules import (
    COLLAPSED_ROUTE, N_CONTROL_REFITS, TMCMC_MAX_STEPS)

__all__ = ["cost_estimate", "revised_estimate", "stop_record", "stop_reserve", "fit_evaluations",
           "collapsed_evaluations"]

#: TMCMC stages of a typical evidence run (β from 0 to 1; measured 10-16 on the validation)
_STAGES = 13
#: CMA-ES generations per noise model of one fit (≈ 3000 evaluations in populations of ≈ 10)
_CMA_CALLS = 300
_CMA_POP = 10
#: wall seconds of one fit beyond its likelihood evaluations (CMA-ES and TMCMC bookkeeping, the
#: noise-model cross-seeding, the coverage): measured 3.0 s on a 40-point ramp whose
#: evaluations take 0.2 s (2-core machine shared by several jobs)
_FIT_OVERHEAD = 3.0


def fit_evaluations(n_samples: int, n_noises: int) -> int:
    """Likelihood evaluations (rows) one fit is expected to make: CMA-ES at each noise model,
    then a TMCMC run of ``n_samples`` particles × ≤ ``TMCMC_MAX_STEPS`` MH steps per stage."""
    return int(_CMA_CALLS * _CMA_POP * n_noises + n_samples * TMCMC_MAX_STEPS * _STAGES)


#: TMCMC stages of a collapsed evidence run (measured 6-10 on the validation and the 150-point record)
_COLLAPSED_STAGES = 8


def collapsed_evaluations(n_samples: int) -> int:
    """Evaluations (rows of the collapsed likelihood) of one collapsed evidence run whose
    importance finish is accepted: the small TMCMC run, the finish, the completion."""
    r = COLLAPSED_ROUTE
    return int(r.pilot_samples * r.pilot_steps * _COLLAPSED_STAGES + r.importance_draws + n_samples)


def _fit_seconds(fitter: Fitter, model: Model, noise: str, n_noises: int) -> float:
    """Expected wall seconds of one fit of ``model``: one timed batch of CMA-ES size and one of
    the TMCMC population (after an untimed call, so set-up costs are not counted), times the
    calls a fit makes (per-call overheads included, which dominate for the cheap base model).
    Where the evidence run takes the collapsed tier (:meth:`Fitter.collapsed`) its batch is timed
    on the collapsed likelihood and counted as :func:`collapsed_evaluations` rows."""
    lik = fitter.likelihood(model, noise)
    b = np.asarray(lik.bounds, float)
    n = max(int(fitter.n_samples), _CMA_POP)
    x = b[:, 0] + (b[:, 1] - b[:, 0]) * np.random.default_rng(0).uniform(0.2, 0.8, (n, b.shape[0]))
    lik(x[:2])
    t0 = _time.perf_counter()
    lik(x[:_CMA_POP])
    t1 = _time.perf_counter()
    lik(x)
    t2 = _time.perf_counter()
    cma = n_noises * _CMA_CALLS * (t1 - t0)
    cl, _ = fitter.collapsed(lik)
    if cl is None:
        return _FIT_OVERHEAD + cma + TMCMC_MAX_STEPS * _STAGES * (t2 - t1)
    phi = x[:, cl.phi_index]
    cl(phi[:2])
    t3 = _time.perf_counter()
    cl(phi)
    per_row = (_time.perf_counter() - t3) / phi.shape[0]
    return _FIT_OVERHEAD + cma + collapsed_evaluations(fitter.n_samples) * per_row


def cost_estimate(base_model: Model, candidates: Sequence[Effect], fitter: Fitter, noises: Sequence[str],
                  top: int, max_effects: int) -> dict:
    """A rough wall-time estimate of a diagnosis, from one timed evaluation per candidate model.

    The base fit, then per greedy round (one, plus one per effect it is likely to name: at most
    two are counted) ``top`` candidate refits at the median candidate's cost plus
    ``N_CONTROL_REFITS`` control refits at the base model's, each fit as :func:`_fit_seconds`;
    the removal test is counted as one fit.  The samplers' own bookkeeping is not timed, and a
    shared machine is slower: the real time can be several-fold longer (the progress log
    revises the estimate after the base fit).
    """
    noise = "iid" if "iid" in noises else noises[0]
    k = len(noises)
    base_s = _fit_seconds(fitter, base_model, noise, k)
    cand_s = {}
    for e in candidates:
        try:
            cand_s[e.name] = _fit_seconds(fitter, base_model.with_effects(e), noise, 2)
        except Exception:    # noqa: BLE001 -- a candidate that cannot be evaluated here is screened (and reported) later
            continue
    med = float(np.median(list(cand_s.values()))) if cand_s else base_s
    rounds = min(2, 1 + int(max_effects))
    refits = max(0, int(top)) + N_CONTROL_REFITS
    # a round's refits share the workers (one refit each): their sum over the workers, at least the dearest
    per_round = max(0, int(top)) * med + N_CONTROL_REFITS * base_s
    per_round = max(per_round / min(fitter.workers, refits or 1), med if top else base_s)
    seconds = base_s * 2 + per_round * rounds
    dear = sorted(cand_s.items(), key=lambda kv: -kv[1])[:3]
    # decisive comparisons are rerun with twice the MH steps (refits.refine_decisive): up to
    # about twice the sampling of the base and every refit again
    refined = 2.0 * seconds
    text = (f"cost estimate: ~{seconds:.0f} s, up to ~{seconds + refined:.0f} s where naming hinges on the evidence "
            f"and the decisive comparisons are rerun (rough; a fit of the base model ~{base_s:.1f} s, of a "
            f"candidate ~{med:.1f} s median" + (", dearest " + ", ".join(f"{n} {v:.1f} s" for n, v in dear) if dear else "")
            + f"; base fit + {refits} refits per round × {rounds} rounds + removal test; {fit_evaluations(fitter.n_samples, k)} "
            f"likelihood evaluations per full-space fit, ~{collapsed_evaluations(fitter.n_samples)} collapsed ones per "
            f"collapsed fit ({fitter.tier} tier); refits in {fitter.workers} process"
            f"{'es' if fitter.workers > 1 else ''}, and a candidate whose optimum cannot gain enough to be named "
            "skips its evidence run, so often less)")
    if fitter.deadline is not None:
        budget = fitter.seconds_left()
        if seconds > budget:
            text += f"; above the --max-time of {budget:.0f} s: the verdict so far will be written when it is reached"
    return {"seconds": float(seconds), "seconds_with_reruns": float(seconds + refined), "base_fit_seconds": float(base_s), "candidate_fit_seconds": cand_s,
            "evaluations_per_fit": fit_evaluations(fitter.n_samples, k), "text": text}


def revised_estimate(estimate: dict, base_wall: float) -> str:
    """The up-front estimate scaled by how long the base fit really took (overheads, load)."""
    f = base_wall / max(estimate["base_fit_seconds"], 1e-9)
    return (f"base fit took {base_wall:.1f} s ({f:.1f}x its estimate): revised estimate of the whole diagnosis "
            f"~{estimate['seconds'] * f:.0f} s")


#: wall seconds a stopped diagnosis keeps for what follows its last fit -- the windows at the best
#: base, the Laplace gains, the caveats -- and for the command around it (start-up, text, JSON,
#: figure).  Measured on the 150-point three-rate record stopped mid-refit (--max-time 8 and 12 s):
#: the diagnosis returned at its deadline (< 0.1 s after it) and the command took 2.5 s more; the
#: reserve covers a machine several times slower
_STOP_RESERVE = 20.0
_STOP_RESERVE_MIN = 3.0


def stop_reserve(max_time: float) -> float:
    """Seconds before ``max_time`` at which fits stop, so that the written verdict lands within
    ``max_time``: a tenth of it, at least ``_STOP_RESERVE_MIN`` and at most ``_STOP_RESERVE``
    (the base fit always runs to its end, so a limit shorter than it is overrun)."""
    return min(_STOP_RESERVE, max(_STOP_RESERVE_MIN, 0.1 * max(float(max_time), 0.0)))


def stop_record(fitter: Fitter, max_time: float | None, t_start: float) -> dict:
    """What a ``--max-time`` stop left undecided (``fitter.undecided``) and a sentence for the verdict."""
    elapsed = _time.perf_counter() - t_start
    items = [{"what": w, "why": y} for w, y in fitter.undecided]
    text = (f"stopped at --max-time ({float(max_time or 0):g} s, {elapsed:.0f} s elapsed): this is the verdict so "
            "far; not decided: " + "; ".join(f"{i['what']} ({i['why']})" for i in items))
    return {"max_time": float(max_time or 0.0), "elapsed": float(elapsed), "undecided": items, "text": text}
