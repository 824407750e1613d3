"""What a specimen's tests identify: a linearised (Fisher) analysis across loading modes (issue 35, item 5).

At one point of the sampling space (:func:`linearised_identifiability`; a fit passes its highest-likelihood
draw, :func:`fit_point`) the Jacobian J_s of every measured series s with respect to the free model
parameters (and the per-test stress scales, when fitted) is taken in the *sampling* coordinates
(``ModesLikelihood.names``: natural units for uniform priors, logs for log-uniform ones) by central
finite differences -- all ±h perturbations in **one** batched ``predict_series`` call.  Per test t::

    F_t = Σ_{s in t} J_sᵀ J_s / σ_k(s)²

with each series' noise sd σ_k at the given point.  The prior box enters as a Gaussian with the box's
own variance (sd = width/√12 in the sampling coordinates; a per-test scale: its N(1, 0.05²) prior), so
a direction no test informs keeps a finite, honest sd: the prior's.  In prior-whitened coordinates
(every parameter's prior sd = 1) the eigenvalues λ of the whitened F = Σ_t F_t are the data's
information relative to the prior's: a direction with λ < 1 is *unidentified* (the data carry less
than the box does).  A direction is *structural* when it stays null (λ < :data:`NULL_TOL`·λ_max) after
a probe of every loading mode the model knows is added (each mode at :data:`PROBE_STRAINS`): no
homogeneous test can inform it; the model's spec says why (``ModelSpec.texts["modes_structural"]``).

Per quantity of the spec (its combinations and shape parameters; ln scale for those physics keeps
positive and unbounded) the linearised sd with all tests, with each test alone and with each left
out; ``width_added`` = sd(all but the test) / sd(all).  A quantity whose data-only sd is above
:data:`PRIOR_DOMINATED` × its prior sd is *prior-dominated* (the tests carry less than 4× the box's
information along it).  ``sd_data`` is the data-only limit: the box's weight → 0 (the per-test scales
keep their Gaussian prior), the structural directions projected out; inf when the tests do not inform it.

This module names no parameter: it reads names from the likelihood and the spec.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from ..errors import HbmError
from ..likelihood.modes import TEST_SCALE_SD
from ..model.loadcases import LOAD_CASES, check_mode
from ..model.spec import spec_of

__all__ = ["ModesIdentifiability", "linearised_identifiability", "series_jacobians", "fit_point", "NULL_TOL",
           "PROBE_STRAINS", "PRIOR_DOMINATED", "REL_STEP"]

#: the finite-difference step, relative to each coordinate's prior box width in the sampling space
REL_STEP = 1e-4
#: a whitened eigenvalue below NULL_TOL × the largest is null to rounding (with the probe of every mode)
NULL_TOL = 1e-9
#: the probe's controls (strain, or γ in shear): compression to large tension, so every term engages
PROBE_STRAINS = np.array([-0.2, -0.1, 0.05, 0.1, 0.2, 0.3, 0.4, 0.5])
#: a data-only sd above this share of the prior sd: the quantity is prior-dominated
PRIOR_DOMINATED = 0.5
#: a parameter loads on the structural null space when its share of it is above this (rounding is ~1e-12)
_SHARE_MIN = 1e-6
#: a quantity moves along a null direction when its whitened gradient's share on it exceeds this
#: (finite-difference error leaves ~1e-6 on directions it does not move along)
_ALONG = 1e-3
#: loadings below this share of a direction's largest are left out of its description
_LOADING_MIN = 0.2


@dataclass
class ModesIdentifiability:
    """The linearised identifiability of a specimen's tests (module docstring); built by
    :func:`linearised_identifiability`.

    Attributes
    ----------
    specimen : str
    point : str
        Where the analysis was linearised (and how the noise sds were set).
    space : str
        The coordinates of the Jacobian and of ``parameters``.
    parameters : tuple of str
        The perturbed coordinates (free model parameters, then per-test scales).
    tests : list of dict
        ``id``, ``label``, ``mode`` of every test with a measured series.
    fisher : ndarray (n_tests, p, p)
        Per-test Fisher information in the sampling coordinates.
    prior_sd : ndarray (p,)
        The Gaussian regulariser's sd per coordinate.
    eigenvalues : ndarray (p,)
        Whitened information of all tests together, ascending.
    rank : int
        Directions whose data information is at least the prior's (λ ≥ 1).
    unidentified : list of dict
        Per direction with λ < 1: ``information`` (λ), ``structural`` (bool) and ``loadings``
        (parameter -> whitened component, the ones ≥ 0.2 of the largest).
    n_structural : int
        Directions null in every loading mode (the probe).
    structural_parameters : dict
        Parameter -> its share of the structural null space (whitened; 0..1), those loading on it.
    structural_text : str
        The spec's sentence on why (empty when there is none or no structural direction).
    quantities : list of dict
        Per quantity: ``name``, ``scale`` ("ln" or "linear"), ``unit``, ``value``, ``sd_all``, ``sd_prior``,
        ``sd_data``, ``sd_alone`` / ``sd_without`` / ``width_added`` (test id -> value), ``prior_dominated``,
        ``sd_posterior`` (set by :meth:`compare_posterior`; None until then).
    n_evaluations : int
        Model evaluations (particle × test solves) spent: the file's tests and the probe.
    probe_modes : tuple of str
        The modes of the probe.
    """

    specimen: str
    point: str
    space: str
    parameters: tuple[str, ...]
    tests: list[dict[str, Any]]
    fisher: np.ndarray
    prior_sd: np.ndarray
    eigenvalues: np.ndarray
    rank: int
    unidentified: list[dict[str, Any]]
    n_structural: int
    structural_parameters: dict[str, float]
    structural_text: str
    quantities: list[dict[str, Any]]
    n_evaluations: int
    probe_modes: tuple[str, ...] = field(default_factory=tuple)

    def quantity(self, name: str) -> dict[str, Any]:
        """The row of quantity ``name``."""
        for q in self.quantities:
            if q["name"] == name:
                return q
        raise HbmError(f"no quantity {name!r}; the analysis has {', '.join(q['name'] for q in self.quantities)}")

    def compare_posterior(self, columns: dict[str, np.ndarray]) -> None:
        """Set each quantity's posterior sd (same scale) from posterior columns (name -> draws, natural units,
        the spec's combinations and parameters)."""
        for q in self.quantities:
            v = columns.get(q["name"])
            if v is None:
                continue
            v = np.asarray(v, float)
            if q["scale"] == "ln":
                with np.errstate(divide="ignore", invalid="ignore"):
                    v = np.log(v)
            v = v[np.isfinite(v)]
            q["sd_posterior"] = float(v.std()) if v.size > 1 else None

    def report_lines(self) -> list[str]:
        """The report's section (what each number is, where it was linearised, in which space)."""
        p = len(self.parameters)
        label = {t["id"]: f"test {t['id']} [{t['mode']}]" for t in self.tests}
        named = [f"{t['id']} = {t['label']}" for t in self.tests if t["label"] is not None and t["label"] != str(t["id"])]
        lines = [f"what the tests identify (linearised Fisher analysis at {self.point}; Jacobian in the sampling "
                 f"space: {self.space}; the prior box as a Gaussian of its own variance):",
                 f"  rank {self.rank} of {p}: directions where the tests carry at least the prior box's information"]
        if self.n_structural:
            share = ", ".join(f"{k} {v:.2g}" for k, v in self.structural_parameters.items())
            lines.append(f"  {self.n_structural} direction(s) null in every homogeneous test (still null with a "
                         f"probe of all {len(self.probe_modes)} loading modes added); parameters on them (share "
                         f"of the whitened null space): {share}")
            if self.structural_text:
                lines.append(f"  {self.structural_text}")
        for u in self.unidentified:
            if not u["structural"]:
                load = " ".join(f"{v:+.2f}·{k}" for k, v in u["loadings"].items())
                lines.append(f"  unidentified by these tests (information {u['information']:.2g} x the prior's; "
                             f"whitened direction, structural part removed): {load}")
        # a linear quantity's sd is in its own unit; a log one's is a relative spread (no unit)
        names = [f"ln {q['name']}" if q["scale"] == "ln" else
                 (f"{q['name']} [{q['unit']}]" if q.get("unit") not in (None, "", "1", "-") else q["name"])
                 for q in self.quantities]
        lines.append("  sd of each quantity (ln = of its natural log; lin = linearised, prior box included; data = "
                     "the data-only limit; x = sd(all but the test) / sd(all), the width the test adds):")
        if named:
            lines.append(f"  tests: {', '.join(named)}")
        lines.append("  " + " " * 34 + "".join(f"{n:>16s}" for n in names))

        def row(title, values, fmt="{:.3g}"):
            cells = "".join(f"{'-' if v is None else fmt.format(v):>16s}" for v in values)
            lines.append(f"  {title:<34s}{cells}")

        row("lin, all tests", [q["sd_all"] for q in self.quantities])
        row("posterior draws", [q.get("sd_posterior") for q in self.quantities])
        row("prior box alone", [q["sd_prior"] for q in self.quantities])
        row("data only, all tests", [q["sd_data"] for q in self.quantities])
        for t in label:
            row(f"lin, {label[t]} alone", [q["sd_alone"][t] for q in self.quantities])
        for t in label:
            row(f"lin, without {label[t]}", [q["sd_without"][t] for q in self.quantities])
        for t in label:
            row(f"x, {label[t]}", [q["width_added"][t] for q in self.quantities], "x{:.3g}")
        dom = [q["name"] for q in self.quantities if q["prior_dominated"]]
        lines.append(f"  prior-dominated (data-only sd > {PRIOR_DOMINATED:g} x the prior box's): "
                     f"{', '.join(dom) if dom else 'none'}")
        return lines

    def to_dict(self) -> dict[str, Any]:
        """JSON-able summary (the CLI's ``identifiability`` key and the result file's attribute)."""
        def num(v):
            return None if v is None else (float(v) if math.isfinite(v) else str(v))
        qs = [{k: ({str(t): num(x) for t, x in v.items()} if isinstance(v, dict) else
                   num(v) if isinstance(v, float) else v) for k, v in q.items()} for q in self.quantities]
        return {"specimen": self.specimen, "point": self.point, "space": self.space,
                "parameters": list(self.parameters), "tests": self.tests, "rank": self.rank,
                "n_parameters": len(self.parameters), "n_structural": self.n_structural,
                "structural_parameters": self.structural_parameters, "structural_text": self.structural_text,
                "unidentified": self.unidentified, "eigenvalues": [float(x) for x in self.eigenvalues],
                "prior_sd": [float(x) for x in self.prior_sd], "prior_dominated_share": PRIOR_DOMINATED,
                "quantities": qs, "n_evaluations": self.n_evaluations, "probe_modes": list(self.probe_modes)}


