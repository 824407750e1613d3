"""The organ's force–elongation response over posterior samples, force levels and extrapolation."""

from __future__ import annotations

import time as _time
from dataclasses import dataclass, field
from typing import Mapping, Sequence

import numpy as np

from ..errors import HbmError
from ..model.core import Model
from .geometry import FusiformGeometry
from .geometry import quadrature_weights
from .stretch import _check_theta, _nominal_fn, _solve_stretch, nominal_stress, tendon_strain


# ---------------------------------------------------------------------------------------------
# the response
# ---------------------------------------------------------------------------------------------
@dataclass
class OrganResponse:
    """Force–elongation response of a fusiform muscle for a population of parameter sets.

    Attributes
    ----------
    forces : ndarray (n_f,)
        Axial force levels (N).
    elongation : ndarray (n, n_f)
        Total elongation (mm): belly + tendons; NaN where :attr:`unreachable`.
    belly_elongation : ndarray (n, n_f)
        ∫(λ − 1) dz of the belly (mm).
    tendon_elongation : ndarray (n_f,)
        Elongation of both tendons (mm), the same for every sample.
    max_strain : ndarray (n, n_f)
        Largest fiber (tissue) strain λ − 1 over the belly sections.
    mid_strain : ndarray (n, n_f)
        Fiber strain at mid-belly (z = L/2).
    unreachable : ndarray (n, n_f) bool
        Some section would need a stretch above ``max_stretch`` (or the force is not in the
        range of the nominal stress).
    non_monotone : ndarray (n,) bool
        The nominal stress of the sample decreases somewhere on [1, max_stretch]: the solution
        returned is *a* root, not necessarily unique.
    z : ndarray (n_sections + 1,)
        Section nodes (mm).
    stretch : ndarray (n, n_sections + 1, n_f) or None
        Fiber stretch field λ(z) when requested.
    geometry : FusiformGeometry
    parameter_names : tuple of str
    excluded_effects : tuple of str
        Model effects not used in the organ (non-elastic stages).
    max_stretch, tol : float
        Solver settings.
    wall_time : float
        Seconds spent in :func:`organ_response`.
    n_iterations : int
        Largest number of polishing iterations over the chunks.
    """

    forces: np.ndarray
    elongation: np.ndarray
    belly_elongation: np.ndarray
    tendon_elongation: np.ndarray
    max_strain: np.ndarray
    mid_strain: np.ndarray
    unreachable: np.ndarray
    non_monotone: np.ndarray
    z: np.ndarray
    geometry: FusiformGeometry
    parameter_names: tuple
    excluded_effects: tuple = ()
    stretch: np.ndarray | None = None
    max_stretch: float = 3.0
    tol: float = 1e-10
    wall_time: float = 0.0
    n_iterations: int = 0
    extra: dict = field(default_factory=dict)

    @property
    def n_samples(self) -> int:
        return self.elongation.shape[0]

    def band(self, probs: Sequence[float] = (0.05, 0.5, 0.95)) -> np.ndarray:
        """Pointwise quantiles of the elongation over samples, shape (len(probs), n_f) (NaN-aware)."""
        import warnings

        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)  # all-NaN columns stay NaN
            return np.nanquantile(self.elongation, np.asarray(probs, dtype=float), axis=0)

    def to_dataset(self, tested_max_strain=None):
        """An :class:`xarray.Dataset` with dims (sample, force[, node]) for storage and plots.

        Variables: elongation, belly_elongation, tendon_elongation, max_strain, mid_strain,
        unreachable (int8), non_monotone (int8), optional stretch and extrapolated (int8, when
        ``tested_max_strain`` is given).  Attributes: geometry as JSON, settings.  Group names
        and files are the business of :mod:`hbm.io`.
        """
        import json

        import xarray as xr

        ds = xr.Dataset(
            {
                "elongation": (("sample", "force"), self.elongation, {"units": "mm"}),
                "belly_elongation": (("sample", "force"), self.belly_elongation, {"units": "mm"}),
                "tendon_elongation": (("force",), self.tendon_elongation, {"units": "mm"}),
                "max_strain": (("sample", "force"), self.max_strain, {"units": "-"}),
                "mid_strain": (("sample", "force"), self.mid_strain, {"units": "-"}),
                "unreachable": (("sample", "force"), self.unreachable.astype(np.int8)),
                "non_monotone": (("sample",), self.non_monotone.astype(np.int8)),
            },
            coords={"force": ("force", self.forces, {"units": "N"}), "node": ("node", self.z, {"units": "mm"})},
            attrs={"geometry": json.dumps(self.geometry.to_dict()), "max_stretch": self.max_stretch,
                   "tol": self.tol, "parameter_names": json.dumps(list(self.parameter_names)),
                   "excluded_effects": json.dumps(list(self.excluded_effects)),
                   "model_assumptions": "slender body, uniaxial fibers along the axis, incompressible, "
                                        "quasi-static passive, elastic stage only, tendons in series"},
        )
        if self.stretch is not None:
            ds["stretch"] = (("sample", "node", "force"), self.stretch)
        if tested_max_strain is not None:
            ds["extrapolated"] = (("sample", "force"),
                                  extrapolation_mask(self, tested_max_strain).astype(np.int8))
            ds.attrs["tested_max_strain"] = json.dumps(np.asarray(tested_max_strain, dtype=float).tolist())
        return ds


