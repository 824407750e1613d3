"""Sobol global sensitivity indices of the model (SALib), with the thesis's relevance classes.

Sampling uses ``SALib.sample.sobol.sample`` (scrambled Sobol' sequence, Saltelli's scheme) and the
indices ``SALib.analyze.sobol.analyze`` (bootstrap confidence intervals).  The model receives
the whole sample matrix (n·(D+2), D) in one vectorised call.

Quantity of interest (``qoi``)
------------------------------
``"integrated_stress"`` (default)
    Q = ∫ σ |dε| along the loading path (trapezoid rule over the points in their order, restarted
    at each loading history).  For a monotonic ramp this is the strain-energy density
    W = ∫ σ dε (MPa = MJ/m³) over the tested strain range; the absolute value makes every
    segment of a load–unload path count positively.  It needs no data and summarises the whole
    curve, the choice closest to the thesis's "stress-strain relationship" QoI.
``"log_integrated_stress"``
    Q = log W, the same energy on a log scale: indices of *relative* change.  The stress grows
    exponentially in T2 and with the collagen onset set by THETA, so over the prior box W spans
    several decades and the variance of W is dominated by a few corners of the box; the Sobol
    estimator of W then converges slowly (on a Calvo-like specimen ST of T2 was 1.7 ± 2.2 at
    N = 1024).  log W is stable at N = 1024 and is what ``hbm run`` reports.
``"misfit"``
    Q = Σ_i (σ_model,i − σ_data,i)², the sum of squared residuals to ``data`` (what the
    optimiser and the likelihood see).

Per strain point, the indices of the stress σ(ε_i) itself are also computed (``per_point``).

Relevance classes (thesis Table 2.1) are assigned from the **total** index ST: very important
ST ≥ 0.8, important 0.5 ≤ ST < 0.8, unimportant 0.3 ≤ ST < 0.5, irrelevant ST < 0.3.  ST is used
rather than S1 because a parameter acting only through interactions (small S1, large ST) cannot
be fixed without changing the output (Saltelli's factor-fixing setting).
"""

from __future__ import annotations

import time as _time
from dataclasses import dataclass, field
from typing import Any, Mapping

import numpy as np

from ..errors import HbmError
from ..data.specimen import as_specimen
from ..likelihood.core import observed_stress
from ..model.core import Loading, Model

QOIS = ("integrated_stress", "log_integrated_stress", "misfit")
RELEVANCE = (("very important", 0.8), ("important", 0.5), ("unimportant", 0.3), ("irrelevant", -np.inf))


def relevance_class(st: float) -> str:
    """Thesis Table 2.1 class of a sensitivity index value (applied to ST here)."""
    for label, lo in RELEVANCE:
        if st >= lo:
            return label
    return "irrelevant"  # NaN


