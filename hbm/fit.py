"""Fit one specimen: CMA-ES optima, TMCMC posterior with evidence, posterior predictive, Sobol.

:func:`fit_specimen` is the unit of work of the six-rat workflow (one dask task per specimen)
and of ``hbm fit``.  Every random stream is spawned from one ``SeedSequence(seed)`` so a fit is
reproducible bit for bit, wherever it runs:

=========  ======================================================
child 0    CMA-ES restarts and the bound sweep (hbm.optimize)
child 1    TMCMC (hbm.samplers.tmcmc)
child 2    posterior-predictive noise
child 3    Sobol sampling (hbm.sensitivity)
=========  ======================================================
"""

from __future__ import annotations

import math
import os
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Mapping, Sequence

import numpy as np

from ._version import __version__
from .errors import HbmError
from .io import SpecimenResult, write_specimen_result

__all__ = ["FitResult", "fit_specimen", "summarize", "summary_table", "pointwise_log_likelihood",
           "posterior_predictive", "parse_sweep", "spawn_seeds", "COMBINATIONS"]

#: identifiable combinations reported next to the parameters (hbm.model.identifiable_combinations)
COMBINATIONS = ("G", "VOLF*P1", "(1-VOLF)*T1")
_LOG2PI = math.log(2 * math.pi)


def spawn_seeds(seed: int | np.random.SeedSequence, n: int = 4) -> list[int]:
    """``n`` independent 63-bit integer seeds spawned from ``SeedSequence(seed)``."""
    ss = seed if isinstance(seed, np.random.SeedSequence) else np.random.SeedSequence(int(seed))
    return [int(c.generate_state(1, dtype=np.uint64)[0] >> np.uint64(1)) for c in ss.spawn(n)]


def parse_sweep(sweep: str | tuple | None) -> tuple[str, float] | None:
    """``"VOLF:0.05"`` -> ("VOLF", 0.05)."""
    if sweep is None or sweep == "" or sweep is False:
        return None
    if isinstance(sweep, (tuple, list)):
        name, width = sweep
    else:
        name, _, width = str(sweep).partition(":")
        if not width:
            raise HbmError(f"sweep: expected PARAM:WIDTH (e.g. VOLF:0.05), got {sweep!r}")
    try:
        width = float(width)
    except ValueError:
        raise HbmError(f"sweep: width must be a number, got {width!r}") from None
    if not width > 0:
        raise HbmError(f"sweep: width must be > 0, got {width}")
    return str(name), width


# ----------------------------------------------------------------------------- pieces
def pointwise_log_likelihood(likelihood, theta: np.ndarray, model_stress: np.ndarray | None = None) -> np.ndarray:
    """Pointwise log-likelihood (n, p) whose row sums equal ``likelihood(theta)``.

    For AR(1) noise the pointwise terms are the conditional densities of the innovations
    p(r_t | r_{t-1}) (the exact factorisation of the joint Gaussian), as PSIS-LOO expects.
    """
    m = likelihood.predict(theta) if model_stress is None else model_stress
    r = likelihood.observed - m
    names = list(likelihood.names)
    if getattr(likelihood, "noise", "iid") == "ar1":
        s = theta[:, names.index("sigma")][:, None]
        rho = theta[:, names.index("rho")][:, None]
        a = (~likelihood.loading.history_starts).astype(float)
        rprev = np.zeros_like(r)
        rprev[:, 1:] = r[:, :-1]
        u = r - rho * a * rprev
        v = s * s * (1.0 - rho * rho * a)
        return -0.5 * (_LOG2PI + np.log(v) + u * u / v)
    sd = likelihood.noise_sd(theta, m) if _accepts_model_stress(likelihood) else likelihood.noise_sd(theta)
    out = -0.5 * (_LOG2PI + 2 * np.log(sd) + (r / sd) ** 2)
    if getattr(likelihood, "noise", "") == "weighted":
        pass  # the weights enter through noise_sd = scale * w_i: already in the density
    return out