def _check_forces(forces) -> np.ndarray:
    forces = np.atleast_1d(np.asarray(forces, dtype=float))
    if forces.ndim != 1 or forces.size == 0:
        raise HbmError(f"forces must be a non-empty 1-D array (N), got shape {forces.shape}")
    if not np.isfinite(forces).all() or (forces < 0).any():
        raise HbmError("forces must be finite and >= 0 N (the slender-body model is tension-only)")
    return forces


def organ_response(model: Model, theta: np.ndarray, geometry: FusiformGeometry, forces: np.ndarray, *,
                   max_stretch: float = 3.0, tol: float = 1e-10, return_stretch: bool = False,
                   quadrature: str | None = None, strict: bool = False, n_grid: int = 129,
                   n_anchors: int = 512, max_iter: int = 300, chunk_elements: int = 2_000_000) -> OrganResponse:
    """Force–elongation response of a fusiform muscle for every parameter set in ``theta``.

    Parameters
    ----------
    model : Model
        Constitutive model; its ``"elastic"`` effects define the tissue law.
    theta : array (n, n_params)
        Parameter sets (e.g. posterior samples), columns in ``model.parameter_names`` order.
    geometry : FusiformGeometry
    forces : array (n_f,)
        Axial force levels (N), >= 0.
    max_stretch : float
        Upper end of the stretch bracket; force levels needing more are flagged unreachable.
    tol : float
        Relative equilibrium tolerance per section: |σ(λ)·A0/λ − F| <= tol·F.  Where rounding
        in the model makes this unreachable (a very steep exponential branch, or forces so
        small that λ − 1 ~ 1e-7) the stretch is instead resolved to a few ulps.
    return_stretch : bool
        Also return the stretch field (n, n_sections + 1, n_f).
    quadrature : {"simpson", "trapezoid"}, optional
        Rule for ∫(λ − 1) dz; default Simpson for an even number of sections, else trapezoid.
    strict : bool
        Raise :class:`HbmError` instead of flagging unreachable forces / non-monotone samples.
    n_grid : int
        Stretch-grid size of the per-sample table (monotonicity check, anchor brackets).
    n_anchors : int
        Anchor stresses solved first per sample; they bracket every section's target.
    max_iter : int
        Cap on polishing iterations.
    chunk_elements : int
        Approximate number of (sample, section, force) unknowns solved per chunk (memory bound).

    Returns
    -------
    OrganResponse

    Notes
    -----
    Sections with equal reference area share their stretch, so only the distinct areas of the
    (symmetric) profile are solved: about n_sections/2 + 1 for a spindle, one for a cylinder.
    Work per chunk: one table of ``n_grid`` stretches per sample, a vectorised binary search,
    and a few regula-falsi evaluations on the unconverged unknowns only.
    """
    t0 = _time.perf_counter()
    theta = _check_theta(model, theta)
    forces = _check_forces(forces)
    if not (np.isfinite(max_stretch) and max_stretch > 1.0):
        raise HbmError(f"max_stretch must be a finite number > 1, got {max_stretch!r}")
    if not (0 < tol < 1e-2):
        raise HbmError(f"tol must be in (0, 0.01), got {tol!r}")
    if n_grid < 3:
        raise HbmError(f"n_grid must be >= 3, got {n_grid}")
    P, excluded = _nominal_fn(model)
    z = geometry.nodes
    rule = quadrature or ("simpson" if geometry.n_sections % 2 == 0 else "trapezoid")
    w = quadrature_weights(z, rule)
    A_nodes = geometry.area(z)
    A_mid = float(geometry.area(np.array([geometry.length / 2]))[0])
    areas, inverse = np.unique(np.append(A_nodes, A_mid), return_inverse=True)
    inv_nodes, i_mid = inverse[:-1], inverse[-1]
    W = np.bincount(inv_nodes, weights=w, minlength=areas.size)  # quadrature weight per distinct area
    i_min = int(np.argmin(areas))
    U, nf, n = areas.size, forces.size, theta.shape[0]
    targets_1 = forces[None, :] / areas[:, None]  # (U, n_f) nominal stress per distinct section

    belly = np.empty((n, nf))
    max_strain = np.empty((n, nf))
    mid_strain = np.empty((n, nf))
    unreachable = np.zeros((n, nf), dtype=bool)
    non_monotone = np.zeros(n, dtype=bool)
    stretch = np.empty((n, z.size, nf)) if return_stretch else None
    rows_per_chunk = max(1, int(chunk_elements) // (U * nf))
    n_iter = 0
    names = model.parameter_names
    for start in range(0, n, rows_per_chunk):  # chunks bound memory; each chunk is vectorised
        sl = slice(start, min(n, start + rows_per_chunk))
        th = theta[sl]
        m = th.shape[0]
        lam, unr, nonmono, it = _solve_stretch(P, th, names, targets_1.ravel(), max_stretch=max_stretch,
                                               tol=tol, n_grid=n_grid, n_anchors=n_anchors, max_iter=max_iter)
        n_iter = max(n_iter, it)
        lam = lam.reshape(m, U, nf)
        unr = unr.reshape(m, U, nf).any(axis=1)
        belly[sl] = np.einsum("u,muf->mf", W, lam - 1.0)
        # λ decreases with the area for a monotone P, so the smallest section strains most; the
        # max over sections also covers non-monotone samples.
        max_strain[sl] = lam.max(axis=1) - 1.0 if nonmono.any() else lam[:, i_min, :] - 1.0
        mid_strain[sl] = lam[:, i_mid, :] - 1.0
        unreachable[sl] = unr
        non_monotone[sl] = nonmono
        if return_stretch:
            stretch[sl] = lam[:, inv_nodes, :]
    for arr in (belly, max_strain, mid_strain):
        arr[unreachable] = np.nan
    if return_stretch:
        stretch[np.broadcast_to(unreachable[:, None, :], stretch.shape)] = np.nan
    if strict and unreachable.any():
        i, j = np.argwhere(unreachable)[0]
        raise HbmError(f"{int(unreachable.sum())} (sample, force) pairs need a stretch above max_stretch = "
                       f"{max_stretch:g} (first: sample {i}, force {forces[j]:.4g} N); lower the forces or "
                       f"raise max_stretch")
    if strict and non_monotone.any():
        raise HbmError(f"{int(non_monotone.sum())} samples have a nominal stress that decreases on "
                       f"[1, {max_stretch:g}]: the section stretch is not unique (first: sample "
                       f"{int(np.argmax(non_monotone))})")
    tendon = geometry.tendon_length * tendon_strain(forces, geometry)
    return OrganResponse(
        forces=forces, elongation=belly + tendon[None, :], belly_elongation=belly, tendon_elongation=tendon,
        max_strain=max_strain, mid_strain=mid_strain, unreachable=unreachable, non_monotone=non_monotone,
        z=z, geometry=geometry, parameter_names=tuple(names), excluded_effects=excluded, stretch=stretch,
        max_stretch=float(max_stretch), tol=float(tol), wall_time=_time.perf_counter() - t0,
        n_iterations=n_iter, extra={"quadrature": rule, "distinct_sections": int(U)})


def theta_from_samples(model: Model, names: Sequence[str], samples: np.ndarray,
                       fixed: Mapping[str, float] | None = None) -> np.ndarray:
    """Model theta (n, n_params) from a sample matrix with named columns.

    Picks the model's parameters by name (noise columns such as ``sigma`` are ignored) and
    fills parameters held fixed during the fit from ``fixed``.

    Parameters
    ----------
    model : Model
    names : sequence of str
        Column names of ``samples`` (e.g. ``SpecimenResult.names``).
    samples : array (n, len(names))
    fixed : mapping name -> value, optional

    Raises
    ------
    HbmError
        A model parameter is neither a column nor fixed, or the shapes disagree.
    """
    samples = np.asarray(samples, dtype=float)
    names = list(names)
    if samples.ndim != 2 or samples.shape[1] != len(names):
        raise HbmError(f"samples must have shape (n, {len(names)}) for columns {names}, got {samples.shape}")
    fixed = dict(fixed or {})
    out = np.empty((samples.shape[0], model.n_params))
    for j, q in enumerate(model.parameter_names):
        if q in names:
            out[:, j] = samples[:, names.index(q)]
        elif q in fixed:
            out[:, j] = float(fixed[q])
        else:
            raise HbmError(f"parameter {q!r} of model {model.name!r} is neither a sample column {names} "
                           f"nor fixed")
    return out


def extrapolation_mask(response: OrganResponse, tested_max_strain) -> np.ndarray:
    """True where the largest tissue strain in the organ exceeds the strain tested on the specimen.

    Parameters
    ----------
    response : OrganResponse
    tested_max_strain : float or array (n,)
        Largest strain of the specimen's data (per sample when the samples come from several
        specimens, e.g. the hierarchical layer's individuals).

    Returns
    -------
    ndarray (n, n_f) bool
        Unreachable points count as extrapolated.
    """
    t = np.asarray(tested_max_strain, dtype=float)
    if t.ndim == 1:
        if t.size != response.n_samples:
            raise HbmError(f"tested_max_strain has {t.size} values for {response.n_samples} samples")
        t = t[:, None]
    elif t.ndim != 0:
        raise HbmError("tested_max_strain must be a scalar or an array (n_samples,)")
    if not np.isfinite(t).all() or (t <= 0).any():
        raise HbmError("tested_max_strain must be finite and > 0")
    with np.errstate(invalid="ignore"):
        return ~(response.max_strain <= t)


def force_levels(model: Model, theta: np.ndarray, geometry: FusiformGeometry, tested_max_strain: float, *,
                 factor: float = 1.5, n_forces: int = 200, where: str = "mid", quantile: float = 0.5,
                 include_zero: bool = True) -> np.ndarray:
    """Force levels from 0 up to where the tissue strain reaches ``factor × tested_max_strain``.

    For sample i the force at which the section ``where`` reaches strain ε* = factor·ε_tested
    is F_i = P_i(1 + ε*)·A0 (exact: no root find needed in this direction).  The common upper
    force is the ``quantile`` of F_i over the samples (0 → the softest sample, 1 → the stiffest).

    Parameters
    ----------
    model, theta, geometry
        As for :func:`organ_response`.
    tested_max_strain : float
        Largest strain in the specimen's data.
    factor : float
        Target strain as a multiple of the tested strain.
    n_forces : int
        Number of force levels.
    where : {"mid", "max"}
        Mid-belly section ("mid") or the most strained (smallest) section ("max").
    quantile : float in [0, 1]
    include_zero : bool
        Start at F = 0 (else at F_max/n_forces).

    Returns
    -------
    ndarray (n_forces,)
    """
    theta = _check_theta(model, theta)
    if not (np.isfinite(tested_max_strain) and tested_max_strain > 0):
        raise HbmError(f"tested_max_strain must be > 0, got {tested_max_strain!r}")
    if where not in ("mid", "max"):
        raise HbmError(f"where must be 'mid' or 'max', got {where!r}")
    if not 0 <= quantile <= 1:
        raise HbmError(f"quantile must be in [0, 1], got {quantile!r}")
    if n_forces < 2:
        raise HbmError(f"n_forces must be >= 2, got {n_forces}")
    if where == "mid":
        area = float(geometry.area(np.array([geometry.length / 2]))[0])
    else:
        area = float(geometry.area(geometry.nodes).min())
    lam = np.array([1.0 + factor * tested_max_strain])
    f_i = nominal_stress(model, theta, lam)[:, 0] * area
    f_max = float(np.quantile(f_i, quantile))
    if not (np.isfinite(f_max) and f_max > 0):
        raise HbmError(f"no positive force reaches strain {factor * tested_max_strain:.3g} (F = {f_max!r})")
    if include_zero:
        return np.linspace(0.0, f_max, n_forces)
    return np.linspace(f_max / n_forces, f_max, n_forces)
