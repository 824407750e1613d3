"""Generic, non-physical controls: shapes a misfit of unknown cause can take.

Each control is a small :class:`~hbm.model.core.Effect` class (output stage, like the library
effects) with a linear amplitude and a few shape parameters.  The detective screens and refits
them exactly like physical candidates; a physical effect is named only when it explains the
misfit about as well as the best control and beats it in evidence, otherwise the misfit is
reported as unexplained, with the best control's shape and where it acts
(:meth:`Control.region`).

* :class:`LocalMisfit` — a Gaussian bump in strain;
* :class:`StepMisfit` — a smooth step in strain (a structure that locks or ruptures);
* :class:`KinkMisfit` — a change of slope at one strain;
* :class:`TimeTrend` — a slow trend in time (drift of the load cell);
* :class:`TimeStep` — an abrupt step in time (a grip slip), located at its time;
* :class:`Ripple` — a periodic ripple in time (an actuator artefact), with its period.
"""

from __future__ import annotations

import numpy as np

from ..errors import HbmError
from ..model.core import Effect, Parameter
from .rules import CONTROL_NAME

__all__ = ["Control", "LocalMisfit", "StepMisfit", "KinkMisfit", "TimeTrend", "TimeStep", "Ripple", "controls_for"]


class Control(Effect):
    """Base class of the controls: ``amplitude · shape(loading; shape parameters)``.

    Subclasses set ``name``, ``amp``, ``shape_names`` and define :meth:`shape`; the parameters
    are made by :meth:`__init__` from the data ranges.
    """

    stage = "output"
    physical = False
    amp = "A"
    shape_names: tuple[str, ...] = ()
    axis = "strain"

    def shape(self, loading, q) -> np.ndarray:
        """The unit-amplitude shape; ``q`` maps shape-parameter names to (..., 1) arrays."""
        raise NotImplementedError

    def modify(self, state, p, stress):
        return stress + p[self.amp] * self.shape(state.loading, p)

    def grid(self, n: int = 7) -> list[dict[str, float]]:
        """Shape parameters to try as starts (centre × width grid, inside the box)."""
        qs = [q for q in self.parameters if q.name in self.shape_names]
        axes = []
        for q in qs:
            if q.lower > 0 and q.upper / q.lower > 10:
                axes.append(np.geomspace(q.lower * 1.5, q.upper / 1.5, 3))
            else:
                axes.append(np.linspace(q.lower, q.upper, n + 2)[1:-1])
        mesh = np.meshgrid(*axes, indexing="ij")
        return [{q.name: float(m.ravel()[i]) for q, m in zip(qs, mesh)} for i in range(mesh[0].size)]

    def dense_grid(self, n: int = 40, n_scale: int = 10) -> list[dict[str, float]]:
        """A fine grid of shapes over the whole box, for the calibration's optimum gains
        (:mod:`.calibration`): ``n`` values of a linear shape parameter, ``n_scale`` of one
        spanning more than a decade (log-spaced)."""
        qs = [q for q in self.parameters if q.name in self.shape_names]
        axes = [np.geomspace(q.lower, q.upper, n_scale) if q.lower > 0 and q.upper / q.lower > 10
                else np.linspace(q.lower, q.upper, n + 2)[1:-1] for q in qs]
        mesh = np.meshgrid(*axes, indexing="ij")
        return [{q.name: float(m.ravel()[i]) for q, m in zip(qs, mesh)} for i in range(mesh[0].size)]

    def region(self, x: dict[str, float], data) -> tuple[str, float, float]:
        """Where the fitted control acts: (axis, lo, hi)."""
        raise NotImplementedError

    def describe(self, x: dict[str, float]) -> str:
        """The fitted shape's own numbers in words ("" when its region says it all)."""
        return ""


def _strain_params(prefix: str, strain: np.ndarray, amp: float, wmin: float, wmax: float):
    lo, hi = float(np.min(strain)), float(np.max(strain))
    if not hi > lo:
        raise HbmError("a control needs a strain range")
    span = hi - lo
    a = abs(float(amp)) or 1e-3
    return (Parameter(f"{prefix}_A", -a, a, "MPa", "amplitude of the control", null=0.0),
            Parameter(f"{prefix}_C", lo, hi, "-", "centre strain", null=0.5 * (lo + hi)),
            Parameter(f"{prefix}_W", wmin * span, wmax * span, "-", "width in strain",
                      null=float(np.sqrt(wmin * wmax)) * span))


