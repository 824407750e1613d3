"""Building blocks of the 3-D energy: symmetric tensors in the fibre frame, the collagen readings.

The fibre frame is f = e1 (fibre axis a0), c = e2 (cross-fibre, in the specimen plane), n = e3.
Kinematics enter as ``D = C − I`` (twice the Green–Lagrange strain): near the reference state its
components are small numbers computed without cancellation, so stresses of tiny strains keep their
relative accuracy.

A *collagen reading* is the 3-D meaning given to the thesis's helix stretch λH (DESIGN.md §8).  A
reading that averages W_c over "segments" with structure tensors N (l² = 1 + N:D) only has to
supply a quadrature rule (:meth:`DirectionalCollagen.rule`); energy, stress and tangent follow here.
"""

from __future__ import annotations

from typing import Any, Mapping, NamedTuple

import numpy as np

from ...errors import SettingError
from ..spyrou import _EXP_CLIP, collagen_energy

#: the axes of the fibre frame, in order
AXES = ("f", "c", "n")


def is_zero(a: Any) -> bool:
    """True when ``a`` is a structural zero: the scalar 0 or an array of zeros."""
    return not np.any(a)


class Sym(NamedTuple):
    """A symmetric 3×3 tensor by its components in the fibre frame (f, c, n).

    Each component is an array (all broadcastable) or the float ``0.0``; a zero off-diagonal lets a
    reading pick its closed-form path (diagonal tensors, simple shear).
    """

    ff: Any
    cc: Any
    nn: Any
    fc: Any = 0.0
    fn: Any = 0.0
    cn: Any = 0.0

    def get(self, i: int, j: int) -> Any:
        """Component (i, j), axes numbered 0 = f, 1 = c, 2 = n."""
        a, b = sorted((i, j))
        return getattr(self, AXES[a] + AXES[b])

    @classmethod
    def from_components(cls, comps: Mapping[tuple[int, int], Any]) -> "Sym":
        """From ``{(i, j): value}`` (upper or lower triangle); missing components are 0."""
        kw = {}
        for (i, j), v in comps.items():
            a, b = sorted((i, j))
            kw[AXES[a] + AXES[b]] = v
        return cls(**{**dict(ff=0.0, cc=0.0, nn=0.0), **kw})

    @classmethod
    def from_matrix(cls, m: np.ndarray) -> "Sym":
        """From a matrix (..., 3, 3) (its symmetric part)."""
        m = np.asarray(m, dtype=float)
        s = 0.5 * (m + np.swapaxes(m, -1, -2))
        return cls(s[..., 0, 0], s[..., 1, 1], s[..., 2, 2], s[..., 0, 1], s[..., 0, 2], s[..., 1, 2])

    def matrix(self) -> np.ndarray:
        """The full matrix (..., 3, 3)."""
        shape = np.broadcast_shapes(*(np.shape(v) for v in self))
        out = np.empty(shape + (3, 3))
        for i in range(3):
            for j in range(3):
                out[..., i, j] = self.get(i, j)
        return out

    def contract(self, other: "Sym") -> Any:
        """A:B = Σ A_ij·B_ij (off-diagonal components counted twice)."""
        out = self.ff * other.ff + self.cc * other.cc + self.nn * other.nn
        for name in ("fc", "fn", "cn"):
            a, b = getattr(self, name), getattr(other, name)
            if not (is_zero(a) or is_zero(b)):
                out = out + 2.0 * a * b
        return out


def gauss_unit(n: int) -> tuple[np.ndarray, np.ndarray]:
    """Gauss–Legendre nodes and weights on [0, 1] (weights sum to 1)."""
    x, w = np.polynomial.legendre.leggauss(n)
    return 0.5 * (x + 1.0), 0.5 * w


