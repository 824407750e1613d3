"""``abaqus-uanisohyper``: an Abaqus ``UANISOHYPER_INV`` user subroutine of the energy form (exact in uniaxial).

The strain energy, in Abaqus's invariants (Ī1, J, Ī4(αα) of the local directions α)::

    U = C10·(Ī1 − 3) + (J − 1)²/D1
      + Af/2·⟨√Ī4(11) − 1 − EOPT⟩₊²                               fibres (direction 1 = muscle axis)
      + Σ_{α=2..N+1} Ac·(exp(T2·x_α) − 1 − T2·x_α)/T2,  x_α = ⟨√Ī4(αα) − 1⟩₊   N helical families

with C10 = k_iso·G/2, Af = c·P1, Ac = (1 − c)·T1/N, D1 = 2/K (K = 1000 × the initial shear modulus).
Every family carries hbm's own segment law, so the card is hbm's cone reading (DESIGN.md §8) with the
azimuthal average replaced by N equally spaced families (directions in the ``*ORIENTATION`` of the
header): exact in homogeneous uniaxial tension along direction 1 (every family has hbm's helix
stretch λH), off by the measured N-family deviation in the other loading modes (:mod:`.modes`).  N is
the smallest of :data:`N_LADDER` whose deviation is within :data:`hbm.export.modes.FAMILY_TARGET`, at most
:data:`N_LADDER`'s last: Abaqus passes every pseudo-invariant pair, so the arrays grow as N² (invariants)
and N⁴ (second derivatives), :data:`COST`.  Only for ``form="energy"`` results.  The export compiles
the subroutine with gfortran, calls it for the invariants of every loading mode and solves the mode
(lateral stretches by root finding, :mod:`.verify` and :mod:`.modes`); without gfortran it refuses to
write an unchecked subroutine.
"""

from __future__ import annotations

import ctypes
import shutil
import subprocess
import tempfile
from pathlib import Path

import numpy as np

from ..errors import HbmError
from . import modes, verify
from .card_models import family_energy
from .febio_energy import require_energy
from .laws import BULK_FACTOR, cone_directions
from .registry import Written

DESCRIPTION = "Abaqus UANISOHYPER_INV user subroutine of the energy form (fibres + N helical collagen families)"
SUFFIX = ".f"
VALID = ("3-D hyperelastic (an energy; hbm's cone reading with N collagen families): exact in uniaxial tension "
         "along direction 1, in the other loading modes within the deviations stated below; calibrated in "
         "uniaxial tension along the fibres only, so the other modes are the model's prediction, not data")
#: collagen families offered, smallest first (the first within the family target is written)
N_LADDER = (12, 24)
#: what N costs in Abaqus (measured here: the subroutine alone, gfortran -O2, one call)
COST = ("N = 12: 185 invariants, 17,205 second derivatives, 6 us per call; N = 24: 653, 213,531, 116 us; "
        "N = 48: 2,453, 3.0 million, 4 ms (not offered)")
#: the PROPS of the subroutine, in its order (E0: the fibre onset strain, Rc: the collagen rate; the Fortran
#: comments call them EOPT and T2)
PROPS = ("C10", "D1", "Af", "E0", "Ac", "Rc")

