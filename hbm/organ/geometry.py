"""The fusiform muscle's geometry: belly profile, tendons, fibre field (read from TOML)."""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..errors import HbmError


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
