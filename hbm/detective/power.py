"""Detection power: what this protocol and this noise could reveal (``hbm diagnose --power``).

For each library effect, the fitted model plus the effect at increasing strength (its other
parameters at their nulls) is simulated on the specimen's own strain/time points with the
fitted noise, and the share of replicates in which the decision rule would name the effect is
estimated; the smallest strength named in ≥ 80 % of replicates is the detection limit.

The replicates use the *Laplace screen*, not full refits (hundreds of replicates × effects ×
strengths must stay within minutes): each competitor (every candidate and every control) is
fitted once to the noiseless curve (nonlinear least squares in noise-whitened units, base
parameters free), and each noise replicate's refit is its Gauss–Newton linearisation at that
optimum -- the residual sum of squares of replicate e is ‖r₀ + (I − P)e‖² with r₀ the noiseless
residual and P the projection on the whitened Jacobian there, vectorised over replicates.  The
gain of a competitor is Δmax log L plus its Laplace Occam factor (capped at Δmax log L, as in
:func:`.decision.gain`); the effect counts as named in a replicate when the rule of
:func:`.decision.decide` would name it: gain > ``DELTA_LOGZ_MIN``, ahead of every other
candidate by ``RUNNER_UP_MARGIN``, at least the best control's gain, and within ``REMOVE_TOL``
of the best control's likelihood.  Linearised replicates ignore optimiser failures, so the limit
is optimistic when a fit is hard (the validation in ``results/detective_validation.md`` checks
1.5× the viscoelastic limit end to end).
"""

from __future__ import annotations

import math
from typing import Sequence

import numpy as np
from scipy import optimize as _sopt

from ..effects import applicable
from ..errors import HbmError
from ..model.core import Effect, Model
from .controls import controls_for
from .inputs import SpecimenData
from .noise_check import whitener
from .protocols import describe_protocol, experiments_for, protocol_features
from .refits import primary_parameters
from .results import FitSummary
from .rules import DELTA_LOGZ_MIN, POWER_LEVEL, POWER_REPLICATES, REMOVE_TOL, RUNNER_UP_MARGIN

__all__ = ["detection_power"]