def _accepts_model_stress(likelihood) -> bool:
    import inspect

    try:
        return "model_stress" in inspect.signature(likelihood.noise_sd).parameters
    except (TypeError, ValueError):  # pragma: no cover
        return False


def posterior_predictive(likelihood, theta: np.ndarray, seed, model_stress: np.ndarray | None = None
                         ) -> tuple[np.ndarray, np.ndarray]:
    """(noise-free prediction, noisy replicate), both (n, p), one replicate per posterior draw."""
    rng = np.random.default_rng(seed)
    m = likelihood.predict(theta) if model_stress is None else model_stress
    sd = likelihood.noise_sd(theta)
    z = rng.standard_normal(m.shape)
    if getattr(likelihood, "noise", "iid") == "ar1":
        rho = theta[:, list(likelihood.names).index("rho")]
        starts = likelihood.loading.history_starts
        innov = np.sqrt(1.0 - rho * rho)
        # loop over points (not samples): the recursion is sequential along the curve
        for t in range(1, m.shape[1]):
            if not starts[t]:
                z[:, t] = rho * z[:, t - 1] + innov * z[:, t]
    return m, m + sd * z


def _normalise_optima(res: Any, names: Sequence[str], kind: str) -> list[dict]:
    """Optima from hbm.optimize in the JSON form {"params": {...}, "objective": f, "kind": ...}."""
    items = getattr(res, "optima", None)
    if items is None and isinstance(res, Mapping):
        items = res.get("optima")
    if items is None:
        items = [res]
    out = []
    for o in items:
        if isinstance(o, Mapping):
            d = dict(o)
        elif hasattr(o, "to_dict"):
            d = dict(o.to_dict())
        else:
            d = {k: getattr(o, k) for k in ("params", "objective", "theta", "x", "window") if hasattr(o, k)}
        params = d.get("params")
        if params is None:
            x = d.get("theta", d.get("x"))
            params = {n: float(v) for n, v in zip(names, np.asarray(x, float))}
        entry = {"params": {k: float(v) for k, v in dict(params).items()},
                 "objective": float(d.get("objective", d.get("f", np.nan))), "kind": kind}
        win = d.get("window")
        if win is not None and len(win) == 2:
            entry["window_lower"], entry["window_upper"] = float(win[0]), float(win[1])
        for k in ("window_lower", "window_upper"):
            if k in d:
                entry[k] = float(d[k])
        out.append(entry)
    return out


def run_optima(likelihood, *, restarts: int, seed: int, sweep: tuple[str, float] | None, **options) -> list[dict]:
    """CMA-ES restarts (+ an optional bound sweep) through :func:`hbm.optimize.optimize`."""
    from .optimize import optimize as _cma

    names = list(likelihood.names)
    optima = _normalise_optima(_cma(likelihood, restarts=restarts, seed=seed, **options), names, "restart")
    if sweep is not None:
        sw = _cma(likelihood, restarts=1, seed=seed + 1, sweep=sweep, **options)
        optima += _normalise_optima(sw, names, "sweep")
    return optima


def run_sobol(model, data, *, n: int, seed: int, fix=None, bounds=None, qoi: str = "log_integrated_stress") -> dict:
    """Sobol indices over the prior box (:func:`hbm.sensitivity.sobol`) as a plain dict for io.

    The QoI is log W (the energy on a log scale): its estimator is stable at N = 1024 where the
    raw energy's is not (see :mod:`hbm.sensitivity`).
    """
    from . import sensitivity as _sens

    res = _sens.sobol(model, data=data, n=n, seed=seed, fix=fix, bounds=bounds, qoi=qoi, per_point=True)
    out: dict[str, Any] = {k: {str(a): float(b) for a, b in getattr(res, k).items()}
                           for k in ("S1", "ST", "S1_conf", "ST_conf")}
    out["relevance"] = {str(a): str(b) for a, b in res.relevance.items()}
    if res.per_point is not None:
        for key in ("S1", "ST"):
            arr = np.asarray(res.per_point[key], float)  # (n_points, D)
            out[f"{key}_point"] = {nm: arr[:, j] for j, nm in enumerate(res.names)}
    out["qoi"] = str(res.qoi)
    out["n"] = int(res.n)
    out["n_evaluations"] = int(res.n_evaluations)
    return out