FORTRAN = """\
      subroutine uanisohyper_inv(ainv, ua, zeta, nfibers, ninv,
     $     ui1, ui2, ui3, temp, noel, cmname, incmpflag, ihybflag,
     $     numstatev, statev, numfieldv, fieldv, fieldvinc,
     $     numprops, props)
C     hbm energy form: props = C10, D1, Af, EOPT, Ac, T2 (see header)
      implicit double precision (a-h,o-z)
      character*80 cmname
      dimension ua(2), ainv(ninv), ui1(ninv),
     $     ui2(ninv*(ninv+1)/2), ui3(ninv*(ninv+1)/2),
     $     statev(*), fieldv(*), fieldvinc(*), props(numprops)
      integer indx, ninv4
      c10 = props(1)
      d1 = props(2)
      af = props(3)
      eopt = props(4)
      ac = props(5)
      t2 = props(6)
      do k = 1, ninv
        ui1(k) = 0.d0
      end do
      do k = 1, ninv*(ninv+1)/2
        ui2(k) = 0.d0
        ui3(k) = 0.d0
      end do
      aj = ainv(3)
      udev = c10*(ainv(1) - 3.d0)
      ui1(1) = c10
      uvol = (aj - 1.d0)**2/d1
      ui1(3) = 2.d0*(aj - 1.d0)/d1
      ui2(indx(3,3)) = 2.d0/d1
      do ia = 1, nfibers
        k = ninv4(ia)
        a4 = ainv(k)
        if (a4 .le. 0.d0) cycle
        al = sqrt(a4)
C       g(l): energy as a function of the fibre stretch; g1 = dg/dl, g2 = d2g/dl2
        g = 0.d0
        g1 = 0.d0
        g2 = 0.d0
        if (ia .eq. 1) then
          e = al - 1.d0 - eopt
          if (e .gt. 0.d0) then
            g = 0.5d0*af*e*e
            g1 = af*e
            g2 = af
          end if
        else
          x = al - 1.d0
          if (x .gt. 0.d0) then
            z = min(t2*x, 700.d0)
            if (z .lt. 1.d-3) then
              g = ac*x*z*(0.5d0 + z*(1.d0/6.d0 + z*(1.d0/24.d0
     $            + z/120.d0)))
            else
              g = ac*(exp(z) - 1.d0 - z)/t2
            end if
            g1 = ac*(exp(z) - 1.d0)
            g2 = ac*t2*exp(z)
          end if
        end if
        udev = udev + g
C       chain rule to the invariant I4 = l**2
        ui1(k) = g1/(2.d0*al)
        ui2(indx(k,k)) = (g2 - g1/al)/(4.d0*a4)
      end do
      ua(2) = udev
      ua(1) = udev + uvol
      return
      end
C     triangular storage index of a symmetric matrix (Abaqus convention)
      integer function indx(i, j)
      ii = min(i, j)
      jj = max(i, j)
      indx = ii + jj*(jj - 1)/2
      return
      end
C     position of the pseudo-invariant I4(alpha, alpha) in ainv (Abaqus convention)
      integer function ninv4(ia)
      ninv4 = 4 + ia*(ia - 1) + 2*(ia - 1)
      return
      end
"""


def props(src, n: int) -> dict[str, float]:
    """The subroutine's PROPS of the summary's parameter set with ``n`` collagen families."""
    k = src.constituents()
    c10 = src.k_iso * k.shear_modulus / 2.0
    return {"C10": c10, "D1": 2.0 / (BULK_FACTOR * 2.0 * c10), "Af": k.fibre_amplitude, "E0": k.fibre_onset,
            "Ac": k.collagen_amplitude / n, "Rc": k.collagen_rate}


def directions(src, n: int) -> np.ndarray:
    """(n + 1, 3): the muscle axis and the ``n`` helical family directions."""
    return np.vstack([[1.0, 0.0, 0.0], cone_directions(src.constituents().collagen_angle, n)])


def compile_subroutine(workdir: Path) -> ctypes.CDLL:
    fc = shutil.which("gfortran")
    if fc is None:
        raise HbmError("abaqus-uanisohyper: no gfortran on PATH to compile and check the subroutine; nothing "
                       "written (apt-get install gfortran, or use --to febio-energy / abaqus-marlow)")
    src = workdir / "uaniso.f"
    src.write_text(FORTRAN, encoding="ascii")
    lib = workdir / "uaniso.so"
    res = subprocess.run([fc, "-shared", "-fPIC", "-O2", "-std=legacy", "-o", str(lib), str(src)],
                         capture_output=True, text=True, check=False)
    if res.returncode != 0:
        raise HbmError(f"abaqus-uanisohyper: gfortran failed: {res.stderr.strip()[:300]}")
    return ctypes.CDLL(str(lib))


