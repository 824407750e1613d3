"""What a verdict can and cannot tell: the caveats that decide how to read it.

A verdict ("adequate", "effect", ...) is a statement about *these* data under *this* noise model
and prior box.  The caveats say which of those conditions matter here, each checked on the
diagnosis itself (nothing is claimed that was not computed):

* few points for the free parameters;
* a curve marked (or detected) as digitised or a group mean: its correlated residuals are model
  error, not instrument noise (:func:`digitised_reason`), so AR(1) noise is not offered unless
  the user chooses so (``correlated="noise"``);
* a correlated (AR(1)) noise model that absorbed a smooth misfit: the misfit's shape and size,
  and what the verdict would be under white noise (:func:`white_noise_view`);
* base parts the data do not need (the removal test) and what that means physically;
* base parameters pinned by the prior box.
"""

from __future__ import annotations

import numpy as np

from .fitting import laplace_occam
from .noise_check import misfit_windows, smoothed_residual
from .results import CandidateResult, FitSummary
from .rules import CONTROL_ALONE_MIN, FEW_POINTS, WINDOW_ALPHA

__all__ = ["digitised_reason", "residual_shape", "white_noise_view", "verdict_caveats", "REMOVAL_MEANING",
           "CORRELATED_CHOICES"]

#: ``correlated=`` choices of diagnose/extend: "auto" (model error on digitised/group-mean
#: curves, a noise model otherwise), "noise" (AR(1) offered always), "misfit" (never)
CORRELATED_CHOICES = ("auto", "noise", "misfit")

#: what it means physically that the data do not need a base part (removal test)
REMOVAL_MEANING = {
    "fibers": "these data cannot tell the fibre/ECM load sharing (the fibre parameters P1, EOPT are the prior)",
    "collagen": "these data do not resolve the collagen (ECM) stiffening (T1, T2, THETA are the prior)",
    "matrix": "these data do not resolve the neo-Hookean matrix (GF, GM are the prior)",
}

_YES = ("yes", "true", "1", "y")


def digitised_reason(attrs: dict, model_free: dict, stress: np.ndarray) -> str | None:
    """Why the curve counts as digitised or a group mean (None: it does not).

    From the metadata (``# digitised: yes``, ``# kind: group mean``, or those words in the
    ``provenance``/``source`` lines), or detected: the model-free noise estimate is below
    1e-4 of the stress range -- no instrument noise at the scale of neighbouring points.
    """
    a = {str(k).lower(): str(v) for k, v in (attrs or {}).items()}
    for key in ("digitised", "digitized"):
        if a.get(key, "").strip().lower() in _YES:
            return f"metadata '{key}: {a[key]}'"
    if "mean" in a.get("kind", "").lower():
        return f"metadata 'kind: {a['kind']}'"
    for key in ("provenance", "source"):
        text = a.get(key, "").lower()
        for word in ("group mean", "digitis", "digitiz"):
            if word in text:
                return f"metadata '{key}' says {word.rstrip('sz') + 'sed' if word.startswith('digit') else word}"
    sig = model_free.get("sigma", np.nan)
    span = float(np.ptp(np.asarray(stress, float)))
    if np.isfinite(sig) and span > 0 and sig < 1e-4 * span:
        return f"no noise at the model-free scale (sigma {sig:.2g} < 1e-4 of the stress range)"
    return None