def segment_excess(l2m1: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(l, ⟨l − 1⟩₊) from l² − 1, with l − 1 = (l² − 1)/(l + 1): exact 0 at the reference state."""
    l = np.sqrt(1.0 + l2m1)
    x = l2m1 / (l + 1.0)
    np.maximum(x, 0.0, out=x)
    return l, x


def collagen_force(x: np.ndarray, t1, t2) -> np.ndarray:
    """dW_c/dλH = T1·(exp(T2·x) − 1) (thesis eq. 1.14), exponent clipped like the 1-D model."""
    return t1 * np.expm1(np.minimum(t2 * x, _EXP_CLIP))


def collagen_stiffness(x: np.ndarray, t1, t2) -> np.ndarray:
    """d²W_c/dλH² = T1·T2·exp(T2·x) where taut and below the clip, else 0."""
    z = t2 * x
    return np.where((x > 0) & (z < _EXP_CLIP), t1 * t2 * np.exp(np.minimum(z, _EXP_CLIP)), 0.0)


class CollagenReading:
    """One 3-D reading of the helical collagen (per unit collagen volume; the energy scales it by 1 − c).

    Parameters come as a mapping ``name -> array`` broadcastable against the kinematic arrays
    (``(..., 1)`` against ``(..., n_points)``, or both flat); subclasses read THETA, T1 and T2.

    Class attributes
    ----------------
    name : str
        The value of the ``collagen3d`` option.
    description : str
        One line for tables and ``--help``.
    kernel_code : int or None
        The reading's code in the compiled diagonal kernel (:mod:`.diagonal`); ``None``: the numpy path.
    """

    name: str = ""
    description: str = ""
    #: the code of this reading in the compiled diagonal kernel (:mod:`.diagonal`), None: numpy only
    kernel_code: int | None = None

    def energy(self, p: Mapping[str, np.ndarray], D: Sym) -> np.ndarray:
        """W_coll (MPa) at D = C − I."""
        raise NotImplementedError

    def pk2(self, p: Mapping[str, np.ndarray], D: Sym) -> Sym:
        """Second Piola–Kirchhoff stress 2·∂W_coll/∂C (MPa)."""
        raise NotImplementedError

    def principal(self, p: Mapping[str, np.ndarray], e: tuple, tangent: bool = False):
        """Principal Kirchhoff stresses τ_i = ∂W/∂ln λ_i at a diagonal F = diag(exp(e)).

        Parameters
        ----------
        p : mapping
            Parameters.
        e : tuple of 3 arrays
            Log-stretches (ln λf, ln λc, ln λn), not constrained to sum to 0.
        tangent : bool
            Also return c_ij = ∂τ_i/∂ln λ_j (symmetric, 3×3 nested tuples).

        Returns
        -------
        tau : tuple of 3 arrays
        c : tuple of tuples or None
        """
        raise NotImplementedError

    def __repr__(self) -> str:
        return f"<collagen reading {self.name}>"


class DirectionalCollagen(CollagenReading):
    """A reading that averages W_c over segments with structure tensors N: W = Σ_q ω_q·W_c(l_q),
    l_q² = 1 + N_q:D.  Then S = Σ ω·h·N with h = W_c'(l)/l, and (diagonal D) the principal
    tangent c_ij = 2δ_ij·τ_i + 2λ_i²λ_j²·Σ ω·k·N_ii·N_jj with k = dh/d(l²) = (W_c'' − h)/(2l²)
    (the integrand vanishes where a segment goes slack, so a moving slack boundary adds nothing).

    The segment law is the thesis's W_c (:meth:`segment_energy`, :meth:`segment_force`,
    :meth:`segment_stiffness`); a subclass may replace it, e.g. to evaluate an FE card's fibre law
    on the same quadrature (:mod:`hbm.export.modes`)."""

    def rule(self, D: Sym, theta_deg: np.ndarray, need: str = "tangent") -> tuple[Sym | None, np.ndarray, np.ndarray]:
        """The quadrature at D: structure tensors N (components (..., q)), weights ω (..., q) summing to
        the average, and l² − 1 = N:D at the nodes (..., q).

        ``need`` says what the caller computes: ``"energy"`` (N may be ``None``), ``"stress"`` (only
        linear functionals of N: nodes may stand for symmetric groups of segments) or ``"tangent"``
        (diagonal D; the N's must be exact per node, since the tangent uses N ⊗ N)."""
        raise NotImplementedError

    def segment_energy(self, l, t1, t2):
        """W_c of a segment at stretch ``l`` (per unit collagen volume)."""
        return collagen_energy(l, t1, t2)

    def segment_force(self, x, t1, t2):
        """dW_c/dl of a segment at excess ``x`` = ⟨l − 1⟩₊."""
        return collagen_force(x, t1, t2)

    def segment_stiffness(self, x, t1, t2):
        """d²W_c/dl² of a segment at excess ``x``."""
        return collagen_stiffness(x, t1, t2)

    def _nodes(self, p, D, need):
        N, w, l2m1 = self.rule(D, p["THETA"], need)
        l, x = segment_excess(l2m1)
        return N, w, l, x, p["T1"][..., None], p["T2"][..., None]

    def energy(self, p, D):
        _, w, l, x, t1, t2 = self._nodes(p, D, "energy")
        return np.sum(w * self.segment_energy(l, t1, t2), axis=-1)

    def pk2(self, p, D):
        N, w, l, x, t1, t2 = self._nodes(p, D, "stress")
        wh = w * self.segment_force(x, t1, t2) / l
        return Sym(*(0.0 if is_zero(v) else np.sum(wh * v, axis=-1) for v in N))

    def principal(self, p, e, tangent=False):
        d = tuple(np.expm1(2.0 * np.asarray(ei, dtype=float)) for ei in e)
        N, w, l, x, t1, t2 = self._nodes(p, Sym(*d), "tangent" if tangent else "stress")
        force = self.segment_force(x, t1, t2)
        h = force / l
        wh = w * h
        nd = (N.ff, N.cc, N.nn)
        lam2 = tuple(1.0 + di for di in d)
        tau = tuple(lam2[i] * np.sum(wh * nd[i], axis=-1) for i in range(3))
        if not tangent:
            return tau, None
        wk = w * (self.segment_stiffness(x, t1, t2) - h) / (2.0 * l * l)
        c = [[None] * 3 for _ in range(3)]
        for i in range(3):
            for j in range(i, 3):
                cij = 2.0 * lam2[i] * lam2[j] * np.sum(wk * nd[i] * nd[j], axis=-1)
                if i == j:
                    cij = cij + 2.0 * tau[i]
                c[i][j] = c[j][i] = cij
        return tau, tuple(tuple(r) for r in c)


#: collagen3d option -> reading class (each reading registers itself)
COLLAGEN_READINGS: dict[str, type[CollagenReading]] = {}
#: the reading the stability check and the Abaqus card already discretise (DESIGN.md §8)
DEFAULT_COLLAGEN3D = "cone"


def register_collagen_reading(cls: type[CollagenReading]) -> type[CollagenReading]:
    """Class decorator: make ``cls`` a value of the ``collagen3d`` option (its ``name``)."""
    if not cls.name or cls.name in COLLAGEN_READINGS:
        raise ValueError(f"collagen reading {cls.__name__}: name {cls.name!r} empty or taken")
    COLLAGEN_READINGS[cls.name] = cls
    return cls


def get_collagen_reading(name: str, **kwargs) -> CollagenReading:
    """The reading ``name`` (a value of ``collagen3d``); :class:`SettingError` listing the choices."""
    if name not in COLLAGEN_READINGS:
        raise SettingError(f"collagen3d: expected one of {', '.join(COLLAGEN_READINGS)}, got {name!r}")
    return COLLAGEN_READINGS[name](**kwargs)
