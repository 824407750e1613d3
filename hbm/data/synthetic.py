"""Loading protocols (ramps, holds, cycles) and labelled synthetic specimens."""

from __future__ import annotations


import json
import math


from dataclasses import dataclass


from typing import Any, Mapping, Sequence

import numpy as np

from .._version import __version__
from ..errors import HbmError
from ..model.core import Loading, Model
from ..likelihood.noise import make_noise

from ..runtime.seeds import as_generator
from .specimen import Series, Specimen, as_specimen
from .writer import _attr_text


# ---------------------------------------------------------------------------------------
# protocols
# ---------------------------------------------------------------------------------------
@dataclass(frozen=True)
class Segment:
    """One test of a protocol: a ramp to a target strain or a hold, sampled at ``n`` points.

    Build segments with :func:`ramp`, :func:`hold` and :func:`cycle`, and combine them with
    :func:`protocol`.  A segment starts where the previous segment of its loading history
    ended (or at ``start``/0 when it opens a history).
    """

    kind: str  # "ramp" or "hold"
    n: int
    target: float | None = None  # ramp end strain
    rate: float | None = None  # ramp |dε/dt| in 1/s
    duration: float | None = None  # hold duration in s
    start: float | None = None  # explicit start strain (only when opening a history)
    spacing: str = "linear"  # hold sampling: "linear" or "log"

    def points(self, eps0: float, t0: float, first: bool) -> tuple[np.ndarray, np.ndarray]:
        """Strain and time of the segment's points starting from (eps0, t0).

        When ``first`` the start point itself is included (n points from t0); otherwise the
        start point belongs to the previous segment and the n points follow it.
        """
        k = np.arange(self.n) if first else np.arange(1, self.n + 1)
        m = self.n - 1 if first else self.n
        if self.kind == "ramp":
            span = float(self.target) - eps0
            frac = k / m if m > 0 else np.zeros(1)
            return eps0 + span * frac, t0 + abs(span) / self.rate * frac
        frac = k / m if m > 0 else np.zeros(1)
        if self.spacing == "log":
            # geometric spacing resolves fast relaxation early in a long hold
            d = float(self.duration)
            tau = np.where(frac > 0, d * np.power(1e-3, 1.0 - frac), 0.0)
            times = t0 + tau
        else:
            times = t0 + float(self.duration) * frac
        return np.full(frac.shape, eps0), times


def ramp(to: float, rate: float, n: int, *, start: float | None = None) -> Segment:
    """A constant-rate ramp to strain ``to`` (loading or unloading).

    Parameters
    ----------
    to : float
        End strain.
    rate : float
        Strain rate magnitude |dε/dt| in 1/s (Calvo et al. 2010: 0.022 %/s = 2.2e-4 /s).
    n : int
        Number of points of the segment.  A segment that opens a history includes its start
        point (n ≥ 2); a continuing segment has n new points after the previous segment's end.
    start : float, optional
        Start strain when the segment opens a loading history (default 0, from rest).
    """
    if not (rate > 0 and math.isfinite(rate)):
        raise HbmError(f"ramp: rate must be a positive finite strain rate in 1/s, got {rate!r}")
    if n < 1:
        raise HbmError(f"ramp: n must be >= 1, got {n!r}")
    return Segment("ramp", int(n), target=float(to), rate=float(rate), start=start)


def hold(duration: float, n: int, *, at: float | None = None, spacing: str = "linear") -> Segment:
    """A relaxation hold at constant strain for ``duration`` seconds.

    Parameters
    ----------
    duration : float
        Hold time (s).
    n : int
        Number of points (as for :func:`ramp`).
    at : float, optional
        Strain when the hold opens a history (otherwise the end strain of the previous segment).
    spacing : {"linear", "log"}
        Time sampling inside the hold; "log" spaces points geometrically from 1e-3·duration.
    """
    if not (duration > 0 and math.isfinite(duration)):
        raise HbmError(f"hold: duration must be positive (s), got {duration!r}")
    if spacing not in ("linear", "log"):
        raise HbmError(f"hold: spacing must be 'linear' or 'log', got {spacing!r}")
    if n < 1:
        raise HbmError(f"hold: n must be >= 1, got {n!r}")
    return Segment("hold", int(n), duration=float(duration), start=at, spacing=spacing)