def residual_shape(z: np.ndarray, resid: np.ndarray, segment: np.ndarray, peak: float) -> dict:
    """The smooth shape of a residual: the extremes of its smoothed standardised residual
    between sign changes, in data order, and its largest size in MPa and % of the peak stress.

    Returns ``{"extremes": [z...], "text": "+1.0 → −1.1 → +0.5 sd", "max_mpa", "max_percent"}``.
    """
    z = np.asarray(z, float)
    width = max(3, z.size // 6)
    zs = smoothed_residual(z, segment, width)
    rs = smoothed_residual(np.asarray(resid, float), segment, width)
    ext, cur = [], None
    for v in zs:
        s = np.sign(v)
        if cur is None or s != np.sign(cur):
            if cur is not None:
                ext.append(cur)
            cur = v
        elif abs(v) > abs(cur):
            cur = v
    if cur is not None:
        ext.append(cur)
    ext = [float(e) for e in ext if abs(e) >= 0.3][:6]
    mx = float(np.max(np.abs(rs))) if rs.size else 0.0
    text = " → ".join(f"{e:+.1f}" for e in ext) + " sd" if ext else "no smooth residual above 0.3 sd"
    return {"extremes": ext, "text": text, "max_mpa": mx,
            "max_percent": float(100 * mx / peak) if peak > 0 else float("nan")}


def white_noise_view(base: FitSummary, controls: list[CandidateResult], d, seed: int) -> dict | None:
    """What the diagnosis would say under white noise, from the fits it already has.

    The base model's white-noise (iid) optimum: its misfit windows (family-wise
    ``WINDOW_ALPHA``, ρ = 0) and the best refitted control's Laplace gain at white noise against
    it.  ``None`` when the base has no white-noise fit.
    """
    ent = base.noise_fits.get("iid")
    if ent is None:
        return None
    lik, x = ent["lik"], np.asarray(ent["x"], float)
    pred = np.asarray(lik.predict(x[None, :]))[0]
    sd = np.asarray(lik.noise_sd(x[None, :]))[0]
    resid = d.stress - pred
    windows, _ = misfit_windows(resid / sd, d.strain, d.segment, 0.0, alpha=WINDOW_ALPHA, seed=seed, test=d.test)
    best, gain = None, -np.inf
    for c in controls:
        w = c.fit.noise_fits.get("iid") if c.refit and c.fit is not None else None
        if w is None:
            continue
        new = [n for n in w["lik"].names if n not in lik.names]
        g = float(w["max_log_likelihood"] - ent["max_log_likelihood"]
                  + laplace_occam(w["lik"], w["x"], w["lik"].names, new))
        if g > gain:
            best, gain = c.effect, g
    # the decision rule's signs (decision.misfit_signs): a window, or a shape gaining enough alone
    counts = bool(windows) or gain > CONTROL_ALONE_MIN
    return {"windows": len(windows), "best_control": best, "control_gain": gain if best else None,
            "verdict": "unexplained" if counts else "adequate",
            "rmse": float(np.sqrt(np.mean(resid ** 2))), "z": resid / sd, "resid": resid}


def verdict_caveats(*, n_points: int, base: FitSummary, check_noise: dict, z: np.ndarray, resid: np.ndarray,
                    d, white: dict | None, digitised: str | None, correlated: str, ar1_rejected: str | None,
                    removal: list[dict], at_bounds: list[dict], verdict: str) -> list[dict]:
    """The caveats of one diagnosis (module docstring), each ``{"kind", "text"}``, most decisive first."""
    out = []
    k = len(base.names)
    if n_points < max(FEW_POINTS, 3 * k):
        out.append({"kind": "few_points",
                    "text": f"only {n_points} points for {k} free parameters (model + noise): the misfit windows "
                            "and the evidence have little power, so a misfit these points cannot show may remain"})
    if digitised is not None:
        how = ("treated as model error, not noise (AR(1) noise not offered; --correlated noise to offer it)"
               if correlated != "noise" else "treated as noise (--correlated noise), although such a curve "
               "has no instrument noise to speak of")
        out.append({"kind": "digitised",
                    "text": f"digitised or group-mean curve ({digitised}): correlated residuals are {how}"})
    if ar1_rejected:
        out.append({"kind": "ar1_rejected", "text": f"AR(1) noise rejected ({ar1_rejected}): diagnosed with white noise"})
    rho = float(check_noise.get("rho", 0.0) or 0.0)
    if base.noise == "ar1" and white is not None and white["verdict"] != "adequate" and rho > 0.2:
        shape = residual_shape(white["z"], white["resid"], d.segment, float(np.max(np.abs(d.stress))))
        pref = base.noise_evidence.get("ar1", np.nan) - base.noise_evidence.get("iid", np.nan)
        ctl = (f", best generic shape {white['best_control']} {white['control_gain']:+.1f} nats (Laplace)"
               if white["best_control"] else "")
        would = "the same" if white["verdict"] == verdict else white["verdict"]
        out.append({"kind": "ar1_absorbed",
                    "text": f"the AR(1) noise (rho {rho:.2f}, preferred to white noise by {pref:.1f} nats) absorbs a "
                            f"smooth residual {shape['text']} (largest {shape['max_mpa']:.3g} MPa, "
                            f"{shape['max_percent']:.1f} % of the peak stress); under white noise: "
                            f"{white['windows']} significant misfit window(s){ctl} -> verdict {would}",
                    "shape": {kk: v for kk, v in shape.items()}, "white_noise_verdict": white["verdict"]})
    for r in removal:
        if not r.get("needed", True):
            meaning = REMOVAL_MEANING.get(r["part"], f"the {r['part']} parameters are the prior")
            out.append({"kind": "part_not_needed",
                        "text": f"the {r['part']} part is not needed (removing it: Δlog Z {r['delta_log_evidence']:+.1f}): "
                                f"{meaning}"})
    pinned = sorted({f"{e['parameter']} ({e['side']})" for e in at_bounds if e.get("map_at_edge")})
    if pinned:
        out.append({"kind": "prior_box",
                    "text": f"best fit on the prior box edge: {', '.join(pinned)} -- pinned by the box, not the data; "
                            "the verdict is conditional on that box"})
    return out


def caveat_line(caveats: list[dict]) -> str:
    """The caveats as one clause for the verdict line ("" without any)."""
    if not caveats:
        return ""
    return " | caveats: " + "; ".join(f"({i + 1}) {c['text']}" for i, c in enumerate(caveats))
