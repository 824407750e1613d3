"""Specimen stress–strain curves: CSV (+ metadata) <-> xarray.Dataset, validation, synthetic data.

CSV format
----------
::

    # id: calvo2010_rat1                  <- optional metadata, ``# key: value``, only at the top
    # source: synthetic stand-in for ...
    strain,stress,time,test               <- header: strain and stress required, any column order
    0.0,0.0012,0.0,1
    0.01,0.0031,45.45,1
    ...

* ``strain`` — engineering strain ε = ΔL/L0 (dimensionless), within [−0.5, 2].
* ``stress`` — Cauchy (true) stress along the fibers in MPa.
* ``time`` (optional) — seconds.
* ``test`` (optional) — integer id of a protocol segment (a ramp, a hold, an unloading ...).
  The rows of one test must be contiguous.

Rules for ``time`` (DESIGN.md §2).  Inside a test, time is non-decreasing.  At the first row
of a new test, time either *continues* (≥ the previous row's time): the new test is the next
segment of the same loading history (load → unload → reload, ramp → relaxation hold), and
history-dependent effects see what came before; or it *restarts at exactly 0*: the new test
starts from rest, a new loading history.  Any other drop in time is an error.  Without a
``test`` column, time must be non-decreasing over the whole file (one history).  Without a
``time`` column, every test is its own history (see :class:`hbm.Loading`).

Metadata lines must come before the header and look like ``# key: value`` (key: letters,
digits, ``_ . -``; each key once).  Blank lines are ignored.  ``id`` names the specimen
(default: the file stem); ``provenance`` is ``synthetic`` or ``measured``.

Every problem raises :class:`hbm.errors.DataError` with a one-line message naming the file,
the line (and column) and what was expected.
"""

from __future__ import annotations

import csv
import io
import json
import math
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Mapping, Sequence

import numpy as np
import xarray as xr

from ._version import __version__
from .errors import DataError, HbmError
from .model.core import Loading, Model
from .noise import make_noise
from .utils import atomic_path, as_generator

__all__ = [
    "STRAIN_RANGE", "MIN_POINTS", "load_specimen", "load_specimens", "save_specimen",
    "specimen_loading", "provenance", "synthetic_specimen", "Segment", "ramp", "hold", "cycle",
    "protocol",
]

#: allowed engineering strain (catches percent-vs-fraction mix-ups)
STRAIN_RANGE = (-0.5, 2.0)
#: minimum number of data points in a specimen
MIN_POINTS = 5

_COLUMNS = ("strain", "stress", "time", "test")
_UNITS = {"strain": "-", "stress": "MPa", "time": "s", "test": "-"}
_LONG = {"strain": "engineering strain", "stress": "Cauchy stress along the fibers",
         "time": "time", "test": "protocol segment (test) id"}
_META_RE = re.compile(r"^#\s*([A-Za-z_][A-Za-z0-9_.\-]*)\s*:\s?(.*)$")
_KEY_RE = re.compile(r"^[A-Za-z_][A-Za-z0-9_.\-]*$")


# ---------------------------------------------------------------------------------------
# reading
# ---------------------------------------------------------------------------------------
def _number(cell: str, where: str, *, integer: bool = False) -> float | int:
    text = cell.strip()
    try:
        value = int(text) if integer else float(text)
    except ValueError:
        if integer:
            try:  # accept "3.0" as an integer test id, not "3.5"
                f = float(text)
                if math.isfinite(f) and f == int(f):
                    return int(f)
            except ValueError:
                pass
            raise DataError(f"{where}: expected an integer test id, got {text!r}") from None
        raise DataError(f"{where}: expected a number, got {text!r}") from None
    if not integer and not math.isfinite(value):
        raise DataError(f"{where}: expected a finite number, got {text!r}")
    return value


def _is_float(text: str) -> bool:
    try:
        float(text)
    except ValueError:
        return False
    return True


