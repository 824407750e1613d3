"""Sample only the nonlinear parameters, then complete the posterior over all parameters.

:func:`sample_collapsed` runs the existing TMCMC (:func:`hbm.samplers.tmcmc`) on the collapsed
likelihood (the amplitudes integrated out, :class:`~hbm.likelihood.collapsed.likelihood.CollapsedLikelihood`),
optionally refines the evidence by importance sampling in the same space
(:func:`hbm.samplers.importance.importance_evidence`), and draws the amplitudes -- then the
original parameters -- given each posterior φ.  The evidence is that of the full model: the
prior on φ stays uniform in the likelihood's working coordinates and the amplitudes' prior is
integrated exactly.

Random streams (all from the caller's TMCMC seed ``s``): TMCMC ``s``; the amplitude draws
``SeedSequence([s, 1])``; the importance draws ``SeedSequence([s, 2])``; the resampling of the
accepted importance draws into the posterior population ``SeedSequence([s, 3])``.

Chains (:mod:`hbm.samplers.chains`): the posterior keeps the TMCMC run's islands as chains, or,
after an accepted importance finish, K independent batches of the importance draws each resampled
into its own chain (K = the run's ``n_islands``; pooled as one chain, with the reason, when the
batches' evidences disagree).  A TMCMC run that serves as the importance pilot pools its islands
at β = 1 as before (``final_resampling="pooled"``): the proposal and the evidence are those of the
code before chains; if such a run's population becomes the posterior (finish refused, single-run
route), it is one chain.  The completion draws the amplitudes row by row, so every row stays
in its chain.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from ...samplers.chains import Chains, importance_batches
from ...samplers.importance import FINISH_MIXTURE, FINISH_RESERVE, MIN_ESS, ImportanceResult, importance_evidence
from ...samplers.resampling import resample
from ...samplers.tmcmc import tmcmc
from .likelihood import CollapsedLikelihood

__all__ = ["CollapsedFit", "CollapsedRoute", "FIT_ROUTE", "sample_collapsed", "fit_collapsed", "ERROR_ROWS"]

#: posterior rows on which the quadrature's error estimate is evaluated (a refined second integral)
ERROR_ROWS = 256


@dataclass
class CollapsedFit:
    """Outcome of :func:`sample_collapsed`.

    Attributes
    ----------
    samples : ndarray (n, d_full)
        Posterior over all free parameters, in the full likelihood's working coordinates.
    log_likelihood : ndarray (n,)
        Full log-likelihood of each sample.
    log_evidence, log_evidence_se : float
        From the importance finish when it was accepted, else from TMCMC.
    evidence_source : str
        "tmcmc" or "importance".
    tmcmc : TMCMCResult
        The run over the sampled (nonlinear and noise) parameters.
    importance : ImportanceResult or None
    n_evaluations : int
        Model evaluations: basis evaluations of TMCMC, the importance draws, the completion and
        the error estimate, plus the full-model evaluations of the completed samples.
    quadrature_error : float
        Largest |log L_c − log L_c'| (refined rule) over up to :data:`ERROR_ROWS` posterior rows.
    info : dict
        JSON-able summary (tier, sampled parameters, columns, the numbers above).
    chains : Chains
        How ``samples`` splits into chains (chain-major).
    """

    samples: np.ndarray
    log_likelihood: np.ndarray
    log_evidence: float
    log_evidence_se: float
    evidence_source: str
    tmcmc: Any
    importance: ImportanceResult | None
    n_evaluations: int
    quadrature_error: float
    info: dict = field(default_factory=dict)
    chains: Chains = field(default_factory=lambda: Chains(1, "pooled", "not recorded"))


def sample_collapsed(cl: CollapsedLikelihood, n_samples: int | None = None, *, seed: int,
                     importance_draws: int = 0, min_ess: float = MIN_ESS, importance_adapt: float = 0.3,
                     progress: bool = False,
                     checkpoint=None, n_out: int | None = None, **tmcmc_options) -> CollapsedFit:
    """TMCMC over φ on the collapsed likelihood, optional importance finish, completed posterior.

    Parameters
    ----------
    cl : CollapsedLikelihood
    n_samples : int or None
        TMCMC population size (None: TMCMC's default or its preset's).
    seed : int
        TMCMC seed; the completion and importance streams derive from it (module docstring).
    importance_draws : int
        Proposal draws of the importance finish; 0 skips it.  When it is accepted its evidence
        is reported and the posterior population is resampled from its weighted draws.
    min_ess : float
        Smallest accepted importance ESS (absolute).
    importance_adapt : float
        Share of the importance draws spent on a first round that refits the proposal to its
        own weighted draws (:func:`~hbm.samplers.importance.importance_evidence`, ``adapt``; the
        refit is a mixture of :data:`~hbm.samplers.importance.FINISH_MIXTURE` t components, and
        :data:`~hbm.samplers.importance.FINISH_RESERVE` of the draws are spent only when the
        estimate is refused).  On the muscle benchmark (seeds 0–9, N = 500 pilot) one round was
        refused in 4/10 (ESS 5–9 % or k̂ 1.06), 0.3 in none (ESS 12–20 %, k̂ ≤ 0.5, |Δlog Ẑ| ≤ 0.08).
    progress : bool
    checkpoint : path, optional
        TMCMC checkpoint file.
    n_out : int, optional
        Posterior draws returned when the importance finish is accepted (resampled from its
        weighted draws); default the TMCMC population size.
    **tmcmc_options
        Passed to :func:`hbm.samplers.tmcmc` (preset, max_steps, cov_target, max_evaluations ...).

    Returns
    -------
    CollapsedFit
    """
    start = cl.n_evaluations
    if importance_draws:
        # a pilot for the importance proposal: its final population pooled by evidence as before chains,
        # so proposal and evidence are unchanged (with equal-weight islands here the posterior means came
        # out 0.016 ± 0.008 gold sd worse over 30 seeds, the batch resampling's share of it 0.001)
        tmcmc_options = {"final_resampling": "pooled", **tmcmc_options}
    tr = tmcmc(cl, cl.bounds, n_samples, seed=seed, progress=progress, checkpoint=checkpoint, **tmcmc_options)
    log_z, log_z_se, source = float(tr.log_evidence), float(tr.log_evidence_se), "tmcmc"
    imp = None
    if importance_draws:
        imp = importance_evidence(cl, cl.bounds, tr.samples, int(importance_draws),
                                  seed=np.random.SeedSequence([int(seed), 2]), min_ess=min_ess,
                                  adapt=importance_adapt, mixture=FINISH_MIXTURE, reserve=FINISH_RESERVE)
        if imp.accepted:
            log_z, log_z_se, source = imp.log_evidence, imp.log_evidence_se, "importance"
    phi, chains = np.asarray(tr.samples, float), tr.chains
    if imp is not None and imp.accepted:
        # the accepted importance draws are the better posterior sample (ESS ≫ N): resample N of them,
        # batch by batch into chains (or pooled, as before, when the batches disagree)
        n_post = int(n_out or phi.shape[0])
        rng = np.random.default_rng(np.random.SeedSequence([int(seed), 3]))
        idx, chains = importance_batches(imp.log_weights, n_post, int(tr.config.n_islands), rng)
        if idx is None:  # pooled: one systematic resampling of all the draws
            idx = resample(np.exp(imp.log_weights - np.max(imp.log_weights)), n_post, rng)
        phi = imp.samples[idx]
    full = cl.complete(phi, np.random.default_rng(np.random.SeedSequence([int(seed), 1])))
    ll = cl.lik(full)
    step = max(1, phi.shape[0] // ERROR_ROWS)
    _, err = cl.log_likelihood(phi[::step], refine=True)
    qerr = float(np.nanmax(err)) if err.size else 0.0
    n_eval = cl.n_evaluations - start + full.shape[0]
    info = {**cl.info(), "evidence_source": source, "quadrature_error": qerr,
            "tmcmc_log_evidence": float(tr.log_evidence), "tmcmc_log_evidence_se": float(tr.log_evidence_se),
            "tmcmc_evaluations": int(tr.n_evaluations)}
    if imp is not None:
        info["importance"] = imp.to_dict()
    info["chains"] = {"n_chains": chains.n_chains, "method": chains.method}
    return CollapsedFit(samples=full, log_likelihood=np.asarray(ll, float), log_evidence=log_z,
                        log_evidence_se=log_z_se, evidence_source=source, tmcmc=tr, importance=imp,
                        n_evaluations=int(n_eval), quadrature_error=qerr, info=info, chains=chains)


@dataclass(frozen=True)
class CollapsedRoute:
    """The route of a collapsed fit: a small pilot TMCMC run over φ with an importance finish, and a
    TMCMC run when the finish is refused.

    One route serves every caller; the numbers differ by purpose (:data:`FIT_ROUTE` for
    :func:`hbm.fit.fit_specimen`, the detective's evidence runs in :mod:`hbm.detective.rules`).

    Attributes
    ----------
    pilot_samples : int
        Particles of the pilot run; at most the draws wanted when ``pilot_capped``.
    pilot_steps : int
        MH steps per stage of the pilot (at most).
    importance_draws, draws_per_sample : int
        Draws of the importance finish: ``max(importance_draws, draws_per_sample · n)``.
    fallback_samples : int or None
        Particles of the TMCMC run after a refused finish, at most the draws wanted (None: all of them).
    fallback_steps : int
        Its MH steps per stage (at most).
    fallback_seed_offset : int
        Its seed is the pilot's plus this.
    keep_pilot_info : bool
        Record the refused pilot's ``info`` in the result's (``info["pilot"]``).
    accepted_route, refused_route : str
        ``info["route"]``, formatted with ``pilot``, ``steps``, ``draws`` (accepted) or ``reason``,
        ``n``, ``steps`` (refused).
    """

    pilot_samples: int = 500
    pilot_capped: bool = True
    pilot_steps: int = 5
    importance_draws: int = 10_000
    draws_per_sample: int = 5
    fallback_samples: int | None = None
    fallback_steps: int = 10
    fallback_seed_offset: int = 0
    keep_pilot_info: bool = True
    accepted_route: str = "pilot TMCMC + importance finish"
    refused_route: str = "importance finish refused ({reason}); TMCMC N={n} kept"


#: the collapsed fit of :func:`hbm.fit.fit_specimen`: 500 particles, ≤ 5 steps per stage, an importance
#: finish of max(10 000, 5·n) draws; when it is refused, TMCMC with N = n and ≤ 10 steps per stage
FIT_ROUTE = CollapsedRoute()


def fit_collapsed(cl: CollapsedLikelihood, n_samples: int, *, seed: int, progress: bool = False, checkpoint=None,
                  route: CollapsedRoute = FIT_ROUTE, **tmcmc_options) -> CollapsedFit:
    """The collapsed fit: cheap first, the full run when needed (:class:`CollapsedRoute`).

    With no TMCMC options given: the route's pilot (:data:`FIT_ROUTE`: TMCMC with N = min(``n_samples``,
    500) and at most 5 MH steps per stage), then the importance finish (up to max(10 000, 5·``n_samples``)
    draws, 80 % unless refused), whose resampled draws give the ``n_samples`` posterior draws (~30 k
    evaluations on the muscle benchmark).  When the finish is refused (k̂ > 0.7 or ESS < 200), TMCMC runs
    again (:data:`FIT_ROUTE`: N = ``n_samples``, at most 10 steps per stage; its evidence and population are
    used; the evaluations of both runs are counted).  With TMCMC options (e.g. ``n_steps``,
    ``max_evaluations``): one TMCMC run with N = ``n_samples`` and those options (``max_steps`` the route's
    ``fallback_steps`` unless given), and an importance finish only if ``importance_draws`` is among them.

    Parameters
    ----------
    cl : CollapsedLikelihood
    n_samples : int
        Posterior draws wanted.
    seed : int
        TMCMC seed (streams: :func:`sample_collapsed`; the second run uses ``seed`` plus the route's
        ``fallback_seed_offset``).
    progress : bool
    checkpoint : path, optional
        TMCMC checkpoint of the first run (the pilot, or the single run with options); a second
        run after a refused finish checkpoints to ``<checkpoint>.second.npz`` and removes it
        when it completes.
    route : CollapsedRoute
        The numbers of the route (default :data:`FIT_ROUTE`).
    **tmcmc_options

    Returns
    -------
    CollapsedFit
        ``info["route"]`` says which route produced it.
    """
    n = int(n_samples)
    if tmcmc_options:
        opts = {"max_steps": route.fallback_steps, **tmcmc_options}
        out = sample_collapsed(cl, n, seed=seed, progress=progress, checkpoint=checkpoint, **opts)
        out.info["route"] = "TMCMC" + (" + importance finish" if out.evidence_source == "importance" else "")
        return out
    n_pilot = min(n, route.pilot_samples) if route.pilot_capped else route.pilot_samples
    draws = max(route.importance_draws, route.draws_per_sample * n)
    pilot = sample_collapsed(cl, n_pilot, seed=seed, progress=progress, checkpoint=checkpoint,
                             max_steps=route.pilot_steps, n_out=n, importance_draws=draws)
    if pilot.importance.accepted:
        pilot.info["route"] = route.accepted_route.format(pilot=n_pilot, steps=route.pilot_steps, draws=draws)
        return pilot
    n2 = n if route.fallback_samples is None else min(n, route.fallback_samples)
    # the second run has other settings: its own checkpoint, removed once it is complete
    second = None if checkpoint is None else Path(checkpoint).with_suffix(".second.npz")
    full = sample_collapsed(cl, n2, seed=seed + route.fallback_seed_offset, progress=progress, checkpoint=second,
                            max_steps=route.fallback_steps)
    if second is not None and second.exists():
        second.unlink()
    full.n_evaluations += pilot.n_evaluations
    full.info["route"] = route.refused_route.format(reason=pilot.importance.reason, n=n2, steps=route.fallback_steps)
    if route.keep_pilot_info:
        full.info["pilot"] = pilot.info
    return full