def cycle(eps_max: float, rate: float, n: int, *, eps_min: float = 0.0,
          reload_to: float | None = None) -> list[Segment]:
    """Load–unload–reload: 0 → ``eps_max`` → ``eps_min`` → ``reload_to`` (default ``eps_max``).

    Returns three segments (three tests of one loading history) with ``n`` points each.
    """
    if not eps_max > eps_min:
        raise HbmError(f"cycle: need eps_max > eps_min, got {eps_max!r} <= {eps_min!r}")
    return [ramp(eps_max, rate, n), ramp(eps_min, rate, n),
            ramp(eps_max if reload_to is None else reload_to, rate, n)]


def protocol(*histories: Segment | Sequence[Segment], first_test: int = 1) -> Specimen:
    """Concatenate loading histories into a protocol: a :class:`Specimen` with strain, time and test
    and no measured series (``.with_series("stress", values)`` adds one).

    Each positional argument is one loading history that starts from rest at time 0: a
    single :class:`Segment` or a sequence of segments whose time continues (load, unload,
    reload; a ramp followed by a relaxation hold).  Every segment becomes one test, numbered
    consecutively from ``first_test``.

    Examples
    --------
    Ramps at three rates, each from rest::

        protocol(ramp(0.4, 1e-3, 30), ramp(0.4, 1e-2, 30), ramp(0.4, 1e-1, 30))

    A ramp followed by a 600 s relaxation hold (one history, two tests)::

        protocol([ramp(0.3, 1e-2, 25), hold(600.0, 20)])

    Load–unload–reload::

        protocol(cycle(0.4, 1e-2, 20, eps_min=0.1, reload_to=0.45))
    """
    if not histories:
        raise HbmError("protocol: give at least one segment or list of segments")
    strain, time, test = [], [], []
    tid = int(first_test)
    for h in histories:
        segs = [h] if isinstance(h, Segment) else list(h)
        if not segs or not all(isinstance(s, Segment) for s in segs):
            raise HbmError("protocol: each history must be a Segment or a non-empty list of Segments")
        eps, t = None, 0.0
        for j, seg in enumerate(segs):
            first = j == 0
            if first:
                eps = float(seg.start) if seg.start is not None else 0.0
            elif seg.start is not None:
                raise HbmError("protocol: 'start'/'at' is only allowed on the first segment of a history")
            if first and seg.kind == "ramp" and seg.n < 2:
                raise HbmError("protocol: a ramp that opens a history needs n >= 2")
            e, tt = seg.points(eps, t, first)
            strain.append(e)
            time.append(tt)
            test.append(np.full(e.size, tid, dtype=np.int64))
            eps, t = float(e[-1]), float(tt[-1])
            tid += 1
    return Specimen("protocol", np.concatenate(strain), np.concatenate(time), np.concatenate(test),
                    attrs={"id": "protocol", "provenance": "synthetic"})


# ---------------------------------------------------------------------------------------
# synthetic specimens
# ---------------------------------------------------------------------------------------
def _seed_text(seed) -> str:
    if isinstance(seed, np.random.SeedSequence):
        return json.dumps({"entropy": int(seed.entropy) if isinstance(seed.entropy, int) else seed.entropy,
                           "spawn_key": list(seed.spawn_key)})
    if isinstance(seed, (int, np.integer)):
        return str(int(seed))
    raise HbmError(f"synthetic_specimen: seed must be an int or numpy SeedSequence, got {type(seed).__name__}")


def _theta_array(model: Model, theta) -> np.ndarray:
    if isinstance(theta, Mapping):
        unknown = set(theta) - set(model.parameter_names)
        if unknown:
            raise HbmError(f"synthetic_specimen: unknown parameters {sorted(unknown)}; the model has "
                           f"{model.parameter_names}")
        try:
            return model.null_theta(dict(theta))
        except ValueError:
            missing = [q for q in model.parameter_names if q not in theta]
            raise HbmError(f"synthetic_specimen: no value for parameters {missing}") from None
    arr = np.asarray(theta, dtype=float)
    if arr.shape != (model.n_params,):
        raise HbmError(f"synthetic_specimen: theta must have shape ({model.n_params},) for "
                       f"{model.parameter_names}, got {arr.shape}")
    return arr


