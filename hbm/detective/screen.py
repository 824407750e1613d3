"""What is missing: a cheap screen of every candidate effect (step 3 of the detective).

Two screens per candidate, both in noise-whitened units at the base fit: a projected score
test at the effect's null (:func:`score_screen`) and a few Gauss–Newton steps of a local refit
(:func:`local_refit_screen`).  The non-physical controls (:mod:`.controls`) are screened by
a linear fit of their amplitude over a grid of shapes (their position is multimodal), then a
local refit from the best few shapes.
"""

from __future__ import annotations

from typing import Callable, Mapping, Sequence

import numpy as np
from scipy import optimize as _sopt
from scipy import stats as _stats

from ..errors import HbmError
from ..model.core import Effect, Model, Parameter
from .controls import Control, LocalMisfit, controls_for
from .inputs import SpecimenData
from .noise_check import NoiseCheck, whitener
from .results import CandidateResult, FitSummary
from .rules import SCREEN_STEPS

__all__ = ["LocalMisfit", "score_screen", "candidate_column_sets", "absorbable_basis", "local_refit_screen", "screen_candidates", "screen_controls"]


# =========================================================================================
# the score test
# =========================================================================================
def _candidate_sensitivity(model: Model, effect: Effect, theta_model: np.ndarray, data: SpecimenData,
                           overrides: Mapping[str, float] | None = None,
                           rel_step: float = 1e-4) -> tuple[np.ndarray, list[str], Model]:
    """d stress / d(effect parameters) at their null values, by finite differences.

    One-sided (into the box) where the null sits on a bound.  With a large ``rel_step``
    (fraction of the box width) this is a *secant* sensitivity, which sees signatures that
    are nonlinear in the parameter (a kink that moves, as with slack) and that the
    derivative at the null misses.  Returns (J (n, k), names, model+effect).
    """
    mc = model.with_effects(effect)
    th0 = mc.null_theta(theta_model)
    for k, v in (overrides or {}).items():
        th0[mc.index(k)] = v
    names = [q.name for q in effect.parameters]
    pert, steps = [], []
    for q in effect.parameters:
        i = mc.index(q.name)
        width = q.upper - q.lower
        h = rel_step * width
        x0 = th0[i]
        if x0 + h > q.upper:        # null near the upper bound: step inward (backward)
            a, b = x0 - h, x0
        elif x0 - h < q.lower:      # null near the lower bound: forward
            a, b = x0, x0 + h
        else:
            a, b = x0 - h, x0 + h
        ta, tb = th0.copy(), th0.copy()
        ta[i], tb[i] = a, b
        pert += [ta, tb]
        steps.append(b - a)
    s = np.asarray(mc.stress(data.loading, np.array(pert)))
    J = (s[1::2] - s[0::2]) / np.asarray(steps)[:, None]
    return J.T, names, mc


def _grid(q: Parameter, n: int) -> np.ndarray:
    if q.lower > 0 and q.upper / q.lower > 20:
        return np.geomspace(q.lower, q.upper, n + 2)[1:-1]
    return np.linspace(q.lower, q.upper, n + 2)[1:-1]


def absorbable_basis(model: Model, theta_model: np.ndarray, free: Sequence[str], whiten,
                     data: SpecimenData) -> tuple[np.ndarray, np.ndarray]:
    """Orthonormal basis (n, r) of what the base's free parameters absorb, in whitened units
    (numerically null directions dropped), and the base Jacobian's free columns (n, k)."""
    Jb = np.asarray(model.stress_jacobian(data.loading, theta_model))[:, [model.index(n) for n in free]]
    U, sv, _ = np.linalg.svd(whiten(Jb), full_matrices=False)
    return (U[:, sv > sv.max() * 1e-9] if sv.size and sv.max() > 0 else U[:, :0]), Jb