# ----------------------------------------------------------------------------- summaries
def summarize(result: SpecimenResult, *, prob: float = 0.9) -> dict[str, dict[str, float]]:
    """Posterior mean, sd and central ``prob`` interval per free parameter and combination.

    Returns
    -------
    dict
        ``{name: {"mean", "sd", "lower", "upper", "median"}}``; parameters first, then the
        identifiable combinations (when the model has VOLF, P1, T1, GF, GM).
    """
    from .model import identifiable_combinations

    cols = result.as_dict()
    q = [(1 - prob) / 2, 0.5, (1 + prob) / 2]
    out: dict[str, dict[str, float]] = {}

    def stats(x):
        lo, med, hi = np.quantile(x, q)
        return {"mean": float(np.mean(x)), "sd": float(np.std(x, ddof=1)) if x.size > 1 else 0.0,
                "lower": float(lo), "median": float(med), "upper": float(hi)}

    for nm in result.names:
        out[nm] = stats(cols[nm])
    needed = ("VOLF", "P1", "T1", "GF", "GM")
    if all(k in cols for k in needed):
        names = list(cols)
        combos = identifiable_combinations(names, np.column_stack([cols[k] for k in names]))
        for k in COMBINATIONS:
            if k in combos:
                out[k] = stats(np.asarray(combos[k], float))
    return out


def summary_table(result: SpecimenResult, *, prob: float = 0.9) -> str:
    """Plain-text table of :func:`summarize` plus the log-evidence."""
    s = summarize(result, prob=prob)
    pc = int(round(prob * 100))
    lines = [f"specimen {result.specimen_id}: {result.n_samples} posterior samples, "
             f"log-evidence {result.log_evidence:.3f} ± {result.log_evidence_se:.3f}",
             f"{'quantity':<14}{'mean':>12}{'sd':>12}{f'{pc}% lower':>12}{f'{pc}% upper':>12}"]
    for k, v in s.items():
        if k == COMBINATIONS[0]:
            lines.append("-- identifiable combinations")
        lines.append(f"{k:<14}{v['mean']:>12.5g}{v['sd']:>12.4g}{v['lower']:>12.5g}{v['upper']:>12.5g}")
    if result.fixed:
        lines.append("fixed: " + ", ".join(f"{k}={v:g}" for k, v in result.fixed.items()))
    return "\n".join(lines)


# ----------------------------------------------------------------------------- driver
@dataclass
class FitResult:
    """Outcome of :func:`fit_specimen`.

    Attributes
    ----------
    result : SpecimenResult
        What is (or would be) stored in the netCDF file.
    path : Path or None
        Written file, if ``out`` was given.
    likelihood : Likelihood
        The specimen's likelihood (free parameter names, bounds, predict ...).
    tmcmc : TMCMCResult or None
    timings : dict
        Seconds per phase: ``cmaes``, ``tmcmc``, ``predictive``, ``sobol``, ``write``, ``total``.
    """

    result: SpecimenResult
    path: Path | None
    likelihood: Any
    tmcmc: Any = None
    timings: dict = field(default_factory=dict)

    @property
    def samples(self) -> np.ndarray:
        return self.result.samples

    @property
    def names(self) -> list[str]:
        return self.result.names

    @property
    def log_evidence(self) -> float:
        return self.result.log_evidence

    @property
    def log_evidence_se(self) -> float:
        return self.result.log_evidence_se

    def summary(self, prob: float = 0.9) -> dict:
        return summarize(self.result, prob=prob)

    def table(self, prob: float = 0.9) -> str:
        return summary_table(self.result, prob=prob)


def _specimen_id(data) -> str:
    return str(getattr(data, "attrs", {}).get("id", "specimen"))


