"""The energy cards in every loading mode hbm predicts (issue 35): solved from their own laws, compared with hbm.

A card that claims to be a 3-D material (``febio-energy``, ``abaqus-uanisohyper``) is solved here in every
mode of :data:`hbm.model.loadcases.LOAD_CASES` from its law -- a callable ``T(F)`` giving the card's Cauchy
stress without the pressure at J = 1, written from the card's documentation (:func:`.verify.febio_card_stress`)
or computed by the card itself (the compiled Abaqus subroutine) -- and compared with hbm's prediction
(:func:`hbm.model.loadcases.predict_observables`) for the same parameters and the collagen reading the
cards implement: the **cone** (DESIGN.md §8), with the exact azimuthal average.

The kinematics are the load cases' own (the definition of each test); the card's stresses and its
traction-free faces are solved here, independently of hbm's energy code:

* prescribed F (planar, biaxial): σ_aa = T_aa − T_bb, b the free face;
* simple shear F = I + γ·e_X⊗e_Y: σ_XY = T_XY (the pressure drops out);
* uniaxial (one loaded axis, two free faces): the stretch of the first free face by bracketing and
  Chandrupatla's method (:func:`scipy.optimize.elementwise.find_root`) on T_11 − T_22 of the free faces,
  the second from J = 1; σ = T_load − T_free.

**Range.**  The cards are calibrated along the fibres only; every other mode is the model's prediction,
which the card must reproduce.  The along-fibre tested strain range [lo, hi] is applied as each mode's
control (engineering strain along the load, or the amount of shear γ; biaxial modes equibiaxial), on
that range and on 1.5x it (:data:`MODE_GRID` points).

**Deviation** (dimensionless; pointwise, then the max): a stress's |Δσ| relative to the largest stress
of the mode at that point (its tensor scale -- a held-face stress that crosses zero is not divided by
~0), a lateral strain's |Δε| relative to the control |ε|; both floored at
:data:`hbm.export.laws.FLOOR` x their max over the range compared.

**Three evaluations per mode:** the card solved here (*deviation*, what the report states), hbm's
evaluation of the card (:mod:`.card_models`; *stated*; the two must agree to :data:`MODE_SLACK`), and hbm's
exact segment law on the card's N equally spaced families (*family*: the share of the deviation that is
the discretisation of the azimuthal average, O(N⁻²) because of the slack kink).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field
from typing import Callable, Mapping

import numpy as np
from scipy.optimize import elementwise

from ..errors import HbmError
from ..model.energy3d import Energy3D
from ..model.loadcases import LOAD_CASES, LoadCase, SimpleShear, predict_observables
from .card_models import family_energy
from .laws import FLOOR
from .source import UNITS

#: control points on 1.5x the tested range (the tested range holds two thirds of them)
MODE_GRID = 121
#: the N-family deviation (max over modes and observables, tested range) a card's N is chosen for
FAMILY_TARGET = 5e-3
#: agreement required between the card solved here and hbm's evaluation of it (same metric)
MODE_SLACK = 1e-6
#: traction-free faces and no shear under a diagonal F: residual allowed, relative to the mode's stress
RESIDUAL_TOL = 1e-9
#: the collagen reading every energy card implements
READING = "cone"
#: azimuths of the cone grid that locates a deformation's most stretched helix segment
_PHI = np.linspace(0.0, 2.0 * np.pi, 1441)[:-1]

AXIS = {"f": 0, "c": 1, "n": 2}
CardLaw = Callable[[np.ndarray], np.ndarray]


# ----------------------------------------------------------------------------- kinematics of each mode
def lateral_axes(case: LoadCase) -> tuple[str, ...]:
    """The free faces whose strains a uniaxial mode observes (``strain_f`` -> ``f``), () otherwise."""
    return tuple(o.name[len("strain_"):] for o in case.observables if o.name.startswith("strain_"))


def load_axis(case: LoadCase) -> str | None:
    """The axis of the mode's loaded stress (``None`` in simple shear)."""
    return case.observable("stress").axis


