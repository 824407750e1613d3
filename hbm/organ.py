"""Organ-scale prediction: force–elongation of a fusiform muscle from constitutive parameters.

A reduced-order *slender-body* model replaces the axisymmetric finite-element model of the
thesis (§3.3.2, Figs. 3.64–3.66).  The muscle belly of reference length ``L`` has a circular
cross-section of reference radius ``R(z)``, ``0 ≤ z ≤ L``, and carries tendons in series at
both ends.  Under an axial force ``F`` (N) every cross-section carries the same force, and the
fibers, which run along the axis, are in uniaxial tension.  With incompressibility the current
area of the section is ``A0(z)/λ(z)``, so equilibrium of each section reads::

    F = σ(λ(z)) · A0(z) / λ(z)   ⇔   P(λ(z)) = σ(λ(z)) / λ(z) = F / A0(z)

where σ is the uniaxial Cauchy stress of the constitutive model (MPa = N/mm²) and P the
nominal (first Piola) stress.  ``λ(z)`` follows from a bracketed, vectorised root find of
this scalar equation for every posterior sample, section and force level at once.  The
organ elongation is::

    δ(F) = ∫₀ᴸ (λ(z) − 1) dz  +  (L_prox + L_dist) · ε_t(F / A_t)

(composite Simpson or trapezoid rule on the section grid) where ε_t is the tendon strain law
(linear ``ε_t = F/(E_t·A_t)`` or a documented toe + linear law, see :class:`FusiformGeometry`).

Units: lengths in mm, areas in mm², forces in N, stresses and moduli in MPa (= N/mm²).

Assumptions and where they break
--------------------------------
* **Slender body, uniaxial stress in every section.**  The radius varies slowly compared with
  the length (|dR/dz| ≪ 1); shear and lateral tractions between neighbouring sections are
  neglected, so each section is in the same uniaxial state as the tested specimen.  This
  breaks near strongly tapered ends (|dR/dz| of order 1, e.g. a short belly with a large
  mid-belly radius) and wherever the stress state is three-dimensional (attachments, grips).
  For the sine profile max |dR/dz| = π(R_mid − R_end)/L; keep it well below 1.
* **Fibers parallel to the axis**; no pennation, no aponeuroses, no fiber curvature.  A
  pennate muscle (e.g. a real rat tibialis anterior) is only approximated by its fusiform
  "equivalent".
* **Incompressible** tissue (the current area is A0/λ), as in the constitutive model.
* **Quasi-static, passive**: no active force; only the *elastic* stage of the model is used
  (see below); no inertia, no rate dependence.
* **The constitutive model's uniaxial curve per section**: the tissue tested on the specimen
  is assumed to represent every section.  Beyond the strains tested on the specimen the curve
  is an extrapolation (:func:`extrapolation_mask`; thesis Fig. 3.64).
* **Tendons in series**, uniform, small-strain (nominal tendon stress F/A_t).
* **Tension only** (F ≥ 0); compression would buckle a slender body.

Only the effects of stage ``"elastic"`` enter the tissue law: kinematics effects (slack,
series compliance of the test rig) and output effects (load-cell offset) describe the test,
not the tissue, and history effects (viscoelasticity, damage) are dropped by the quasi-static
assumption.  Excluded effects are listed in :attr:`OrganResponse.excluded_effects`.

Solver: per sample a table of P on a stretch grid (monotonicity check), then anchor stresses
(log-spaced, common to all samples) solved by bracketed Anderson–Björck regula falsi, then
every (sample, section, force) unknown from a cubic Hermite guess in ln s between two anchors,
one vectorised evaluation, and bracketed polishing of the few that are not yet within ``tol``.
No Python loop runs over samples or sections (only over iterations and memory chunks).

A unique stretch needs a nominal stress P(λ) that increases with λ.  The solver checks P on a
stretch grid for every sample (:attr:`OrganResponse.non_monotone`) and marks force levels that
need a stretch above ``max_stretch`` somewhere in the belly (:attr:`OrganResponse.unreachable`,
elongation NaN), or raises :class:`~hbm.errors.HbmError` with ``strict=True``.
"""

from __future__ import annotations

import dataclasses
import math
import time as _time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Mapping, Sequence

import numpy as np

from .errors import HbmError
from .model.core import Loading, Model, State

__all__ = ["FusiformGeometry", "OrganResponse", "load_geometry", "organ_response", "force_levels",
           "extrapolation_mask", "nominal_stress", "tendon_strain", "theta_from_samples", "PROFILES",
           "TENDON_LAWS"]

_EPS = float(np.finfo(float).eps)
PROFILES = ("sine", "parabolic", "linear", "uniform")
TENDON_LAWS = ("linear", "toe_linear")