def load_specimen(path: str | Path) -> xr.Dataset:
    """Read and validate one specimen CSV.

    Parameters
    ----------
    path : str or Path
        CSV file in the format described in the module docstring.

    Returns
    -------
    xarray.Dataset
        Dimension ``point``; variables ``strain``, ``stress`` (MPa) and, when present,
        ``time`` (s) and ``test`` (int).  Attributes: the metadata (strings), ``id``
        (metadata ``id`` or the file stem) and ``source_file``.

    Raises
    ------
    DataError
        One-line message naming the file, line (and column) and the expectation.
    """
    path = Path(path)
    name = str(path)
    try:
        text = path.read_text(encoding="utf-8-sig")
    except FileNotFoundError:
        raise DataError(f"{name}: file not found") from None
    except IsADirectoryError:
        raise DataError(f"{name}: is a directory, expected a CSV file") from None
    except UnicodeDecodeError as exc:
        raise DataError(f"{name}: not a UTF-8 text file ({exc.reason} at byte {exc.start})") from None
    except OSError as exc:
        raise DataError(f"{name}: cannot read ({exc.strerror})") from None
    if not text.strip():
        raise DataError(f"{name}: empty file, expected '# key: value' metadata lines and a "
                        "header with strain,stress")

    attrs: dict[str, str] = {}
    meta_line: dict[str, int] = {}
    header: list[str] | None = None
    header_lineno = 0
    cols: dict[str, int] = {}
    rows: list[tuple[int, list[str]]] = []
    for lineno, line in enumerate(text.splitlines(), start=1):
        if not line.strip():
            continue
        if line.lstrip().startswith("#"):
            if header is not None:
                raise DataError(f"{name}: line {lineno}: expected a data row, got a '#' line after "
                                f"the header (metadata '# key: value' lines go before the header)")
            m = _META_RE.match(line.strip())
            if not m:
                raise DataError(f"{name}: line {lineno}: unknown metadata format {line.strip()!r}, "
                                "expected '# key: value'")
            key, value = m.group(1), m.group(2).strip()
            if key in attrs:
                raise DataError(f"{name}: line {lineno}: metadata key {key!r} repeated "
                                f"(first on line {meta_line[key]})")
            attrs[key], meta_line[key] = value, lineno
            continue
        cells = next(csv.reader([line]))
        if header is None:
            if all(_is_float(c) for c in cells):
                raise DataError(f"{name}: line {lineno}: expected a header with strain,stress before the data, "
                                f"got a numeric row {line.strip()!r}")
            header, header_lineno = [c.strip().lower() for c in cells], lineno
            for j, col in enumerate(header):
                if col not in _COLUMNS:
                    raise DataError(f"{name}: line {lineno}, column {j + 1}: unknown column {cells[j].strip()!r}, "
                                    f"expected one of {', '.join(_COLUMNS)}")
                if col in cols:
                    raise DataError(f"{name}: line {lineno}, column {j + 1}: duplicate column name "
                                    f"{col!r} (also column {cols[col] + 1})")
                cols[col] = j
            for need in ("strain", "stress"):
                if need not in cols:
                    raise DataError(f"{name}: line {lineno}: header has no {need!r} column, expected "
                                    f"columns strain,stress[,time][,test], got {line.strip()!r}")
            continue
        if [c.strip().lower() for c in cells] == header:
            raise DataError(f"{name}: line {lineno}: duplicate header (first on line {header_lineno}), "
                            "expected a data row")
        if len(cells) != len(header):
            raise DataError(f"{name}: line {lineno}: ragged row with {len(cells)} cells, expected "
                            f"{len(header)} like the header on line {header_lineno}")
        rows.append((lineno, cells))

    if header is None:
        raise DataError(f"{name}: no header line, expected a header with strain,stress after the metadata")
    if len(rows) < MIN_POINTS:
        raise DataError(f"{name}: {len(rows)} data rows, expected at least {MIN_POINTS} points")

    data: dict[str, np.ndarray] = {}
    for col, j in cols.items():
        integer = col == "test"
        vals = [_number(cells[j], f"{name}: line {lineno}, column {col!r}", integer=integer)
                for lineno, cells in rows]
        data[col] = np.asarray(vals, dtype=np.int64 if integer else float)
    linenos = [ln for ln, _ in rows]

    lo, hi = STRAIN_RANGE
    bad = np.flatnonzero((data["strain"] < lo) | (data["strain"] > hi))
    if bad.size:
        i = bad[0]
        raise DataError(f"{name}: line {linenos[i]}, column 'strain': expected engineering strain in "
                        f"[{lo}, {hi}] (a fraction, not percent), got {data['strain'][i]!r}")
    _check_tests_and_time(name, data.get("time"), data.get("test"), linenos)

    attrs.setdefault("id", path.stem)
    attrs["source_file"] = str(path)
    return _dataset(data, attrs)