def score_screen(model: Model, theta_model: np.ndarray, free: Sequence[str], effect: Effect,
                 residual: np.ndarray, whiten, data: SpecimenData, n_grid: int = 5) -> dict:
    """Projected score statistic of one candidate effect.

    The candidate's sensitivity columns J_c (at the null) and the base model's Jacobian J_b
    (free parameters, at the fit) are whitened with the noise model; the part of J_c in the
    span of J_b is what parameter drift absorbs and is projected out.  The statistic is the
    reduction of the whitened residual sum of squares by a (sign-constrained where the null
    sits on a bound) linear fit of the remaining columns — chi-square with rank(J̃) degrees of
    freedom under the null.  Parameters whose sensitivity vanishes at the null (e.g. a time
    constant when the amplitude is zero) are nuisances: the statistic is maximised over a grid
    of their values.  Besides the derivative at the null, secant sensitivities over 10 % and
    30 % of the box (``SCREEN_STEPS``) are tried, because some signatures are nonlinear in the
    parameter (slack moves a kink).  The p-value is Bonferroni-corrected for grid × steps.

    Returns
    -------
    dict with ``chi2``, ``dof``, ``p``, ``z``, ``absorbed`` and ``start`` (linearised estimate
    of the effect's parameters, a warm start for the refit).
    """
    U, _ = absorbable_basis(model, theta_model, free, whiten, data)
    r = whiten(residual)
    r = r - U @ (U.T @ r)

    best, n_tries = None, 0
    for cs in candidate_column_sets(model, theta_model, effect, whiten, data, U, float(np.linalg.norm(r)), n_grid):
        n_tries += 1
        ov, act, keep, A = cs["ov"], cs["act"], cs["keep"], cs["A"]
        if A is None:
            res = {"chi2": 0.0, "dof": 0, "absorbed": 1.0, "beta": np.zeros(len(act)), "ov": ov, "act": act}
        else:
            # column scaling keeps lsq_linear well conditioned
            cs_ = np.linalg.norm(A, axis=0)
            sol = _sopt.lsq_linear(A / cs_, r, bounds=(cs["lb"], cs["ub"]))
            beta_s = sol.x
            chi2 = float(r @ r - np.sum((r - (A / cs_) @ beta_s) ** 2))
            beta = np.zeros(len(act))
            beta[np.flatnonzero(keep)] = beta_s / cs_
            res = {"chi2": max(chi2, 0.0), "dof": int(np.linalg.matrix_rank(A)), "absorbed": cs["absorbed"],
                   "beta": beta, "ov": ov, "act": act}
        if best is None or res["chi2"] > best["chi2"]:
            best = res
    dof = max(best["dof"], 1)
    p = float(_stats.chi2.sf(best["chi2"], dof)) * n_tries
    p = min(max(p, 1e-300), 1.0)
    z = float(_stats.norm.isf(p)) if p < 0.5 else 0.0
    # warm start: null + linearised step (clipped into the box), nuisances at their best grid value
    start = {q.name: q.null for q in effect.parameters}
    start.update(best["ov"])
    for i, b in zip(best["act"], best["beta"]):
        q = effect.parameters[i]
        start[q.name] = float(np.clip(q.null + b, q.lower + 1e-3 * (q.upper - q.lower),
                                      q.upper - 1e-3 * (q.upper - q.lower)))
    return {"chi2": best["chi2"], "dof": best["dof"], "p": p, "z": z,
            "absorbed": best["absorbed"], "start": start}