def fit_point(lik, samples: np.ndarray, log_likelihood: np.ndarray) -> tuple[np.ndarray, str]:
    """The point a fit is linearised at: its highest-likelihood draw (the MAP in the sampling space, where
    the box prior is flat) with each noise sd at exp(posterior mean of ln σ).

    Parameters
    ----------
    lik : ModesLikelihood
    samples : ndarray (n, d)
        Posterior draws in natural units.
    log_likelihood : ndarray (n,)

    Returns
    -------
    row : ndarray (d,)
        Sampling coordinates.
    description : str
    """
    samples = np.asarray(samples, float)
    nat = samples[int(np.argmax(log_likelihood))].copy()
    k = slice(lik.n_model, lik.n_model + len(lik.kinds))
    # in natural units, then to the sampling coordinates (log or linear, as the prior declares the noise sds)
    nat[k] = np.exp(np.log(samples[:, k]).mean(axis=0))
    return lik.from_natural(nat[None, :])[0], "the highest-likelihood draw (noise sds at the geometric posterior mean)"


def _perturbed(lik) -> np.ndarray:
    """Columns perturbed: the free model parameters, then the per-test stress scales (``scale_test<id>``)."""
    scales = [lik.names.index(n) for n in lik.noise_names if n.startswith("scale_test")]
    return np.r_[np.arange(lik.n_model), scales].astype(int)