# ---------------------------------------------------------------------------------------------
# geometry
# ---------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class FusiformGeometry:
    """Reference geometry of a fusiform muscle–tendon unit.

    The belly radius is symmetric about mid-belly.  With ξ = 2z/L − 1 ∈ [−1, 1] and
    ΔR = R_mid − R_end the profiles are::

        "sine"       R(z) = R_end + ΔR · sin(π z / L)^p          (p = ``exponent``)
        "parabolic"  R(z) = R_end + ΔR · (1 − ξ²)
        "linear"     R(z) = R_end + ΔR · (1 − |ξ|)               (double cone)
        "uniform"    R(z) = R_mid                                 (cylinder)

    and A0(z) = π R(z)².  ``p = 1`` gives a smooth spindle; larger ``p`` a thinner waist
    towards the ends.

    Tendon laws (ε_t tendon strain, S = F/A_t nominal tendon stress, E = ``tendon_modulus``)::

        "linear"      ε_t = S / E
        "toe_linear"  S = E·ε²/(2·ε_toe)  for ε ≤ ε_toe  (quadratic toe, slope continuous),
                      S = E·(ε − ε_toe/2) for ε > ε_toe   (linear region)
                      ⇒ ε_t = sqrt(2·ε_toe·S/E) if S ≤ E·ε_toe/2, else S/E + ε_toe/2

    Parameters
    ----------
    length : float
        Reference belly length L (mm).
    radius_mid : float
        Mid-belly radius R_mid (mm).
    radius_end : float
        Radius at both ends of the belly R_end (mm).
    profile : {"sine", "parabolic", "linear", "uniform"}
        Radius profile (formulas above).
    exponent : float
        Exponent p of the sine profile (ignored otherwise).
    tendon_length_proximal, tendon_length_distal : float
        Free tendon lengths (mm); 0 for no tendon.
    tendon_area : float
        Tendon cross-section area A_t (mm²).
    tendon_modulus : float
        Tendon Young's modulus E_t (MPa); ``inf`` for rigid tendons.
    tendon_law : {"linear", "toe_linear"}
        Tendon strain law (formulas above).
    tendon_toe_strain : float
        ε_toe of the toe + linear law.
    n_sections : int
        Number of belly intervals of the quadrature grid (n_sections + 1 nodes).
    name, source : str
        Label and provenance text for reports.
    """

    length: float
    radius_mid: float
    radius_end: float
    profile: str = "sine"
    exponent: float = 1.0
    tendon_length_proximal: float = 0.0
    tendon_length_distal: float = 0.0
    tendon_area: float = 1.0
    tendon_modulus: float = math.inf
    tendon_law: str = "linear"
    tendon_toe_strain: float = 0.02
    n_sections: int = 64
    name: str = "fusiform"
    source: str = ""

    def __post_init__(self) -> None:
        for key in ("length", "radius_mid", "radius_end", "exponent", "tendon_area", "tendon_modulus",
                    "tendon_toe_strain"):
            v = getattr(self, key)
            if not isinstance(v, (int, float)) or isinstance(v, bool) or not v > 0 or math.isnan(v):
                raise HbmError(f"geometry {self.name!r}: {key} must be a positive number, got {v!r}")
            if key != "tendon_modulus" and not math.isfinite(v):
                raise HbmError(f"geometry {self.name!r}: {key} must be finite, got {v!r}")
        for key in ("tendon_length_proximal", "tendon_length_distal"):
            v = getattr(self, key)
            if not isinstance(v, (int, float)) or isinstance(v, bool) or not (v >= 0 and math.isfinite(v)):
                raise HbmError(f"geometry {self.name!r}: {key} must be a finite number >= 0 (mm), got {v!r}")
        if self.profile not in PROFILES:
            raise HbmError(f"geometry {self.name!r}: profile must be one of {PROFILES}, got {self.profile!r}")
        if self.tendon_law not in TENDON_LAWS:
            raise HbmError(f"geometry {self.name!r}: tendon_law must be one of {TENDON_LAWS}, "
                           f"got {self.tendon_law!r}")
        if not isinstance(self.n_sections, int) or isinstance(self.n_sections, bool) or self.n_sections < 2:
            raise HbmError(f"geometry {self.name!r}: n_sections must be an integer >= 2, got {self.n_sections!r}")

    # -- constructors -------------------------------------------------------------------------
    @classmethod
    def uniform_cylinder(cls, length: float, radius: float, *, tendon_length: float = 0.0,
                         tendon_area: float = 1.0, tendon_modulus: float = math.inf,
                         n_sections: int = 2, **kw) -> "FusiformGeometry":
        """A cylinder of uniform radius (optionally with tendons split equally at both ends).

        Parameters
        ----------
        length, radius : float
            Belly length and radius (mm).
        tendon_length : float
            Total free tendon length (mm), split equally between the two ends.
        tendon_area, tendon_modulus : float
            Tendon cross-section (mm²) and modulus (MPa).
        n_sections : int
            Quadrature intervals (a cylinder is integrated exactly by any rule).
        **kw
            Further :class:`FusiformGeometry` fields (e.g. ``tendon_law``).
        """
        return cls(length=length, radius_mid=radius, radius_end=radius, profile="uniform",
                   tendon_length_proximal=tendon_length / 2, tendon_length_distal=tendon_length / 2,
                   tendon_area=tendon_area, tendon_modulus=tendon_modulus, n_sections=n_sections,
                   **{"name": "cylinder", **kw})

    def replace(self, **changes) -> "FusiformGeometry":
        """A copy with some fields changed (validated again)."""
        return dataclasses.replace(self, **changes)

    # -- profile ------------------------------------------------------------------------------
    def radius(self, z: np.ndarray) -> np.ndarray:
        """Reference radius R(z) (mm) for positions z in [0, L] (mm)."""
        z = np.asarray(z, dtype=float)
        L = self.length
        # Fold onto the proximal half so that R(z) == R(L − z) bit for bit: symmetric sections
        # then share one area and are solved once (see organ_response).
        zf = np.minimum(z, L - z)
        d = self.radius_mid - self.radius_end
        if self.profile == "uniform":
            return np.full_like(zf, self.radius_mid)
        if self.profile == "sine":
            return self.radius_end + d * np.sin(np.pi * zf / L) ** self.exponent
        xi = 1.0 - 2.0 * zf / L  # = |2z/L − 1|
        if self.profile == "parabolic":
            return self.radius_end + d * (1.0 - xi * xi)
        return self.radius_end + d * (1.0 - xi)  # linear double cone

    def area(self, z: np.ndarray) -> np.ndarray:
        """Reference cross-section area A0(z) = π R(z)² (mm²)."""
        r = self.radius(z)
        return np.pi * r * r

    @property
    def nodes(self) -> np.ndarray:
        """Quadrature nodes z_k = k·L/n_sections, k = 0..n_sections (mm)."""
        return np.linspace(0.0, self.length, self.n_sections + 1)

    @property
    def tendon_length(self) -> float:
        """Total free tendon length (mm)."""
        return self.tendon_length_proximal + self.tendon_length_distal

    @property
    def volume(self) -> float:
        """Belly volume ∫ A0 dz (mm³), composite Simpson on the section grid (trapezoid if odd)."""
        return float(quadrature_weights(self.nodes, "simpson" if self.n_sections % 2 == 0 else "trapezoid")
                     @ self.area(self.nodes))

    @property
    def max_slope(self) -> float:
        """max |dR/dz| of the profile: the slender-body assumption wants it ≪ 1."""
        d = abs(self.radius_mid - self.radius_end)
        L = self.length
        if self.profile == "uniform":
            return 0.0
        if self.profile == "parabolic":
            return 4.0 * d / L
        if self.profile == "linear":
            return 2.0 * d / L
        z = np.linspace(0.0, L / 2, 2001)
        return float(np.max(np.abs(np.gradient(self.radius(z), z))))

    def describe(self) -> str:
        """One paragraph for reports."""
        return (f"{self.name}: belly L = {self.length:g} mm, R_mid = {self.radius_mid:g} mm, "
                f"R_end = {self.radius_end:g} mm ({self.profile}"
                + (f", p = {self.exponent:g}" if self.profile == "sine" else "")
                + f"), tendons {self.tendon_length_proximal:g} + {self.tendon_length_distal:g} mm, "
                f"A_t = {self.tendon_area:g} mm², E_t = {self.tendon_modulus:g} MPa ({self.tendon_law}), "
                f"{self.n_sections} sections, max |dR/dz| = {self.max_slope:.3g}")

    def to_dict(self) -> dict:
        """Plain dict of the fields (for JSON attributes of results files)."""
        return dataclasses.asdict(self)