def inv4_index(alpha: int) -> int:
    """0-based position of Ī4(αα) in Abaqus's invariant array (α from 1)."""
    return 3 + alpha * (alpha - 1) + 2 * (alpha - 1)


class Subroutine:
    """The compiled subroutine with one card's PROPS and directions; its arrays are allocated once.

    Parameters
    ----------
    lib : ctypes.CDLL
        From :func:`compile_subroutine`.
    pr : dict
        PROPS (:func:`props`).
    dirs : ndarray (nfib, 3)
        The local directions (:func:`directions`).

    Attributes
    ----------
    ninv : int
        Length of the invariant array.
    i4 : ndarray (nfib,)
        Positions of Ī4(αα) in it.
    """

    def __init__(self, lib: ctypes.CDLL, pr: dict, dirs: np.ndarray) -> None:
        self.lib, self.dirs = lib, np.asarray(dirs, float)
        nfib = self.dirs.shape[0]
        self.ninv = 3 + 2 * nfib * (nfib + 1) // 2
        dbl = ctypes.c_double
        self._props = (dbl * 6)(*[pr[k] for k in PROPS])
        # cosines between the directions (Abaqus passes them; this energy does not use them)
        self._zeta = (dbl * max(1, nfib * (nfib - 1) // 2))(
            *[float(self.dirs[a] @ self.dirs[b]) for b in range(nfib) for a in range(b)])
        n2 = self.ninv * (self.ninv + 1) // 2
        self._ainv, self._ua, self._ui1 = (dbl * self.ninv)(), (dbl * 2)(), (dbl * self.ninv)()
        self._ui2, self._ui3, self._dummy = (dbl * n2)(), (dbl * n2)(), (dbl * 1)()
        self._nfib, self._n = ctypes.c_int(nfib), ctypes.c_int(self.ninv)
        self._name = ctypes.create_string_buffer(b"MUSCLE".ljust(80), 80)
        self._views = [np.ctypeslib.as_array(a) for a in (self._ainv, self._ua, self._ui1, self._ui2)]
        self.i4 = np.array([inv4_index(al) for al in range(1, nfib + 1)])

    def __call__(self, ainv) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(UA, UI1, UI2) at invariants ``ainv`` (Abaqus ordering), copies."""
        self._run(ainv)
        return tuple(v.copy() for v in self._views[1:])

    def _run(self, ainv) -> None:
        i, dbl = ctypes.c_int, ctypes.c_double
        self._views[0][:] = ainv
        self.lib.uanisohyper_inv_(self._ainv, self._ua, self._zeta, ctypes.byref(self._nfib), ctypes.byref(self._n),
                                  self._ui1, self._ui2, self._ui3, ctypes.byref(dbl(0.0)), ctypes.byref(i(1)),
                                  self._name, ctypes.byref(i(0)), ctypes.byref(i(0)), ctypes.byref(i(0)),
                                  self._dummy, ctypes.byref(i(0)), self._dummy, self._dummy, ctypes.byref(i(6)),
                                  self._props, ctypes.c_size_t(80))

    def stress(self, F: np.ndarray) -> np.ndarray:
        """Cauchy stress without the pressure at J = 1, (m, 3, 3) for F (m, 3, 3): 2·U1·B + Σ_α 2·U4α·(F a_α)⊗(F a_α)
        with U1 = ∂U/∂Ī1 and U4α = ∂U/∂Ī4(αα) from the subroutine at Ī1 = tr C, J = 1, Ī4(αα) = a_α·C·a_α."""
        F = np.asarray(F, float).reshape(-1, 3, 3)
        Fa = np.einsum("mij,kj->mki", F, self.dirs)
        I4 = np.einsum("mki,mki->mk", Fa, Fa)
        ainv = np.zeros(self.ninv)
        ainv[2] = 1.0
        out = np.empty_like(F)
        ui1 = self._views[2]
        for m in range(F.shape[0]):
            ainv[0] = float(np.sum(F[m] * F[m]))
            ainv[self.i4] = I4[m]
            self._run(ainv)
            out[m] = 2.0 * ui1[0] * F[m] @ F[m].T + np.einsum("k,ki,kj->ij", 2.0 * ui1[self.i4], Fa[m], Fa[m])
        return out


def call_subroutine(lib: ctypes.CDLL, pr: dict, dirs: np.ndarray, ainv) -> tuple[np.ndarray, ...]:
    """(UA, UI1, UI2) of the compiled subroutine at invariants ``ainv`` (Abaqus ordering)."""
    return Subroutine(lib, pr, dirs)(ainv)


def subroutine_stress(lib: ctypes.CDLL, pr: dict, dirs: np.ndarray):
    """Diagonal extra stress T(f) at F = diag(f) from the compiled subroutine (:meth:`Subroutine.stress`)."""
    sub = Subroutine(lib, pr, dirs)
    return lambda f: np.diagonal(sub.stress(np.diag(np.asarray(f, float))), axis1=1, axis2=2)[0]


METHOD = ("the subroutine compiled with gfortran and called for the invariants, 3-D incompressible, lateral "
          "stretch by root finding")


def check(src, n: int) -> tuple[verify.Check, list[modes.ModeCheck]]:
    """The along-fibre check (exact card) and the check in every loading mode, with ``n`` families."""
    pr, dirs = props(src, n), directions(src, n)
    with tempfile.TemporaryDirectory(prefix="hbm-uaniso-") as d:
        lib = compile_subroutine(Path(d))
        along = verify.compare("abaqus-uanisohyper", subroutine_stress(lib, pr, dirs), src.curve_strain,
                               src.stress(src.curve_strain), src.tested_mask(), True, verify.EXACT_TOLERANCE, METHOD)
        every = modes.check_card("abaqus-uanisohyper", Subroutine(lib, pr, dirs).stress, src,
                                 family_energy(src.k_iso, n), n, METHOD)
    return along, every


def write(src) -> Written:
    require_energy(src)
    n, seen = modes.choose_families(src, N_LADDER)
    chk, every = check(src, n)
    pr = props(src, n)
    head = ["C hbm export: " + DESCRIPTION]
    head += [f"C {k}: {v}" for k, v in src.provenance().items()]
    head += [f"C valid for: {VALID}",
             f"C check ({chk.method}): max relative difference to hbm {chk.error_tested:.3g} on the tested range, "
             f"{chk.error_extended:.3g} on 1.5x it; tolerance {chk.bound:.3g}: {'passed' if chk.passed else 'FAILED'}"]
    tradeoff = modes.tradeoff_line("abaqus-uanisohyper", n, seen, COST)
    head += ["C " + line for line in modes.header_lines(every, tradeoff)]
    head += [f"C input file lines (local direction 1 = muscle axis, 2-{n + 1} = helical collagen families):",
             f"C   *ORIENTATION, NAME=MUSCLE_AXES, LOCAL DIRECTIONS={n + 1}",
             "C   1., 0., 0., 0., 1., 0.",
             "C   1, 0."]
    head += ["C   " + ", ".join(f"{x + 0.0:.10g}" for x in a) for a in directions(src, n)]
    head += ["C   *MATERIAL, NAME=MUSCLE",
             f"C   *ANISOTROPIC HYPERELASTIC, USER, FORMULATION=INVARIANT, LOCAL DIRECTIONS={n + 1}, PROPERTIES=6",
             "C   " + ", ".join(f"{pr[k]:.10g}" for k in PROPS),
             "C   (C10, D1, Af, EOPT, Ac, T2; D1 = 2/K with K = 1000 x initial shear modulus)",
             "C the keyword lines above follow the Abaqus manual's layout but were not run here (no Abaqus);",
             "C the subroutine below was compiled and checked"]
    return Written(text="\n".join(head) + "\n" + FORTRAN, checks=[chk], card={**pr, "n_families": n},
                   notes=[tradeoff], modes=every, scope=modes.SCOPE_3D)
