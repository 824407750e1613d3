"""Fitting a model at its best noise model: CMA-ES optimum, BIC choice of the noise, TMCMC
evidence and posterior-predictive coverage (used by every step that fits: the base model,
the candidate refits, each step of :func:`hbm.extend`).
"""

from __future__ import annotations

import math
import multiprocessing as mp
import sys
import time as _time
from concurrent.futures import ProcessPoolExecutor
from typing import Mapping, Sequence

import cma
import numpy as np

from ..runtime.blas import one_blas_thread
from ..likelihood.collapsed import TIERS, CollapsedLikelihood, choose_tier, fit_collapsed
from ..errors import HbmError, SettingError
from ..likelihood.core import make_likelihood
from ..model.core import Model
from ..fit.optimization import optimize
from ..samplers.tmcmc import tmcmc
from .inputs import SpecimenData, added_effects
from .results import FitSummary
from .rules import (
    BAND, COLLAPSED_MAX_COLUMNS, COLLAPSED_ROUTE, TMCMC_MAX_STEPS, TMCMC_MIN_SAMPLES, TMCMC_REFINE_MOVE,
    TMCMC_REFINE_STEPS)

__all__ = ["Fitter", "FitInterrupted", "coverage", "laplace_occam", "noise_evidence", "sample_tier"]


class FitInterrupted(Exception):
    """A fit stopped at the diagnosis's ``max_time`` (raised by a :class:`_Guarded` likelihood:
    the step that ran it is recorded as undecided, and the verdict so far stands)."""


class _Guarded:
    """A likelihood (full or collapsed) that raises :class:`FitInterrupted` once its fitter's
    deadline has passed.  Checked before every batch of evaluations, so a fit under way stops at
    its next batch -- within a fraction of a second -- rather than at its end (a refit of a slow
    candidate takes minutes on a busy machine).  Every other attribute is the wrapped object's."""

    __slots__ = ("_lik", "_fitter")

    def __init__(self, lik, fitter: "Fitter"):
        object.__setattr__(self, "_lik", lik)
        object.__setattr__(self, "_fitter", fitter)

    def __call__(self, *args, **kwargs):
        self._fitter.check_time()
        return self._lik(*args, **kwargs)

    def __getattr__(self, name):
        return getattr(self._lik, name)

    def __setattr__(self, name, value):
        setattr(self._lik, name, value)


def cma_maximise(lik, x0s: Sequence[np.ndarray], sigma0: float, seed: int, maxfevals: int,
                 popsize: int | None = None) -> tuple[np.ndarray, float]:
    """Maximise ``lik`` from each start in ``x0s`` (CMA-ES in the unit box); best (x, f)."""
    b = np.asarray(lik.bounds, float)
    lo, span = b[:, 0], b[:, 1] - b[:, 0]
    best_x, best_f = None, -np.inf
    if len(x0s):
        # CMA-ES never evaluates its mean: score the starts themselves, so a warm start at the
        # previous optimum can only improve
        X0 = np.array([np.clip(np.asarray(x, float), b[:, 0], b[:, 1]) for x in x0s])
        f0 = np.asarray(lik(X0), float)
        if np.isfinite(f0).any():
            i = int(np.nanargmax(np.where(np.isfinite(f0), f0, -np.inf)))
            best_x, best_f = X0[i].copy(), float(f0[i])
    for k, x0 in enumerate(x0s):
        u0 = np.clip((np.asarray(x0, float) - lo) / span, 1e-3, 1 - 1e-3)
        opts = {"bounds": [0.0, 1.0], "seed": int(seed) * 7919 + k + 1, "verbose": -9,
                "verb_log": 0, "verb_disp": 0, "maxfevals": int(maxfevals), "tolfun": 1e-7,
                "tolx": 1e-7}
        if popsize:
            opts["popsize"] = int(popsize)
        state = np.random.get_state()  # cma reseeds numpy's global RNG: restore the caller's
        try:
            es = cma.CMAEvolutionStrategy(u0, sigma0, opts)
            while not es.stop():
                u = np.asarray(es.ask())
                f = np.asarray(lik(lo + u * span), float)
                f = np.where(np.isfinite(f), f, -1e300)
                i = int(np.argmax(f))
                if f[i] > best_f:
                    best_f, best_x = float(f[i]), lo + u[i] * span
                es.tell(list(u), (-f).tolist())
        finally:
            np.random.set_state(state)
    if best_x is None:  # pragma: no cover - cma always evaluates something
        raise HbmError("diagnose: the optimiser found no finite likelihood value")
    return best_x, best_f