def _prior_sd(lik, cols: np.ndarray) -> np.ndarray:
    width = lik.bounds[cols, 1] - lik.bounds[cols, 0]
    sd = width / math.sqrt(12.0)
    is_scale = np.array([lik.names[c].startswith("scale_test") for c in cols])
    return np.where(is_scale, TEST_SCALE_SD, sd)


def _stencil(lik, row: np.ndarray, cols: np.ndarray, rel_step: float) -> tuple[np.ndarray, np.ndarray]:
    """The 2p rows (+h for each column, then −h) and the step b − a per column.

    Central differences even at the prior box's edge (the model is defined beyond the box; a posterior
    piled against an edge is common): h shrinks to half the distance to the *physical* range of a
    natural-unit parameter (:attr:`hbm.model.spec.ModelSpec.physical_range`), one-sided only on it."""
    x = row[cols]
    h = rel_step * (lik.bounds[cols, 1] - lik.bounds[cols, 0])
    phys = spec_of(lik.model).physical_range
    lo, hi = np.full(cols.size, -np.inf), np.full(cols.size, np.inf)
    for j, c in enumerate(cols):
        if c < lik.n_model and lik.forms[c] == "uniform" and lik.names[c] in phys:
            lo[j], hi[j] = phys[lik.names[c]]
    room = np.minimum(x - lo, hi - x)
    h = np.where(room > 0, np.minimum(h, 0.5 * room), h)
    a, b = np.maximum(x - h, lo), np.minimum(x + h, hi)
    p = cols.size
    rows = np.repeat(row[None], 2 * p, axis=0)
    rows[np.arange(p), cols] = b
    rows[p + np.arange(p), cols] = a
    return rows, b - a