def synthetic_specimen(model: Model, theta, strain_or_protocol, noise_sd: float, seed, *,
                       noise: str = "iid", rho: float = 0.0, relative: bool = False,
                       attrs: Mapping[str, Any] | None = None) -> Specimen:
    """A labelled synthetic specimen: model stress plus Gaussian noise.

    Parameters
    ----------
    model : Model
        Generating model (may include effects, e.g. a hidden effect).
    theta : array (n_params,) or mapping name -> value
        Generating parameters; with a mapping, parameters of added effects that are not given
        take their null values.
    strain_or_protocol : array (n_points,), Loading, Specimen or Dataset
        A strain array, or a protocol (see :func:`protocol`) with ``time``/``test``.
    noise_sd : float
        Marginal noise standard deviation in MPa, or a fraction of the maximum |stress| of the
        noise-free curve when ``relative=True``.
    seed : int or numpy.random.SeedSequence
        Seed of the numpy Generator (recorded in the attributes).
    noise : {"iid", "ar1"}
        Independent noise, or AR(1) noise with lag-one correlation ``rho`` and marginal sd
        ``noise_sd`` that restarts (stationary) at each loading history.
    rho : float
        AR(1) coefficient in (−1, 1).
    relative : bool
        Interpret ``noise_sd`` relative to the maximum |stress|.
    attrs : mapping, optional
        Extra attributes (e.g. ``id``, ``source``); they override the defaults.

    Returns
    -------
    Specimen
        Like :func:`load_specimen`, with attributes ``provenance="synthetic"``, ``generator``,
        ``model``, ``parameters`` (JSON), ``noise``, ``noise_sd`` (MPa), ``rho``, ``seed``.
    """
    if noise not in ("iid", "ar1"):
        raise HbmError(f"synthetic_specimen: noise must be 'iid' or 'ar1', got {noise!r}")
    if not (-1.0 < rho < 1.0):
        raise HbmError(f"synthetic_specimen: rho must be in (-1, 1), got {rho!r}")
    if not (noise_sd >= 0 and math.isfinite(noise_sd)):
        raise HbmError(f"synthetic_specimen: noise_sd must be >= 0, got {noise_sd!r}")
    seed_text = _seed_text(seed)
    if isinstance(strain_or_protocol, Loading):
        loading = strain_or_protocol
    elif isinstance(strain_or_protocol, (Specimen, Mapping)) or hasattr(strain_or_protocol, "data_vars"):
        loading = as_specimen(strain_or_protocol).loading
    else:  # a bare strain array: the control path of a specimen without time or tests
        loading = Specimen("synthetic", np.asarray(strain_or_protocol, dtype=float)).loading
    th = _theta_array(model, theta)
    clean = np.asarray(model.stress(loading, th), dtype=float)
    if not np.all(np.isfinite(clean)):
        raise HbmError("synthetic_specimen: the model stress is not finite for these parameters")
    sd = float(noise_sd) * (float(np.max(np.abs(clean))) if relative else 1.0)
    rng = as_generator(seed if not isinstance(seed, (int, np.integer)) else int(seed))
    noise_model = make_noise(noise, history_starts=loading.history_starts)
    q = np.array([[sd, float(rho)]] if noise == "ar1" else [[sd]])
    stress = clean + noise_model.simulate(rng, q)[0]

    meta = {
        "id": "synthetic",
        "provenance": "synthetic",
        "source": "synthetic (hbm.synthetic_specimen)",
        "generator": f"hbm.data.synthetic_specimen (hbm {__version__})",
        "model": model.name,
        "effects": ",".join(model.effect_names),
        "parameters": json.dumps({k: float(v) for k, v in zip(model.parameter_names, th)}),
        "noise": noise,
        "noise_sd": repr(sd),
        "noise_relative": repr(float(noise_sd)) if relative else "",
        "rho": repr(float(rho)) if noise == "ar1" else "0.0",
        "seed": seed_text,
    }
    if not relative:
        del meta["noise_relative"]
    for k, v in (attrs or {}).items():
        meta[k] = _attr_text(k, v)
    return Specimen(meta["id"], loading.strain, loading.time, loading.test,
                    {"stress": Series.known("stress", stress)}, meta)