class _StrainControl(Control):
    """A control acting around a centre strain C with width W."""

    prefix = "X"
    width = (0.01, 0.33)
    reach = 2.0     # the region is C ± reach·W

    def __init__(self, amplitude: float = 0.05, strain_range: tuple[float, float] = (0.0, 0.5)) -> None:
        self.parameters = _strain_params(self.prefix, np.asarray(strain_range, float), amplitude, *self.width)
        self.amp = f"{self.prefix}_A"
        self.shape_names = (f"{self.prefix}_C", f"{self.prefix}_W")

    @classmethod
    def for_data(cls, strain: np.ndarray, stress: np.ndarray):
        """The control with amplitude up to half the stress range, centre inside the data."""
        amp = 0.5 * float(np.ptp(np.asarray(stress, float))) or 1e-3
        return cls(amp, (float(np.min(strain)), float(np.max(strain))))

    def _z(self, loading, q):
        return (loading.strain - q[f"{self.prefix}_C"]) / q[f"{self.prefix}_W"]

    def region(self, x, data):
        c, w = x[f"{self.prefix}_C"], x[f"{self.prefix}_W"]
        lo, hi = float(np.min(data.strain)), float(np.max(data.strain))
        return "strain", float(max(c - self.reach * w, lo)), float(min(c + self.reach * w, hi))


class LocalMisfit(_StrainControl):
    """Generic local misfit: a Gaussian bump in applied strain, ``A·exp(−½((ε − C)/W)²)``.

    Not a physical effect: a *control*.  If a control explains a misfit much better than every
    physical candidate, the misfit is reported as unexplained in ε ∈ [C − 2W, C + 2W] instead of
    being absorbed by (or misattributed to) a physical effect.
    """

    name = CONTROL_NAME
    prefix = "BUMP"
    strength = "BUMP_A"
    description = "non-physical control: Gaussian stress bump in strain (amplitude, centre, width)"

    def __init__(self, amplitude: float = 0.05, strain_range: tuple[float, float] = (0.0, 0.5),
                 width_range: tuple[float, float] | None = None) -> None:
        super().__init__(amplitude, strain_range)
        if width_range is not None:
            q = self.parameters[2]
            self.parameters = self.parameters[:2] + (
                Parameter(q.name, float(width_range[0]), float(width_range[1]), q.unit, q.meaning,
                          null=float(np.sqrt(width_range[0] * width_range[1]))),)

    def shape(self, loading, q):
        z = self._z(loading, q)
        return np.exp(-0.5 * z * z)


class _SharpControl(_StrainControl):
    """A strain control whose transition can be sharp (a few points wide)."""

    width = (0.003, 0.1)
    reach = 4.0


class StepMisfit(_SharpControl):
    """A smooth step in strain, ``A / (1 + exp(−(ε − C)/W))``: extra load engaging (or lost) at C."""

    name = "local_step"
    prefix = "STEP"
    strength = "STEP_A"
    description = "non-physical control: smooth stress step in strain (amplitude, centre, width)"

    def shape(self, loading, q):
        return 0.5 * (1.0 + np.tanh(0.5 * self._z(loading, q)))


class KinkMisfit(_SharpControl):
    """A change of slope at strain C, ``A·W·softplus((ε − C)/W)/span``: A is the stress change
    the new slope adds over the whole strain span."""

    name = "local_kink"
    prefix = "KINK"
    strength = "KINK_A"
    description = "non-physical control: change of slope in strain (amplitude, position, smoothness)"

    def shape(self, loading, q):
        z = self._z(loading, q)
        span = self.parameters[1].upper - self.parameters[1].lower
        return q[f"{self.prefix}_W"] * np.logaddexp(0.0, z) / span

    def region(self, x, data):
        c, w = x["KINK_C"], x["KINK_W"]
        return "strain", float(max(c - self.reach * w, np.min(data.strain))), float(np.max(data.strain))


