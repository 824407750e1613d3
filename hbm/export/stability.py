"""Drucker stability of the energy form in uniaxial, equibiaxial and planar modes.

The 3-D energy of the base's energy form (incompressible, fibres along x), read from its export map
(:meth:`hbm.model.spec.ExportMap.energy`; the Spyrou base evaluates it by
:class:`hbm.model.energy3d.Energy3D` with the collagen's cone reading, DESIGN.md §8)::

    W = k_iso·G/2·(I1 − 3) + c·P1/2·⟨λf − 1 − EOPT⟩₊² + (1 − c)·⟨W_c(λH(φ))⟩_φ

with λf the fibre stretch and the helical collagen averaged exactly over its azimuth φ around the
fibre (λH(φ)² = cos²θ·λ1² + sin²θ·(cos²φ·λ2² + sin²φ·λ3²); in uniaxial tension every azimuth has
the λH of hbm's uniaxial formula).  Each mode is a one-parameter, volume-preserving path with the
fibre direction loaded::

    uniaxial     F = diag(λ, λ^−1/2, λ^−1/2)
    equibiaxial  F = diag(λ, λ, λ^−2)
    planar       F = diag(λ, 1, 1/λ)

Along a path the work-conjugate force is dw/dλ (w(λ) = W(F(λ))); Drucker's condition
dP·dλ > 0 is d²w/dλ² > 0.  It is checked by central differences on a grid over 1.5x the tested
strain range (λ = 1 excluded from the compressive side only when the data had none).
"""

from __future__ import annotations

from dataclasses import dataclass, asdict

import numpy as np

from ..errors import HbmError
from ..model.spec import ModelSpec, base_spec, spec_of
from .source import base_names, median_draw, parse_model_name

MODES = ("uniaxial", "equibiaxial", "planar")
#: strain grid points per mode
N_GRID = 241
#: relative tolerance on d²w/dλ² (finite-difference noise)
TOL = 1e-9


def _stretches(mode: str, lam: np.ndarray):
    one = np.ones_like(lam)
    if mode == "uniaxial":
        return lam, lam ** -0.5, lam ** -0.5
    if mode == "equibiaxial":
        return lam, lam, lam ** -2.0
    if mode == "planar":
        return lam, one, 1.0 / lam
    raise ValueError(mode)


def energy(theta: np.ndarray, k_iso: float, l1, l2, l3, spec: ModelSpec | None = None) -> np.ndarray:
    """W (MPa) of parameter sets ``theta`` (n, base parameters) at principal stretches (m,) -> (n, m): the
    base's energy through its export map (:meth:`hbm.model.spec.ExportMap.energy`)."""
    spec = spec or base_spec()
    t = np.atleast_2d(np.asarray(theta, float))
    return spec.export.energy({n: t[:, i:i + 1] for i, n in enumerate(base_names(spec))}, k_iso, l1, l2, l3)


@dataclass
class Stability:
    """Drucker check of one parameter set or a population."""

    strain_range: tuple[float, float]
    n_draws: int
    unstable_fraction: dict       # mode -> fraction of draws unstable somewhere on the range
    first_unstable_strain: dict   # mode -> smallest |strain| where some draw is unstable (None if none)
    median_stable: bool

    def as_dict(self) -> dict:
        return asdict(self)

    def line(self) -> str:
        """One line for ``hbm fit``."""
        fr = ", ".join(f"{m} {100 * f:.1f} %" for m, f in self.unstable_fraction.items())
        where = [f"{m} from strain {s:.3g}" for m, s in self.first_unstable_strain.items() if s is not None]
        lo, hi = self.strain_range
        return (f"stability (Drucker, energy form, strain {1.5 * lo:.3g}..{1.5 * hi:.3g} = 1.5x tested): "
                f"median {'stable' if self.median_stable else 'UNSTABLE'}; unstable draws: {fr}"
                + (f" ({'; '.join(where)})" if where else "") + f" of {self.n_draws}")


def unstable(theta, k_iso: float, strain_range, spec: ModelSpec | None = None) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """mode -> (bool (n,) unstable somewhere, strain grid interior points (m,), bool (n, m) where)."""
    lo, hi = strain_range
    eps = np.linspace(1.5 * lo, 1.5 * hi, N_GRID)
    lam = 1.0 + eps
    h = 1e-4
    out = {}
    for mode in MODES:
        ws = [energy(theta, k_iso, *_stretches(mode, lam + d), spec=spec) for d in (-h, 0.0, h)]
        d2 = (ws[0] - 2 * ws[1] + ws[2]) / h ** 2
        scale = np.max(np.abs(d2), axis=1, keepdims=True) + 1e-300
        bad = d2 <= -TOL * scale - 1e-12
        bad &= np.abs(eps) > 2 * h  # λ = 1 itself: d²w = 3G-like, kept out of the noise
        out[mode] = (bad.any(axis=1), eps, bad)
    return out


def check(draws, theta, k_iso: float, strain_range, spec: ModelSpec | None = None) -> Stability:
    """Drucker check of ``theta`` (the summary) and of every row of ``draws`` (columns: the base's parameters)."""
    res = unstable(draws, k_iso, strain_range, spec)
    med = unstable(theta, k_iso, strain_range, spec)
    frac, first = {}, {}
    for mode, (any_bad, eps, bad) in res.items():
        frac[mode] = float(any_bad.mean())
        cols = bad.any(axis=0)
        first[mode] = float(eps[cols][np.argmin(np.abs(eps[cols]))]) if cols.any() else None
    return Stability(strain_range=tuple(map(float, strain_range)), n_draws=int(np.atleast_2d(draws).shape[0]),
                     unstable_fraction=frac, first_unstable_strain=first,
                     median_stable=not any(v[0][0] for v in med.values()))


def fit_line(result, max_draws: int = 500) -> str:
    """The one stability line ``hbm fit`` prints for a :class:`hbm.io.SpecimenResult`."""
    try:
        form, k_iso = parse_model_name(result.model)
    except HbmError:
        return "stability: not checked (not the base Spyrou model)"
    if form != "energy":
        return "stability: not checked (the thesis form is not derived from a strain energy; fit --form energy)"
    spec = spec_of(result)
    if spec.export is None:
        return f"stability: not checked (the base model {spec.name!r} declares no export map)"
    cols = result.as_dict()
    draws = np.column_stack([cols[n] for n in base_names(spec)])
    take = np.linspace(0, draws.shape[0] - 1, min(max_draws, draws.shape[0])).round().astype(int)
    lo, hi = min(0.0, float(np.min(result.data.strain))), float(np.max(result.data.strain))
    theta = draws[median_draw(draws, form, k_iso, (lo, hi), spec)]
    return check(draws[take], theta, k_iso, (lo, hi), spec).line()