_TOML_LAYOUT: dict[str, dict[str, tuple[str, type]]] = {
    # section -> key -> (dataclass field, expected python type)
    "belly": {
        "length": ("length", float), "radius_mid": ("radius_mid", float),
        "radius_end": ("radius_end", float), "profile": ("profile", str), "exponent": ("exponent", float),
        "n_sections": ("n_sections", int),
    },
    "tendon": {
        "length_proximal": ("tendon_length_proximal", float),
        "length_distal": ("tendon_length_distal", float), "area": ("tendon_area", float),
        "modulus": ("tendon_modulus", float), "law": ("tendon_law", str),
        "toe_strain": ("tendon_toe_strain", float),
    },
}
_REQUIRED = {("belly", "length"), ("belly", "radius_mid"), ("belly", "radius_end")}


def load_geometry(path: str | Path) -> FusiformGeometry:
    """Read a :class:`FusiformGeometry` from a TOML file.

    Layout (lengths mm, areas mm², moduli MPa)::

        name = "rat TA-sized fusiform"      # optional
        source = "..."                      # optional provenance text
        [belly]
        length = 32.0                       # required
        radius_mid = 3.5                    # required
        radius_end = 1.2                    # required
        profile = "sine"                    # sine | parabolic | linear | uniform
        exponent = 1.0                      # sine profile exponent p
        n_sections = 64
        [tendon]                            # optional (default: no tendon)
        length_proximal = 2.0
        length_distal = 12.0
        area = 0.8
        modulus = 1000.0                    # use inf for rigid tendons
        law = "linear"                      # linear | toe_linear
        toe_strain = 0.02

    Raises
    ------
    HbmError
        One line naming the file and key for a missing file, invalid TOML, unknown, missing,
        ill-typed, negative or zero values.
    """
    try:
        import tomllib
    except ModuleNotFoundError:  # pragma: no cover - Python 3.10
        try:
            import tomli as tomllib  # type: ignore[no-redef]
        except ModuleNotFoundError:
            raise HbmError("reading geometry TOML files needs Python >= 3.11 (tomllib) or the tomli package")
    path = Path(path)
    try:
        with open(path, "rb") as fh:
            doc = tomllib.load(fh)
    except FileNotFoundError:
        raise HbmError(f"{path}: geometry file not found") from None
    except OSError as exc:
        raise HbmError(f"{path}: cannot read geometry file ({exc.strerror})") from None
    except tomllib.TOMLDecodeError as exc:
        raise HbmError(f"{path}: invalid TOML ({str(exc).splitlines()[0]})") from None

    kw: dict = {}
    for key in ("name", "source"):
        if key in doc:
            if not isinstance(doc[key], str):
                raise HbmError(f"{path}: '{key}' must be a string, got {doc[key]!r}")
            kw[key] = doc[key]
    unknown = set(doc) - {"name", "source", *_TOML_LAYOUT}
    if unknown:
        raise HbmError(f"{path}: unknown top-level key(s) {sorted(unknown)}; expected name, source, "
                       f"[belly], [tendon]")
    for section, layout in _TOML_LAYOUT.items():
        table = doc.get(section, {})
        if not isinstance(table, dict):
            raise HbmError(f"{path}: '{section}' must be a table ([{section}])")
        unknown = set(table) - set(layout)
        if unknown:
            raise HbmError(f"{path}: unknown key(s) {sorted(unknown)} in [{section}]; expected {sorted(layout)}")
        for key, (fname, typ) in layout.items():
            where = f"{path}: [{section}] {key}"
            if key not in table:
                if (section, key) in _REQUIRED:
                    raise HbmError(f"{where} is missing (a positive number in mm is required)")
                continue
            v = table[key]
            if typ is float:
                if isinstance(v, bool) or not isinstance(v, (int, float)):
                    raise HbmError(f"{where} must be a number, got {v!r}")
                v = float(v)
                if math.isnan(v):
                    raise HbmError(f"{where} must be a number, got nan")
                positive_only = key not in ("length_proximal", "length_distal")
                if (positive_only and not v > 0) or v < 0:
                    need = "> 0" if positive_only else ">= 0"
                    raise HbmError(f"{where} must be {need}, got {v!r}")
                if not math.isfinite(v) and key != "modulus":
                    raise HbmError(f"{where} must be finite, got {v!r}")
            elif typ is int:
                if isinstance(v, bool) or not isinstance(v, int) or v < 2:
                    raise HbmError(f"{where} must be an integer >= 2, got {v!r}")
            elif not isinstance(v, str):
                raise HbmError(f"{where} must be a string, got {v!r}")
            kw[fname] = v
    kw.setdefault("name", path.stem)
    try:
        return FusiformGeometry(**kw)
    except HbmError as exc:
        raise HbmError(f"{path}: {exc}") from None


# ---------------------------------------------------------------------------------------------
# tissue and tendon laws
# ---------------------------------------------------------------------------------------------
def tendon_strain(force: np.ndarray, geometry: FusiformGeometry) -> np.ndarray:
    """Tendon strain ε_t for axial force(s) ``force`` (N), closed-form inverse of the tendon law."""
    s = np.asarray(force, dtype=float) / geometry.tendon_area  # nominal tendon stress (MPa)
    E = geometry.tendon_modulus
    if math.isinf(E):
        return np.zeros_like(s)
    if geometry.tendon_law == "linear":
        return s / E
    et = geometry.tendon_toe_strain
    toe = s <= 0.5 * E * et
    return np.where(toe, np.sqrt(2.0 * et * np.maximum(s, 0.0) / E), s / E + 0.5 * et)


def _elastic_effects(model: Model):
    elastic = [e for e in model.effects if e.stage == "elastic"]
    if not elastic:
        raise HbmError(f"model {model.name!r} has no elastic effect: no tissue law for the organ")
    excluded = tuple(e.name for e in model.effects if e.stage != "elastic")
    return elastic, excluded