def _check_tests_and_time(name: str, time: np.ndarray | None, test: np.ndarray | None,
                          linenos: Sequence[int]) -> None:
    n = len(linenos)
    if test is not None:
        seen: dict[int, int] = {}
        for i in range(n):
            t = int(test[i])
            if i and t != test[i - 1] and t in seen:
                raise DataError(f"{name}: line {linenos[i]}, column 'test': test {t} reappears after "
                                f"other tests (first block ends before line {linenos[seen[t]]}), expected "
                                "the rows of each test to be contiguous")
            seen.setdefault(t, i)
    if time is None:
        return
    drops = np.flatnonzero(np.diff(time) < 0) + 1
    for i in drops:
        new_test = test is not None and test[i] != test[i - 1]
        if new_test and time[i] == 0.0:
            continue  # a new test that starts from rest: a new loading history
        where = f"{name}: line {linenos[i]}, column 'time'"
        if new_test:
            raise DataError(f"{where}: time drops from {time[i - 1]!r} to {time[i]!r} at the start of test "
                            f"{test[i]}; expected it to continue (>= {time[i - 1]!r}, same loading history) "
                            "or to restart at exactly 0 (new history from rest)")
        raise DataError(f"{where}: decreasing time ({time[i - 1]!r} -> {time[i]!r}); expected non-decreasing "
                        "time within a test (time may restart at 0 only where a new test starts)")


def _dataset(data: Mapping[str, np.ndarray], attrs: Mapping[str, str]) -> xr.Dataset:
    variables = {}
    for col in _COLUMNS:
        if col in data:
            variables[col] = xr.Variable("point", np.asarray(data[col]),
                                         {"units": _UNITS[col], "long_name": _LONG[col]})
    return xr.Dataset(variables, attrs=dict(attrs))


def load_specimens(folder: str | Path) -> dict[str, xr.Dataset]:
    """Load every ``*.csv`` in ``folder`` (not recursive).

    Returns
    -------
    dict
        ``id -> Dataset`` sorted by id.

    Raises
    ------
    DataError
        If the folder is missing or has no CSV, a file is malformed, or two files share an id.
    """
    folder = Path(folder)
    if not folder.is_dir():
        raise DataError(f"{folder}: not a directory, expected a folder of specimen CSV files")
    files = sorted(folder.glob("*.csv"))
    if not files:
        raise DataError(f"{folder}: no *.csv files, expected at least one specimen file")
    out: dict[str, xr.Dataset] = {}
    for f in files:
        ds = load_specimen(f)
        sid = ds.attrs["id"]
        if sid in out:
            raise DataError(f"{f}: duplicate specimen id {sid!r} (also in {out[sid].attrs['source_file']}), "
                            "expected unique ids (metadata 'id' or file stem)")
        out[sid] = ds
    return dict(sorted(out.items()))


# ---------------------------------------------------------------------------------------
# writing
# ---------------------------------------------------------------------------------------
def _attr_text(key: str, value: Any) -> str:
    if isinstance(value, str):
        text = value
    elif isinstance(value, (np.ndarray, list, tuple, dict)):
        text = json.dumps(np.asarray(value).tolist() if isinstance(value, np.ndarray) else value)
    else:
        text = str(value.item() if isinstance(value, np.generic) else value)
    if "\n" in text or "\r" in text:
        raise HbmError(f"attribute {key!r}: metadata values must be one line, got {text[:40]!r}...")
    return text