@dataclass
class SobolResult:
    """Sobol indices of a scalar QoI, per-point indices, and relevance classes.

    Attributes
    ----------
    names : tuple of str
        Parameters varied (model order, fixed ones excluded).
    bounds : ndarray (D, 2)
        Sampling box (uniform).
    S1, ST, S1_conf, ST_conf : dict name -> float
        First-order and total indices of the scalar QoI and their bootstrap half-widths
        (``conf_level``).
    relevance : dict name -> str
        Thesis Table 2.1 class from ST.
    qoi : str
    n : int
        Base sample size N (a power of 2); model evaluations = N·(D+2) (or N·(2D+2)).
    strain : ndarray (n_points,)
    per_point : dict or None
        ``{"S1": (n_points, D), "ST": (n_points, D), "S1_conf": ..., "ST_conf": ...}`` of the
        stress at each strain point (NaN where the stress does not vary, e.g. at ε = 0).
    S2 : ndarray (D, D) or None
        Second-order indices when ``calc_second_order``.
    n_evaluations : int
    wall_time : float
    """

    names: tuple[str, ...]
    bounds: np.ndarray
    S1: dict[str, float]
    ST: dict[str, float]
    S1_conf: dict[str, float]
    ST_conf: dict[str, float]
    qoi: str
    n: int
    strain: np.ndarray
    per_point: dict[str, np.ndarray] | None
    n_evaluations: int
    wall_time: float
    S2: np.ndarray | None = None
    settings: dict[str, Any] = field(default_factory=dict)  # SALib calls and their options
    relevance: dict[str, str] = field(init=False)

    def __post_init__(self) -> None:
        self.relevance = {k: relevance_class(v) for k, v in self.ST.items()}

    @property
    def ranking(self) -> list[str]:
        """Parameters by decreasing ST."""
        return sorted(self.names, key=lambda k: -np.nan_to_num(self.ST[k], nan=-1.0))

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready dict (NaN -> None)."""
        def f(x):
            return None if not np.isfinite(x) else float(x)

        def arr(a):
            return [[f(v) for v in row] for row in np.asarray(a)]

        out = {"S1": {k: f(v) for k, v in self.S1.items()}, "ST": {k: f(v) for k, v in self.ST.items()},
               "S1_conf": {k: f(v) for k, v in self.S1_conf.items()},
               "ST_conf": {k: f(v) for k, v in self.ST_conf.items()},
               "relevance": dict(self.relevance), "ranking": self.ranking, "qoi": self.qoi,
               "n": int(self.n), "n_evaluations": int(self.n_evaluations),
               "bounds": {k: [float(a), float(b)] for k, (a, b) in zip(self.names, self.bounds)},
               "wall_time": float(self.wall_time)}
        if self.per_point is not None:
            out["per_point"] = {"strain": [float(x) for x in self.strain],
                                **{k: arr(v) for k, v in self.per_point.items()}}
        return out


def _path_weights(loading: Loading) -> np.ndarray:
    """Trapezoid weights w with Q = σ·w = Σ ½(σ_i + σ_{i+1})|ε_{i+1} − ε_i| within each history."""
    e = loading.strain
    w = np.zeros(e.size)
    if e.size < 2:
        return w
    de = np.abs(np.diff(e))
    de[loading.history[1:] != loading.history[:-1]] = 0.0  # no segment across a restart
    w[:-1] += 0.5 * de
    w[1:] += 0.5 * de
    return w


def sobol(model: Model, strain=None, *, bounds: Mapping[str, tuple[float, float]] | None = None,
          fix: Mapping[str, float] | None = None, n: int = 1024, qoi: str = "integrated_stress",
          data=None, seed: int = 0, per_point: bool = True, calc_second_order: bool = False,
          num_resamples: int = 100, conf_level: float = 0.95) -> SobolResult:
    """Sobol first-order and total indices of the model over a (narrowed) prior box.

    Parameters
    ----------
    model : Model
    strain : array (n_points,) or Loading, optional
        Strain points; default: those of ``data``.
    bounds : dict name -> (lo, hi), optional
        Narrowed sampling boxes (the thesis used prior sub-ranges); default the prior box.
    fix : dict name -> value, optional
        Parameters held fixed (not varied, not reported).
    n : int
        Base sample size N, a power of 2; the model is evaluated N·(D+2) times
        (N·(2D+2) with ``calc_second_order``).
    qoi : {"integrated_stress", "log_integrated_stress", "misfit"}
        Scalar quantity of interest (module docstring); "misfit" needs ``data``.
    data : Specimen or xarray.Dataset, optional
        The specimen (a Dataset is converted once).
    seed : int
        Seeds the scrambling of the Sobol' sequence and the bootstrap.
    per_point : bool
        Also compute the indices of the stress at every strain point.
    calc_second_order : bool
        Passed consistently to the SALib sampler and analyser.
    num_resamples, conf_level
        Bootstrap settings of ``SALib.analyze.sobol.analyze``.

    Returns
    -------
    SobolResult
    """
    import SALib
    from SALib.analyze import sobol as sobol_analyze
    from SALib.sample import sobol as sobol_sample

    if qoi not in QOIS:
        raise HbmError(f"qoi must be one of {', '.join(QOIS)}, got {qoi!r}")
    n = int(n)
    if n < 2 or n & (n - 1):
        raise HbmError(f"n must be a power of 2 (Sobol' sequence), got {n}")
    observed = None
    if data is not None:
        spec = as_specimen(data)
        observed = observed_stress(spec)
        if strain is None:
            strain = spec.loading
    if strain is None:
        raise HbmError("sobol needs strain points or data")
    loading = strain if isinstance(strain, Loading) else Loading(np.asarray(strain, dtype=float))
    if qoi == "misfit":
        if observed is None:
            raise HbmError("qoi='misfit' needs data (a specimen with stress)")
        if observed.size != loading.n_points:
            raise HbmError("qoi='misfit': data and strain have different numbers of points")

    names_all = model.parameter_names
    box = model.bounds.copy()
    fix = {k: float(v) for k, v in (fix or {}).items()}
    bounds = dict(bounds or {})
    for kind, dct in (("fix", fix), ("bounds", bounds)):
        bad = [k for k in dct if k not in names_all]
        if bad:
            raise HbmError(f"{kind}: unknown parameter(s) {', '.join(bad)}; the model has {', '.join(names_all)}")
    for k, (lo, hi) in bounds.items():
        i = model.index(k)
        if not (np.isfinite(lo) and np.isfinite(hi) and lo < hi):
            raise HbmError(f"bounds: {k} needs finite LO < HI, got {lo}:{hi}")
        box[i] = float(lo), float(hi)
    free = [i for i, k in enumerate(names_all) if k not in fix]
    if not free:
        raise HbmError("sobol: every parameter is fixed; nothing to vary")
    names = tuple(names_all[i] for i in free)
    problem = {"num_vars": len(free), "names": list(names), "bounds": box[free].tolist()}

    t0 = _time.perf_counter()
    X = sobol_sample.sample(problem, n, calc_second_order=calc_second_order, scramble=True, seed=seed)
    full = np.empty((X.shape[0], model.n_params))
    full[:] = [fix.get(k, np.nan) for k in names_all]
    full[:, free] = X
    with np.errstate(all="ignore"):
        stress = _stress_chunks(model, loading, full)  # (N', P)
    if not np.isfinite(stress).all():
        raise HbmError("sobol: the model gave non-finite stress inside the sampling box; narrow --bounds")
    if qoi == "integrated_stress":
        y = stress @ _path_weights(loading)
    elif qoi == "log_integrated_stress":
        # floor: a box corner with (numerically) zero stress must not give -inf
        y = np.log(np.maximum(stress @ _path_weights(loading), 1e-300))
    else:
        r = stress - observed
        y = np.einsum("ij,ij->i", r, r)

    def analyze(v):
        if not np.ptp(v) > 0:
            nan = np.full(len(free), np.nan)
            return {"S1": nan, "ST": nan, "S1_conf": nan, "ST_conf": nan}
        return sobol_analyze.analyze(problem, v, calc_second_order=calc_second_order,
                                     num_resamples=num_resamples, conf_level=conf_level,
                                     print_to_console=False, seed=seed)

    res = analyze(y)
    pp = None
    if per_point:
        keys = ("S1", "ST", "S1_conf", "ST_conf")
        rows = [analyze(stress[:, j]) for j in range(loading.n_points)]  # one SALib call per point
        pp = {k: np.array([np.asarray(r_[k], dtype=float) for r_ in rows]) for k in keys}
    wall = _time.perf_counter() - t0

    def d(key):
        return {k: float(v) for k, v in zip(names, np.asarray(res[key], dtype=float))}

    return SobolResult(names=names, bounds=box[free], S1=d("S1"), ST=d("ST"), S1_conf=d("S1_conf"),
                       ST_conf=d("ST_conf"), qoi=qoi, n=n, strain=loading.strain.copy(), per_point=pp,
                       n_evaluations=X.shape[0], wall_time=wall,
                       S2=np.asarray(res["S2"]) if calc_second_order and "S2" in res else None,
                       settings={"salib_version": str(getattr(SALib, "__version__", "")),
                                 "salib_sampler": "SALib.sample.sobol.sample(scramble=True)",
                                 "salib_analyzer": "SALib.analyze.sobol.analyze",
                                 "calc_second_order": int(bool(calc_second_order)),
                                 "num_resamples": int(num_resamples), "conf_level": float(conf_level),
                                 "sampler_seed": int(seed)})


def _stress_chunks(model: Model, loading: Loading, theta: np.ndarray, chunk: int = 1 << 16) -> np.ndarray:
    """Model stress over many rows, in large vectorised chunks to bound memory."""
    if theta.shape[0] <= chunk:
        return model.stress(loading, theta)
    return np.concatenate([model.stress(loading, theta[i:i + chunk])
                           for i in range(0, theta.shape[0], chunk)])