def _fit_noiseless(mc: Model, th0: np.ndarray, idx: np.ndarray, y0: np.ndarray, whiten, d: SpecimenData,
                   starts: Sequence[np.ndarray], max_nfev: int = 40) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Least-squares fit of ``mc`` (parameters ``idx`` free) to the noiseless curve ``y0``.

    Returns the whitened residual at the optimum, the whitened Jacobian of the prediction
    there (n, k) and the optimum.
    """
    box = mc.bounds[idx]
    width = box[:, 1] - box[:, 0]

    def put(x):
        t = np.repeat(th0[None, :], x.shape[0], axis=0)
        t[:, idx] = x
        return t

    def fun(x):
        return whiten(y0 - np.asarray(mc.stress(d.loading, put(x[None, :])))[0])

    def jac_pred(x):
        h = 1e-6 * width
        xp = np.clip(x + np.diag(h), box[:, 0], box[:, 1])
        xm = np.clip(x - np.diag(h), box[:, 0], box[:, 1])
        s = np.asarray(mc.stress(d.loading, put(np.vstack([xp, xm]))))
        k = x.size
        dx = np.maximum(np.diag(xp - xm), 1e-300)
        return whiten(((s[:k] - s[k:]) / dx[:, None]).T)

    best = None
    for x0 in starts:
        x0 = np.clip(np.asarray(x0, float), box[:, 0] + 1e-9 * width, box[:, 1] - 1e-9 * width)
        try:
            with np.errstate(all="ignore"):
                res = _sopt.least_squares(fun, x0, jac=lambda x: -jac_pred(x), bounds=(box[:, 0], box[:, 1]),
                                          x_scale=width, max_nfev=max_nfev, method="trf")
        except (ValueError, np.linalg.LinAlgError):
            continue
        if np.isfinite(res.cost) and (best is None or res.cost < best.cost):
            best = res
    if best is None:
        x = np.asarray(starts[0], float)
        return fun(x), jac_pred(x), x
    return best.fun, jac_pred(best.x), best.x


def _occam(A: np.ndarray, new: np.ndarray, width: np.ndarray) -> float:
    """Laplace Occam factor (≤ 0) of the columns ``new`` of the whitened Jacobian ``A``
    (Gauss–Newton information, the other columns profiled out by a Schur complement)."""
    F = A.T @ A
    old = np.setdiff1d(np.arange(A.shape[1]), new)
    S = F[np.ix_(new, new)] - F[np.ix_(new, old)] @ np.linalg.pinv(F[np.ix_(old, old)], rcond=1e-10) @ F[np.ix_(old, new)]
    S = 0.5 * (S + S.T)
    ev, V = np.linalg.eigh(S)
    # a direction without information is bounded by the box (sd ≈ width/√12)
    ev = np.maximum(ev, 12.0 / float(np.max(width)) ** 2)
    occ = 0.5 * (new.size * math.log(2 * math.pi) - float(np.sum(np.log(ev)))) - float(np.sum(np.log(width)))
    return min(0.0, occ)


def _competitor(model: Model, e: Effect, theta: np.ndarray, free: list[str], y0: np.ndarray, whiten,
                d: SpecimenData, extra_starts: Sequence[dict] = ()) -> dict:
    """Noiseless fit of base + ``e`` to ``y0``: residual, projection basis and Occam factor."""
    mc = model.with_effects(e)
    th0 = mc.null_theta(theta)
    names = list(free) + [q.name for q in e.parameters]
    idx = np.array([mc.index(n) for n in names])
    base_x = th0[idx]
    starts = [base_x]
    for st in extra_starts:
        x = base_x.copy()
        for j, q in enumerate(e.parameters):
            if q.name in st:
                x[len(free) + j] = st[q.name]
        starts.append(x)
    # a start on the null bound keeps a bounded optimiser there: nudge the new parameters inside
    nudged = base_x.copy()
    for j, q in enumerate(e.parameters):
        w = q.upper - q.lower
        nudged[len(free) + j] = min(max(nudged[len(free) + j], q.lower + 0.05 * w), q.upper - 0.05 * w)
    starts.append(nudged)
    r0, A, _ = _fit_noiseless(mc, th0, idx, y0, whiten, d, starts)
    U, sv, _ = np.linalg.svd(A, full_matrices=False)
    U = U[:, sv > sv.max() * 1e-9] if sv.size and sv.max() > 0 else U[:, :0]
    new = np.arange(len(free), len(names))
    width = mc.bounds[idx[new], 1] - mc.bounds[idx[new], 0]
    return {"r0": r0, "U": U, "occam": _occam(A, new, width)}


def _ssr(comp: dict, E: np.ndarray) -> np.ndarray:
    """Residual sum of squares of every replicate's linearised refit: ‖r₀ + (I − P)e‖²."""
    r0, U = comp["r0"], comp["U"]
    EU = E @ U
    return float(r0 @ r0) + 2.0 * (E @ r0) + np.sum(E * E, axis=1) - np.sum(EU * EU, axis=1)


def _named_fraction(model: Model, eff: Effect, others: Sequence[Effect], ctrls: Sequence[Effect], theta: np.ndarray,
                    free: list[str], y0: np.ndarray, truth: dict, whiten, d: SpecimenData, E: np.ndarray,
                    critical: float | None = None) -> float:
    """Share of the replicates ``E`` in which ``eff`` would be named (module docstring); with a
    calibrated ``critical`` likelihood gain, the calibrated rule (gain beyond it, evidence > 0)."""
    mb = model
    idx_b = np.array([mb.index(n) for n in free])
    r0, A, _ = _fit_noiseless(mb, theta, idx_b, y0, whiten, d, [theta[idx_b]])
    U, sv, _ = np.linalg.svd(A, full_matrices=False)
    U = U[:, sv > sv.max() * 1e-9]
    ssr_b = _ssr({"r0": r0, "U": U}, E)

    def gains(e, starts=()):
        c = _competitor(model, e, theta, free, y0, whiten, d, starts)
        dl = 0.5 * (ssr_b - _ssr(c, E))
        return np.minimum(dl + c["occam"], dl), dl

    g_eff, dl_eff = gains(eff, [truth])
    g_other = np.full(E.shape[0], -np.inf)
    for o in others:
        g_other = np.maximum(g_other, gains(o)[0])
    g_ctrl, dl_ctrl = np.full(E.shape[0], -np.inf), np.full(E.shape[0], -np.inf)
    for c in ctrls:
        g, dl = gains(c, c.grid()[::3])
        better = g > g_ctrl
        g_ctrl, dl_ctrl = np.where(better, g, g_ctrl), np.where(better, dl, dl_ctrl)
    strong = (g_eff > DELTA_LOGZ_MIN) if critical is None else ((dl_eff > critical) & (g_eff > 0))
    named = (strong & (g_eff - g_other >= RUNNER_UP_MARGIN) & (g_eff >= g_ctrl)
             & (dl_eff >= dl_ctrl - REMOVE_TOL))
    return float(np.mean(named))