def candidate_column_sets(model: Model, theta_model: np.ndarray, effect: Effect, whiten, data: SpecimenData,
                          U: np.ndarray, ref: float, n_grid: int = 5):
    """The linear alternatives the score test of ``effect`` fits, one per nuisance value × step.

    Yields dicts: ``A`` the whitened sensitivity columns with the base's absorbable directions
    (orthonormal ``U``) projected out (None when all are absorbed), ``lb``/``ub`` the sign
    bounds of their coefficients (0 on the side where the null sits on a box edge), ``ov`` the
    nuisance values, ``act`` the active parameter indices, ``keep`` which of them survive the
    projection and ``absorbed``.  Shared by :func:`score_screen` and the calibration's null
    replicates (:mod:`.calibration`), so both test the very same alternatives.  ``ref``: the
    norm of the whitened residual (a parameter whose sensitivity is negligible beside it is a
    nuisance, maximised over a grid).
    """
    J0, names, _ = _candidate_sensitivity(model, effect, theta_model, data)
    steps = SCREEN_STEPS
    scale = np.linalg.norm(whiten(J0), axis=0)
    ref = max(ref, 1e-300)
    nuis = [n for n, s in zip(names, scale) if not (s * 1e-3 > 1e-12 * ref and s > 0)]
    nuis_params = [q for q in effect.parameters if q.name in nuis]
    if nuis_params and len(nuis_params) < len(names):
        grids = np.array(np.meshgrid(*[_grid(q, n_grid) for q in nuis_params], indexing="ij"))
        combos = grids.reshape(len(nuis_params), -1).T
        if combos.shape[0] > 25:
            combos = combos[np.linspace(0, combos.shape[0] - 1, 25).astype(int)]
    else:
        combos = np.zeros((1, 0))
    for combo, rel in ((c, r) for c in combos for r in steps):
        ov = {q.name: v for q, v in zip(nuis_params, combo)}
        J = J0 if not ov and rel == steps[0] else \
            _candidate_sensitivity(model, effect, theta_model, data, ov, rel_step=rel)[0]
        act = [i for i, n in enumerate(names) if n not in ov]
        Wc = whiten(J[:, act])
        norm0 = np.linalg.norm(Wc, axis=0)
        Wp = Wc - U @ (U.T @ Wc)
        normp = np.linalg.norm(Wp, axis=0)
        keep = normp > 1e-8 * np.maximum(norm0, 1e-300)
        if not keep.any():
            yield {"A": None, "lb": None, "ub": None, "ov": ov, "act": act, "keep": keep, "absorbed": 1.0}
            continue
        qa = [effect.parameters[i] for i in np.array(act)[keep]]
        yield {"A": Wp[:, keep], "ov": ov, "act": act, "keep": keep,
               "lb": np.array([0.0 if q.null is not None and q.null <= q.lower else -np.inf for q in qa]),
               "ub": np.array([0.0 if q.null is not None and q.null >= q.upper else np.inf for q in qa]),
               "absorbed": float(1 - np.sum(normp ** 2) / max(np.sum(norm0 ** 2), 1e-300))}