def _nominal_fn(model: Model) -> tuple[Callable[[np.ndarray, Mapping[str, np.ndarray]], np.ndarray], tuple]:
    """P(λ; p) = σ_elastic(λ)/λ from the model's elastic effects, for any broadcastable shapes."""
    elastic, excluded = _elastic_effects(model)
    # Elastic effects read only the strain; a one-point loading satisfies the State contract.
    loading = Loading(np.zeros(1))

    def P(lam: np.ndarray, p: Mapping[str, np.ndarray]) -> np.ndarray:
        state = State(lam - 1.0, loading)
        total = elastic[0].stress(state, p)
        for e in elastic[1:]:
            total = total + e.stress(state, p)
        return total / lam

    return P, excluded


def nominal_stress(model: Model, theta: np.ndarray, stretch: np.ndarray) -> np.ndarray:
    """Nominal stress P = σ/λ (MPa) of the model's elastic effects.

    Parameters
    ----------
    model : Model
    theta : array (n, n_params)
    stretch : array (n_points,) or (n, n_points)
        Fiber stretch λ.

    Returns
    -------
    ndarray (n, n_points)
    """
    theta = _check_theta(model, theta)
    P, _ = _nominal_fn(model)
    lam = np.asarray(stretch, dtype=float)
    p = {q.name: theta[:, i, None] for i, q in enumerate(model.parameters)}
    return np.broadcast_to(P(lam, p), (theta.shape[0],) + lam.shape[-1:]).copy()


def _check_theta(model: Model, theta) -> np.ndarray:
    theta = np.asarray(theta, dtype=float)
    if theta.ndim == 1:
        theta = theta[None, :]
    if theta.ndim != 2 or theta.shape[1] != model.n_params:
        raise HbmError(f"theta must have shape (n_samples, {model.n_params}) with columns "
                       f"{model.parameter_names}, got {theta.shape}")
    if not np.isfinite(theta).all():
        raise HbmError("theta contains non-finite values")
    return theta


def quadrature_weights(z: np.ndarray, rule: str = "simpson") -> np.ndarray:
    """Weights w with ∫ f dz ≈ w·f(z) on equally spaced nodes z (composite Simpson or trapezoid)."""
    n = z.size - 1
    h = (z[-1] - z[0]) / n
    if rule == "trapezoid":
        w = np.full(n + 1, h)
        w[[0, -1]] = h / 2
        return w
    if rule == "simpson":
        if n % 2:
            raise HbmError(f"Simpson's rule needs an even number of sections, got n_sections = {n}")
        w = np.full(n + 1, 2.0 * h / 3.0)
        w[1::2] = 4.0 * h / 3.0
        w[[0, -1]] = h / 3.0
        return w
    raise HbmError(f"quadrature must be 'simpson' or 'trapezoid', got {rule!r}")


# ---------------------------------------------------------------------------------------------
# the solver
# ---------------------------------------------------------------------------------------------
def _ab_step(P, p, a, b, fa, fb, side, s, tol, x0=None, bisect=False):
    """One Anderson–Björck regula-falsi step on bracket arrays (updated in place).

    Invariant: fa = P(a) − s < 0 <= fb = P(b) − s (up to the Anderson–Björck scaling of the
    function value kept twice).  Returns (x, converged).
    """
    with np.errstate(divide="ignore", invalid="ignore"):
        if bisect:
            x = 0.5 * (a + b)
        else:
            x = b - fb * (b - a) / (fb - fa) if x0 is None else x0.copy()
        bad = ~((x - a) * (x - b) < 0)  # outside (a, b) in either order, or NaN
        np.copyto(x, 0.5 * (a + b), where=bad)  # bisection fallback
        fx = P(x, p) - s
        conv = (np.abs(fx) <= tol * s) | (np.abs(b - a) <= 4.0 * _EPS * np.abs(b))
        up = fx > 0  # the root is left of x: x becomes the upper end
        # Anderson–Björck: when the same end survives twice, scale its function value down
        m_up = 1.0 - fx / fb
        m_dn = 1.0 - fx / fa
    np.copyto(m_up, 0.5, where=~(m_up > 0))
    np.copyto(m_dn, 0.5, where=~(m_dn > 0))
    np.multiply(fa, m_up, out=fa, where=up & (side == 1))
    np.multiply(fb, m_dn, out=fb, where=~up & (side == -1))
    np.copyto(b, x, where=up)
    np.copyto(fb, fx, where=up)
    np.copyto(a, x, where=~up)
    np.copyto(fa, fx, where=~up)
    np.copyto(side, np.where(up, 1, -1).astype(np.int8))
    return x, conv


def _polish_flat(P, theta, names, idx, K, a, b, fa, fb, side, s, out, *, tol, max_iter, n_iter=0,
                 x_first=None):
    """Anderson–Björck iterations on flat unknowns ``idx`` (indices into a (n, K) block).

    a, b, fa, fb, side, s are (N, 1) arrays for the unknowns; converged roots are written to
    ``out`` (the flat (n·K,) result).  Parameters are gathered once and compressed with the
    unknowns.  ``x_first`` (N, 1) replaces the first regula-falsi point (bisection if it lies
    outside the bracket).  Returns the total number of iterations.
    """
    rows = idx // K
    p = {q: theta[rows, i, None] for i, q in enumerate(names)}
    flat = [a, b, fa, fb, side, s]
    first, k = True, 0
    while idx.size and n_iter < max_iter:
        n_iter += 1
        k += 1
        # Every third step after the sixth is a bisection: guarantees the bracket collapses
        # even where rounding noise in P (tiny forces, P ≈ 0) stalls regula falsi.
        x, conv = _ab_step(P, p, *flat, tol, x_first if first else None, bisect=k > 6 and k % 3 == 0)
        first = False
        conv = conv[:, 0]
        out[idx[conv]] = x[conv, 0]
        keep = ~conv
        if not keep.all():
            idx = idx[keep]
            flat = [v[keep] for v in flat]
            p = {q: v[keep] for q, v in p.items()}
    if idx.size:
        raise HbmError(f"organ stretch solver did not converge for {idx.size} (sample, section, force) "
                       f"points in {max_iter} iterations")
    return n_iter