def save_specimen(ds: xr.Dataset, path: str | Path) -> Path:
    """Write a specimen Dataset to CSV atomically; :func:`load_specimen` reads it back exactly.

    Attributes become ``# key: value`` metadata lines (except ``source_file``); floats are
    written with ``repr`` (shortest string that round-trips).

    Parameters
    ----------
    ds : xarray.Dataset
        With ``strain`` and ``stress`` over dim ``point``, optional ``time`` and ``test``.
    path : str or Path
        Destination (parent folders are created).

    Returns
    -------
    Path
    """
    path = Path(path)
    for need in ("strain", "stress"):
        if need not in ds:
            raise HbmError(f"save_specimen: dataset has no {need!r} variable")
    cols = [c for c in _COLUMNS if c in ds]
    arrays = {c: np.asarray(ds[c].values).ravel() for c in cols}
    n = arrays["strain"].size
    for c, a in arrays.items():
        if a.size != n:
            raise HbmError(f"save_specimen: variable {c!r} has {a.size} values, strain has {n}")
    buf = io.StringIO()
    for key, value in ds.attrs.items():
        if key == "source_file":
            continue
        if not _KEY_RE.match(str(key)):
            raise HbmError(f"save_specimen: attribute name {key!r} is not a valid metadata key")
        buf.write(f"# {key}: {_attr_text(key, value)}\n")
    buf.write(",".join(cols) + "\n")
    fmt = {c: (lambda v: str(int(v))) if c == "test" else (lambda v: repr(float(v))) for c in cols}
    for i in range(n):
        buf.write(",".join(fmt[c](arrays[c][i]) for c in cols) + "\n")
    with atomic_path(path) as tmp:
        tmp.write_text(buf.getvalue(), encoding="utf-8")
    return path


# ---------------------------------------------------------------------------------------
# helpers for consumers
# ---------------------------------------------------------------------------------------
def specimen_loading(ds: xr.Dataset | Loading) -> Loading:
    """The :class:`hbm.Loading` (strain, time, test) of a specimen or protocol Dataset."""
    if isinstance(ds, Loading):
        return ds
    time = np.asarray(ds["time"].values, dtype=float) if "time" in ds else None
    test = np.asarray(ds["test"].values) if "test" in ds else None
    return Loading(np.asarray(ds["strain"].values, dtype=float), time, test)


def provenance(ds: xr.Dataset) -> str:
    """``"synthetic"``, ``"measured"`` or ``"unknown"`` from the ``provenance``/``source`` metadata."""
    prov = str(ds.attrs.get("provenance", "")).strip().lower()
    if prov:
        return prov
    source = str(ds.attrs.get("source", "")).lower()
    if "synthetic" in source:
        return "synthetic"
    return "measured" if source else "unknown"


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


def protocol(*histories: Segment | Sequence[Segment], first_test: int = 1) -> xr.Dataset:
    """Concatenate loading histories into a protocol Dataset (strain, time, test).

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
    return _dataset({"strain": np.concatenate(strain), "time": np.concatenate(time),
                     "test": np.concatenate(test)}, {"id": "protocol", "provenance": "synthetic"})


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
                       attrs: Mapping[str, Any] | None = None) -> xr.Dataset:
    """A labelled synthetic specimen: model stress plus Gaussian noise.

    Parameters
    ----------
    model : Model
        Generating model (may include effects, e.g. a hidden effect).
    theta : array (n_params,) or mapping name -> value
        Generating parameters; with a mapping, parameters of added effects that are not given
        take their null values.
    strain_or_protocol : array (n_points,), Loading or Dataset
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
    xarray.Dataset
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
    if isinstance(strain_or_protocol, (xr.Dataset, Loading)):
        loading = specimen_loading(strain_or_protocol)
    else:
        loading = Loading(np.asarray(strain_or_protocol, dtype=float))
    th = _theta_array(model, theta)
    clean = np.asarray(model.stress(loading, th), dtype=float)
    if not np.all(np.isfinite(clean)):
        raise HbmError("synthetic_specimen: the model stress is not finite for these parameters")
    sd = float(noise_sd) * (float(np.max(np.abs(clean))) if relative else 1.0)
    rng = as_generator(seed if not isinstance(seed, (int, np.integer)) else int(seed))
    noise_model = make_noise(noise, history_starts=loading.history_starts)
    q = np.array([[sd, float(rho)]] if noise == "ar1" else [[sd]])
    stress = clean + noise_model.simulate(rng, q)[0]

    data = {"strain": loading.strain.copy(), "stress": stress}
    if loading.time is not None:
        data["time"] = loading.time.copy()
    if loading.test is not None:
        data["test"] = np.asarray(loading.test, dtype=np.int64)
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
    return _dataset(data, meta)