def series_jacobians(lik, point, rel_step: float = REL_STEP) -> tuple[list[np.ndarray], np.ndarray, np.ndarray]:
    """The Jacobian of every measured series at ``point`` in the sampling coordinates, by central finite
    differences in **one** batched ``predict_series`` call over all ±h rows.

    Parameters
    ----------
    lik : ModesLikelihood
    point : array_like (d,)
        A row in the sampling coordinates (``lik.names``).
    rel_step : float
        Step relative to each coordinate's prior box width (shrunk near a physical limit).

    Returns
    -------
    jacobians : list of ndarray (n_values, p)
        Parallel to ``lik.series``; columns: the free model parameters, then the per-test scales.
    rows : ndarray (2p, d)
        The stencil (+h rows, then −h rows).
    step : ndarray (p,)
        The difference of the two rows of each column.
    """
    row = np.asarray(point, float).ravel()
    cols = _perturbed(lik)
    p = cols.size
    rows, step = _stencil(lik, row, cols, rel_step)
    values = lik.predict_series(rows)          # one batched call: every ±h row, every test
    return [((v[:p] - v[p:]) / step[:, None]).T for v in values], rows, step


def _probe_fisher(lik, rows: np.ndarray, step: np.ndarray, sd: np.ndarray) -> tuple[np.ndarray, tuple[str, ...], int]:
    """Whitened information of every loading mode the energy evaluates, each observable at PROBE_STRAINS,
    noise 1 % of the observable's largest |value| (only its null space is used)."""
    p = step.size
    params = lik.model._params(lik.model_theta(rows))
    total = np.zeros((p, p))
    modes, n = [], 0
    for name, case in LOAD_CASES.items():
        try:
            check_mode(lik.energy, case)
            with np.errstate(all="ignore"):
                out = case.solve(lik.energy, params, PROBE_STRAINS, None)
        except HbmError:   # a mode this energy cannot evaluate, or no lateral solution at a probe strain
            continue
        n += rows.shape[0]
        used = False
        for v in out.values():
            v = np.asarray(v, float)
            if v.shape != (rows.shape[0], PROBE_STRAINS.size) or not np.isfinite(v).all():
                continue
            scale = 0.01 * max(float(np.abs(v).max()), 1e-300)
            J = ((v[:p] - v[p:]) / step[:, None]).T * sd[None, :] / scale
            total += J.T @ J
            used = True
        if used:
            modes.append(name)
    return total, tuple(modes), n