def _polish(P, theta, names, s, a, b, fa, fb, active, lam, *, tol, max_iter):
    """Anderson–Björck iterations on (n, K) bracket arrays; writes converged roots into ``lam``.

    The first iterations run on the whole block (parameters broadcast per row, nothing
    gathered); once fewer than a fifth of the unknowns remain they continue as flat arrays
    (:func:`_polish_flat`).  Returns the number of iterations.
    """
    n, K = lam.shape
    p_rows = {q: theta[:, i, None] for i, q in enumerate(names)}
    side = np.zeros((n, K), dtype=np.int8)
    n_iter = 0
    while n_iter < max_iter and active.any() and active.mean() > 0.2:
        n_iter += 1
        x, conv = _ab_step(P, p_rows, a, b, fa, fb, side, s, tol)
        now = active & conv
        lam[now] = x[now]
        active &= ~conv
    idx = np.flatnonzero(active)
    flat = [v.ravel()[idx][:, None] for v in (a, b, fa, fb, side, s)]
    return _polish_flat(P, theta, names, idx, K, *flat, lam.reshape(-1), tol=tol, max_iter=max_iter,
                        n_iter=n_iter)


def _solve_stretch(P, theta: np.ndarray, names: Sequence[str], targets: np.ndarray, *,
                   max_stretch: float, tol: float, n_grid: int, n_anchors: int, max_iter: int):
    """Solve P(λ; θ_i) = targets[j] for λ in [1, max_stretch] and every sample i, vectorised.

    ``targets`` (K,) are the nominal stresses F/A0 (the same for every sample).  Returns
    (lam (n, K), unreachable (n, K) bool, non_monotone (n,) bool, n_iter).

    Two levels, both bracketed (a root always lies in the bracket, by continuity):

    1. A table of P on ``n_grid`` stretches per sample flags non-monotone samples and brackets
       ``n_anchors`` anchor stresses, log-spaced over the targets and common to all samples;
       the anchors are solved to full accuracy (vectorised binary search + polishing).
    2. Every target lies between two anchors; their stretches (with P recomputed there) are a
       narrow, exact bracket, so the (n, K) polishing needs only a few evaluations and no
       per-element search.
    """
    n = theta.shape[0]
    K = targets.size
    grid = np.linspace(1.0, max_stretch, n_grid)
    p_rows = {q: theta[:, i, None] for i, q in enumerate(names)}
    T = np.broadcast_to(P(grid[None, :], p_rows), (n, n_grid))  # (n, m) table
    with np.errstate(invalid="ignore"):
        dT = np.diff(T, axis=1)
    scale = np.maximum(np.abs(T[:, -1:]), 1e-300)
    non_monotone = (dT < -1e-12 * scale).any(axis=1) | ~np.isfinite(T).all(axis=1)
    # The largest tabulated P bounds the reachable stresses (the last point for a monotone P).
    i_top = np.argmax(np.where(np.isfinite(T), T, -np.inf), axis=1)
    Pmax = T[np.arange(n), i_top][:, None]
    lam_top = grid[i_top][:, None]
    P0 = T[:, :1]

    # -- level 1: anchors --------------------------------------------------------------------
    pos = targets[targets > 0]
    if pos.size == 0:
        anchors = np.empty(0)
    else:
        anchors = np.unique(np.geomspace(pos.min(), pos.max(), n_anchors)) if pos.min() < pos.max() \
            else pos[:1]
    M = anchors.size
    sA = np.broadcast_to(anchors, (n, M))
    lamA = np.full((n, M), np.nan)
    okA = (sA > P0) & (sA <= Pmax)
    lo = np.zeros((n, M), dtype=np.intp)
    hi = np.repeat(i_top[:, None], M, axis=1)
    for _ in range(int(np.ceil(np.log2(n_grid))) + 1):  # bracket T[lo] < s <= T[hi]
        mid = (lo + hi) // 2
        below = np.take_along_axis(T, mid, axis=1) < sA
        np.copyto(lo, mid, where=below)
        np.copyto(hi, mid, where=~below)
    it1 = _polish(P, theta, names, np.where(okA, sA, 1.0), np.where(okA, grid[lo], 1.0),
                  np.where(okA, grid[hi], 1.0),
                  np.where(okA, np.take_along_axis(T, lo, axis=1) - sA, -1.0),
                  np.where(okA, np.take_along_axis(T, hi, axis=1) - sA, 1.0), okA.copy(), lamA,
                  tol=tol, max_iter=max_iter)
    # Augmented anchor table: λ = 1 first, the stretch of the largest tabulated P last (the
    # max_stretch for a monotone P); anchors out of reach take the end values so that every
    # reachable target still has a valid bracket.
    lamA = np.where(okA, lamA, np.where(sA <= P0, 1.0, lam_top))
    lamA = np.concatenate([np.ones((n, 1)), lamA, lam_top], axis=1)
    PA = np.broadcast_to(P(lamA, p_rows), lamA.shape)  # exact P at the bracket ends
    # dP/dλ at the anchors (central differences) for a cubic Hermite first guess of λ(s)
    h = 1e-6 * lamA
    dPA = np.broadcast_to((P(lamA + h, p_rows) - P(np.maximum(lamA - h, 1.0), p_rows))
                          / (lamA + h - np.maximum(lamA - h, 1.0)), lamA.shape)

    # -- level 2: every target between two anchors --------------------------------------------
    # Cubic Hermite coefficients of λ(u), u = ln s, on every anchor interval, with slopes
    # dλ/du = P/P'(λ) (secant slope where unusable: kinks, flat P, P = 0).  In ln s the
    # exponential collagen branch is nearly linear and the small-strain branch smooth, so the
    # interpolant is accurate to about the solver tolerance:  λ ≈ λ_k + t·(c1 + t·(c2 + t·c3)),
    # t = (u − u_k)/(u_{k+1} − u_k).  Computed per (sample, interval), then gathered.
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        UA = np.log(PA)
        du = np.diff(UA, axis=1)  # (n, M+1)
        d = np.diff(lamA, axis=1)
        g = np.where((dPA > 0) & (PA > 0), PA / dPA, np.nan)  # dλ/du at the nodes
        ma = g[:, :-1] * du
        mb = g[:, 1:] * du
        ma = np.where(np.isfinite(ma), ma, d)
        mb = np.where(np.isfinite(mb), mb, d)
        c2 = 3.0 * d - 2.0 * ma - mb
        c3 = ma + mb - 2.0 * d
        inv_du = 1.0 / du
    kb = np.searchsorted(anchors, targets, side="right") + 1  # anchors[kb-2] <= s < anchors[kb-1]
    ka = kb - 1  # interval index (common to all samples); an anchor hit exactly gives t = 0
    s = targets[None, :]
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        t = (np.log(s) - UA[:, ka]) * inv_du[:, ka]
        x0 = lamA[:, ka] + t * (ma[:, ka] + t * (c2[:, ka] + t * c3[:, ka]))
        fx = P(x0, p_rows) - s  # one evaluation on the whole (n, K) block
        conv = np.abs(fx) <= tol * s
    unreachable = (s < P0) | ~(s <= Pmax)  # includes NaN
    exact_rest = s == P0
    active = ~(unreachable | exact_rest)
    lam = np.where(conv & active, x0, np.nan)
    lam[exact_rest] = 1.0
    # the few unconverged unknowns: exact bracket from the anchors, updated with x0 when inside
    idx = np.flatnonzero(active & ~conv)
    rows, cols = np.divmod(idx, K)
    kk = ka[cols]
    a, b = lamA[rows, kk], lamA[rows, kk + 1]
    sf = targets[cols]
    fa, fb = PA[rows, kk] - sf, PA[rows, kk + 1] - sf
    broken = ~((fa < 0) & (fb > 0))  # tolerance-level sign slips or non-monotone samples
    a[broken], b[broken] = 1.0, lam_top[rows[broken], 0]
    fa[broken] = P0[rows[broken], 0] - sf[broken]
    fb[broken] = Pmax[rows[broken], 0] - sf[broken]
    xf, ff = x0.ravel()[idx], fx.ravel()[idx]
    inside = ((xf - a) * (xf - b) < 0) & np.isfinite(ff)
    up = inside & (ff > 0)
    dn = inside & (ff < 0)
    b[up], fb[up] = xf[up], ff[up]
    a[dn], fa[dn] = xf[dn], ff[dn]
    side = np.where(up, 1, np.where(dn, -1, 0)).astype(np.int8)
    # Next point: a Newton step from x0 with the Hermite slope dλ/ds (accurate to high order
    # inside an interval, so it typically lands within tolerance); bisection if outside.
    tf = t.ravel()[idx]
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        slope = (ma[rows, kk] + tf * (2.0 * c2[rows, kk] + 3.0 * tf * c3[rows, kk])) * inv_du[rows, kk] / sf
        x1 = np.where(inside, xf - ff * slope, np.nan)
    it2 = 1 + _polish_flat(P, theta, names, idx, K, a[:, None], b[:, None], fa[:, None], fb[:, None],
                           side[:, None], sf[:, None], lam.reshape(-1), tol=tol, max_iter=max_iter,
                           x_first=x1[:, None])
    return lam, unreachable, non_monotone, it1 + it2


