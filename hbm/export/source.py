"""What an export starts from: a result file read into a law (parameters) or a curve (quantiles).

A *summary* turns a posterior into one thing an FE model can hold:

``median``      the posterior draw whose noise-free stress curve is closest (max abs. difference
                over the tested range) to the pointwise median curve -- a real parameter set, not
                a vector of marginal medians (those need not be a parameter set the data support);
``p05``/``p95`` the pointwise 5 %/95 % quantile *curves* of the posterior predictive noise-free
                stress (``stress_model``), computed on a strain grid; for a card that needs
                parameters, the draw nearest to that curve (its distance is reported);
``population``  the hierarchical result's new-specimen predictive: the draw nearest to its
                pointwise median curve (a typical new specimen, not the mean specimen);
``draws:N``     N posterior draws (every n/N-th of the equal-weight population; csv/json only).

Only this module knows how a result file is read for export; the formats get an :class:`ExportSource`,
and read the parameters through the base model's export map (:attr:`hbm.model.spec.ModelSpec.export`:
:meth:`ExportSource.constituents`), never by name.
"""

from __future__ import annotations

import re
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .._version import __version__
from ..errors import HbmError
from ..io import read_attrs, read_hierarchical, read_specimen_result
from ..io.conventions import udunits
from ..model.spec import BASES, Constituents, ModelSpec, base_spec, spec_of


def base_names(spec: ModelSpec) -> tuple[str, ...]:
    """The base's parameters in model order (the columns of the exported draws)."""
    return spec.parameter_names


def base_units(spec: ModelSpec) -> dict[str, str]:
    """UDUNITS unit of each base parameter."""
    return {p.name: udunits(p.unit) for p in spec.parameters}


#: the default base's parameters in model order, and their UDUNITS units
NAMES: tuple[str, ...] = base_names(base_spec())
UNITS: dict[str, str] = base_units(base_spec())
#: Strain-grid size of the curves on 1.5x the tested range; tables hold every other point
#: (:attr:`ExportSource.table`), the checks use all of them (so half fall between table points).
GRID = 1201
SUMMARIES = ("median", "p05", "p95", "population")
#: unit system of every exported file
UNIT_SYSTEM = "stress MPa, length mm, force N, time s (MPa = N/mm^2)"


@dataclass
class ExportSource:
    """A result file read for export.

    Attributes
    ----------
    path : Path
    specimen : str
        Specimen id (``population`` for a hierarchical result).
    form : {"thesis", "energy"}
    k_iso : float
    strain_range : (float, float)
        Tested engineering-strain range [min(0, ε_min), ε_max].
    draws : ndarray (n, 8)
        Posterior (or new-specimen) draws of the eight base parameters, model order.
    summary : str
    theta : ndarray (8,)
        The summary's parameter set (see module docstring).
    curve_strain, curve_stress : ndarray (m,)
        hbm's curve of the summary on 1.5x the tested range (Cauchy stress along the fibres, MPa).
    nearest_gap : float
        For quantile summaries: max |σ(theta) − quantile curve| / max|quantile curve| over the tested
        range (0 for median/population, where theta is the stated choice itself).
    """

    path: Path
    specimen: str
    form: str
    k_iso: float
    strain_range: tuple[float, float]
    draws: np.ndarray
    summary: str
    theta: np.ndarray
    curve_strain: np.ndarray
    curve_stress: np.ndarray
    nearest_gap: float = 0.0
    notes: list[str] = field(default_factory=list)
    n_draws: int = 0
    quantile: float | None = None
    spec: ModelSpec = field(default_factory=base_spec)

    @property
    def names(self) -> tuple[str, ...]:
        """The base's parameters: the columns of ``draws`` and ``theta``."""
        return base_names(self.spec)

    @property
    def units(self) -> dict[str, str]:
        return base_units(self.spec)

    def params(self, theta=None) -> dict[str, float]:
        """name -> value of ``theta`` (default the summary's)."""
        t = self.theta if theta is None else theta
        return {n: float(v) for n, v in zip(self.names, t)}

    def constituents(self, theta=None) -> Constituents:
        """What a card reads from ``theta`` (default the summary's; rows (n, d) give arrays (n,)): the
        base's export map."""
        t = self.theta if theta is None else np.asarray(theta, float)
        if t.ndim == 2:
            return self.spec.export.constituents({n: t[:, i] for i, n in enumerate(self.names)})
        return self.spec.export.constituents(self.params(t))

    def model(self):
        """hbm's model of this result."""
        return _base_model(self.spec, self.k_iso, self.form)

    def stress(self, strain, theta=None) -> np.ndarray:
        """hbm's Cauchy stress (MPa) of ``theta`` (default the summary's) at ``strain``."""
        t = self.theta if theta is None else np.asarray(theta, float)
        return self.model().stress(np.asarray(strain, float), t)

    def provenance(self) -> dict[str, object]:
        """What every exported file carries."""
        return {"hbm_version": __version__, "source": str(self.path), "specimen": self.specimen,
                "form": self.form, "k_iso": self.k_iso,
                "tested_strain_range": [float(self.strain_range[0]), float(self.strain_range[1])],
                "summary": self.summary, "units": UNIT_SYSTEM}

    def table(self) -> tuple[np.ndarray, np.ndarray]:
        """(strain, stress) the curve cards tabulate: every other point of the curve grid plus the
        kinks of the summary's draw (zero strain, fibre onset EOPT, collagen onset λ* − 1), so that
        a linear table does not cut the corners there."""
        kinks = self.spec.export.kinks(self.params())
        lo, hi = self.curve_strain[0], self.curve_strain[-1]
        strain = np.unique(np.concatenate([self.curve_strain[::2], [k for k in kinks if lo < k < hi]]))
        if self.quantile is None:
            return strain, self.stress(strain)
        return strain, np.quantile(self.model().stress(strain, self.draws), self.quantile, axis=0)

    def reference(self) -> tuple[np.ndarray, np.ndarray]:
        """(strain, stress) a curve card is checked against.  For a parameter set: hbm's curve on the
        full grid (half of it between table points).  For a quantile curve: the quantile at the
        table's points -- the pointwise quantile of a finite posterior switches between draws
        (each with its own fibre onset) and is not smooth at the grid scale, so between table
        points it is defined by the card's interpolation, not by hbm."""
        if self.quantile is None:
            return self.curve_strain, self.curve_stress
        return self.table()

    def in_tested(self, strain) -> np.ndarray:
        """Mask of ``strain`` inside the tested range."""
        lo, hi = self.strain_range
        return (strain >= lo - 1e-12) & (strain <= hi + 1e-12)

    def tested_mask(self) -> np.ndarray:
        lo, hi = self.strain_range
        return (self.curve_strain >= lo - 1e-12) & (self.curve_strain <= hi + 1e-12)