class TimeTrend(Control):
    """A slow trend in time, ``A·(t/t_max)^P``: the drift of a load cell over the test."""

    name = "time_trend"
    strength = "TREND_A"
    axis = "time"
    description = "non-physical control: slow stress trend in time (amplitude at the end, power)"

    def __init__(self, amplitude: float = 0.05, t_max: float = 1.0) -> None:
        a = abs(float(amplitude)) or 1e-3
        self.t_max = float(t_max)
        self.parameters = (Parameter("TREND_A", -a, a, "MPa", "trend at the end of the test", null=0.0),
                           Parameter("TREND_P", 0.5, 3.0, "-", "power of the trend in time", null=1.0))
        self.amp, self.shape_names = "TREND_A", ("TREND_P",)

    @classmethod
    def for_data(cls, time: np.ndarray | None, stress: np.ndarray):
        if time is None or not np.max(time) > 0:
            raise HbmError("the time-trend control needs a time column")
        return cls(0.5 * float(np.ptp(np.asarray(stress, float))) or 1e-3, float(np.max(time)))

    def shape(self, loading, q):
        if loading.time is None:
            raise HbmError("the time-trend control needs a time column")
        tau = np.clip(loading.time / self.t_max, 0.0, None)
        return tau ** q["TREND_P"]

    def grid(self, n: int = 7) -> list[dict[str, float]]:
        return [{"TREND_P": p} for p in (0.7, 1.0, 2.0)]

    def region(self, x, data):
        t = data.time
        return "time", float(np.min(t)), float(np.max(t))


class TimeStep(Control):
    """An abrupt (smooth) step in time, ``A / (1 + exp(−(t − C)/W))``: a grip slip, a load-cell
    jump -- located at its time C, not spread over the test like a drift."""

    name = "time_step"
    strength = "TSTEP_A"
    axis = "time"
    reach = 4.0
    description = "non-physical control: abrupt stress step in time (amplitude, time, duration)"

    def __init__(self, amplitude: float = 0.05, t_range: tuple[float, float] = (0.0, 1.0), dt: float = 0.01) -> None:
        a = abs(float(amplitude)) or 1e-3
        lo, hi = float(t_range[0]), float(t_range[1])
        w_lo, w_hi = max(0.3 * dt, 1e-6 * (hi - lo)), max(0.1 * (hi - lo), 0.6 * dt)
        self.parameters = (Parameter("TSTEP_A", -a, a, "MPa", "step height", null=0.0),
                           Parameter("TSTEP_C", lo, hi, "s", "time of the step", null=0.5 * (lo + hi)),
                           Parameter("TSTEP_W", w_lo, w_hi, "s", "duration of the step",
                                     null=float(np.sqrt(w_lo * w_hi))))
        self.amp, self.shape_names = "TSTEP_A", ("TSTEP_C", "TSTEP_W")

    @classmethod
    def for_data(cls, time: np.ndarray | None, stress: np.ndarray):
        t = np.asarray(time, float)
        dt = float(np.median(np.abs(np.diff(t)))) if t.size > 1 else 1.0
        return cls(0.5 * float(np.ptp(np.asarray(stress, float))) or 1e-3, (float(np.min(t)), float(np.max(t))),
                   dt or 1.0)

    def shape(self, loading, q):
        if loading.time is None:
            raise HbmError("the time-step control needs a time column")
        return 0.5 * (1.0 + np.tanh(0.5 * (loading.time - q["TSTEP_C"]) / q["TSTEP_W"]))

    def grid(self, n: int = 15) -> list[dict[str, float]]:
        c_q, w_q = self.parameters[1], self.parameters[2]
        cs = np.linspace(c_q.lower, c_q.upper, n + 2)[1:-1]
        ws = np.geomspace(w_q.lower * 1.5, w_q.upper / 1.5, 3)
        return [{"TSTEP_C": float(c), "TSTEP_W": float(w)} for c in cs for w in ws]

    def region(self, x, data):
        c, w = x["TSTEP_C"], x["TSTEP_W"]
        t = data.time
        return "time", float(max(c - self.reach * w, np.min(t))), float(min(c + self.reach * w, np.max(t)))