def _quantities(lik, rows: np.ndarray, row: np.ndarray, step: np.ndarray, p: int) -> list[dict[str, Any]]:
    """Value, scale, unit and gradient (sampling coordinates) of the spec's combinations and shape parameters."""
    spec = spec_of(lik.model)
    pts = lik.model_theta(np.vstack([row[None], rows]))
    cols = {n: pts[:, i] for i, n in enumerate(lik.model.parameter_names)}
    phys = dict(spec.physical_range)
    out = []
    items = [(c.name, c.compute(cols), c.unit,
              all(phys.get(k, (-np.inf,))[0] >= 0 for k in c.parameters)) for c in spec.combinations
             if all(k in cols for k in c.parameters)]
    units = {q.name: q.unit for q in spec.parameters}
    for name in spec.shape_parameters:
        lo, hi = phys.get(name, (-np.inf, np.inf))
        if name in lik.model_names:
            items.append((name, cols[name], units.get(name, "-"), lo >= 0 and hi == np.inf))
    for name, v, unit, positive in items:
        v = np.asarray(v, float)
        ln = bool(positive and v[0] > 0 and (v > 0).all())
        f = np.log(v) if ln else v
        g = (f[1:p + 1] - f[p + 1:]) / step
        out.append({"name": name, "scale": "ln" if ln else "linear", "unit": "-" if ln else unit,
                    "value": float(v[0]), "gradient": g})
    return out


def _sd(Fw: np.ndarray, gw: np.ndarray) -> float:
    """sqrt(gᵀ (F + I)⁻¹ g) in whitened coordinates."""
    lam, V = np.linalg.eigh(Fw + np.eye(Fw.shape[0]))
    return float(math.sqrt(max(np.sum((V.T @ gw) ** 2 / lam), 0.0)))


def _sd_data(Fw: np.ndarray, gw: np.ndarray, null: np.ndarray) -> float:
    """The data-only limit: the structural null space projected out, inf when the rest is still singular
    along g."""
    Q = _complement(null, Fw.shape[0])
    g = Q.T @ gw
    if null.shape[1] and np.linalg.norm(null.T @ gw) > _ALONG * max(np.linalg.norm(gw), 1e-300):
        return math.inf   # the quantity moves along a structural direction: no test informs it
    lam, V = np.linalg.eigh(Q.T @ Fw @ Q)
    keep = lam > NULL_TOL * max(lam.max(), 1e-300)
    proj = V.T @ g
    if np.any(np.abs(proj[~keep]) > _ALONG * max(np.linalg.norm(g), 1e-300)):
        return math.inf
    return float(math.sqrt(np.sum(proj[keep] ** 2 / lam[keep])))


def _loadings(v: np.ndarray, names: tuple[str, ...]) -> dict[str, float]:
    """A whitened direction as {parameter: component}, largest first, normalised to a largest |component| of 1,
    components below _LOADING_MIN left out."""
    v = v / np.abs(v).max()
    return {names[i]: float(v[i]) for i in np.argsort(-np.abs(v)) if abs(v[i]) >= _LOADING_MIN}


def _complement(N: np.ndarray, p: int) -> np.ndarray:
    """An orthonormal basis of the complement of span(N) (columns)."""
    if N.shape[1] == 0:
        return np.eye(p)
    u, _, _ = np.linalg.svd(N, full_matrices=True)
    return u[:, N.shape[1]:]


