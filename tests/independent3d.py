"""An independent implementation of the 3-D base model (DESIGN.md §8), for tests only.

Written from the formulas, sharing no code with :mod:`hbm.model.energy3d`:
* W(F) directly from F (|F·n| per segment, I1 = |F|²), the cone's azimuthal average by adaptive
  ``scipy.integrate.quad`` between slack boundaries found by brute force (sign changes on a fine grid,
  refined by ``brentq``);
* stresses by 5-point central differences of W with respect to F (Kirchhoff τ_ii = ∂W/∂ln F_ii for a
  diagonal F, P_XY = ∂W/∂F_XY in simple shear), the incompressibility constraint by a Lagrange pressure
  (σ = ∂W/∂F·Fᵀ − p·I with p from the free face);
* traction-free lateral faces by ``brentq`` on the free stretch.
"""

from __future__ import annotations

import math

import numpy as np
from scipy.integrate import quad
from scipy.optimize import brentq

CALVO = dict(VOLF=0.9, EOPT=0.18, P1=0.13, T1=1.5, T2=9.3, THETA=60.0, GF=0.012, GM=0.009)
HAWKINS = dict(VOLF=0.97, EOPT=0.192, P1=0.005, T1=0.127, T2=162.0, THETA=59.8, GF=0.006, GM=0.006)
BOX = dict(VOLF=(0.5, 0.99), EOPT=(0.0, 0.2), P1=(1e-4, 0.5), T1=(0.0, 20.0), T2=(1.0, 200.0),
           THETA=(55.0, 60.0), GF=(1e-4, 0.1), GM=(1e-4, 0.1))


def random_box(seed: int) -> dict:
    rng = np.random.default_rng(seed)
    return {k: float(rng.uniform(lo, hi)) for k, (lo, hi) in BOX.items()}


def _wc(l, t1, t2):
    """Collagen energy per unit volume at segment stretch l: T1·(e^{T2 x} − 1 − T2 x)/T2, x = ⟨l − 1⟩₊."""
    x = l - 1.0
    if x <= 0:
        return 0.0
    z = t2 * x
    if z < 1e-4:
        return t1 * x * z * (0.5 + z / 6.0 + z * z / 24.0)
    return t1 * (math.expm1(z) - z) / t2


def _segment(theta):
    th = math.radians(theta)
    return lambda phi: np.array([math.cos(th), math.sin(th) * math.cos(phi), math.sin(th) * math.sin(phi)])


def cone_energy(F, t1, t2, theta):
    n = _segment(theta)
    C = F.T @ F
    excess = lambda phi: n(phi) @ C @ n(phi) - 1.0          # noqa: E731
    grid = np.linspace(0.0, 2 * np.pi, 4097)
    th = math.radians(theta)
    ns = np.stack([np.full_like(grid, math.cos(th)), math.sin(th) * np.cos(grid), math.sin(th) * np.sin(grid)])
    vals = np.einsum("ip,ij,jp->p", ns, C, ns) - 1.0
    cuts = [0.0]
    for i in np.flatnonzero((vals[:-1] > 0) != (vals[1:] > 0)):
        a, b = grid[i], grid[i + 1]
        fa, fb = excess(a), excess(b)
        if fa * fb < 0:
            cuts.append(brentq(excess, a, b, xtol=1e-15, rtol=4 * np.finfo(float).eps))
        else:   # a root on the grid itself (the grid and the scalar evaluation round differently)
            cuts.append(a if abs(fa) <= abs(fb) else b)
    cuts.append(2 * np.pi)
    f = lambda phi: _wc(math.sqrt(max(1.0 + excess(phi), 0.0)), t1, t2)   # noqa: E731
    total = sum(quad(f, a, b, epsabs=1e-17, epsrel=1e-12, limit=200)[0]
                for a, b in zip(cuts[:-1], cuts[1:]) if excess(0.5 * (a + b)) > 0)   # the sign holds between cuts
    return total / (2 * np.pi)


def gst_energy(F, t1, t2, theta):
    c2 = math.cos(math.radians(theta)) ** 2
    H = np.diag([c2, (1 - c2) / 2, (1 - c2) / 2])
    return _wc(math.sqrt(np.sum(H * (F.T @ F))), t1, t2)


def energy(F, prm: dict, reading: str, k_iso: float = 1.0) -> float:
    c = prm["VOLF"]
    mu = k_iso * (c * prm["GF"] + (1 - c) * prm["GM"])
    lf = np.linalg.norm(F[:, 0])
    fib = max(lf - 1.0 - prm["EOPT"], 0.0)
    coll = (cone_energy if reading == "cone" else gst_energy)(F, prm["T1"], prm["T2"], prm["THETA"])
    return mu / 2 * (np.sum(F * F) - 3.0) + c * prm["P1"] / 2 * fib * fib + (1 - c) * coll


def _d5(f, x, h):
    """5-point central difference f'(x)."""
    return (-f(x + 2 * h) + 8 * f(x + h) - 8 * f(x - h) + f(x - 2 * h)) / (12 * h)