# =========================================================================================
# the cheap local refit
# =========================================================================================
def local_refit_screen(model: Model, theta_model: np.ndarray, free: Sequence[str], effect: Effect,
                       whiten, data: SpecimenData, starts: Sequence[Mapping[str, float]],
                       max_nfev: int = 25) -> dict:
    """Cheap local refit: a few bounded Gauss–Newton (trust-region) steps of the base model plus
    the effect from the base fit, on noise-whitened residuals.

    Complements the score test (a linearisation at the null) for effects whose signature is
    nonlinear in their parameter.  Returns ``chi2`` (drop of the whitened residual sum of
    squares, ≈ 2·Δlog-likelihood), ``dof``, ``z`` and the refit ``start``.
    """
    mc = model.with_effects(effect)
    th0 = mc.null_theta(theta_model)
    names = list(free) + [q.name for q in effect.parameters]
    idx = np.array([mc.index(n) for n in names])
    box = mc.bounds[idx]
    y = data.stress
    loading = data.loading

    def put(x):
        x = np.atleast_2d(x)
        t = np.repeat(th0[None, :], x.shape[0], axis=0)
        t[:, idx] = x
        return t

    def fun(x):
        return whiten(y - np.asarray(mc.stress(loading, put(x)))[0])

    width = box[:, 1] - box[:, 0]

    def jac(x):
        h = 1e-6 * width
        xp = np.clip(x + np.diag(h), box[:, 0], box[:, 1])
        xm = np.clip(x - np.diag(h), box[:, 0], box[:, 1])
        s = np.asarray(mc.stress(loading, put(np.vstack([xp, xm]))))
        k = x.size
        dx = np.maximum(xp[np.arange(k), np.arange(k)] - xm[np.arange(k), np.arange(k)], 1e-300)
        # residual = y − stress, whitening is linear
        return -whiten(((s[:k] - s[k:]) / dx[:, None]).T)

    r0 = fun(th0[idx])
    ssr0 = float(r0 @ r0)
    best = (ssr0, th0[idx])
    for st in starts:
        x0 = th0[idx].copy()
        for j, q in enumerate(effect.parameters):
            v = float(st.get(q.name, q.null))
            w = q.upper - q.lower
            x0[len(free) + j] = min(max(v, q.lower + 0.02 * w), q.upper - 0.02 * w)
        x0 = np.clip(x0, box[:, 0] + 1e-9 * width, box[:, 1] - 1e-9 * width)
        try:
            with np.errstate(all="ignore"):
                res = _sopt.least_squares(fun, x0, jac=jac, bounds=(box[:, 0], box[:, 1]), x_scale=width,
                                          max_nfev=max_nfev, method="trf")
        except (ValueError, np.linalg.LinAlgError):
            continue
        if np.isfinite(res.cost) and 2 * res.cost < best[0]:
            best = (2 * float(res.cost), res.x)
    chi2 = max(ssr0 - best[0], 0.0)
    dof = len(effect.parameters)
    p = min(max(float(_stats.chi2.sf(chi2, dof)), 1e-300), 1.0)
    z = float(_stats.norm.isf(p)) if p < 0.5 else 0.0
    start = {n: float(v) for n, v in zip(names[len(free):], best[1][len(free):])}
    # the whole local optimum (base parameters included): the refit's best warm start when the
    # base parameters had moved to absorb the misfit
    full = {n: float(v) for n, v in zip(names, best[1])}
    return {"chi2": chi2, "dof": dof, "z": z, "start": start, "full": full}


# =========================================================================================
# the step
# =========================================================================================
def screen_candidates(base: FitSummary, candidates: Sequence[Effect], check: NoiseCheck, d: SpecimenData,
                      log: Callable[[str], None]) -> tuple[list[CandidateResult], list[CandidateResult], dict[str, str]]:
    """Screen every candidate and the controls at the base fit.

    The screen whitens with the same noise as the windows: an AR(1) fit that soaked up the
    misfit would whiten the very signature looked for away.

    Returns
    -------
    results : list of CandidateResult
        The physical candidates, ranked by the stronger of their two screens.
    controls : list of CandidateResult
        The non-physical controls (:mod:`.controls`), ranked the same way.
    skipped : dict
        Candidate -> why it could not be screened (e.g. no time column).
    """
    base_model, lik = base.model, base.likelihood
    theta_model = np.asarray(lik.model_theta(base.theta_max[None, :]))[0]
    free = [n for n in lik.names if n in base_model.parameter_names]
    whiten = whitener(check.sd, check.rho, d.ar_first)
    resid = check.resid
    results: list[CandidateResult] = []
    skipped: dict[str, str] = {}
    for e in candidates:
        try:
            sc = score_screen(base_model, theta_model, free, e, resid, whiten, d)
        except HbmError as exc:
            # e.g. viscoelasticity on a specimen without a time column: not applicable here
            skipped[e.name] = str(exc)
            log(f"candidate {e.name} skipped: {exc}")
            continue
        except Exception as exc:  # a broken user effect: one clear line, not a traceback
            raise HbmError(f"candidate {e.name!r}: screening failed ({type(exc).__name__}: {exc})") from None
        lr = local_refit_screen(base_model, theta_model, free, e, whiten, d,
                                [sc["start"], {q.name: q.null for q in e.parameters}])
        results.append(CandidateResult(effect=e.name, score=sc["z"], chi2=sc["chi2"], dof=sc["dof"],
                                       absorbed=sc["absorbed"], rmse_before=base.rmse, start=lr["start"],
                                       local_z=lr["z"], local_chi2=lr["chi2"], effect_instance=e,
                                       score_start=sc["start"], local_full=lr["full"]))
    ctrls = screen_controls(controls_for(d), base_model, theta_model, free, resid, whiten, d, base.rmse)
    # rank by the stronger of the two screens (score test at the null, cheap local refit)
    results.sort(key=_rank)
    log("screen: " + ", ".join(f"{c.effect} z={c.score:.1f}/{c.local_z:.1f}" for c in results)
        + "; controls " + ", ".join(f"{c.effect} z={c.local_z:.1f}" for c in ctrls))
    return results, ctrls, skipped