def fit_specimen(data, *, model=None, samples: int = 2000, kernel: str = "rw", noise: str = "iid",
                 fix: Mapping[str, float] | None = None, bounds: Mapping[str, tuple[float, float]] | None = None,
                 seed: int | np.random.SeedSequence = 0, restarts: int = 4, sweep: str | tuple | None = None,
                 sobol_n: int | None = None, checkpoint_dir: str | os.PathLike | None = None,
                 out: str | os.PathLike | None = None, progress: bool = True,
                 tmcmc_options: Mapping[str, Any] | None = None,
                 optimize_options: Mapping[str, Any] | None = None,
                 sigma_bounds: tuple[float, float] | None = None,
                 config_extra: Mapping[str, Any] | None = None,
                 on_phase: Callable[[str], None] | None = None,
                 max_evaluations: int | None = None) -> FitResult:
    """CMA-ES optima, TMCMC posterior, posterior predictive and (optionally) Sobol for one specimen.

    Parameters
    ----------
    data : xarray.Dataset
        A specimen (:func:`hbm.data.load_specimen`); ``attrs["id"]`` names it.
    model : Model, optional
        Default :func:`hbm.spyrou_model`.
    samples : int
        TMCMC population size N (= posterior draws stored).
    kernel : {"rw", "manifold"}
        TMCMC move kernel; "manifold" uses the likelihood's gradient and Fisher information.
    noise : {"iid", "weighted", "proportional", "ar1"}
        Noise model (:func:`hbm.likelihood.make_likelihood`).
    fix, bounds : dict, optional
        Parameters held fixed / narrowed prior boxes.
    seed : int or SeedSequence
        Root seed; the four phases get spawned children (module docstring).
    restarts : int
        CMA-ES restarts (0 skips the optimisation).
    sweep : "PARAM:WIDTH" or (name, width), optional
        Thesis §3.1 bound sweep tracing a manifold (e.g. "VOLF:0.05").
    sobol_n : int or None
        Sobol base sample size (power of 2); None or 0 skips Sobol.
    checkpoint_dir : path, optional
        TMCMC checkpoint ``<dir>/<id>.npz``: an interrupted fit resumes from its last stage.
        Removed once the result file is written.
    out : path, optional
        Write the result netCDF here (atomically; ``complete`` flag last).
    progress : bool
        tqdm bar per TMCMC stage.
    tmcmc_options : dict, optional
        Extra keyword arguments for :func:`hbm.samplers.tmcmc` (n_steps, max_stages, ...).
    optimize_options : dict, optional
        Extra keyword arguments for :func:`hbm.optimize.optimize`; default
        ``{"maxfevals": 5000}`` per CMA-ES run (the optima only seed figures and the manifold;
        an unlimited budget costs minutes per specimen for no visible gain).
    sigma_bounds : (lo, hi), optional
        Box of the first noise parameter (the workflow uses one box for all specimens so the
        hierarchical layer sees a common stage-1 prior).
    config_extra : dict, optional
        Extra JSON-able entries for the stored ``config`` attribute (e.g. a settings hash).
    on_phase : callable, optional
        Called with the phase name when a phase starts (progress reporting).
    max_evaluations : int, optional
        Cap on TMCMC log-likelihood evaluations (:func:`hbm.samplers.tmcmc`); None = no cap.

    Returns
    -------
    FitResult
    """
    from .likelihood import make_likelihood
    from .model import spyrou_model
    from .samplers import tmcmc as _tmcmc

    t_start = time.perf_counter()
    model = spyrou_model() if model is None else model
    if kernel not in ("rw", "manifold"):
        raise HbmError(f"kernel must be 'rw' or 'manifold', got {kernel!r}")
    if int(samples) < 4:
        raise HbmError(f"samples must be >= 4, got {samples}")
    sid = _specimen_id(data)
    lik = make_likelihood(model, data, noise=noise, fix=fix, bounds=bounds, sigma_bounds=sigma_bounds)
    s_opt, s_tm, s_pred, s_sob = spawn_seeds(seed, 4)
    sweep_t = parse_sweep(sweep)
    timings: dict[str, float] = {}
    phase = on_phase or (lambda name: None)

    optima = None
    if restarts and int(restarts) > 0:
        phase("cmaes")
        t = time.perf_counter()
        oopts = {"maxfevals": 5000, **dict(optimize_options or {})}
        optima = run_optima(lik, restarts=int(restarts), seed=s_opt, sweep=sweep_t, **oopts)
        timings["cmaes"] = time.perf_counter() - t

    phase("tmcmc")
    t = time.perf_counter()
    ckpt = None
    if checkpoint_dir is not None:
        ckpt = Path(checkpoint_dir) / f"{sid}.npz"
        ckpt.parent.mkdir(parents=True, exist_ok=True)
    opts = dict(tmcmc_options or {})
    if max_evaluations is not None:
        opts["max_evaluations"] = int(max_evaluations)
    if kernel == "manifold":
        opts.setdefault("gradient_fim", lik.gradient_fim)
    tr = _tmcmc(lik, lik.bounds, int(samples), seed=s_tm, kernel=kernel, checkpoint=ckpt,
                progress=progress, **opts)
    timings["tmcmc"] = time.perf_counter() - t

    phase("predictive")
    t = time.perf_counter()
    theta = np.asarray(tr.samples, float)
    m = lik.predict(theta)
    pll = pointwise_log_likelihood(lik, theta, m)
    pred_model, pred = posterior_predictive(lik, theta, s_pred, m)
    timings["predictive"] = time.perf_counter() - t

    sob = None
    if sobol_n:
        phase("sobol")
        t = time.perf_counter()
        sob = run_sobol(model, data, n=int(sobol_n), seed=s_sob, fix=fix, bounds=bounds)
        timings["sobol"] = time.perf_counter() - t

    strain = np.asarray(data["strain"].values, float)
    config = {"samples": int(samples), "kernel": kernel, "noise": noise, "fix": dict(fix or {}) or None,
              "bounds": {k: list(map(float, v)) for k, v in (bounds or {}).items()} or None,
              "restarts": int(restarts or 0), "sweep": list(sweep_t) if sweep_t else None,
              "sobol_n": int(sobol_n or 0), "optimize_options": dict(optimize_options or {}) or None,
              "sigma_bounds": list(map(float, sigma_bounds)) if sigma_bounds is not None else None,
              "tmcmc_options": {k: v for k, v in opts.items() if k != "gradient_fim"} or None,
              "seeds": {"cmaes": s_opt, "tmcmc": s_tm, "predictive": s_pred, "sobol": s_sob},
              "n_evaluations": int(tr.n_evaluations), "n_stages": len(tr.stages),
              "source_file": str(data.attrs.get("source_file", ""))}
    config.update(dict(config_extra or {}))
    if isinstance(seed, np.random.SeedSequence):
        root_seed = int(seed.entropy)
        config["seed_spawn_key"] = list(map(int, seed.spawn_key))
    else:
        root_seed = int(seed)
    res = SpecimenResult(
        specimen_id=sid, names=list(lik.names), samples=theta, log_likelihood=np.asarray(tr.log_likelihood, float),
        log_evidence=float(tr.log_evidence), log_evidence_se=float(tr.log_evidence_se),
        bounds=np.asarray(lik.bounds, float), stages=list(tr.stages), strain=strain,
        stress=np.asarray(data["stress"].values, float),
        time=np.asarray(data["time"].values, float) if "time" in data else None,
        test=np.asarray(data["test"].values) if "test" in data else None,
        pointwise_log_likelihood=pll, predictive=pred, predictive_model=pred_model, optima=optima, sobol=sob,
        model=model.name, effects=list(model.effect_names), config=config, seed=root_seed,
        fixed=dict(lik.fixed), version=__version__)
    path = None
    if out is not None:
        t = time.perf_counter()
        res.timings = dict(timings)
        path = write_specimen_result(res, out)
        timings["write"] = time.perf_counter() - t
        if ckpt is not None and ckpt.exists():
            ckpt.unlink()  # the result file supersedes the checkpoint
            try:
                ckpt.parent.rmdir()  # only if empty
            except OSError:
                pass
    timings["total"] = time.perf_counter() - t_start
    res.timings = dict(timings)
    return FitResult(result=res, path=path, likelihood=lik, tmcmc=tr, timings=timings)