def principal_tau(logs, prm, reading, h=1e-4, axes=(0, 1, 2)):
    """τ_ii = F_ii·∂W/∂F_ii = ∂W/∂ln F_ii at F = diag(exp(logs)) (W unconstrained: the pressure is separate);
    NaN for the axes not asked for."""
    out = []
    for i in range(3):
        if i not in axes:
            out.append(np.nan)
            continue
        def w(x, i=i):
            e = np.array(logs, dtype=float)
            e[i] = x
            return energy(np.diag(np.exp(e)), prm, reading)
        out.append(_d5(w, logs[i], h))
    return np.array(out)


def shear_stress(gamma, X, Y, prm, reading, h=1e-4):
    """σ_XY = (∂W/∂F·Fᵀ)_XY = ∂W/∂F_XY at F = I + γ e_X⊗e_Y (F_Ya = δ_Ya; the pressure drops out)."""
    def w(g):
        F = np.eye(3)
        F[X, Y] = g
        return energy(F, prm, reading)
    return _d5(w, gamma, h)


def _free_root(g, x0):
    """The root of g near x0 by brentq after widening a bracket."""
    a, b, step = x0 - 0.05, x0 + 0.05, 0.05
    while g(a) * g(b) > 0:
        step *= 2
        a, b = x0 - step, x0 + step
        if step > 4:
            raise RuntimeError("no bracket")
    return brentq(g, a, b, xtol=1e-14, rtol=4 * np.finfo(float).eps)


AX = {"f": 0, "c": 1, "n": 2}
PRESCRIBED = {   # mode -> (log-stretches from (e1, e2), free axis, {observable: axis})
    "planar_f_hold_c": (lambda a, b: (a, 0.0, -a), "n", {"stress": "f", "stress_2": "c"}),
    "planar_c_hold_f": (lambda a, b: (0.0, a, -a), "n", {"stress": "c", "stress_2": "f"}),
    "planar_c_hold_n": (lambda a, b: (-a, a, 0.0), "f", {"stress": "c", "stress_2": "n"}),
    "biaxial_fc": (lambda a, b: (a, b, -a - b), "n", {"stress": "f", "stress_2": "c"}),
    "biaxial_cn": (lambda a, b: (-a - b, a, b), "f", {"stress": "c", "stress_2": "n"}),
}
SHEAR = {"shear_fc": (0, 1), "shear_cf": (1, 0), "shear_cn": (1, 2)}


def predict(mode, strain, prm, reading, strain_2=None) -> dict:
    """Every observable of ``mode`` at one strain (floats)."""
    if mode in SHEAR:
        return {"stress": shear_stress(strain, *SHEAR[mode], prm, reading)}
    a = math.log1p(strain)
    b = a if strain_2 is None else math.log1p(strain_2)
    if mode in PRESCRIBED:
        logs, free, axes = PRESCRIBED[mode]
        tau = principal_tau(logs(a, b), prm, reading)
        return {k: tau[AX[ax]] - tau[AX[free]] for k, ax in axes.items()}
    if mode == "uniaxial_f":    # unknown ln λc, λn = 1/(λ·λc): τ_cc = τ_nn
        g = lambda x: np.subtract(*principal_tau((a, x, -a - x), prm, reading, axes=(1, 2))[1:])   # noqa: E731
        x = _free_root(g, -a / 2)
        tau = principal_tau((a, x, -a - x), prm, reading)
        return {"stress": tau[0] - tau[1], "strain_c": math.expm1(x), "strain_n": math.expm1(-a - x)}
    if mode == "uniaxial_c":    # unknown ln λf, λn = 1/(λ·λf): τ_ff = τ_nn
        g = lambda x: (lambda t: t[0] - t[2])(principal_tau((x, a, -a - x), prm, reading, axes=(0, 2)))  # noqa: E731
        x = _free_root(g, -a / 2)
        tau = principal_tau((x, a, -a - x), prm, reading)
        return {"stress": tau[1] - tau[0], "strain_f": math.expm1(x), "strain_n": math.expm1(-a - x)}
    raise KeyError(mode)


#: the synthetic specimen of issue 35's check: along-fibre tension, cross-fibre tension, shear along the fibres
SYNTHETIC_TESTS = (("uniaxial_f", np.linspace(0.02, 0.30, 10)), ("uniaxial_c", np.linspace(0.02, 0.20, 10)),
                   ("shear_fc", np.linspace(0.02, 0.30, 10)))


def synthetic_csv(path, seed: int, prm: dict = CALVO, reading: str = "cone", noise: float = 0.02,
                  tests=SYNTHETIC_TESTS) -> dict:
    """Write a specimen CSV of ``tests`` generated by this implementation with iid Gaussian noise of sd
    ``noise``·max|series| per (test, observable); returns the noise sd per test (MPa)."""
    rng = np.random.default_rng(seed)
    lines = [f"# id: synthetic_modes_{seed}", "# provenance: synthetic (tests/independent3d.py)",
             "strain,stress,test,mode"]
    sds = {}
    for k, (mode, strains) in enumerate(tests):
        clean = np.array([predict(mode, float(e), prm, reading)["stress"] for e in strains])
        sds[mode] = noise * float(np.max(np.abs(clean)))
        noisy = clean + sds[mode] * rng.standard_normal(clean.size)
        lines += [f"{e!r},{s!r},{k},{mode}" for e, s in zip(strains.tolist(), noisy.tolist())]
    with open(path, "w") as fh:
        fh.write("\n".join(lines) + "\n")
    return sds