def parse_model_name(name: str) -> tuple[str, float]:
    """(form, k_iso) from a stored model name such as ``spyrou(k_iso=0.6667, form=energy)``.

    The name keeps k_iso to 4 significant digits; 0.6667 is read as 2/3 (the only other k_iso the
    CLI offers), any other value as written.
    """
    m = re.fullmatch(r"spyrou(?:\((.*)\))?", name.strip())
    if m is None:
        raise HbmError(f"model {name!r} is not the Spyrou model; only its base form can be exported")
    form, k_iso = "thesis", 1.0
    for part in filter(None, (s.strip() for s in (m.group(1) or "").split(","))):
        key, _, val = part.partition("=")
        if key == "form":
            form = val
        elif key == "k_iso":
            k_iso = float(val)
            if abs(k_iso - 2.0 / 3.0) < 1e-4:
                k_iso = 2.0 / 3.0
        else:
            raise HbmError(f"model {name!r}: unknown option {key!r}")
    return form, k_iso


def parse_summary(text: str) -> tuple[str, int]:
    """``("draws", N)`` or ``(name, 0)``; raises HbmError naming --summary."""
    if text in SUMMARIES:
        return text, 0
    m = re.fullmatch(r"draws:(\d+)", text)
    if m and int(m.group(1)) >= 1:
        return "draws", int(m.group(1))
    raise HbmError(f"--summary {text!r}: expected one of {', '.join(SUMMARIES)} or draws:N (N >= 1)")


def _base_model(spec: ModelSpec, k_iso: float, form: str):
    """The base model of a result (its registered factory) with the card's k_iso and form."""
    return BASES[spec.name][1](iso_factor=k_iso, form=form)


def _base_draws(result, spec: ModelSpec) -> np.ndarray:
    cols = result.as_dict()
    names = base_names(spec)
    missing = [n for n in names if n not in cols]
    if missing:
        raise HbmError(f"{result.specimen_id}: parameters {missing} missing from the result")
    return np.column_stack([cols[n] for n in names])


def _check_effects(effects, path, spec: ModelSpec) -> None:
    if spec.export is None:
        raise HbmError(f"{path}: the base model {spec.name!r} declares no export map (how an FE card reads its "
                       "parameters); nothing to export")
    extra = [e for e in effects if e not in spec.effects]
    if extra:
        raise HbmError(f"{path}: the model has effects {extra} beyond {list(spec.effects)}; an FE card "
                       f"holds only the base {spec.name} model")


def _strain(result, path) -> np.ndarray:
    """The tested strains of a specimen result (its observed specimen)."""
    if result.data is None:
        raise HbmError(f"{path}: the result holds no observed data (needed for the tested strain range)")
    return result.data.strain