def deformation(case: LoadCase, strain: np.ndarray, lateral: Mapping[str, np.ndarray] | None = None) -> np.ndarray:
    """F (m, 3, 3) of ``case`` at the controls ``strain`` (biaxial: equibiaxial); for a uniaxial mode the
    free faces' engineering strains come from ``lateral`` (``{"strain_f": ...}``)."""
    s = np.asarray(strain, float)
    F = np.zeros((s.size, 3, 3))
    if isinstance(case, SimpleShear):
        F[:] = np.eye(3)
        F[:, AXIS[case.X], AXIS[case.Y]] = s
        return F
    free = lateral_axes(case)
    if free:
        F[:, AXIS[load_axis(case)], AXIS[load_axis(case)]] = 1.0 + s
        for a in free:
            F[:, AXIS[a], AXIS[a]] = 1.0 + np.asarray(lateral[f"strain_{a}"], float)
        return F
    s2 = s if "strain_2" in case.inputs else None
    for i, e in enumerate(case.log_stretches(s, s2)):
        F[:, i, i] = np.exp(e)
    return F


def segment_stretch(src) -> tuple[float, float]:
    """The largest helix-segment stretch (cone at the fit's helix angle, on a 0.25° azimuth grid) over every
    mode at hbm's solution, on the tested range and on 1.5x it: what an energy card's collagen law covers."""
    strain, tested = control_grid(src.strain_range)
    p = src.params()
    th = np.deg2rad(theta_of(src))
    n = np.stack([np.full(_PHI.size, np.cos(th)), np.sin(th) * np.cos(_PHI), np.sin(th) * np.sin(_PHI)])
    cone = Energy3D(src.k_iso, "energy", READING)
    out_t, out_x = 1.0, 1.0
    for case in LOAD_CASES.values():
        lateral = predict_observables(cone, case, p, strain) if lateral_axes(case) else None
        lmax = np.linalg.norm(deformation(case, strain, lateral) @ n, axis=1).max(axis=1)
        out_t, out_x = max(out_t, float(lmax[tested].max())), max(out_x, float(lmax.max()))
    return out_t, out_x


def theta_of(src) -> float:
    """The helix angle (degrees) of the summary's parameter set: the one base parameter in degrees."""
    names = [k for k, u in UNITS.items() if u == "degree"]
    if len(names) != 1:
        raise HbmError("export: the model has no single helix-angle parameter (unit degree)")
    return float(src.params()[names[0]])


def control_grid(strain_range) -> tuple[np.ndarray, np.ndarray]:
    """(controls on 1.5x the tested range, mask of the tested range)."""
    lo, hi = (float(v) for v in strain_range)
    s = np.linspace(1.5 * lo, 1.5 * hi, MODE_GRID)
    return s, (s >= lo - 1e-12) & (s <= hi + 1e-12)


# ----------------------------------------------------------------------------- the card, solved here
def solve_card(T: CardLaw, case: LoadCase, strain: np.ndarray) -> tuple[dict[str, np.ndarray], float]:
    """Every observable of ``case`` for the card law ``T`` (F (m,3,3) -> Cauchy stress without the pressure,
    (m,3,3)), and the solve's residual: traction on the free faces (uniaxial) or shear under a diagonal F,
    relative to the mode's stress (max over the points)."""
    s = np.asarray(strain, float)
    if isinstance(case, SimpleShear):
        t = T(deformation(case, s))
        return {"stress": t[:, AXIS[case.X], AXIS[case.Y]]}, 0.0
    free = lateral_axes(case)
    load = load_axis(case)
    if free:
        a, b = AXIS[free[0]], AXIS[free[1]]
        ec = np.log1p(s)

        def F_of(u, e):
            F = np.zeros(np.shape(u) + (3, 3))
            F[..., AXIS[load], AXIS[load]] = np.exp(e)
            F[..., a, a], F[..., b, b] = np.exp(u), np.exp(-u - e)
            return F

        def g(u, e):
            t = T(F_of(u, e).reshape(-1, 3, 3)).reshape(np.shape(u) + (3, 3))
            return t[..., a, a] - t[..., b, b]

        u0 = -0.5 * ec
        br = elementwise.bracket_root(g, u0 - 0.05, u0 + 0.05, args=(ec,))
        if not np.all(br.success):
            raise HbmError(f"mode {case.name}: the card's lateral stretch could not be bracketed")
        root = elementwise.find_root(g, (br.bracket[0], br.bracket[1]), args=(ec,),
                                     tolerances=dict(xatol=1e-15, xrtol=4 * np.finfo(float).eps, fatol=0.0,
                                                     frtol=0.0))
        u = root.x
        t = T(F_of(u, ec))
        out = {"stress": t[:, AXIS[load], AXIS[load]] - t[:, b, b],
               f"strain_{free[0]}": np.expm1(u), f"strain_{free[1]}": np.expm1(-u - ec)}
        resid = np.abs(t[:, a, a] - t[:, b, b])
    else:
        t = T(deformation(case, s))
        free_ax = AXIS[case.free]
        out = {k: t[:, AXIS[ax], AXIS[ax]] - t[:, free_ax, free_ax] for k, ax in case.stress_axes.items()}
        resid = np.zeros(s.size)
    off = np.max(np.abs(t[:, [0, 0, 1], [1, 2, 2]]), axis=1)
    scale = np.max(np.abs([v for k, v in out.items() if case.observable(k).is_stress]), axis=0)
    bad = np.maximum(resid, off) / np.maximum(scale, 1e-300)
    return out, float(np.max(np.where(scale > 0, bad, 0.0)))