# ---------------------------------------------------------------------------------------------
# the response
# ---------------------------------------------------------------------------------------------
@dataclass
class OrganResponse:
    """Force–elongation response of a fusiform muscle for a population of parameter sets.

    Attributes
    ----------
    forces : ndarray (n_f,)
        Axial force levels (N).
    elongation : ndarray (n, n_f)
        Total elongation (mm): belly + tendons; NaN where :attr:`unreachable`.
    belly_elongation : ndarray (n, n_f)
        ∫(λ − 1) dz of the belly (mm).
    tendon_elongation : ndarray (n_f,)
        Elongation of both tendons (mm), the same for every sample.
    max_strain : ndarray (n, n_f)
        Largest fiber (tissue) strain λ − 1 over the belly sections.
    mid_strain : ndarray (n, n_f)
        Fiber strain at mid-belly (z = L/2).
    unreachable : ndarray (n, n_f) bool
        Some section would need a stretch above ``max_stretch`` (or the force is not in the
        range of the nominal stress).
    non_monotone : ndarray (n,) bool
        The nominal stress of the sample decreases somewhere on [1, max_stretch]: the solution
        returned is *a* root, not necessarily unique.
    z : ndarray (n_sections + 1,)
        Section nodes (mm).
    stretch : ndarray (n, n_sections + 1, n_f) or None
        Fiber stretch field λ(z) when requested.
    geometry : FusiformGeometry
    parameter_names : tuple of str
    excluded_effects : tuple of str
        Model effects not used in the organ (non-elastic stages).
    max_stretch, tol : float
        Solver settings.
    wall_time : float
        Seconds spent in :func:`organ_response`.
    n_iterations : int
        Largest number of polishing iterations over the chunks.
    """

    forces: np.ndarray
    elongation: np.ndarray
    belly_elongation: np.ndarray
    tendon_elongation: np.ndarray
    max_strain: np.ndarray
    mid_strain: np.ndarray
    unreachable: np.ndarray
    non_monotone: np.ndarray
    z: np.ndarray
    geometry: FusiformGeometry
    parameter_names: tuple
    excluded_effects: tuple = ()
    stretch: np.ndarray | None = None
    max_stretch: float = 3.0
    tol: float = 1e-10
    wall_time: float = 0.0
    n_iterations: int = 0
    extra: dict = field(default_factory=dict)

    @property
    def n_samples(self) -> int:
        return self.elongation.shape[0]

    def band(self, probs: Sequence[float] = (0.05, 0.5, 0.95)) -> np.ndarray:
        """Pointwise quantiles of the elongation over samples, shape (len(probs), n_f) (NaN-aware)."""
        import warnings

        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)  # all-NaN columns stay NaN
            return np.nanquantile(self.elongation, np.asarray(probs, dtype=float), axis=0)

    def to_dataset(self, tested_max_strain=None):
        """An :class:`xarray.Dataset` with dims (sample, force[, node]) for storage and plots.

        Variables: elongation, belly_elongation, tendon_elongation, max_strain, mid_strain,
        unreachable (int8), non_monotone (int8), optional stretch and extrapolated (int8, when
        ``tested_max_strain`` is given).  Attributes: geometry as JSON, settings.  Group names
        and files are the business of :mod:`hbm.io`.
        """
        import json

        import xarray as xr

        ds = xr.Dataset(
            {
                "elongation": (("sample", "force"), self.elongation, {"units": "mm"}),
                "belly_elongation": (("sample", "force"), self.belly_elongation, {"units": "mm"}),
                "tendon_elongation": (("force",), self.tendon_elongation, {"units": "mm"}),
                "max_strain": (("sample", "force"), self.max_strain, {"units": "-"}),
                "mid_strain": (("sample", "force"), self.mid_strain, {"units": "-"}),
                "unreachable": (("sample", "force"), self.unreachable.astype(np.int8)),
                "non_monotone": (("sample",), self.non_monotone.astype(np.int8)),
            },
            coords={"force": ("force", self.forces, {"units": "N"}), "node": ("node", self.z, {"units": "mm"})},
            attrs={"geometry": json.dumps(self.geometry.to_dict()), "max_stretch": self.max_stretch,
                   "tol": self.tol, "parameter_names": json.dumps(list(self.parameter_names)),
                   "excluded_effects": json.dumps(list(self.excluded_effects)),
                   "model_assumptions": "slender body, uniaxial fibers along the axis, incompressible, "
                                        "quasi-static passive, elastic stage only, tendons in series"},
        )
        if self.stretch is not None:
            ds["stretch"] = (("sample", "node", "force"), self.stretch)
        if tested_max_strain is not None:
            ds["extrapolated"] = (("sample", "force"),
                                  extrapolation_mask(self, tested_max_strain).astype(np.int8))
            ds.attrs["tested_max_strain"] = json.dumps(np.asarray(tested_max_strain, dtype=float).tolist())
        return ds