def screen_controls(controls: Sequence[Control], model: Model, theta_model: np.ndarray, free: Sequence[str],
                    resid: np.ndarray, whiten, d: SpecimenData, rmse_before: float,
                    n_starts: int = 3) -> list[CandidateResult]:
    """Screen each control: its amplitude fitted linearly over a grid of shapes (with the base
    model's absorbable directions projected out), then a local refit from the best shapes.

    Returns the controls as CandidateResults, the strongest (local-refit z) first.
    """
    U, _ = absorbable_basis(model, theta_model, free, whiten, d)
    r = whiten(resid)
    r = r - U @ (U.T @ r)
    out = []
    for ctl in controls:
        grid = ctl.grid()
        scored = []
        for g in grid:
            q = {k: np.asarray(v) for k, v in g.items()}
            f = whiten(np.asarray(ctl.shape(d.loading, q), float) * np.ones(d.stress.size))
            f = f - U @ (U.T @ f)
            ff = float(f @ f)
            if ff <= 0:
                continue
            amp = float(r @ f) / ff
            a_max = ctl.parameters[0].upper * 0.95
            scored.append(((r @ f) ** 2 / ff, {ctl.amp: float(np.clip(amp, -a_max, a_max)), **g}))
        scored.sort(key=lambda t: -t[0])
        starts = [st for _, st in scored[:n_starts]] or [ctl.null_values]
        lr = local_refit_screen(model, theta_model, free, ctl, whiten, d, starts, max_nfev=40)
        chi2_lin = scored[0][0] if scored else 0.0
        out.append(CandidateResult(effect=ctl.name, score=float(_stats.norm.isf(
            min(max(_stats.chi2.sf(chi2_lin, 1) * max(len(grid), 1), 1e-300), 0.5))), chi2=float(chi2_lin), dof=1,
            absorbed=float("nan"), physical=False, rmse_before=rmse_before, start=lr["start"], local_z=lr["z"],
            local_chi2=lr["chi2"], effect_instance=ctl, score_start=starts[0], local_full=lr["full"]))
    out.sort(key=lambda c: _rank(c, local_only=True))
    return out


#: the screens' z at their p-value floor (1e-300): a strong signal saturates every candidate there
Z_CEILING = float(_stats.norm.isf(1e-300))


def _rank(c: CandidateResult, local_only: bool = False) -> tuple[float, float]:
    """Sort key of a screened candidate: the stronger of its screens' z, best first; where z sits
    at its ceiling (a dense or strongly misfitting record saturates several candidates) the larger
    χ² (≈ 2 Δlog L) decides, so that the ranking -- which candidates are refitted -- does not
    fall back on the registry's order."""
    z = c.local_z if local_only else max(c.score, c.local_z)
    chi2 = c.local_chi2 if local_only else max(c.chi2, c.local_chi2)
    return (-z, -chi2 if z >= Z_CEILING - 1e-9 else 0.0)