def detection_power(fit: FitSummary, d: SpecimenData, candidates: Sequence[Effect], seed: int,
                    n_rep: int = POWER_REPLICATES, level: float = POWER_LEVEL, n_levels: int = 7,
                    refine: int = 3, with_controls: bool = True, noise_fit: FitSummary | None = None,
                    run_tasks=None, calibration=None) -> dict:
    """Detection limit of every candidate effect on this specimen's protocol and fitted noise.

    Parameters
    ----------
    fit : FitSummary
        The fitted model (its optimum and noise generate the replicates).
    d : SpecimenData
        The specimen (its strain/time points are the protocol).
    candidates : sequence of Effect
        The effects to assess (those already in the model are skipped).
    seed : int
        Seed of the noise replicates (shared by all effects and strengths).
    n_rep : int
        Noise replicates per strength.
    level : float
        Share of replicates in which the effect must be named (0.8).
    n_levels, refine : int
        Strengths on a geometric grid toward the far bound of the strength parameter, then
        bisection steps between the last missed and the first named strength.
    with_controls : bool
        Let the non-physical controls compete (the decision rule; ``False`` only for checks).
    noise_fit : FitSummary, optional
        Take the noise from this fit instead (diagnose: the final model's, once effects were
        named, so a misfit of the starting model does not inflate the noise of the replicates).
        Effects that need another first (a further relaxation time, ``requires``) are assessed
        at this fit when its model has what they need (their rows say ``beside``).
    run_tasks : callable, optional
        ``run_tasks(task, calls)`` returns ``[task(*c) for c in calls]``, e.g. in worker processes
        (diagnose passes its refit workers); every effect's limit is computed independently, from
        the same noise replicates, so the result does not depend on how they run.
    calibration : Calibration, optional
        The calibration of ``fit`` (:mod:`.calibration`): an effect counts as named when its
        likelihood gain exceeds its calibrated critical value (family-wise) instead of the fixed
        ``DELTA_LOGZ_MIN``.

    Returns
    -------
    dict
        ``effects``: one dict per effect (``effect``, ``parameter``, ``limit`` or None,
        ``levels`` [[strength, share named], ...], ``shape`` (other parameters, at their
        nulls), ``protocol`` (what would reveal it when not detectable)); ``method``;
        ``replicates``; ``text``.
    """
    model, theta, free = _at(fit)
    nf = fit if noise_fit is None else noise_fit
    sd = np.asarray(nf.likelihood.noise_sd(nf.theta_max[None, :]))[0]
    rho = float(dict(zip(nf.likelihood.names, nf.theta_max)).get("rho", 0.0))
    whiten = whitener(sd, rho, d.ar_first)
    rng = np.random.default_rng(seed)
    E = rng.standard_normal((int(n_rep), d.stress.size))   # whitened noise: common to every effect
    have = set(model.effect_names)
    usable, later = [], []
    for e in candidates:
        if e.name in have:
            continue
        if not applicable(e, model):
            # a further relaxation time: assessed beside the relaxation the final model names
            if noise_fit is not None and e.name not in noise_fit.model.effect_names and applicable(e, noise_fit.model):
                later.append(e)
            continue
        try:
            model.with_effects(e).stress(d.loading, model.with_effects(e).null_theta(theta))
        except HbmError:
            continue   # e.g. viscoelasticity without a time column
        usable.append(e)
    ctrls = controls_for(d) if with_controls else []
    feats = protocol_features(d)
    crit = {k: v["critical"] for k, v in calibration.stats.items()} if calibration is not None else {}
    calls = [(e, model, [o for o in usable if o is not e], ctrls, theta, free, whiten, d, E, n_levels, refine, level,
              feats, crit.get(e.name)) for e in usable]
    if later:
        # (not among the calibrated candidates of the starting model: these rows use the fixed rule)
        final, theta_f, free_f = _at(noise_fit)
        rivals = [o for o in candidates if o.name not in final.effect_names and applicable(o, final)]
        calls += [(e, final, [o for o in rivals if o is not e], ctrls, theta_f, free_f, whiten, d, E, n_levels,
                   refine, level, feats, None) for e in later]
    rows = run_tasks(_effect_limit, calls) if run_tasks is not None else [_effect_limit(*c) for c in calls]
    if calibration is not None:
        for row in rows[len(usable):]:
            row["rule"] = f"fixed (gain > {DELTA_LOGZ_MIN:g} nats): not among the calibrated candidates"
    out = {"effects": rows, "replicates": int(n_rep), "level": level,
           "method": "Laplace screen: linearised refits of every candidate and control at their noiseless optima"
           + (f"; named by the calibrated rule (likelihood gain beyond its family-wise {calibration.alpha:.0%} null "
              f"quantile from {calibration.replicates} replicates)" if calibration is not None else
              f"; named by the fixed rule (gain > {DELTA_LOGZ_MIN:g} nats)"),
           "protocol": describe_protocol(feats)}
    out["text"] = _text(out)
    return out


