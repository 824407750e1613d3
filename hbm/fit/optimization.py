"""CMA-ES point estimates (MAP or weighted least squares) with IPOP restarts and bound sweeps.

The optimiser works in the unit box [0, 1]^d of the likelihood's free parameters (one scale for
all coordinates; sigma0 = 0.25) with the ``cma`` package's ask/tell interface, so each
generation is one vectorised likelihood call over the whole population.  Restarts follow IPOP
(population size doubled at each restart, fresh random start) and every restart's optimum is
kept: on the non-identifiable muscle model the spread of these optima is informative.

``sweep=(name, 0.01)`` reproduces the thesis §3.1 bound sweep: the parameter's box is cut into
consecutive windows of width ``d`` and one optimisation is run per window (warm-started from the
previous window's optimum), which traces the model's manifold (the Spyrou base: VOLF–T1, name VOLF).
"""

from __future__ import annotations

import functools
import time as _time
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from ..runtime.progress import progress_bar
from ..errors import HbmError
from ..likelihood.core import Likelihood
from ..settings.rules import check_int

OBJECTIVES = ("map", "wls")
# cma needs finite values; anything out of the feasible set is ranked behind every real value
_BAD = 1e300


@dataclass
class OptimizeResult:
    """Optima of :func:`optimize`.

    Attributes
    ----------
    optima : list of dict
        One per restart (or per sweep window): ``params`` ({name: value} of all model parameters,
        fixed ones included, then the noise parameters for ``objective="map"``), ``objective``
        (value minimised), ``log_likelihood``, ``restart``, ``popsize``, ``evaluations``,
        ``theta`` (free-parameter vector in ``names`` order), ``stop`` (cma's stop reasons) and for
        sweeps ``window`` (lo, hi).
    best : dict
        The optimum with the smallest objective.
    names : tuple of str
        Free parameters optimised.
    objective : str
        ``"map"`` (−log posterior = −log likelihood up to the constant log prior volume) or
        ``"wls"`` (thesis eq. 1.19).
    n_evaluations : int
    wall_time : float
        Seconds.
    sweep : tuple or None
    """

    optima: list[dict[str, Any]]
    names: tuple[str, ...]
    objective: str
    n_evaluations: int
    wall_time: float
    sweep: tuple[str, float] | None = None
    best: dict[str, Any] = field(init=False)

    def __post_init__(self) -> None:
        self.best = min(self.optima, key=lambda o: o["objective"])

    def manifold(self, *names: str) -> dict[str, np.ndarray]:
        """Arrays of parameter values over the optima (e.g. of a manifold's two parameters)."""
        keys = names or tuple(self.optima[0]["params"])
        return {k: np.array([o["params"][k] for o in self.optima]) for k in keys}

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready ``{"optima": [...], "best": {...}, ...}``."""
        def clean(o):
            out = {k: v for k, v in o.items() if k != "theta"}
            out["objective"] = float(o["objective"])
            return out
        return {"optima": [clean(o) for o in self.optima], "best": clean(self.best),
                "names": list(self.names), "objective_kind": self.objective,
                "n_evaluations": int(self.n_evaluations), "wall_time": float(self.wall_time),
                "sweep": None if self.sweep is None else list(self.sweep)}


def _objective_fn(lik: Likelihood, objective: str):
    """f(X unit (n, k)) -> (n,) values to minimise, with the parameter count k."""
    if objective == "map":
        k = lik.d

        def f(x):
            ll = lik(lik.from_unit(x))
            return np.where(np.isfinite(ll), -ll, _BAD)
    else:
        k = lik.n_model
        lo, hi = lik.bounds[:k, 0], lik.bounds[:k, 1]

        def f(x):
            e = lik.wls(lo + x * (hi - lo))
            return np.where(np.isfinite(e), e, _BAD)
    return f, k


@functools.lru_cache(maxsize=1)   # one class, made when cma is first used
def _bound_transform():
    """cma's ``BoundTransform`` with its box transformation computed per coordinate in Python floats.

    cma calls the transformation once per solution; its ~20 numpy operations on a 5-vector were ~15 % of
    a default ``hbm fit``.  The same formulas in the same order on Python floats (IEEE doubles, as numpy's
    elementwise operations) give the same bits; a coordinate far enough outside to need cma's periodic
    shift, a NaN, or any other input goes through cma's own code.  ``tests/test_optimize.py`` runs both
    and compares every solution."""
    import cma
    from cma.transformations import BoxConstraintsLinQuadTransformation

    class _LinQuad(BoxConstraintsLinQuadTransformation):
        def initialize(self, length=None):
            super().initialize(length)
            lb, ub, al, au = self._lb, self._ub, self._al, self._au
            # per coordinate: lb, ub, al, au, the identity part's ends and the periodic shift's thresholds
            self._coords = list(zip(lb.tolist(), ub.tolist(), al.tolist(), au.tolist(), (lb + al).tolist(),
                                    (ub - au).tolist(), (lb - 2 * al - (ub - lb) / 2.0).tolist(),
                                    (ub + 2 * au + (ub - lb) / 2.0).tolist()))

        def __call__(self, solution_genotype, copy=True):
            y = solution_genotype
            if not (isinstance(y, np.ndarray) and y.dtype == np.float64 and y.ndim == 1
                    and y.size == len(self._coords)):
                return super().__call__(solution_genotype, copy)
            vals = y.tolist()
            changed = False
            for i, (v, (lb, ub, al, au, id_lo, id_hi, far_lo, far_hi)) in enumerate(zip(vals, self._coords)):
                if id_lo <= v <= id_hi:
                    continue            # the identity part (NaN fails this and the next test)
                if not far_lo <= v <= far_hi:
                    return super().__call__(solution_genotype, copy)
                if v > ub + au:
                    v -= 2 * (v - ub - au)
                if v < lb - al:
                    v += 2 * (lb - al - v)
                if v < lb + al:
                    t = v - (lb - al)
                    v = lb + t * t / 4 / al
                if v > ub - au:
                    t = v - (ub + au)
                    v = ub - t * t / 4 / au
                vals[i], changed = v, True
            if not changed:
                return y
            if copy:
                return np.array(vals)
            y[:] = vals
            return y

    class _Bounds(cma.BoundTransform):
        def __init__(self, bounds=None):
            super().__init__(bounds)
            self.bounds_tf = _LinQuad(self.to_dim_times_two(bounds))

    return _Bounds


def _cma_run(f, x0, popsize: int, seed: int, maxfevals: int | None, tolfun: float, sigma0: float = 0.25):
    import cma

    # cma's own bound handling (BoundTransform) is used: a plain reflection at the box faces was
    # tried and is 2x cheaper per generation, but along the flat non-identifiable directions it
    # lets the mean drift and sigma grow (runs end on 'tolupsigma' far from converged).
    # tolupsigma 1e3 (cma default 1e20): on a flat non-identifiable ridge that ends on a box
    # face the genotype drifts outside the box and sigma grows without further progress; the
    # default let such runs burn ~50k evaluations to gain < 0.01 in log-likelihood.
    opts = {"bounds": [0.0, 1.0], "popsize": int(popsize), "seed": int(seed), "verbose": -9,
            "verb_log": 0, "verb_disp": 0, "tolfun": tolfun, "tolx": 1e-11, "tolupsigma": 1e3,
            "maxiter": int(100 + 150 * (len(x0) + 3) ** 2 / np.sqrt(popsize)), "BoundaryHandler": _bound_transform()}
    if maxfevals:
        opts["maxfevals"] = int(maxfevals)
    es = cma.CMAEvolutionStrategy(list(np.clip(x0, 0.0, 1.0)), sigma0, opts)
    while not es.stop():
        X = es.ask()
        x = np.clip(np.asarray(X), 0.0, 1.0)  # BoundTransform already maps into [0,1]; clip rounding
        es.tell(X, f(x))
    xbest = np.clip(np.asarray(es.result.xbest, dtype=float), 0.0, 1.0)
    return xbest, float(es.result.fbest), int(es.result.evaluations), dict(es.stop())


def _record(lik: Likelihood, objective: str, xbest, fbest, **extra) -> dict[str, Any]:
    if objective == "map":
        theta = lik.from_unit(xbest)
    else:
        theta = np.empty(lik.d)
        theta[: lik.n_model] = lik.from_unit(np.r_[xbest, np.zeros(lik.d - lik.n_model)])[: lik.n_model]
        # report the iid-like noise estimate implied by the fit where it is closed-form
        r = lik.observed - lik.predict(np.r_[theta[: lik.n_model], lik.bounds[lik.n_model:, 0]][None])[0]
        # the closed-form noise estimate is in natural units; theta is in the likelihood's
        # working coordinates (log for a loguniform noise prior)
        nat = lik.to_natural(theta)
        if lik.noise == "iid":
            nat[lik.n_model:] = np.clip(np.sqrt(np.mean(r * r)), *lik.natural_bounds[-1])
            theta = lik.from_natural(nat)
        elif lik.noise == "weighted":
            nat[lik.n_model:] = np.clip(np.sqrt(np.mean((r / lik.weights) ** 2)), *lik.natural_bounds[-1])
            theta = lik.from_natural(nat)
        else:
            theta[lik.n_model:] = lik.bounds[lik.n_model:].mean(axis=1)
    params = lik.as_dict(theta)
    if objective == "wls" and lik.noise not in ("iid", "weighted"):
        params = {k: v for k, v in params.items() if k not in lik.noise_names}
    ll = float(lik(theta[None])[0])
    return {"params": params, "objective": float(fbest), "log_likelihood": ll,
            "theta": theta, **extra}


def optimize(likelihood: Likelihood, *, restarts: int = 4, seed: int = 0, objective: str = "map",
             sweep: tuple[str, float] | None = None, popsize: int | None = None,
             maxfevals: int | None = None, tolfun: float = 1e-9, progress: bool = False) -> OptimizeResult:
    """Minimise −log posterior (MAP) or the weighted least squares of eq. 1.19 with CMA-ES.

    Parameters
    ----------
    likelihood : Likelihood
        From :func:`hbm.likelihood.make_likelihood` (its box is the search box).
    restarts : int
        Number of CMA-ES runs (IPOP: popsize doubles each restart).  With ``sweep``: the number
        of runs of the initial global search; each window then gets one run warm-started from
        the previous window's optimum, and windows left in a worse local mode (objective more
        than 0.01 above the best) are re-run from the nearest window in the best basin.
    seed : int
        Seeds the random starting points (numpy Generator) and cma's own ``seed`` option (cma
        reseeds numpy's *global* RNG; its state is saved and restored around the call).
    objective : {"map", "wls"}
        ``"map"``: −log likelihood with the noise parameters optimised too (uniform prior:
        −log posterior up to a constant).  ``"wls"``: Er of thesis eq. 1.19, model parameters only.
    sweep : (name, width), optional
        Thesis §3.1 bound sweep over parameter ``name`` with windows of ``width``.
    popsize : int, optional
        Initial population size (default cma's 4 + 3 ln d).
    maxfevals : int, optional
        Evaluation budget per CMA-ES run.
    tolfun : float
        cma ``tolfun`` (absolute change of the objective; it is a log-likelihood, so 1e-9 is tight).
    progress : bool
        Show a tqdm bar over runs.

    Returns
    -------
    OptimizeResult
    """
    if objective not in OBJECTIVES:
        raise HbmError(f"objective must be one of {', '.join(OBJECTIVES)}, got {objective!r}")
    if int(restarts) < 1:
        raise HbmError(f"restarts must be >= 1, got {restarts}")
    seed = check_int(seed, "seed", 0)  # (fits pass 64-bit child seeds of the root seed here)
    if popsize is not None:
        popsize = check_int(popsize, "popsize", 2)
    if sweep is not None:
        _sweep_windows(likelihood, sweep)  # fail before spending any evaluations
    t0 = _time.perf_counter()
    rng = np.random.default_rng(seed)
    state = np.random.get_state()  # cma reseeds the global RNG: leave the caller's untouched
    try:
        optima, nev = _multistart(likelihood, objective, int(restarts), rng, popsize, maxfevals, tolfun,
                                  progress)
        if sweep is not None:
            optima, n2 = _sweep(likelihood, objective, sweep, optima, rng, popsize, maxfevals, tolfun,
                                progress)
            nev += n2
    finally:
        np.random.set_state(state)
    return OptimizeResult(optima=optima, names=likelihood.names if objective == "map"
                          else likelihood.model_names, objective=objective, n_evaluations=nev,
                          wall_time=_time.perf_counter() - t0,
                          sweep=None if sweep is None else (sweep[0], float(sweep[1])))


def _bar(total, progress, desc):
    if not progress:
        return None
    return progress_bar(total, desc, leave=False)


def _multistart(lik, objective, restarts, rng, popsize, maxfevals, tolfun, progress):
    f, k = _objective_fn(lik, objective)
    pop0 = int(popsize or 4 + int(3 * np.log(k)))
    optima, nev = [], 0
    bar = _bar(restarts, progress, "CMA-ES restarts")
    for r in range(restarts):
        x0 = rng.uniform(0.1, 0.9, k)
        cseed = int(rng.integers(1, 2**31 - 1))
        ps = pop0 * 2**r
        xb, fb, ne, stop = _cma_run(f, x0, ps, cseed, maxfevals, tolfun)
        nev += ne
        optima.append(_record(lik, objective, xb, fb, restart=r, popsize=ps, evaluations=ne,
                              stop=sorted(stop)))
        if bar is not None:
            bar.update()
    if bar is not None:
        bar.close()
    return optima, nev


def _sweep_windows(lik, sweep):
    """Validate ``sweep`` and cut the parameter's box into consecutive windows."""
    try:
        name, width = sweep
        width = float(width)
    except (TypeError, ValueError):
        raise HbmError(f"sweep must be (NAME, WIDTH), got {sweep!r}") from None
    if name not in lik.model_names:
        raise HbmError(f"sweep: {name!r} is not a free model parameter; free: {', '.join(lik.model_names)}")
    j = lik.model_names.index(name)
    lo, hi = lik.bounds[j]
    if not (0 < width <= hi - lo):
        raise HbmError(f"sweep: width must be in (0, {hi - lo:g}] for {name}, got {width:g}")
    nwin = int(np.ceil((hi - lo) / width - 1e-9))
    # rounding keeps edges like 0.57 instead of 0.5700000000000001 in tables and JSON
    edges = [(round(lo + i * width, 12), round(min(lo + (i + 1) * width, hi), 12)) for i in range(nwin)]
    return name, j, edges


def _sweep(lik, objective, sweep, start, rng, popsize, maxfevals, tolfun, progress, repair_tol=0.01):
    name, j, edges = _sweep_windows(lik, sweep)
    nwin = len(edges)
    subs = [lik.with_bounds(**{name: (a, b)}) for a, b in edges]
    nev = 0

    def run_window(w, start_theta, sigma0):
        nonlocal nev
        sub = subs[w]
        a, b = edges[w]
        f, k = _objective_fn(sub, objective)
        th0 = start_theta.copy()
        th0[j] = np.clip(th0[j], a, b)  # nearest point of the window: the smallest disturbance
        x0 = np.clip(sub.to_unit(th0), 0.0, 1.0)[:k]
        pop0 = int(popsize or 4 + int(3 * np.log(k)))
        # warm start near a neighbouring optimum: a small initial step keeps the run in that
        # basin (a large one lets windows hop between local modes, which scrambles the manifold)
        xb, fb, ne, stop = _cma_run(f, x0, pop0, int(rng.integers(1, 2**31 - 1)), maxfevals, tolfun,
                                    sigma0=sigma0)
        nev += ne
        return _record(sub, objective, xb, fb, restart=w, popsize=pop0, evaluations=ne,
                       stop=sorted(stop), window=[float(a), float(b)])

    prev = min(start, key=lambda o: o["objective"])["theta"]
    optima = []
    bar = _bar(nwin, progress, f"sweep {name}")
    for w in range(nwin):
        rec = run_window(w, prev, 0.05)
        optima.append(rec)
        prev = rec["theta"]
        if bar is not None:
            bar.update()
    if bar is not None:
        bar.close()
    # Repair pass: a window can land in a worse local mode (e.g. a second THETA-T2 basin) than
    # the best found anywhere along the sweep; restart such windows from the best optimum so
    # that the traced manifold belongs to one basin.  Kept only if it improves.
    for _ in range(2):
        best = min(optima, key=lambda o: o["objective"])
        worse = [w for w, o in enumerate(optima) if o["objective"] > best["objective"] + repair_tol]
        if not worse:
            break
        for w in worse:
            # start from the nearest window already in the best basin (its optimum is closest
            # in the swept parameter), a few attempts, keep the best
            good = [v for v, o in enumerate(optima) if o["objective"] <= best["objective"] + repair_tol]
            src = min(good, key=lambda v: abs(v - w))
            for _attempt in range(3):
                rec = run_window(w, optima[src]["theta"], 0.02)
                rec["repaired"] = True
                if rec["objective"] < optima[w]["objective"]:
                    optima[w] = rec
                if optima[w]["objective"] <= best["objective"] + repair_tol:
                    break
    return optima, nev