# ----------------------------------------------------------------------------- deviations
def deviation(case: LoadCase, ref: Mapping[str, np.ndarray], got: Mapping[str, np.ndarray],
              control: np.ndarray) -> dict[str, np.ndarray]:
    """Pointwise deviation of ``got`` from ``ref`` per observable (module docstring)."""
    stresses = [k for k in ref if case.observable(k).is_stress]
    S = np.max(np.abs([np.asarray(ref[k], float) for k in stresses]), axis=0)
    S = np.maximum(S, FLOOR * max(float(np.max(S)), 1e-300))
    E = np.abs(np.asarray(control, float))
    E = np.maximum(E, FLOOR * max(float(np.max(E)), 1e-300))
    return {k: np.abs(np.asarray(got[k], float) - np.asarray(ref[k], float)) / (S if k in stresses else E)
            for k in ref}


def deviations(case: LoadCase, ref: Mapping[str, np.ndarray], got: Mapping[str, np.ndarray], control: np.ndarray,
               tested: np.ndarray) -> dict[str, list[float]]:
    """observable -> [max deviation on the tested range, on 1.5x it]; each range with its own floor (the
    stresses grow exponentially: a floor taken over 1.5x the range would hide the tested part)."""
    def on(mask):
        return deviation(case, {k: v[mask] for k, v in ref.items()}, {k: np.asarray(v)[mask] for k, v in got.items()},
                         control[mask])

    inner, outer = on(tested), on(np.ones(control.size, dtype=bool))
    return {k: [float(np.max(inner[k])), float(np.max(outer[k]))] for k in ref}


@dataclass
class ModeCheck:
    """One energy card in one loading mode (deviations: observable -> [tested range, 1.5x it])."""

    format: str
    mode: str
    families: int
    deviation: dict          # the card solved here vs hbm's exact cone
    stated: dict             # hbm's evaluation of the card vs the exact cone
    family: dict             # hbm's exact law on the card's N families vs the exact cone
    consistency: float       # max over 1.5x the range between the card solved here and hbm's evaluation of it
    residual: float          # the solve's traction / shear residual, relative to the mode's stress
    method: str
    reading: str = READING
    passed: bool = field(init=False)

    def __post_init__(self) -> None:
        self.passed = bool(self.consistency <= MODE_SLACK and self.residual <= RESIDUAL_TOL)

    @property
    def error_tested(self) -> float:
        return max(v[0] for v in self.deviation.values())

    @property
    def error_extended(self) -> float:
        return max(v[1] for v in self.deviation.values())

    @property
    def family_tested(self) -> float:
        return max(v[0] for v in self.family.values())

    def as_dict(self) -> dict:
        out = asdict(self)
        out.update(error_tested=self.error_tested, error_extended=self.error_extended)
        return out

    def line(self) -> str:
        """One line: the deviation per observable on the tested range, the worst on 1.5x, the family share."""
        per = ", ".join(f"{k} {v[0]:.2g}" for k, v in self.deviation.items())
        return (f"{self.mode}: {self.error_tested:.3g} on the tested range ({per}), {self.error_extended:.3g} on "
                f"1.5x; of which {self.families} families instead of the exact average {self.family_tested:.3g}"
                + ("" if self.passed else f": FAILED (card vs hbm's evaluation of it {self.consistency:.2g}, "
                                          f"solve residual {self.residual:.2g})"))