def global_fit(lik, seed: int, restarts: int) -> tuple[np.ndarray, float]:
    """Global fit of a fresh likelihood (:func:`hbm.optimize`, IPOP CMA-ES restarts)."""
    res = optimize(lik, restarts=restarts, seed=seed, maxfevals=2500)
    x = np.asarray(res.best["theta"], float)
    return x, float(np.asarray(lik(x[None, :]))[0])


def sample(lik, n_samples: int, seed: int, max_evaluations: int | None = None,
           max_steps: int = TMCMC_MAX_STEPS, move: str = "rw"):
    """TMCMC evidence run of ``n_samples`` particles, at most ``max_steps`` MH steps per stage
    (the sampler's decorrelation criterion ends a stage's moves earlier when it can) with the
    TMCMC ``move`` (``"rw"``: the global random walk; ``"local"``: the walk with the
    covariance of each point's neighbours, the refined runs of :meth:`Fitter.refine`).

    With an evaluation budget ``max_evaluations`` (opt-in) the population shrinks to what the
    budget affords: a run costs about N · (steps per stage) · (≈ 15 stages) likelihood
    evaluations.  The size depends only on the inputs (never on a wall-clock measurement), so
    the same seed gives the same diagnosis under any machine load.
    """
    n = int(n_samples)
    if max_evaluations:
        n = int(np.clip(int(max_evaluations) // (15 * int(max_steps)), TMCMC_MIN_SAMPLES, n))
        # and a hard cap: the sampler stops at the budget and says so in its result
        return tmcmc(lik, np.asarray(lik.bounds, float), n, seed=int(seed), progress=False,
                     max_steps=int(max_steps), move=move, max_evaluations=max(int(max_evaluations), n))
    return tmcmc(lik, np.asarray(lik.bounds, float), n, seed=int(seed), progress=False,
                 max_steps=int(max_steps), move=move)


def sample_tier(cl: CollapsedLikelihood, n_samples: int, seed: int, max_evaluations: int | None = None):
    """The evidence run of the collapsed tier: TMCMC over φ only (the amplitudes integrated out
    exactly, :class:`hbm.likelihood.collapsed.CollapsedLikelihood`), an importance finish in the same space,
    then the full posterior by conditional draws of the amplitudes: :func:`hbm.likelihood.collapsed.fit_collapsed`
    on the detective's route (:data:`~hbm.detective.rules.COLLAPSED_ROUTE`: 500 particles, ≤ 5 MH steps per
    stage, 10 000 importance draws; when the finish is refused (k̂ > 0.7 or a low ESS, e.g. a relaxation
    time the protocol hardly identifies) a TMCMC run over φ with 400 particles (at most ``n_samples``) and
    ≤ 25 steps per stage, whose evidence is used, both runs' evaluations counted).  With
    ``max_evaluations``: one TMCMC run of ``n_samples`` particles under the cap.

    Returns
    -------
    CollapsedFit
        ``info["route"]`` says which route produced it.
    """
    if max_evaluations:
        return fit_collapsed(cl, int(n_samples), seed=int(seed), max_evaluations=int(max_evaluations),
                             max_steps=COLLAPSED_ROUTE.fallback_steps)
    return fit_collapsed(cl, int(n_samples), seed=int(seed), route=COLLAPSED_ROUTE)


def laplace_occam(lik, x, all_names: Sequence[str], names: Sequence[str], samples: np.ndarray | None = None) -> float:
    """Laplace Occam factor of a block of parameters at the optimum, ≤ 0.

    ½·log det(2π·Σ) − Σ log(width), with Σ the inverse of the negative Hessian of the
    log-likelihood over the block (other parameters held at the optimum; finite differences,
    one batched likelihood call).  Local curvature, not the sampler's spread: a sampler that
    missed a narrow mode (a bump at one location among many) would otherwise make a chance
    improvement look free.  Directions without curvature (parameter on a bound, or not
    identified) fall back to the posterior sd.
    """
    all_names = list(all_names)
    names = [n for n in names if n in all_names]
    if not names:
        return 0.0
    x0 = np.asarray(x, float)
    b = np.asarray(lik.bounds, float)
    idx = [all_names.index(n) for n in names]
    w = b[idx, 1] - b[idx, 0]
    h = 1e-3 * w
    k = len(idx)
    pts = [x0]
    for a in range(k):
        for sa in (1, -1):
            x = x0.copy()
            x[idx[a]] += sa * h[a]
            pts.append(x)
    for a in range(k):
        for c in range(a + 1, k):
            for sa, sc in ((1, 1), (1, -1), (-1, 1), (-1, -1)):
                x = x0.copy()
                x[idx[a]] += sa * h[a]
                x[idx[c]] += sc * h[c]
                pts.append(x)
    X = np.array(pts)
    X[:, idx] = np.clip(X[:, idx], b[idx, 0], b[idx, 1])
    f = np.asarray(lik(X), float)
    f0 = f[0]
    H = np.zeros((k, k))
    j = 1
    for a in range(k):
        H[a, a] = -(f[j] - 2 * f0 + f[j + 1]) / h[a] ** 2
        j += 2
    for a in range(k):
        for c in range(a + 1, k):
            fpp, fpm, fmp, fmm = f[j:j + 4]
            H[a, c] = H[c, a] = -(fpp - fpm - fmp + fmm) / (4 * h[a] * h[c])
            j += 4
    post_sd = np.array([float(np.std(samples[:, i])) if samples is not None else wi / 3.5
                        for i, wi in zip(idx, w)])
    ok = np.isfinite(H).all()
    if ok:
        evals = np.linalg.eigvalsh(H)
        ok = bool(evals.min() > 0)
    if ok:
        logdet = -float(np.linalg.slogdet(H)[1])
        occ = 0.5 * (k * math.log(2 * math.pi) + logdet) - float(np.sum(np.log(w)))
    else:
        sd = np.where(np.isfinite(np.diag(H)) & (np.diag(H) > 0), 1.0 / np.sqrt(np.abs(np.diag(H)) + 1e-300),
                      post_sd)
        sd = np.minimum(sd, np.maximum(post_sd, 1e-12 * w))
        occ = float(np.sum(np.log(math.sqrt(2 * math.pi) * np.maximum(sd, 1e-300) / w)))
    return min(0.0, occ)


def noise_evidence(entry: dict, model_names: Sequence[str]) -> float:
    """Laplace log-evidence of one noise model's fit up to the terms shared by all noise models:
    max log L + Occam factor of the noise parameters beyond the marginal sd (ρ of AR(1),
    the relative sd of the proportional model).  Nested comparisons (iid ⊂ AR(1) at ρ = 0):
    the sd and model parameters' Occam factors cancel."""
    lik = entry["lik"]
    extra = [n for n in lik.names if n not in model_names and n != "sigma"]
    return float(entry["max_log_likelihood"]) + laplace_occam(lik, entry["x"], lik.names, extra)


def rmse(lik, x: np.ndarray, data: SpecimenData) -> float:
    """Root-mean-square error of the prediction at the free vector ``x``."""
    pred = np.asarray(lik.predict(np.asarray(x)[None, :]))[0]
    return float(np.sqrt(np.mean((data.stress - pred) ** 2)))


def coverage(lik, samples: np.ndarray, data: SpecimenData, seed: int, band: float = BAND) -> dict:
    """Posterior-predictive band and its coverage (overall, per test, along strain)."""
    rng = np.random.default_rng(seed)
    idx = rng.choice(samples.shape[0], size=min(400, samples.shape[0]), replace=False)
    th = samples[idx]
    mu = np.asarray(lik.predict(th))
    sd = np.asarray(lik.noise_sd(th))
    draws = mu + sd * rng.standard_normal(mu.shape)
    q = (1 - band) / 2
    lo, hi = np.quantile(draws, [q, 1 - q], axis=0)
    inside = (data.stress >= lo) & (data.stress <= hi)
    out = {"band": band, "overall": float(inside.mean()), "lower": lo, "upper": hi,
           "mean": mu.mean(axis=0)}
    tests = data.test if data.test is not None else np.zeros(data.stress.size, int)
    out["per_test"] = {str(t): float(inside[tests == t].mean()) for t in np.unique(tests)}
    edges = np.quantile(data.strain, np.linspace(0, 1, 11))
    b = np.clip(np.searchsorted(edges, data.strain, side="right") - 1, 0, 9)
    out["along_strain"] = [[float(edges[i]), float(edges[i + 1]), float(inside[b == i].mean())]
                           for i in range(10) if np.any(b == i)]
    return out


def fill_nan(x: np.ndarray, bounds: np.ndarray) -> np.ndarray:
    """``x`` with NaN entries set to the box centre, clipped into the box."""
    x = x.copy()
    bad = ~np.isfinite(x)
    x[bad] = 0.5 * (bounds[bad, 0] + bounds[bad, 1])
    return np.clip(x, bounds[:, 0], bounds[:, 1])


def warm_start(prev: FitSummary, lik_names: Sequence[str], effect_start: Mapping[str, float],
               noise: str, model_new: Model) -> np.ndarray:
    """A start vector for an extended likelihood: the previous optimum + the effect's start."""
    table = prev.noise_fits
    src = table.get(noise) or table.get(prev.noise)
    vals = dict(zip(src["lik"].names, src["x"])) if src else dict(zip(prev.names, prev.theta_max))
    # a noise model not fitted on the previous model: start its extra parameters mid-range/at zero
    x = []
    for n in lik_names:
        if n in effect_start:
            v = float(effect_start[n])
            if n in model_new.parameter_names:
                # a start on a bound (nulls often are) keeps CMA-ES there: nudge 2 % inside
                q = model_new.parameters[model_new.index(n)]
                w = q.upper - q.lower
                v = min(max(v, q.lower + 0.02 * w), q.upper - 0.02 * w)
            x.append(v)
        elif n in vals:
            x.append(vals[n])
        elif n == "rho":
            x.append(0.0)
        elif n in model_new.parameter_names:
            q = model_new.parameters[model_new.index(n)]
            x.append(q.null if q.null is not None else 0.5 * (q.lower + q.upper))
        else:
            x.append(np.nan)
    return np.asarray(x, float)


class Fitter:
    """Shared settings of all fits in one diagnosis (same data, same noise prior)."""

    def __init__(self, data: SpecimenData, fix, seed: int, n_samples: int, sigma_bounds, progress: bool,
                 max_evaluations: int | None = None, likelihood: str = "full", workers: int = 1):
        if likelihood not in TIERS:
            raise SettingError(f"likelihood must be one of {', '.join(TIERS)}, got {likelihood!r}")
        self.data, self.fix, self.seed = data, fix, seed
        #: the likelihood tier asked for (``--tier``): "auto", "collapsed" or "full"
        self.tier = likelihood
        self._tiers: dict[int, tuple] = {}        # id(lik) -> (lik, collapsed or None, note)
        self.n_samples, self.sigma_bounds, self.progress = n_samples, sigma_bounds, progress
        self.max_evaluations = max_evaluations   # per TMCMC evidence run (``--max-evaluations``)
        self.n = data.stress.size
        self.refine_seconds = 0.0                 # wall time of the refined evidence reruns
        #: wall-clock (``time.time()``) moment of --max-time (None: no limit); the wall clock, not
        #: perf_counter, because the refits' worker processes read it too
        self.deadline: float | None = None
        #: processes of the refits (1: this one): only by fork, and not from a daemonic process (a
        #: dask or multiprocessing worker may not start processes of its own)
        self.workers = (max(1, int(workers)) if "fork" in mp.get_all_start_methods()
                        and not mp.current_process().daemon else 1)
        self._pool = None
        self._blas: list = []                     # BLAS thread settings to restore at close()
        #: once True (after the base fit), a fit running past ``deadline`` is interrupted
        #: (:class:`FitInterrupted`); before, fits run to their end (a diagnosis needs its base fit)
        self.interruptible = False
        #: what was left undecided when the deadline passed: (what, why) in order
        self.undecided: list[tuple[str, str]] = []

    def out_of_time(self) -> bool:
        """Has the diagnosis's ``max_time`` passed?  (No new step starts after it.)"""
        return self.deadline is not None and _time.time() > self.deadline

    def seconds_left(self) -> float:
        """Seconds until the deadline (inf without one)."""
        return math.inf if self.deadline is None else self.deadline - _time.time()

    def pool(self):
        """The worker processes of the candidate refits (None: refit in this process).

        Created at its first use, after the base fit, by forking this process: the workers start
        with the data, the compiled model and the user's effect modules already loaded, and no
        argument but the refit's own inputs crosses (pickled).  None where fork is unavailable
        or ``workers`` is 1 (see ``__init__``)."""
        if self._pool is None and self.workers > 1:
            # the workers are the parallelism: one BLAS thread each (and here, until close())
            self._blas = one_blas_thread()
            self._pool = ProcessPoolExecutor(self.workers, mp_context=mp.get_context("fork"),
                                             initializer=one_blas_thread)
        return self._pool

    def close(self) -> None:
        """Stop the worker processes (if any)."""
        if self._pool is not None:
            self._pool.shutdown(wait=True, cancel_futures=True)
            self._pool = None
            for setter, n in self._blas:
                setter(n)
            self._blas = []

    def __enter__(self) -> "Fitter":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def __getstate__(self):
        # a worker gets the settings and caches, not the pool
        state = dict(self.__dict__)
        state["_pool"], state["_blas"] = None, []      # (ctypes setters do not pickle)
        return state

    def guard(self, lik):
        """``lik`` for an optimiser's or sampler's loop: interrupted at the deadline (once
        :attr:`interruptible`).  Only the long loops are guarded -- the cheap steps after them
        (Laplace curvatures, predictions) run to their end, so a stop never leaves a fit half-read."""
        return _Guarded(lik, self)

    def check_time(self) -> None:
        """Raise :class:`FitInterrupted` when the deadline has passed and fits are interruptible."""
        if self.interruptible and self.out_of_time():
            raise FitInterrupted("max_time reached")

    def skip(self, what: str, why: str) -> None:
        """Record a step left undecided at the deadline (and say so in the progress log)."""
        self.undecided.append((what, why))
        self.log(f"max-time reached: {what} not run ({why})")

    def log(self, msg: str) -> None:
        """A progress line on stderr (when ``progress``)."""
        if self.progress:
            print(f"[diagnose] {msg}", file=sys.stderr, flush=True)

    def bic(self, lik, f: float) -> float:
        return -2.0 * f + len(lik.names) * math.log(self.n)

    def likelihood(self, model: Model, noise: str, fix: Mapping[str, float] | None = None):
        """The likelihood of ``model`` at noise model ``noise`` with this diagnosis's prior box.

        Every fit of the detective (base, candidate refits, extend's steps, the removal test, the
        cost estimate) builds its likelihood here: the one place to choose a likelihood tier.
        ``fix`` overrides the diagnosis's fixed parameters (the removal test's reduced models).
        """
        fix = dict(self.fix) if fix is None and self.fix else fix
        return make_likelihood(model, self.data.ds, noise=noise, fix=fix or None, sigma_bounds=self.sigma_bounds)

    def collapsed(self, lik) -> tuple[CollapsedLikelihood | None, str]:
        """The collapsed likelihood of ``lik`` for the evidence run (None: the full tier) and
        one line saying which tier and why (:func:`hbm.likelihood.collapsed.choose_tier`).

        Under ``"auto"`` a model with more than ``COLLAPSED_MAX_COLUMNS`` integrated amplitude
        columns keeps the full tier: its nested quadrature costs ~2 ms per evaluation (an offset
        or an exponential fibre term beside the base's three columns) against ~0.07 ms with
        three, so its collapsed run would take minutes where the full one takes seconds.  The
        choice depends only on the model, the noise model and the setting, never on a clock.
        Each likelihood is examined once (the structure's numerical check is not free).
        """
        hit = self._tiers.get(id(lik))
        if hit is not None and hit[0] is lik:
            return hit[1], hit[2]
        # "collapsed" in a diagnosis: wherever the tier exists, however dear (no error where it
        # does not: damage, series compliance and proportional noise keep the full tier)
        cl, note = choose_tier(lik, "auto" if self.tier == "collapsed" else self.tier)
        if cl is not None and self.tier == "auto" and len(cl.free_columns) > COLLAPSED_MAX_COLUMNS:
            note = (f"full likelihood (a collapsed tier exists, but its {len(cl.free_columns)} amplitude columns "
                    f"({', '.join(cl.free_columns)}) make the quadrature dear; --tier collapsed forces it)")
            cl = None
        self._tiers[id(lik)] = (lik, cl, note)
        return cl, note

    def warm_starts(self, prev: FitSummary, model: Model, noises: Sequence[str],
                    effect_starts: Sequence[Mapping[str, float]]) -> dict[str, list[np.ndarray]]:
        """Starts of an extended model at each noise model: the previous optimum completed with
        each of ``effect_starts`` (values of the added effect's parameters)."""
        out = {}
        for nz in noises:
            lk = self.likelihood(model, nz)
            bnd = np.asarray(lk.bounds, float)
            out[nz] = [fill_nan(warm_start(prev, lk.names, st, nz, model), bnd) for st in effect_starts]
        return out

    def fit(self, model: Model, noises: Sequence[str], starts: Mapping[str, Sequence[np.ndarray]] | None,
            seed: int, sample: bool = True, global_restarts: int = 0,
            names_effects: list[str] | None = None, expected_log_z=None) -> FitSummary:
        """CMA-ES for each noise model, choose by BIC, TMCMC at the chosen one.

        The first noise model gets the global (or warm-started) search; the others start from
        its optimum (same mean parameters, noise parameters added), which is cheap and keeps
        the comparison of noise models about the noise, not about optimiser luck.
        ``expected_log_z`` (a BIC-type expectation) triggers one TMCMC rerun when the evidence
        comes out implausibly low: a population that missed the posterior mass fails low.
        """
        t0 = _time.perf_counter()
        table: dict[str, dict] = {}
        for k, noise in enumerate(noises):
            first = table[noises[0]] if k > 0 else None
            table[noise] = self._optimum(model, noise, k, first, starts, seed, global_restarts)
        if len(noises) > 1:
            self._cross_seed(noises, table, seed)
        fs = FitSummary(effects=list(names_effects if names_effects is not None else added_effects(model)),
                        noise="", names=[], theta_max=np.zeros(0), max_log_likelihood=-np.inf, bic=np.inf,
                        rmse=np.nan, model=model, noise_fits=table)
        self.choose(fs, seed, sample=False)
        fs.wall_time = _time.perf_counter() - t0
        if sample:
            self.evidence_run(fs, seed, expected_log_z)
        else:
            self.log(f"fit {'+'.join(fs.effects) or 'base'} [{fs.noise}]: max logL {fs.max_log_likelihood:.2f}, "
                     f"RMSE {fs.rmse:.4g} (optimum only, {fs.wall_time:.1f} s)")
        return fs

    def evidence_run(self, fs: FitSummary, seed: int, expected_log_z=None) -> None:
        """The evidence run of a fit made with ``sample=False`` (or of :meth:`fit` itself): TMCMC
        (or the collapsed tier) at its chosen noise model -- log Z, posterior, coverage."""
        t0 = _time.perf_counter()
        n_stages = self._sample(fs, seed, expected_log_z)
        t_cma = fs.wall_time
        fs.wall_time += _time.perf_counter() - t0
        self.log(f"fit {'+'.join(fs.effects) or 'base'} [{fs.noise}]: max logL {fs.max_log_likelihood:.2f}, "
                 f"log Z {fs.log_evidence:.2f} ± {fs.log_evidence_se:.2f}, RMSE {fs.rmse:.4g} "
                 f"({fs.wall_time:.1f} s, CMA-ES {t_cma:.1f} s, {fs.tier} tier, {fs.n_evaluations} evaluations, "
                 f"{n_stages} stages)")

    def choose(self, fs: FitSummary, seed: int, sample: bool = True) -> None:
        """(Re)choose ``fs``'s noise model by evidence (:func:`noise_evidence`) among its
        ``noise_fits`` and copy that optimum into ``fs``; when the choice changes and ``sample``,
        re-run the TMCMC (the evidence and posterior belong to the noise model)."""
        table = fs.noise_fits
        model_names = fs.model.parameter_names
        score = {k: noise_evidence(v, model_names) for k, v in table.items()}
        best = max(table, key=lambda k: score[k])   # the first of equals, as a loop would
        self._apply(fs, best, score, seed, sample)

    def use_noise(self, fs: FitSummary, noise: str, seed: int) -> None:
        """Put ``fs`` at its optimum under ``noise`` (one of its ``noise_fits``), re-running the
        TMCMC when that changes its noise model: the steps of one comparison share a noise model."""
        if noise == fs.noise or noise not in fs.noise_fits:
            return
        score = {k: noise_evidence(v, fs.model.parameter_names) for k, v in fs.noise_fits.items()}
        self._apply(fs, noise, score, seed, True)

    def settle(self, fs: FitSummary) -> None:
        """Copy the optimum of ``fs``'s own noise model from its ``noise_fits`` into ``fs`` (after a
        re-optimisation stopped part-way), keeping its noise model and evidence run."""
        score = {k: noise_evidence(v, fs.model.parameter_names) for k, v in fs.noise_fits.items()}
        self._apply(fs, fs.noise, score, 0, False)

    def _apply(self, fs: FitSummary, best: str, score: dict, seed: int, sample: bool) -> None:
        table = fs.noise_fits
        ch = table[best]
        changed = best != fs.noise
        lik, x = ch["lik"], np.asarray(ch["x"], float)
        fs.noise, fs.names, fs.theta_max, fs.likelihood = best, list(lik.names), x, lik
        fs.max_log_likelihood, fs.bic = float(ch["max_log_likelihood"]), float(ch["bic"])
        fs.rmse = rmse(lik, x, self.data)
        fs.noise_bic = {k: v["bic"] for k, v in table.items()}
        fs.noise_evidence = score
        if changed and sample:
            self._sample(fs, seed, None)

    def _optimum(self, model: Model, noise: str, k: int, first: dict | None, starts, seed: int,
                 global_restarts: int) -> dict:
        """CMA-ES optimum at the ``k``-th noise model tried, ``noise``.

        The first (``k = 0``) gets the global or warm-started search; later ones start from
        ``first``, the optimum at the first noise model.
        """
        lik = self.likelihood(model, noise)
        b = np.asarray(lik.bounds, float)
        x0s = [fill_nan(np.asarray(x, float), b) for x in (starts or {}).get(noise, [])]
        if k > 0:
            prev = first
            vals = dict(zip(prev["lik"].names, prev["x"]))
            # new noise parameters start from moment estimates of the previous residuals
            # (CMA-ES started on a bound, e.g. rho = 0, tends to stay there)
            r = self.data.stress - np.asarray(prev["lik"].predict(prev["x"][None, :]))[0]
            guess = lik.noise_model.moment_guess(r)
            x0 = np.array([vals.get(n, guess.get(n, np.nan)) for n in lik.names])
            x0s = [fill_nan(x0, b)] + x0s[:1]
            x, f = cma_maximise(self.guard(lik), x0s, 0.02, seed + 7 * k, maxfevals=800)
        elif global_restarts:
            x, f = global_fit(self.guard(lik), seed + 101 * k, global_restarts)
            if x0s:
                x2, f2 = cma_maximise(self.guard(lik), x0s, 0.02, seed + 7 * k, maxfevals=1000)
                if f2 > f:
                    x, f = x2, f2
        else:
            x, f = cma_maximise(self.guard(lik), x0s, 0.02, seed + 7 * k, maxfevals=1500)
        return {"bic": self.bic(lik, f), "max_log_likelihood": f, "x": x, "lik": lik}

    def _cross_seed(self, noises: Sequence[str], table: dict, seed: int) -> None:
        """Restart each noise model from the other models' optimal mean parameters.

        A poorly converged iid fit would otherwise hand the comparison to an AR(1) fit that
        soaks up the misfit, or vice versa.
        """
        for noise in noises:
            lik = table[noise]["lik"]
            b = np.asarray(lik.bounds, float)
            for other in noises:
                if other == noise:
                    continue
                vals = dict(zip(table[other]["lik"].names, table[other]["x"]))
                own = dict(zip(lik.names, table[noise]["x"]))
                x0 = np.array([vals[n] if (n in vals and n in lik.model.parameter_names) else own[n]
                               for n in lik.names])
                x, f = cma_maximise(self.guard(lik), [fill_nan(x0, b)], 0.01, seed + 31, maxfevals=500)
                if f > table[noise]["max_log_likelihood"]:
                    table[noise].update(x=x, max_log_likelihood=f, bic=self.bic(lik, f))

    def _sample(self, fs: FitSummary, seed: int, expected_log_z) -> int:
        """The evidence run at the chosen noise model (collapsed tier where :meth:`collapsed`
        allows, else full-space TMCMC): evidence, samples, coverage; returns the TMCMC stages run."""
        lik = fs.likelihood
        cl, note = self.collapsed(lik)
        fs.tier, fs.tier_note = ("full", note) if cl is None else ("collapsed", note)
        if cl is not None:
            cf = sample_tier(self.guard(cl), self.n_samples, seed, self.max_evaluations)
            samples, log_z, log_z_se = cf.samples, cf.log_evidence, cf.log_evidence_se
            ll, stages, evals = cf.log_likelihood, len(cf.tmcmc.stages), cf.n_evaluations
            fs.tier_info = {k: v for k, v in cf.info.items() if k in (
                "sampled", "integrated_columns", "evidence_source", "quadrature_error", "route")}
        else:
            res = sample(self.guard(lik), self.n_samples, seed, self.max_evaluations)
            expected = None if expected_log_z is None else expected_log_z(fs.max_log_likelihood, len(lik.names))
            if expected is not None and res.log_evidence < expected - 25.0:
                res2 = sample(self.guard(lik), self.n_samples, seed + 99991, self.max_evaluations)
                self.log(f"  TMCMC rerun (log Z {res.log_evidence:.1f} far below the BIC-type "
                         f"expectation {expected:.1f}) -> {res2.log_evidence:.1f}")
                if res2.log_evidence > res.log_evidence:
                    res = res2
            samples, log_z, log_z_se = res.samples, res.log_evidence, res.log_evidence_se
            ll, stages, evals = res.log_likelihood, len(res.stages), res.n_evaluations
            fs.tier_info = {}
        fs.n_evaluations = int(evals)
        fs.samples = np.asarray(samples)
        fs.log_evidence = float(log_z)
        fs.log_evidence_se = float(log_z_se)
        fs.refined_log_evidence = fs.refined_log_evidence_se = float("nan")
        # the posterior population may contain a better point than CMA-ES found
        ll = np.asarray(ll)
        j = int(np.argmax(ll))
        if ll[j] > fs.max_log_likelihood:
            fs.theta_max, fs.max_log_likelihood = fs.samples[j].copy(), float(ll[j])
            chosen = fs.noise_fits[fs.noise]
            chosen["x"], chosen["max_log_likelihood"] = fs.theta_max, fs.max_log_likelihood
            fs.rmse = rmse(lik, fs.theta_max, self.data)
            fs.bic = self.bic(lik, fs.max_log_likelihood)
        fs.predictive = coverage(lik, fs.samples, self.data, seed)
        fs.coverage = fs.predictive["overall"]
        return stages

    def refine(self, fs: FitSummary, seed: int) -> None:
        """Rerun ``fs``'s evidence with the refined settings (``TMCMC_REFINE_MOVE`` walk, up to
        ``TMCMC_REFINE_STEPS`` MH steps per stage; same population and budget as the standard
        run); fills ``fs.refined_log_evidence`` ± SE, once per sampling.

        The standard log Z, samples and optimum are left alone: every other comparison of this
        fit (the next round's, the controls') stays between runs of the same settings.
        """
        if np.isfinite(fs.refined_log_evidence) or fs.likelihood is None:
            return
        if fs.tier == "collapsed":
            # the collapsed run is not under-mixed the way the 25-step full-space runs are (its
            # importance finish converges to |Δlog Z| ≲ 0.1): it is its own refined value
            fs.refined_log_evidence, fs.refined_log_evidence_se = fs.log_evidence, fs.log_evidence_se
            return
        t0 = _time.perf_counter()
        res = sample(self.guard(fs.likelihood), self.n_samples, seed, self.max_evaluations, max_steps=TMCMC_REFINE_STEPS,
                     move=TMCMC_REFINE_MOVE)
        fs.refined_log_evidence = float(res.log_evidence)
        fs.refined_log_evidence_se = float(res.log_evidence_se)
        self.refine_seconds += _time.perf_counter() - t0
        steps = [int(st.n_steps) for st in res.stages]
        self.log(f"  refined evidence {'+'.join(fs.effects) or 'base'} [{fs.noise}]: log Z "
                 f"{fs.log_evidence:.2f} -> {fs.refined_log_evidence:.2f} ± {fs.refined_log_evidence_se:.2f} "
                 f"({TMCMC_REFINE_MOVE} walk, ≤ {TMCMC_REFINE_STEPS} steps/stage, max {max(steps, default=0)}, "
                 f"{_time.perf_counter() - t0:.1f} s)")
