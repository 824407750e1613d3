"""The one type of a specimen: its control path, its tests and its measured series.

A :class:`Specimen` is what :func:`hbm.data.load_specimen` and :func:`hbm.data.synthetic_specimen`
return and what every fit, check, figure and export reads: the applied (engineering) strain with
optional time and test ids -- the *control path*, from which :attr:`Specimen.loading` builds the
model's :class:`~hbm.model.Loading` once -- and the *observed* series measured at its points, each a
:class:`Series` with its name and unit (today one, ``stress``: Cauchy stress along the fibres, MPa).
The rows of a specimen split into contiguous :class:`Test` records; each test carries its load
case (``"uniaxial_f"``: uniaxial tension along the fibres, the only one hbm models today; issue 35
adds load cases and per-test observables such as ``stress_2`` or lateral strains).

A Specimen is frozen and checked when it is built (shapes, dtypes, finite control path, contiguous
tests).  ``Specimen.from_dataset`` / :func:`as_specimen` convert an ``xarray.Dataset`` (older code,
notebooks, a result file's ``observed_data``) once; :meth:`Specimen.to_dataset` gives the xarray
view (xarray is imported only there, so loading a file does not import it).
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from functools import cached_property
from types import MappingProxyType
from typing import Any, Mapping

import numpy as np

from ..errors import DataError
from ..model.core import Loading

__all__ = ["Series", "Test", "Specimen", "as_specimen", "CONTROLS", "OBSERVABLES", "DEFAULT_LOAD_CASE",
           "DEFAULT_ID"]

#: the load case of a test whose file names none: uniaxial tension along the fibres, lateral faces free
DEFAULT_LOAD_CASE = "uniaxial_f"
#: the id of a specimen that names none (a hand-built Dataset without an ``id`` attribute)
DEFAULT_ID = "specimen"
#: the control path's variables -> (unit, long_name), in the order files and Datasets hold them
CONTROLS: dict[str, tuple[str, str]] = {
    "strain": ("-", "engineering strain"),
    "time": ("s", "time"),
    "test": ("-", "protocol segment (test) id"),
}
#: measured quantities hbm knows -> (unit of the loaded data, long_name); a Dataset variable of another
#: name is not an observation (issue 35 adds ``stress_2``, ``strain_f`` ...)
OBSERVABLES: dict[str, tuple[str, str]] = {
    "stress": ("MPa", "Cauchy stress along the fibers"),
}
#: the series whose values :attr:`Specimen.stress` returns (what today's likelihood fits)
MAIN_SERIES = "stress"


def _frozen_array(values, dtype, what: str, n: int | None = None) -> np.ndarray:
    arr = np.array(values, dtype=dtype, copy=True).reshape(-1) if np.ndim(values) else None
    if arr is None:
        raise DataError(f"{what}: expected an array over the specimen's points, got a scalar")
    if n is not None and arr.size != n:
        raise DataError(f"{what}: {arr.size} values, expected {n} (one per point, like the strain)")
    arr.flags.writeable = False   # shared by likelihoods, figures and workers: nobody may edit the data
    return arr


@dataclass(frozen=True, eq=False)
class Series:
    """One measured observable over a specimen's points.

    Attributes
    ----------
    name : str
        Its variable name (``"stress"``; issue 35: ``"stress_2"``, ``"strain_c"`` ...).
    values : ndarray (n_points,)
        float64, read-only; NaN where the quantity was not measured at that point.
    unit : str
        Unit of ``values`` (``"MPa"`` for stresses, ``"-"`` for strains).
    long_name : str
        One line for tables and files.
    """

    name: str
    values: np.ndarray
    unit: str
    long_name: str = ""

    def __post_init__(self) -> None:
        if not isinstance(self.name, str) or not self.name:
            raise DataError(f"a measured series needs a non-empty name, got {self.name!r}")
        object.__setattr__(self, "values", _frozen_array(self.values, np.float64, f"series {self.name!r}"))

    @classmethod
    def known(cls, name: str, values) -> "Series":
        """A series of a known observable (:data:`OBSERVABLES`) with its unit and long name."""
        unit, long_name = OBSERVABLES.get(name, ("", name))
        return cls(name, values, unit, long_name)


@dataclass(frozen=True)
class Test:
    """One test of a specimen: a contiguous range of rows with one load case.

    Attributes
    ----------
    id : int
        The file's test id (0 for a file without a test column: the whole file is one test).
    label : str or None
        The file's label (``load``, ``ramp_0.01`` ...) when the file labels its tests.
    start, stop : int
        Its rows ``start .. stop - 1``.
    load_case : str
        Mode and direction relative to the fibres; ``"uniaxial_f"`` (default): uniaxial tension
        along the fibres.
    """

    __test__ = False  # not a pytest test class

    id: int
    label: str | None
    start: int
    stop: int
    load_case: str = DEFAULT_LOAD_CASE

    @property
    def rows(self) -> slice:
        return slice(self.start, self.stop)

    @property
    def n_points(self) -> int:
        return self.stop - self.start


def _labels(attrs: Mapping[str, Any]) -> list[str] | None:
    text = attrs.get("test_labels")
    if not text:
        return None
    try:
        labels = json.loads(text) if isinstance(text, str) else list(text)
    except (TypeError, ValueError):
        return None
    return [str(x) for x in labels] if isinstance(labels, list) else None


def _derive_tests(test: np.ndarray | None, n: int, attrs: Mapping[str, Any], sid: str) -> tuple[Test, ...]:
    """The contiguous tests of a test-id column (one test without it); refuses a test that reappears."""
    if test is None:
        return (Test(0, None, 0, n),)
    cut = np.flatnonzero(test[1:] != test[:-1]) + 1
    starts, stops = np.r_[0, cut], np.r_[cut, n]
    ids = test[starts]
    if np.unique(ids).size != ids.size:
        again = next(int(t) for i, t in enumerate(ids) if t in ids[:i])
        raise DataError(f"{sid}: test {again} reappears after other tests; expected the rows of each test "
                        "to be contiguous")
    labels = _labels(attrs)
    return tuple(Test(int(t), labels[int(t)] if labels is not None and 0 <= int(t) < len(labels) else None,
                      int(a), int(b)) for t, a, b in zip(ids, starts, stops))


@dataclass(frozen=True, eq=False)
class Specimen:
    """A specimen: control path (strain, time, test), measured series, tests and metadata.

    Parameters
    ----------
    id : str
        Its name (the file's ``# id:`` or stem); also ``attrs["id"]``.
    strain : array (n_points,)
        Applied engineering strain (float64, finite).
    time : array (n_points,), optional
        Seconds (float64, finite).
    test : array (n_points,), optional
        Integer test ids; the rows of each test contiguous.
    observed : mapping name -> Series
        The measured series (``{"stress": Series(...)}``); may be empty (a protocol to simulate).
    attrs : mapping
        The file's ``# key: value`` lines and the loader's conversion records (``units_stress_original``,
        ``test_labels`` ...), ``source_file``; ``id`` is added when missing.
    tests : tuple of Test, optional
        The tests (default: derived from ``test``, labels from ``attrs["test_labels"]``, load case
        ``"uniaxial_f"``); given ones must cover the same rows.

    Raises
    ------
    DataError
        Shapes, dtypes, non-finite control values, non-contiguous tests, an ``attrs["id"]`` that is
        not ``id``.
    """

    id: str
    strain: np.ndarray
    time: np.ndarray | None = None
    test: np.ndarray | None = None
    observed: Mapping[str, Series] = field(default_factory=dict)
    attrs: Mapping[str, Any] = field(default_factory=dict)
    tests: tuple[Test, ...] | None = None

    def __post_init__(self) -> None:
        sid = self.id
        if not isinstance(sid, str) or not sid:
            raise DataError(f"a specimen needs a non-empty string id, got {sid!r}")
        strain = _frozen_array(self.strain, np.float64, f"{sid}: strain")
        n = strain.size
        if n == 0:
            raise DataError(f"{sid}: no points, expected a non-empty strain")
        for name, arr in (("strain", strain), ("time", self.time)):
            if arr is not None and not np.isfinite(np.asarray(arr, float)).all():
                raise DataError(f"{sid}: '{name}' must be finite numbers")
        time = None if self.time is None else _frozen_array(self.time, np.float64, f"{sid}: time", n)
        test = None
        if self.test is not None:
            raw = np.asarray(self.test)
            if raw.dtype.kind not in "iub":
                ok = raw.dtype.kind == "f" and np.isfinite(raw).all() and (raw == np.round(raw)).all()
                if not ok:
                    raise DataError(f"{sid}: 'test' must hold integer test ids")
            test = _frozen_array(raw, np.int64, f"{sid}: test", n)
        observed: dict[str, Series] = {}
        for key, s in dict(self.observed).items():
            if not isinstance(s, Series):
                raise DataError(f"{sid}: observed[{key!r}] must be an hbm.data.Series, got {type(s).__name__}")
            if s.name != key:
                raise DataError(f"{sid}: observed[{key!r}] holds the series {s.name!r}")
            if s.values.size != n:
                raise DataError(f"{sid}: series {key!r} has {s.values.size} values, expected {n} like the strain")
            observed[key] = s
        attrs = dict(self.attrs)
        if "id" not in attrs:
            attrs["id"] = sid
        elif str(attrs["id"]) != sid:
            raise DataError(f"{sid}: attrs['id'] is {attrs['id']!r}, expected the specimen's id")
        derived = _derive_tests(test, n, attrs, sid)
        tests = derived if self.tests is None else tuple(self.tests)
        if [(t.id, t.start, t.stop) for t in tests] != [(t.id, t.start, t.stop) for t in derived]:
            raise DataError(f"{sid}: the given tests do not cover the rows of the test column")
        object.__setattr__(self, "strain", strain)
        object.__setattr__(self, "time", time)
        object.__setattr__(self, "test", test)
        object.__setattr__(self, "observed", MappingProxyType(observed))
        object.__setattr__(self, "attrs", MappingProxyType(attrs))
        object.__setattr__(self, "tests", tests)

    def __reduce__(self):
        # read-only mappings do not pickle: rebuild from plain ones (workers, forked refits)
        return (Specimen, (self.id, self.strain, self.time, self.test, dict(self.observed), dict(self.attrs),
                           self.tests))

    def __repr__(self) -> str:
        series = ", ".join(f"{k} ({s.unit})" for k, s in self.observed.items()) or "no series"
        return f"<Specimen {self.id}: {self.n_points} points, {len(self.tests)} test(s), {series}>"

    # -- what consumers read ------------------------------------------------------------
    @property
    def n_points(self) -> int:
        return int(self.strain.size)

    @cached_property
    def loading(self) -> Loading:
        """The model's :class:`~hbm.model.Loading` of this control path (built once)."""
        return Loading(self.strain, self.time, self.test)

    @property
    def stress(self) -> np.ndarray:
        """The values of the main series (``stress``, Cauchy, MPa).

        Raises
        ------
        DataError
            If the specimen has no stress series (a protocol).
        """
        s = self.observed.get(MAIN_SERIES)
        if s is None:
            raise DataError(f"{self.id}: missing variable 'stress' (need 'strain' and 'stress' along dim 'point')")
        return s.values

    @property
    def has_stress(self) -> bool:
        return MAIN_SERIES in self.observed

    @property
    def source_file(self) -> str:
        """The file it was read from (``""`` when not read from a file)."""
        return str(self.attrs.get("source_file", ""))

    @property
    def load_cases(self) -> tuple[str, ...]:
        """The distinct load cases of its tests, in order of appearance."""
        return tuple(dict.fromkeys(t.load_case for t in self.tests))

    def key_extras(self) -> dict[str, Any]:
        """What the result key hashes beyond today's arrays (:func:`hbm.io.identity.data_key`): the
        series other than ``stress`` and the tests' load cases that are not the default -- empty for
        a specimen with only stress along the fibres, so that its key stays byte for byte the same."""
        extra: dict[str, Any] = {}
        series = {k: {"unit": s.unit, "values": s.values} for k, s in self.observed.items() if k != MAIN_SERIES}
        if series:
            extra["series"] = series
        cases = {str(t.id): t.load_case for t in self.tests if t.load_case != DEFAULT_LOAD_CASE}
        if cases:
            extra["load_cases"] = cases
        return extra

    # -- new specimens from this one ----------------------------------------------------------
    def with_series(self, name: str, values, unit: str | None = None, long_name: str | None = None) -> "Specimen":
        """A copy with the series ``name`` added or replaced (unit and long name of :data:`OBSERVABLES`
        unless given)."""
        default = Series.known(name, values)
        s = Series(name, default.values, default.unit if unit is None else unit,
                   default.long_name if long_name is None else long_name)
        return Specimen(self.id, self.strain, self.time, self.test, {**self.observed, name: s}, self.attrs,
                        self.tests)

    def with_attrs(self, **attrs: Any) -> "Specimen":
        """A copy with some metadata replaced (``id=`` renames the specimen)."""
        new = {**self.attrs, **attrs}
        return Specimen(str(new["id"]), self.strain, self.time, self.test, self.observed, new, self.tests)

    def select(self, rows) -> "Specimen":
        """The specimen restricted to ``rows`` (a boolean mask or indices, in order); tests re-derived."""
        idx = np.arange(self.n_points)[rows]
        pick = (lambda a: None if a is None else a[idx])  # noqa: E731
        return Specimen(self.id, self.strain[idx], pick(self.time), pick(self.test),
                        {k: Series(s.name, s.values[idx], s.unit, s.long_name) for k, s in self.observed.items()},
                        self.attrs)

    # -- xarray --------------------------------------------------------------------------------
    def to_dataset(self):
        """The xarray view: dim ``point``; ``strain``, the series, ``time``, ``test`` with ``units`` and
        ``long_name``; the attributes."""
        import xarray as xr  # only here: loading and fitting a file never import xarray for it

        def var(values, unit, long_name):
            return xr.Variable("point", np.array(values), {"units": unit, "long_name": long_name})

        variables = {"strain": var(self.strain, *CONTROLS["strain"])}
        for name, s in self.observed.items():
            variables[name] = var(s.values, s.unit, s.long_name)
        for name in ("time", "test"):
            arr = getattr(self, name)
            if arr is not None:
                variables[name] = var(arr, *CONTROLS[name])
        return xr.Dataset(variables, attrs=dict(self.attrs))

    @classmethod
    def from_dataset(cls, ds, *, id: str | None = None) -> "Specimen":  # noqa: A002 - the field's name
        """A Specimen from an ``xarray.Dataset`` (or a mapping of arrays) with ``strain`` along dim
        ``point`` and, optionally, ``time``, ``test`` and the measured series of :data:`OBSERVABLES`
        (other variables are not observations and are left out).

        Raises
        ------
        DataError
            Without ``strain``, or with arrays that are not a specimen.
        """
        attrs = dict(getattr(ds, "attrs", {}) or {})
        sid = str(id if id is not None else attrs.get("id", DEFAULT_ID))
        attrs["id"] = sid
        try:
            names = list(getattr(ds, "data_vars", ds)) + list(getattr(ds, "coords", ()))
        except TypeError:
            raise DataError(f"a specimen must be an xarray.Dataset or a mapping of arrays, got {type(ds).__name__}") \
                from None
        if "strain" not in names:
            raise DataError(f"{sid}: missing variable 'strain' (need 'strain' and 'stress' along dim 'point')")

        def values(name):
            return np.asarray(ds[name]).ravel()

        observed = {}
        for name in names:
            if name in OBSERVABLES:
                v = ds[name]
                unit, long_name = OBSERVABLES[name]
                va = getattr(v, "attrs", {}) or {}
                observed[name] = Series(name, np.asarray(v, dtype=float).ravel(), str(va.get("units", unit)),
                                        str(va.get("long_name", long_name)))
        strain = np.asarray(ds["strain"], dtype=float).ravel()
        for name, s in observed.items():
            if s.values.size != strain.size:
                raise DataError(f"{sid}: 'strain' and {name!r} must be of equal length, got {strain.size} and "
                                f"{s.values.size}")
        return cls(sid, strain, values("time").astype(float) if "time" in names else None,
                   values("test") if "test" in names else None, observed, attrs)


def as_specimen(obj) -> Specimen:
    """``obj`` as a :class:`Specimen`: itself, or converted once from an ``xarray.Dataset`` or a
    mapping of arrays (:meth:`Specimen.from_dataset`).

    Raises
    ------
    DataError
        For anything that is not a specimen.
    """
    if isinstance(obj, Specimen):
        return obj
    return Specimen.from_dataset(obj)