def _grid(strain_range) -> np.ndarray:
    lo, hi = strain_range
    return np.linspace(1.5 * lo, 1.5 * hi, GRID)


def _nearest(curves: np.ndarray, target: np.ndarray, mask: np.ndarray) -> tuple[int, float]:
    gap = np.max(np.abs(curves[:, mask] - target[mask]), axis=1)
    i = int(np.argmin(gap))
    return i, float(gap[i] / max(np.max(np.abs(target[mask])), 1e-300))


def median_draw(draws: np.ndarray, form: str, k_iso: float, strain_range, spec: ModelSpec | None = None) -> int:
    """Index of the draw whose curve is nearest (max abs.) the pointwise median curve on the tested range."""
    strain = np.linspace(strain_range[0], strain_range[1], GRID)
    curves = _base_model(spec or base_spec(), k_iso, form).stress(strain, draws)
    return _nearest(curves, np.median(curves, axis=0), np.ones(strain.size, bool))[0]


def load_source(path: str | Path, summary: str) -> ExportSource:
    """Read ``path`` (a specimen result or ``hierarchical.nc``) and apply ``summary``.

    Raises
    ------
    HbmError
        Unreadable file, a model with extra effects, ``population`` on a specimen result
        (or another summary on a hierarchical one).
    """
    path = Path(path)
    kind, n_req = parse_summary(summary)
    if not path.is_file():
        raise HbmError(f"{path}: no such result file")
    attrs = read_attrs(path)
    if not attrs:
        raise HbmError(f"{path}: not a readable hbm result file")
    notes: list[str] = []
    if "param_names" in attrs:  # hierarchical.nc
        if kind != "population":
            raise HbmError(f"{path} is a hierarchical result: use --summary population")
        h = read_hierarchical(path)
        if h.new_specimen is None:
            raise HbmError(f"{path}: no new-specimen predictive stored")
        sibs = sorted((path.parent / "specimens").glob("*.nc"))
        if not sibs:
            raise HbmError(f"{path}: no specimens/*.nc beside it to read the model form and strain range from")
        lo, hi, model_name, spec = 0.0, 0.0, None, None
        for s in sibs:
            r = read_specimen_result(s)
            spec = spec or spec_of(r)
            _check_effects(r.effects, s, spec)
            lo, hi = min(lo, float(np.min(_strain(r, s)))), max(hi, float(np.max(_strain(r, s))))
            model_name = model_name or r.model
        cols = h.pooled_names or h.param_names
        missing = [n for n in base_names(spec) if n not in cols]
        if missing:
            raise HbmError(f"{path}: new-specimen predictive lacks {missing}")
        draws = np.column_stack([h.new_specimen[:, cols.index(n)] for n in base_names(spec)])
        form, k_iso = parse_model_name(model_name)
        specimen = "population"
        notes.append(f"tested range: union of the {len(sibs)} specimens' strain ranges")
    else:
        if kind == "population":
            raise HbmError(f"{path} is a specimen result: --summary population needs hierarchical.nc")
        r = read_specimen_result(path)
        spec = spec_of(r)
        _check_effects(r.effects, path, spec)
        form, k_iso = parse_model_name(r.model)
        draws = _base_draws(r, spec)
        lo, hi = min(0.0, float(np.min(_strain(r, path)))), float(np.max(_strain(r, path)))
        specimen = r.specimen_id
    if hi <= 0:
        raise HbmError(f"{path}: no tensile strain in the data; nothing to export along the fibres")
    strain = _grid((lo, hi))
    model = _base_model(spec, k_iso, form)
    curves = model.stress(strain, draws)  # (n, m): vectorised over the population
    mask = (strain >= lo - 1e-12) & (strain <= hi + 1e-12)
    src = ExportSource(path=path, specimen=specimen, form=form, k_iso=k_iso, strain_range=(lo, hi), draws=draws,
                       summary=summary, theta=draws[0], curve_strain=strain, curve_stress=curves[0], notes=notes,
                       n_draws=draws.shape[0], spec=spec)
    if kind in ("median", "population", "draws"):
        i, _ = _nearest(curves, np.median(curves, axis=0), mask)
        src.theta, src.curve_stress = draws[i], curves[i]
        if kind == "draws":
            take = np.linspace(0, draws.shape[0] - 1, min(n_req, draws.shape[0])).round().astype(int)
            src.draws = draws[take]
            if n_req > draws.shape[0]:
                notes.append(f"draws:{n_req} asked, the result holds {draws.shape[0]}: all written")
    else:
        src.quantile = 0.05 if kind == "p05" else 0.95
        q = np.quantile(curves, src.quantile, axis=0)
        i, gap = _nearest(curves, q, mask)
        src.theta, src.curve_stress, src.nearest_gap = draws[i], q, gap
    return src