def _check_forces(forces) -> np.ndarray:
    forces = np.atleast_1d(np.asarray(forces, dtype=float))
    if forces.ndim != 1 or forces.size == 0:
        raise HbmError(f"forces must be a non-empty 1-D array (N), got shape {forces.shape}")
    if not np.isfinite(forces).all() or (forces < 0).any():
        raise HbmError("forces must be finite and >= 0 N (the slender-body model is tension-only)")
    return forces


def organ_response(model: Model, theta: np.ndarray, geometry: FusiformGeometry, forces: np.ndarray, *,
                   max_stretch: float = 3.0, tol: float = 1e-10, return_stretch: bool = False,
                   quadrature: str | None = None, strict: bool = False, n_grid: int = 129,
                   n_anchors: int = 512, max_iter: int = 300, chunk_elements: int = 2_000_000) -> OrganResponse:
    """Force–elongation response of a fusiform muscle for every parameter set in ``theta``.

    Parameters
    ----------
    model : Model
        Constitutive model; its ``"elastic"`` effects define the tissue law.
    theta : array (n, n_params)
        Parameter sets (e.g. posterior samples), columns in ``model.parameter_names`` order.
    geometry : FusiformGeometry
    forces : array (n_f,)
        Axial force levels (N), >= 0.
    max_stretch : float
        Upper end of the stretch bracket; force levels needing more are flagged unreachable.
    tol : float
        Relative equilibrium tolerance per section: |σ(λ)·A0/λ − F| <= tol·F.  Where rounding
        in the model makes this unreachable (a very steep exponential branch, or forces so
        small that λ − 1 ~ 1e-7) the stretch is instead resolved to a few ulps.
    return_stretch : bool
        Also return the stretch field (n, n_sections + 1, n_f).
    quadrature : {"simpson", "trapezoid"}, optional
        Rule for ∫(λ − 1) dz; default Simpson for an even number of sections, else trapezoid.
    strict : bool
        Raise :class:`HbmError` instead of flagging unreachable forces / non-monotone samples.
    n_grid : int
        Stretch-grid size of the per-sample table (monotonicity check, anchor brackets).
    n_anchors : int
        Anchor stresses solved first per sample; they bracket every section's target.
    max_iter : int
        Cap on polishing iterations.
    chunk_elements : int
        Approximate number of (sample, section, force) unknowns solved per chunk (memory bound).

    Returns
    -------
    OrganResponse

    Notes
    -----
    Sections with equal reference area share their stretch, so only the distinct areas of the
    (symmetric) profile are solved: about n_sections/2 + 1 for a spindle, one for a cylinder.
    Work per chunk: one table of ``n_grid`` stretches per sample, a vectorised binary search,
    and a few regula-falsi evaluations on the unconverged unknowns only.
    """
    t0 = _time.perf_counter()
    theta = _check_theta(model, theta)
    forces = _check_forces(forces)
    if not (np.isfinite(max_stretch) and max_stretch > 1.0):
        raise HbmError(f"max_stretch must be a finite number > 1, got {max_stretch!r}")
    if not (0 < tol < 1e-2):
        raise HbmError(f"tol must be in (0, 0.01), got {tol!r}")
    if n_grid < 3:
        raise HbmError(f"n_grid must be >= 3, got {n_grid}")
    P, excluded = _nominal_fn(model)
    z = geometry.nodes
    rule = quadrature or ("simpson" if geometry.n_sections % 2 == 0 else "trapezoid")
    w = quadrature_weights(z, rule)
    A_nodes = geometry.area(z)
    A_mid = float(geometry.area(np.array([geometry.length / 2]))[0])
    areas, inverse = np.unique(np.append(A_nodes, A_mid), return_inverse=True)
    inv_nodes, i_mid = inverse[:-1], inverse[-1]
    W = np.bincount(inv_nodes, weights=w, minlength=areas.size)  # quadrature weight per distinct area
    i_min = int(np.argmin(areas))
    U, nf, n = areas.size, forces.size, theta.shape[0]
    targets_1 = forces[None, :] / areas[:, None]  # (U, n_f) nominal stress per distinct section

    belly = np.empty((n, nf))
    max_strain = np.empty((n, nf))
    mid_strain = np.empty((n, nf))
    unreachable = np.zeros((n, nf), dtype=bool)
    non_monotone = np.zeros(n, dtype=bool)
    stretch = np.empty((n, z.size, nf)) if return_stretch else None
    rows_per_chunk = max(1, int(chunk_elements) // (U * nf))
    n_iter = 0
    names = model.parameter_names
    for start in range(0, n, rows_per_chunk):  # chunks bound memory; each chunk is vectorised
        sl = slice(start, min(n, start + rows_per_chunk))
        th = theta[sl]
        m = th.shape[0]
        lam, unr, nonmono, it = _solve_stretch(P, th, names, targets_1.ravel(), max_stretch=max_stretch,
                                               tol=tol, n_grid=n_grid, n_anchors=n_anchors, max_iter=max_iter)
        n_iter = max(n_iter, it)
        lam = lam.reshape(m, U, nf)
        unr = unr.reshape(m, U, nf).any(axis=1)
        belly[sl] = np.einsum("u,muf->mf", W, lam - 1.0)
        # λ decreases with the area for a monotone P, so the smallest section strains most; the
        # max over sections also covers non-monotone samples.
        max_strain[sl] = lam.max(axis=1) - 1.0 if nonmono.any() else lam[:, i_min, :] - 1.0
        mid_strain[sl] = lam[:, i_mid, :] - 1.0
        unreachable[sl] = unr
        non_monotone[sl] = nonmono
        if return_stretch:
            stretch[sl] = lam[:, inv_nodes, :]
    for arr in (belly, max_strain, mid_strain):
        arr[unreachable] = np.nan
    if return_stretch:
        stretch[np.broadcast_to(unreachable[:, None, :], stretch.shape)] = np.nan
    if strict and unreachable.any():
        i, j = np.argwhere(unreachable)[0]
        raise HbmError(f"{int(unreachable.sum())} (sample, force) pairs need a stretch above max_stretch = "
                       f"{max_stretch:g} (first: sample {i}, force {forces[j]:.4g} N); lower the forces or "
                       f"raise max_stretch")
    if strict and non_monotone.any():
        raise HbmError(f"{int(non_monotone.sum())} samples have a nominal stress that decreases on "
                       f"[1, {max_stretch:g}]: the section stretch is not unique (first: sample "
                       f"{int(np.argmax(non_monotone))})")
    tendon = geometry.tendon_length * tendon_strain(forces, geometry)
    return OrganResponse(
        forces=forces, elongation=belly + tendon[None, :], belly_elongation=belly, tendon_elongation=tendon,
        max_strain=max_strain, mid_strain=mid_strain, unreachable=unreachable, non_monotone=non_monotone,
        z=z, geometry=geometry, parameter_names=tuple(names), excluded_effects=excluded, stretch=stretch,
        max_stretch=float(max_stretch), tol=float(tol), wall_time=_time.perf_counter() - t0,
        n_iterations=n_iter, extra={"quadrature": rule, "distinct_sections": int(U)})


def theta_from_samples(model: Model, names: Sequence[str], samples: np.ndarray,
                       fixed: Mapping[str, float] | None = None) -> np.ndarray:
    """Model theta (n, n_params) from a sample matrix with named columns.

    Picks the model's parameters by name (noise columns such as ``sigma`` are ignored) and
    fills parameters held fixed during the fit from ``fixed``.

    Parameters
    ----------
    model : Model
    names : sequence of str
        Column names of ``samples`` (e.g. ``SpecimenResult.names``).
    samples : array (n, len(names))
    fixed : mapping name -> value, optional

    Raises
    ------
    HbmError
        A model parameter is neither a column nor fixed, or the shapes disagree.
    """
    samples = np.asarray(samples, dtype=float)
    names = list(names)
    if samples.ndim != 2 or samples.shape[1] != len(names):
        raise HbmError(f"samples must have shape (n, {len(names)}) for columns {names}, got {samples.shape}")
    fixed = dict(fixed or {})
    out = np.empty((samples.shape[0], model.n_params))
    for j, q in enumerate(model.parameter_names):
        if q in names:
            out[:, j] = samples[:, names.index(q)]
        elif q in fixed:
            out[:, j] = float(fixed[q])
        else:
            raise HbmError(f"parameter {q!r} of model {model.name!r} is neither a sample column {names} "
                           f"nor fixed")
    return out


def extrapolation_mask(response: OrganResponse, tested_max_strain) -> np.ndarray:
    """True where the largest tissue strain in the organ exceeds the strain tested on the specimen.

    Parameters
    ----------
    response : OrganResponse
    tested_max_strain : float or array (n,)
        Largest strain of the specimen's data (per sample when the samples come from several
        specimens, e.g. the hierarchical layer's individuals).

    Returns
    -------
    ndarray (n, n_f) bool
        Unreachable points count as extrapolated.
    """
    t = np.asarray(tested_max_strain, dtype=float)
    if t.ndim == 1:
        if t.size != response.n_samples:
            raise HbmError(f"tested_max_strain has {t.size} values for {response.n_samples} samples")
        t = t[:, None]
    elif t.ndim != 0:
        raise HbmError("tested_max_strain must be a scalar or an array (n_samples,)")
    if not np.isfinite(t).all() or (t <= 0).any():
        raise HbmError("tested_max_strain must be finite and > 0")
    with np.errstate(invalid="ignore"):
        return ~(response.max_strain <= t)


def force_levels(model: Model, theta: np.ndarray, geometry: FusiformGeometry, tested_max_strain: float, *,
                 factor: float = 1.5, n_forces: int = 200, where: str = "mid", quantile: float = 0.5,
                 include_zero: bool = True) -> np.ndarray:
    """Force levels from 0 up to where the tissue strain reaches ``factor × tested_max_strain``.

    For sample i the force at which the section ``where`` reaches strain ε* = factor·ε_tested
    is F_i = P_i(1 + ε*)·A0 (exact: no root find needed in this direction).  The common upper
    force is the ``quantile`` of F_i over the samples (0 → the softest sample, 1 → the stiffest).

    Parameters
    ----------
    model, theta, geometry
        As for :func:`organ_response`.
    tested_max_strain : float
        Largest strain in the specimen's data.
    factor : float
        Target strain as a multiple of the tested strain.
    n_forces : int
        Number of force levels.
    where : {"mid", "max"}
        Mid-belly section ("mid") or the most strained (smallest) section ("max").
    quantile : float in [0, 1]
    include_zero : bool
        Start at F = 0 (else at F_max/n_forces).

    Returns
    -------
    ndarray (n_forces,)
    """
    theta = _check_theta(model, theta)
    if not (np.isfinite(tested_max_strain) and tested_max_strain > 0):
        raise HbmError(f"tested_max_strain must be > 0, got {tested_max_strain!r}")
    if where not in ("mid", "max"):
        raise HbmError(f"where must be 'mid' or 'max', got {where!r}")
    if not 0 <= quantile <= 1:
        raise HbmError(f"quantile must be in [0, 1], got {quantile!r}")
    if n_forces < 2:
        raise HbmError(f"n_forces must be >= 2, got {n_forces}")
    if where == "mid":
        area = float(geometry.area(np.array([geometry.length / 2]))[0])
    else:
        area = float(geometry.area(geometry.nodes).min())
    lam = np.array([1.0 + factor * tested_max_strain])
    f_i = nominal_stress(model, theta, lam)[:, 0] * area
    f_max = float(np.quantile(f_i, quantile))
    if not (np.isfinite(f_max) and f_max > 0):
        raise HbmError(f"no positive force reaches strain {factor * tested_max_strain:.3g} (F = {f_max!r})")
    if include_zero:
        return np.linspace(0.0, f_max, n_forces)
    return np.linspace(f_max / n_forces, f_max, n_forces)