def _at(fit: FitSummary) -> tuple[Model, np.ndarray, list[str]]:
    """The fitted model, its full parameter row at the optimum and its free model parameters."""
    lik = fit.likelihood
    theta = np.asarray(lik.model_theta(fit.theta_max[None, :]))[0]
    return fit.model, theta, [n for n in lik.names if n in fit.model.parameter_names]


def _effect_limit(e: Effect, model: Model, others: list, ctrls: list, theta: np.ndarray, free: list, whiten,
                  d: SpecimenData, E: np.ndarray, n_levels: int, refine: int, level: float, feats: dict,
                  critical: float | None = None) -> dict:
    """One effect's detection limit (a row of :func:`detection_power`): the shares named on a
    geometric grid of strengths, then bisection; independent of the other effects' rows."""
    mc = model.with_effects(e)
    q = next(p for p in e.parameters if p.name == primary_parameters(e)[0])
    far = q.upper if abs(q.upper - q.null) >= abs(q.lower - q.null) else q.lower

    def share(frac):
        th = mc.null_theta(theta)
        th[mc.index(q.name)] = q.null + frac * (far - q.null)
        y0 = np.asarray(mc.stress(d.loading, th))
        truth = {p.name: float(th[mc.index(p.name)]) for p in e.parameters}
        return _named_fraction(model, e, others, ctrls, theta, free, y0, truth, whiten, d, E, critical)

    fracs = list(np.geomspace(0.01, 1.0, n_levels))
    levels = [(f, share(f)) for f in fracs]
    hit = next((i for i, (_, s) in enumerate(levels) if s >= level), None)
    if hit is not None and hit > 0:
        lo, hi = levels[hit - 1][0], levels[hit][0]
        for _ in range(int(refine)):
            mid = math.sqrt(lo * hi)
            s = share(mid)
            levels.append((mid, s))
            lo, hi = (mid, hi) if s < level else (lo, mid)
        limit_frac = hi
    else:
        limit_frac = None if hit is None else levels[hit][0]
    levels.sort()
    val = (lambda f: float(q.null + f * (far - q.null)))
    beside = [n for n in getattr(e, "requires", ()) if n in model.effect_names]
    return {**({"beside": beside} if beside else {}), "effect": e.name, "parameter": q.name, "unit": q.unit,
            "limit": None if limit_frac is None else val(limit_frac),
            "levels": [[val(f), s] for f, s in levels],
            "shape": {p.name: p.null for p in e.parameters if p.name != q.name},
            "protocol": None if limit_frac is not None else experiments_for([e], feats)}


def _text(p: dict) -> str:
    lines = [f"detection power on this protocol ({p['protocol']}) with the fitted noise: the smallest strength "
             f"named in >= {p['level']:.0%} of {p['replicates']} replicates ({p['method']}; other parameters of "
             "each effect at their nulls)"]
    for r in p["effects"]:
        shape = ", ".join(f"{k}={v:g}" for k, v in r["shape"].items())
        if r.get("beside"):
            shape += f"{', ' if shape else ''}beside the fitted {' + '.join(r['beside'])}"
        if r.get("rule"):
            shape += f"{', ' if shape else ''}{r['rule'].split(':')[0]} rule"
        if r["limit"] is not None:
            lines.append(f"  {r['effect']:<18} {r['parameter']} >= {r['limit']:.3g} {r['unit']}"
                         + (f"  ({shape})" if shape else ""))
        else:
            lines.append(f"  {r['effect']:<18} not detectable with this protocol -- would need: {r['protocol']}")
    return "\n".join(lines)