def check_card(fmt: str, T: CardLaw, src, card_energy: Energy3D, n_families: int, method: str) -> list[ModeCheck]:
    """Every mode of :data:`LOAD_CASES` for one card: ``T`` its law (solved here), ``card_energy`` hbm's
    evaluation of it (:mod:`.card_models`), ``n_families`` its collagen families."""
    strain, tested = control_grid(src.strain_range)
    p = src.params()
    cone = Energy3D(src.k_iso, "energy", READING)
    fam = family_energy(src.k_iso, n_families)
    out = []
    for name, case in LOAD_CASES.items():
        ref = predict_observables(cone, case, p, strain)
        hbm_card = predict_observables(card_energy, case, p, strain)
        hbm_fam = predict_observables(fam, case, p, strain)
        got, residual = solve_card(T, case, strain)
        consistency = max(max(v) for v in deviations(case, hbm_card, got, strain, tested).values())
        out.append(ModeCheck(format=fmt, mode=name, families=n_families,
                             deviation=deviations(case, ref, got, strain, tested),
                             stated=deviations(case, ref, hbm_card, strain, tested),
                             family=deviations(case, ref, hbm_fam, strain, tested),
                             consistency=consistency, residual=residual, method=method))
    return out


def family_deviations(src, n: int) -> tuple[float, float]:
    """Max deviation (tested range, 1.5x) over every mode and observable of hbm's exact law on ``n``
    equally spaced families from the exact cone."""
    strain, tested = control_grid(src.strain_range)
    p = src.params()
    cone = Energy3D(src.k_iso, "energy", READING)
    fam = family_energy(src.k_iso, n)
    worst = [0.0, 0.0]
    for case in LOAD_CASES.values():
        dev = deviations(case, predict_observables(cone, case, p, strain), predict_observables(fam, case, p, strain),
                         strain, tested)
        for v in dev.values():
            worst = [max(worst[0], v[0]), max(worst[1], v[1])]
    return worst[0], worst[1]


def choose_families(src, ladder: tuple[int, ...]) -> tuple[int, dict[int, list[float]]]:
    """The smallest N of ``ladder`` whose family deviation on the tested range is <= :data:`FAMILY_TARGET`
    (the last one when none is), and the deviations measured on the way (N -> [tested, 1.5x])."""
    seen: dict[int, list[float]] = {}
    for n in ladder:
        seen[n] = list(family_deviations(src, n))
        if seen[n][0] <= FAMILY_TARGET:
            break
    return n, seen


def tradeoff_line(fmt: str, chosen: int, seen: Mapping[int, list[float]], cost: str) -> str:
    """One line: the N chosen, the family deviations measured for the N tried, what N costs."""
    tried = "; ".join(f"N = {n}: {t:.2g} (1.5x: {x:.2g})" for n, (t, x) in seen.items())
    met = seen[chosen][0] <= FAMILY_TARGET
    return (f"{fmt}: {chosen} collagen families, chosen for a family deviation <= {FAMILY_TARGET:g} on the tested "
            f"range ({'met' if met else 'NOT met: the largest N offered'}; measured {tried}); {cost}")


#: what a card that claims to be a 3-D material is (the report's scope line)
SCOPE_3D = ("3-D material: verified in every loading mode hbm predicts, against hbm's cone reading "
            "(collagen3d = cone, the exact azimuthal average)")
#: what a curve card is
SCOPE_ALONG = ("along-fibre uniaxial only: not a 3-D material (transverse, shear and multiaxial loading are "
               "outside it; use febio-energy or abaqus-uanisohyper for those)")


def header_lines(checks: list[ModeCheck], tradeoff: str) -> list[str]:
    """The lines a card's header and the report carry for its check in every mode."""
    lines = [f"3-D check ({checks[0].method}) in every loading mode against hbm's {READING} reading (the exact "
             "azimuthal average); controls: the tested along-fibre strain range (shear: gamma), and 1.5x it; "
             "deviation: |difference| relative to the mode's largest stress (lateral strains: to the applied "
             "strain):"] if checks else []
    lines += ["  " + c.line() for c in checks]
    return lines + ([tradeoff] if tradeoff else [])