def linearised_identifiability(lik, point, *, point_label: str = "the given point",
                               rel_step: float = REL_STEP) -> ModesIdentifiability:
    """The linearised identifiability of ``lik``'s tests at ``point`` (module docstring).

    Parameters
    ----------
    lik : ModesLikelihood
        The specimen's joint likelihood (its tests, noise kinds and box).
    point : array_like (d,)
        A row in the sampling coordinates (``lik.names``); its noise sds are the series' σ.
    point_label : str
        How the report names the point.
    rel_step : float
        Finite-difference step relative to each coordinate's box width.

    Returns
    -------
    ModesIdentifiability

    Raises
    ------
    HbmError
        A point of the wrong length, or a model solve that fails at the stencil.
    """
    row = np.asarray(point, float).ravel()
    if row.size != lik.d or not np.isfinite(row).all():
        raise HbmError(f"identifiability: the point must be {lik.d} finite numbers ({', '.join(lik.names)})")
    cols = _perturbed(lik)
    p = cols.size
    J, rows, step = series_jacobians(lik, row, rel_step)
    sig = lik.to_natural(row[None])[0, lik.n_model: lik.n_model + len(lik.kinds)]
    test_ids = list(dict.fromkeys(s.test.id for s in lik.series))
    tests = [{"id": int(t.id), "label": t.label, "mode": t.load_case} for t in lik.data.tests if t.id in test_ids]
    fisher = np.zeros((len(test_ids), p, p))
    for s, Js in zip(lik.series, J):
        w = Js / sig[lik.kinds.index(s.kind)]
        fisher[test_ids.index(s.test.id)] += w.T @ w
    sd = _prior_sd(lik, cols)
    D = np.diag(sd)
    Fw_t = np.einsum("ij,tjk,kl->til", D, fisher, D)          # whitened: prior sd 1 per coordinate
    Fw = Fw_t.sum(axis=0)
    # the per-test scales' N(1, 0.05²) is a chosen prior, not the box: the data-only limit keeps it
    kept = np.diag([1.0 if lik.names[c].startswith("scale_test") else 0.0 for c in cols])
    lam = np.linalg.eigvalsh(Fw)
    probe, probe_modes, n_probe = _probe_fisher(lik, rows, step, sd)
    lp, Vp = np.linalg.eigh(Fw + probe)
    null = Vp[:, lp < NULL_TOL * max(lp.max(), 1e-300)]
    names = tuple(lik.names[c] for c in cols)
    # the unidentified directions: the structural null space, then the weak directions of the rest
    unident = [{"information": 0.0, "structural": True, "loadings": _loadings(null[:, k], names)}
               for k in range(null.shape[1])]
    Q = _complement(null, p)
    lq, Vq = np.linalg.eigh(Q.T @ Fw @ Q)
    unident += [{"information": float(max(lq[k], 0.0)), "structural": False,
                 "loadings": _loadings(Q @ Vq[:, k], names)} for k in np.flatnonzero(lq < 1.0)]
    share = np.sum(null ** 2, axis=1)
    structural_parameters = {names[i]: float(share[i]) for i in np.argsort(-share) if share[i] >= _SHARE_MIN}
    text = spec_of(lik.model).texts.get("modes_structural", "") if null.shape[1] else ""
    quantities = []
    for q in _quantities(lik, rows, row, step, p):
        gw = sd * q.pop("gradient")
        alone = {t: _sd(Fw_t[i], gw) for i, t in enumerate(test_ids)}
        without = {t: _sd(Fw - Fw_t[i], gw) for i, t in enumerate(test_ids)}
        sd_all, sd_data = _sd(Fw, gw), _sd_data(Fw + kept, gw, null)
        sd_prior = float(np.linalg.norm(gw))
        quantities.append({**q, "sd_all": sd_all, "sd_prior": sd_prior, "sd_data": sd_data,
                           "sd_alone": alone, "sd_without": without,
                           "width_added": {t: without[t] / sd_all for t in test_ids},
                           "prior_dominated": bool(sd_data > PRIOR_DOMINATED * sd_prior), "sd_posterior": None})
    space = ", ".join(f"ln {n}" if lik.forms[c] == "loguniform" else n for n, c in zip(names, cols))
    return ModesIdentifiability(
        specimen=str(lik.label), point=point_label, space=space, parameters=names, tests=tests, fisher=fisher,
        prior_sd=sd, eigenvalues=lam, rank=int(np.sum(lam >= 1.0)), unidentified=unident,
        n_structural=int(null.shape[1]), structural_parameters=structural_parameters, structural_text=text,
        quantities=quantities, n_evaluations=int(rows.shape[0] * len(lik.data.tests) + n_probe),
        probe_modes=probe_modes)