class Ripple(Control):
    """A periodic artefact in time, ``A·sin(2π·t/P + φ)``: an actuator or mains ripple, with a
    fitted period, phase and amplitude (a smooth misfit control cannot absorb it, and AR(1)
    noise only partly)."""

    name = "periodic"
    strength = "RIP_A"
    axis = "time"
    description = "non-physical control: periodic stress ripple in time (amplitude, period, phase)"

    def __init__(self, amplitude: float = 0.05, period_range: tuple[float, float] = (1.0, 100.0)) -> None:
        a = abs(float(amplitude)) or 1e-3
        p_lo, p_hi = float(period_range[0]), float(period_range[1])
        self.parameters = (Parameter("RIP_A", -a, a, "MPa", "ripple amplitude", null=0.0),
                           Parameter("RIP_P", p_lo, p_hi, "s", "ripple period", null=float(np.sqrt(p_lo * p_hi))),
                           Parameter("RIP_PH", 0.0, 2 * np.pi, "rad", "ripple phase", null=0.0))
        self.amp, self.shape_names = "RIP_A", ("RIP_P", "RIP_PH")

    @classmethod
    def for_data(cls, time: np.ndarray | None, stress: np.ndarray):
        t = np.asarray(time, float)
        dt = float(np.median(np.abs(np.diff(t)))) if t.size > 1 else 1.0
        span = float(np.ptp(t))
        if not (dt > 0 and span > 8 * dt):
            raise HbmError("the periodic control needs a time column with at least 8 samples per test")
        # from 2.5 samples per period (near Nyquist) to half the record
        return cls(0.5 * float(np.ptp(np.asarray(stress, float))) or 1e-3, (2.5 * dt, 0.5 * span))

    def shape(self, loading, q):
        if loading.time is None:
            raise HbmError("the periodic control needs a time column")
        return np.sin(2 * np.pi * loading.time / q["RIP_P"] + q["RIP_PH"])

    def grid(self, n: int = 8) -> list[dict[str, float]]:
        """Periods spaced by the frequency resolution of the record (one cycle more over it),
        at most 150, and ``n`` phases."""
        p_lo, p_hi = self.parameters[1].lower, self.parameters[1].upper
        span = 2.0 * p_hi
        k = int(np.clip(np.ceil(span / p_lo - span / p_hi) + 1, 4, 150))
        freqs = np.linspace(1.0 / p_hi, 1.0 / p_lo, k)
        phases = np.arange(n) * 2 * np.pi / n
        return [{"RIP_P": float(1.0 / f), "RIP_PH": float(ph)} for f in freqs for ph in phases]

    def dense_grid(self, n: int = 12, n_scale: int = 0) -> list[dict[str, float]]:
        """Frequencies three times finer than the record's resolution (at most 600) and ``n``
        phases over [0, π) (the amplitude takes the sign; the gain lost between two phases is at most
        1 − cos²(π/2n), 2 % at 12)."""
        p_lo, p_hi = self.parameters[1].lower, self.parameters[1].upper
        k = int(np.clip(np.ceil(3 * (2.0 * p_hi) * (1.0 / p_lo - 1.0 / p_hi)) + 1, 8, 600))
        freqs = np.linspace(1.0 / p_hi, 1.0 / p_lo, k)
        return [{"RIP_P": float(1.0 / f), "RIP_PH": float(ph)} for f in freqs for ph in np.arange(n) * np.pi / n]

    def region(self, x, data):
        t = data.time
        return "time", float(np.min(t)), float(np.max(t))

    def describe(self, x: dict[str, float]) -> str:
        return f"period {x['RIP_P']:.3g} s, amplitude {abs(x['RIP_A']):.3g} MPa"


def controls_for(data) -> list[Control]:
    """The controls applicable to a specimen (the time controls need a time column)."""
    out: list[Control] = [cls.for_data(data.strain, data.stress) for cls in (LocalMisfit, StepMisfit, KinkMisfit)]
    if data.time is not None and np.max(data.time) > 0:
        out.append(TimeTrend.for_data(data.time, data.stress))
        out.append(TimeStep.for_data(data.time, data.stress))
        try:
            out.append(Ripple.for_data(data.time, data.stress))
        except HbmError:     # too short a record for a period: no periodic control
            pass
    return out
