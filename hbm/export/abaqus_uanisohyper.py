"""``abaqus-uanisohyper``: an Abaqus ``UANISOHYPER_INV`` user subroutine of the energy form (exact in uniaxial).

The strain energy, in Abaqus's invariants (Ī1, J, Ī4(αα) of the local directions α)::

    U = C10·(Ī1 − 3) + (J − 1)²/D1
      + Af/2·⟨√Ī4(11) − 1 − EOPT⟩₊²                               fibres (direction 1 = muscle axis)
      + Σ_{α=2..7} Ac·(exp(T2·x_α) − 1 − T2·x_α)/T2,  x_α = ⟨√Ī4(αα) − 1⟩₊   six helical families

with C10 = k_iso·G/2, Af = c·P1, Ac = (1 − c)·T1/6, D1 = 2/K (K = 1000 × the initial shear modulus).
In homogeneous uniaxial tension along direction 1 every family has hbm's helix stretch λH, so the
stress is hbm's energy form exactly; in 3-D the helix average around the fibre is replaced by six
families 60° apart (directions given in the ``*ORIENTATION`` of the header).  Only for
``form="energy"`` results.  The export compiles the subroutine with gfortran, calls it for the
invariants of the uniaxial state and solves for the lateral stretch by root finding
(:mod:`hbm.export.verify`); without gfortran it refuses to write an unchecked subroutine.
"""

from __future__ import annotations

import ctypes
import shutil
import subprocess
import tempfile
from pathlib import Path

import numpy as np

from ..errors import HbmError
from . import verify
from .febio_energy import require_energy
from .laws import BULK_FACTOR, family_directions
from .registry import Written

DESCRIPTION = "Abaqus UANISOHYPER_INV user subroutine of the energy form (fibres + 6 helical collagen families)"
SUFFIX = ".f"
VALID = ("3-D hyperelastic (an energy), exact in uniaxial tension along direction 1; the helix average is "
         "six families; calibrated in uniaxial tension only")
N_FAM = 6
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


def props(src) -> dict[str, float]:
    """The subroutine's PROPS of the summary's parameter set."""
    k = src.constituents()
    c10 = src.k_iso * k.shear_modulus / 2.0
    return {"C10": c10, "D1": 2.0 / (BULK_FACTOR * 2.0 * c10), "Af": k.fibre_amplitude, "E0": k.fibre_onset,
            "Ac": k.collagen_amplitude / N_FAM, "Rc": k.collagen_rate}


def directions(src) -> np.ndarray:
    """(7, 3): the muscle axis and the six helical family directions."""
    return np.vstack([[1.0, 0.0, 0.0], family_directions(src.constituents().collagen_angle, N_FAM)])


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


def call_subroutine(lib: ctypes.CDLL, pr: dict, dirs: np.ndarray, ainv) -> tuple[np.ndarray, ...]:
    """(UA, UI1, UI2) of the compiled subroutine at invariants ``ainv`` (Abaqus ordering)."""
    nfib = dirs.shape[0]
    ninv = len(ainv)
    dbl, i = ctypes.c_double, ctypes.c_int
    p = (dbl * 6)(*[pr[k] for k in PROPS])
    # cosines between the directions (Abaqus passes them; this energy does not use them)
    zeta = (dbl * max(1, nfib * (nfib - 1) // 2))(*[float(dirs[a] @ dirs[b]) for b in range(nfib) for a in range(b)])
    a = (dbl * ninv)(*ainv)
    ua, ui1 = (dbl * 2)(), (dbl * ninv)()
    ui2, ui3 = (dbl * (ninv * (ninv + 1) // 2))(), (dbl * (ninv * (ninv + 1) // 2))()
    dummy = (dbl * 1)()
    name = ctypes.create_string_buffer(b"MUSCLE".ljust(80), 80)
    lib.uanisohyper_inv_(a, ua, zeta, ctypes.byref(i(nfib)), ctypes.byref(i(ninv)), ui1, ui2, ui3,
                         ctypes.byref(dbl(0.0)), ctypes.byref(i(1)), name, ctypes.byref(i(0)), ctypes.byref(i(0)),
                         ctypes.byref(i(0)), dummy, ctypes.byref(i(0)), dummy, dummy, ctypes.byref(i(6)), p,
                         ctypes.c_size_t(80))
    return np.array(ua[:]), np.array(ui1[:]), np.array(ui2[:])


def inv4_index(alpha: int) -> int:
    """0-based position of Ī4(αα) in Abaqus's invariant array (α from 1)."""
    return 3 + alpha * (alpha - 1) + 2 * (alpha - 1)


def subroutine_stress(lib: ctypes.CDLL, pr: dict, dirs: np.ndarray):
    """Diagonal extra stress T(f) = 2·U1·f² + Σ 2·U4α·(f∘aα)² from the compiled subroutine (J = 1)."""
    nfib = dirs.shape[0]
    ninv = 3 + 2 * nfib * (nfib + 1) // 2

    def T(f):
        ainv = np.zeros(ninv)
        ainv[0], ainv[2] = np.sum(f ** 2), 1.0
        fa = f[None, :] * dirs
        for al in range(1, nfib + 1):
            ainv[inv4_index(al)] = float(fa[al - 1] @ fa[al - 1])
        u = call_subroutine(lib, pr, dirs, ainv)[1]
        t = 2.0 * u[0] * f ** 2
        for al in range(1, nfib + 1):
            t = t + 2.0 * u[inv4_index(al)] * fa[al - 1] ** 2
        return t

    return T


def check(src) -> verify.Check:
    with tempfile.TemporaryDirectory(prefix="hbm-uaniso-") as d:
        lib = compile_subroutine(Path(d))
        T = subroutine_stress(lib, props(src), directions(src))
        return verify.compare("abaqus-uanisohyper", T, src.curve_strain, src.stress(src.curve_strain),
                              src.tested_mask(), True, verify.EXACT_TOLERANCE,
                              "the subroutine compiled with gfortran and called for the invariants, 3-D "
                              "incompressible, lateral stretch by root finding")


def write(src) -> Written:
    require_energy(src)
    chk = check(src)
    pr = props(src)
    head = ["C hbm export: " + DESCRIPTION]
    head += [f"C {k}: {v}" for k, v in src.provenance().items()]
    head += [f"C valid for: {VALID}",
             f"C check ({chk.method}): max relative difference to hbm {chk.error_tested:.3g} on the tested range, "
             f"{chk.error_extended:.3g} on 1.5x it; tolerance {chk.bound:.3g}: {'passed' if chk.passed else 'FAILED'}",
             "C input file lines (local direction 1 = muscle axis, 2-7 = helical collagen families):",
             "C   *ORIENTATION, NAME=MUSCLE_AXES, LOCAL DIRECTIONS=7",
             "C   1., 0., 0., 0., 1., 0.",
             "C   1, 0."]
    head += ["C   " + ", ".join(f"{x + 0.0:.10g}" for x in a) for a in directions(src)]
    head += ["C   *MATERIAL, NAME=MUSCLE",
             "C   *ANISOTROPIC HYPERELASTIC, USER, FORMULATION=INVARIANT, LOCAL DIRECTIONS=7, PROPERTIES=6",
             "C   " + ", ".join(f"{pr[k]:.10g}" for k in PROPS),
             "C   (C10, D1, Af, EOPT, Ac, T2; D1 = 2/K with K = 1000 x initial shear modulus)",
             "C the keyword lines above follow the Abaqus manual's layout but were not run here (no Abaqus);",
             "C the subroutine below was compiled and checked"]
    return Written(text="\n".join(head) + "\n" + FORTRAN, checks=[chk], card=pr)
