"""The joint log-likelihood of a specimen tested in several loading modes (issue 35, item 4).

Each test of the specimen names its mode (:mod:`hbm.model.loadcases`); the model's 3-D energy
(:func:`hbm.model.energy3d.energy_from_model`, collagen reading ``collagen3d``) predicts every observable
of every test in one vectorised call per test (particles × points).  The log-likelihood is a sum over the
measured *series* -- one (test, observable) pair, its finite cells only (an empty cell is not measured)::

    log L = Σ_series Σ_i log N(y_i; s_t·m_i(θ), σ_k²)     (+ Σ_t log N(s_t; 1, 0.05²) + const)

with one noise scale σ_k per *kind* k = (mode, observable): stresses of different modes differ by
orders of magnitude and strains are dimensionless, so no kind shares a σ with another.  σ_k has a
log-uniform prior on ``[1e-3, 0.5]·max|y_k|`` (sampled as ln σ_k).  With ``test_scale=True`` each test
has a multiplicative factor s_t on its predicted stresses (cross-section and gauge errors), prior
N(1, 0.05²) truncated to [0.8, 1.2] (±4 sd): the sampler draws s_t uniformly on that box and this
likelihood carries the Gaussian density times the box width, so the evidence is that of the Gaussian
prior (the truncated mass, 6e-5, is neglected).

Only the full tier exists here: ``uniaxial_c`` is not linear in the amplitudes (its free lateral
stretch depends on them), and the prescribed-F modes' collapse is not implemented; the fit states it.
The thesis form is refused in every mode but ``uniaxial_f`` (:func:`hbm.model.loadcases.check_mode`).

Effects beyond the base model act per test where they are defined in 3-D (:mod:`hbm.model.modes_effects`):
quasi-linear viscoelasticity on each predicted stress observable's own history (``stress``, ``stress_2``;
strains are kinematic and stay elastic), an offset per stress observable (``S0``, ``S0_2``); an effect that
knows only the along-fibre path is refused in every other mode, with its reason.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Mapping

import numpy as np

from ..data.specimen import Specimen, Test, as_specimen
from ..errors import DataError, HbmError, SettingError
from ..model.core import Model
from ..model.energy3d import energy_from_model
from ..model.loadcases import LoadCase, check_mode, get_load_case
from ..model.modes_effects import ModeEffects
from .core import exp_columns, free_index, log_columns
from .prior import Prior, load_prior

__all__ = ["ModeSeries", "ModesLikelihood", "make_modes_likelihood", "is_multimode", "TEST_SCALE_SD",
           "SIGMA_RANGE"]

#: prior sd of the per-test stress scale
TEST_SCALE_SD = 0.05
#: the σ box of a kind, relative to the largest |value| of its series
SIGMA_RANGE = (1e-3, 0.5)
_SCALE_BOX = (1.0 - 4 * TEST_SCALE_SD, 1.0 + 4 * TEST_SCALE_SD)
_LOG_2PI = math.log(2.0 * math.pi)


def is_multimode(specimen) -> bool:
    """True when a specimen needs this likelihood: a test in a mode other than ``uniaxial_f`` or a
    measured series besides ``stress`` (a file without the per-test columns never does)."""
    s = as_specimen(specimen)
    return bool(s.key_extras()) or (s.has_stress and not np.isfinite(s.stress).all())


@dataclass(frozen=True)
class ModeSeries:
    """One measured series: an observable of one test, at the rows where it was measured.

    Attributes
    ----------
    test : Test
    observable : str
        ``stress``, ``stress_2``, ``strain_c`` ...
    kind : str
        The noise group ``<mode>.<observable>``.
    rows : ndarray of int
        Rows of the specimen (finite cells only).
    local : ndarray of int
        The same rows counted from the test's first row.
    observed : ndarray
        The measured values.
    is_stress : bool
    """

    test: Test
    observable: str
    kind: str
    rows: np.ndarray
    local: np.ndarray
    observed: np.ndarray
    is_stress: bool

    @property
    def name(self) -> str:
        """``<observable>[<test label or id>]`` (tables)."""
        return f"{self.observable}[{self.test.label if self.test.label is not None else self.test.id}]"


def _series(spec: Specimen) -> list[ModeSeries]:
    out = []
    for t in spec.tests:
        case = get_load_case(t.load_case)
        for obs in case.observables:
            s = spec.observed.get(obs.name)
            if s is None:
                continue
            v = s.values[t.rows]
            local = np.flatnonzero(np.isfinite(v))
            if local.size:
                out.append(ModeSeries(t, obs.name, f"{case.name}.{obs.name}", t.start + local, local, v[local],
                                      obs.is_stress))
    return out


class ModesLikelihood:
    """Joint log-likelihood of the tests of one specimen in their modes; built by :func:`make_modes_likelihood`.

    The interface the samplers and :func:`hbm.fit.modes.fit_modes` use is that of
    :class:`~hbm.likelihood.Likelihood`: ``names``, ``bounds`` (working coordinates), ``natural_bounds``,
    ``forms``, ``prior``, ``d``, ``n_model``, ``model_names``, ``noise_names``, ``fixed``, ``__call__``,
    ``to_natural``/``from_natural``, ``model_theta``, ``in_box``, ``as_dict``, ``index``.

    Attributes
    ----------
    energy : Energy3D
        The model's 3-D energy (its ``collagen3d`` is the reading in use: record it).
    series : list of ModeSeries
    kinds : tuple of str
        The noise groups, in the order of their σ parameters.
    test_scale : bool
    """

    noise = "iid per series kind"
    tier = "full"

    def __init__(self, model: Model, data, *, collagen3d: str | None = None,
                 fix: Mapping[str, float] | None = None, bounds: Mapping[str, tuple[float, float]] | None = None,
                 prior: Prior | str | Mapping | None = None, test_scale: bool = False) -> None:
        spec = as_specimen(data)
        self.data, self.label = spec, spec.id
        self.energy = energy_from_model(model, collagen3d)
        self.cases: dict[int, LoadCase] = {}
        for t in spec.tests:
            check_mode(self.energy, t.load_case)
            self.cases[t.id] = get_load_case(t.load_case)
        self.series = _series(spec)
        if not self.series:
            raise DataError(f"{spec.id}: no measured value in any test; nothing to fit")
        try:  # effects beyond the base act per test where they are defined in 3-D; refused elsewhere
            self.effects = ModeEffects(model, spec.loading, [(t, self.cases[t.id]) for t in spec.tests],
                                       [(s.test, s.observable) for s in self.series])
        except SettingError as exc:
            raise SettingError(f"{spec.id}: {exc}") from None
        self.model = model = self.effects.model
        self.kinds = tuple(dict.fromkeys(s.kind for s in self.series))
        self.n_points = int(sum(s.rows.size for s in self.series))
        self.test_scale = bool(test_scale)
        self._params_box(model, fix, bounds, load_prior(prior))

    # -- parameters ----------------------------------------------------------------------------
    def _params_box(self, model, fix, bounds, user_prior) -> None:
        names = model.parameter_names
        box = np.array(model.bounds, dtype=float)
        forms = {n: "uniform" for n in names}
        if user_prior is not None:
            for n in names:
                if n in user_prior:
                    box[model.index(n)] = user_prior[n].lo, user_prior[n].hi
                    forms[n] = user_prior[n].form
        fix = {k: float(v) for k, v in dict(fix or {}).items()}
        for kind, d in (("fix", fix), ("bounds", dict(bounds or {}))):
            unknown = [k for k in d if k not in names]
            if unknown:
                raise HbmError(f"{kind}: unknown parameter(s) {', '.join(unknown)}; the model has {', '.join(names)}")
        for k, (lo, hi) in dict(bounds or {}).items():
            i = model.index(k)
            if not (box[i, 0] <= float(lo) < float(hi) <= box[i, 1]):
                raise HbmError(f"bounds: {k}={lo}:{hi} must be LO < HI inside the prior box "
                               f"[{box[i, 0]:g}, {box[i, 1]:g}]")
            box[i] = float(lo), float(hi)
        for k, v in fix.items():
            i = model.index(k)
            if not (np.isfinite(v) and box[i, 0] <= v <= box[i, 1]):
                raise HbmError(f"fix: {k}={v} is outside its box [{box[i, 0]:g}, {box[i, 1]:g}]")
        self.fixed = fix
        self.free_index = np.array([i for i, n in enumerate(names) if n not in fix], dtype=int)
        self.model_names = tuple(names[i] for i in self.free_index)
        self.n_model = len(self.model_names)
        self._fixed_row = np.array([fix.get(n, np.nan) for n in names], dtype=float)
        noise: dict[str, tuple[float, float, str]] = {}
        for k in self.kinds:
            top = max(float(np.max(np.abs(s.observed))) for s in self.series if s.kind == k) or 1e-3
            noise[f"sigma_{k.replace('.', '_')}"] = (SIGMA_RANGE[0] * top, SIGMA_RANGE[1] * top, "loguniform")
        if self.test_scale:
            for t in self.data.tests:
                if any(s.test.id == t.id and s.is_stress for s in self.series):
                    noise[f"scale_test{t.id}"] = (*_SCALE_BOX, "uniform")
        if user_prior is not None:
            user_prior.check_names(list(names) + list(noise), what="the model with per-kind noise")
            for n in noise:
                if n in user_prior:
                    noise[n] = (user_prior[n].lo, user_prior[n].hi, user_prior[n].form)
        self.noise_names = tuple(noise)
        self._scale_tests = [int(n[len("scale_test"):]) for n in noise if n.startswith("scale_test")]
        self.names = self.model_names + self.noise_names
        self.d = len(self.names)
        self.natural_bounds = np.vstack([box[self.free_index].reshape(-1, 2),
                                         np.array([v[:2] for v in noise.values()], float).reshape(-1, 2)])
        self.forms = tuple([forms[n] for n in self.model_names] + [v[2] for v in noise.values()])
        self._log = np.array([f == "loguniform" for f in self.forms], dtype=bool)
        self.bounds = self.from_natural(self.natural_bounds.T).T
        allb = {n: (*box[i], forms[n]) for i, n in enumerate(names)}
        allb.update(noise)
        self.prior = Prior(allb, source="likelihood")

    def __repr__(self) -> str:
        return (f"<ModesLikelihood {self.label}: {self.energy.label}, {len(self.series)} series in "
                f"{len(self.kinds)} kinds, {self.n_points} values, free={', '.join(self.names)}>")

    def index(self, name: str) -> int:
        """Column of free parameter ``name`` in theta."""
        return free_index(self.names, name)

    def to_natural(self, theta) -> np.ndarray:
        """Working rows -> natural units (exp of the log-uniform columns)."""
        return exp_columns(theta, self._log)

    def from_natural(self, theta) -> np.ndarray:
        """Natural rows -> working coordinates (inverse of :meth:`to_natural`)."""
        return log_columns(theta, self._log)

    def _as2d(self, theta) -> np.ndarray:
        theta = np.atleast_2d(np.asarray(theta, dtype=float))
        if theta.ndim != 2 or theta.shape[1] != self.d:
            raise HbmError(f"theta must have shape (n, {self.d}) for parameters {', '.join(self.names)}, "
                           f"got {theta.shape}")
        return theta

    def model_theta(self, theta) -> np.ndarray:
        """Full model rows (n, n_params) in natural units."""
        nat = self.to_natural(self._as2d(theta))
        out = np.empty((nat.shape[0], self.model.n_params))
        out[:] = self._fixed_row
        out[:, self.free_index] = nat[:, : self.n_model]
        return out

    def in_box(self, theta) -> np.ndarray:
        theta = self._as2d(theta)
        return ((theta >= self.bounds[:, 0]) & (theta <= self.bounds[:, 1])).all(axis=1)

    def as_dict(self, row) -> dict[str, float]:
        """{name: natural value} of one working row, fixed parameters included."""
        row = np.asarray(row, float).reshape(1, -1)
        full = self.model_theta(row)[0]
        nat = self.to_natural(row)[0]
        out = {n: float(full[i]) for i, n in enumerate(self.model.parameter_names)}
        out.update({n: float(nat[self.n_model + j]) for j, n in enumerate(self.noise_names)})
        return out

    # -- predictions ------------------------------------------------------------------------------
    def _solve_tests(self, rows: np.ndarray) -> dict[int, dict[str, np.ndarray]]:
        return self.effects.solve(self.energy, rows, self.data.strain_2)

    def predict_series(self, theta) -> list[np.ndarray]:
        """The model's value of every series (list parallel to :attr:`series`, each (n, n_values)),
        per-test scales applied to stresses."""
        theta = self._as2d(theta)
        with np.errstate(all="ignore"):
            pred = self._solve_tests(self.model_theta(theta))
        scale = self._scales(self.to_natural(theta))
        return [pred[s.test.id][s.observable][:, s.local] * (scale[s.test.id][:, None] if s.is_stress else 1.0)
                for s in self.series]

    def _scales(self, nat: np.ndarray) -> dict[int, np.ndarray]:
        ones = np.ones(nat.shape[0])
        out = {t.id: ones for t in self.data.tests}
        for tid in self._scale_tests:
            out[tid] = nat[:, self.names.index(f"scale_test{tid}")]
        return out

    def _sigmas(self, nat: np.ndarray) -> dict[str, np.ndarray]:
        return {k: nat[:, self.n_model + j] for j, k in enumerate(self.kinds)}

    def pointwise(self, theta, predictions: list[np.ndarray] | None = None) -> list[np.ndarray]:
        """Log-density of every measured value: a list parallel to :attr:`series`, each (n, n_values)."""
        theta = self._as2d(theta)
        m = self.predict_series(theta) if predictions is None else predictions
        sig = self._sigmas(self.to_natural(theta))
        out = []
        for s, mi in zip(self.series, m):
            sd = sig[s.kind][:, None]
            z = (s.observed - mi) / sd
            out.append(-0.5 * z * z - np.log(sd) - 0.5 * _LOG_2PI)
        return out

    def _loglik(self, theta: np.ndarray) -> np.ndarray:
        total = np.zeros(theta.shape[0])
        for part in self.pointwise(theta):
            total += part.sum(axis=1)
        if self._scale_tests:  # the scales' Gaussian prior times the box width (module docstring)
            nat = self.to_natural(theta)
            width = _SCALE_BOX[1] - _SCALE_BOX[0]
            for tid in self._scale_tests:
                z = (nat[:, self.names.index(f"scale_test{tid}")] - 1.0) / TEST_SCALE_SD
                total += -0.5 * z * z - math.log(TEST_SCALE_SD) - 0.5 * _LOG_2PI + math.log(width)
        return total

    def _safe(self, theta: np.ndarray) -> np.ndarray:
        """The log-likelihood, halving the population where a lateral solve refuses some particle (so one
        bad particle costs itself, never the population)."""
        try:
            return self._loglik(theta)
        except HbmError:
            if theta.shape[0] == 1:
                return np.array([-np.inf])
            h = theta.shape[0] // 2
            return np.concatenate([self._safe(theta[:h]), self._safe(theta[h:])])

    def __call__(self, theta) -> np.ndarray:
        """Log-likelihood of each row (n, d) -> (n,); -inf out of box or non-finite."""
        theta = np.asarray(theta, dtype=float)
        single = theta.ndim == 1
        theta = self._as2d(theta)
        out = np.full(theta.shape[0], -np.inf)
        ok = self.in_box(theta)
        if ok.any():
            with np.errstate(all="ignore"):
                val = self._safe(theta[ok])
            out[ok] = np.where(np.isfinite(val), val, -np.inf)
        return out[0] if single else out

    log_density = __call__

    def simulate(self, theta_row, rng: np.random.Generator) -> list[np.ndarray]:
        """One noisy replicate of every series at one working row (posterior predictive)."""
        row = np.asarray(theta_row, float).reshape(1, -1)
        sig = self._sigmas(self.to_natural(row))
        return [m[0] + sig[s.kind][0] * rng.standard_normal(m.shape[1])
                for s, m in zip(self.series, self.predict_series(row))]


def make_modes_likelihood(model: Model, data, *, collagen3d: str | None = None,
                          fix: Mapping[str, float] | None = None,
                          bounds: Mapping[str, tuple[float, float]] | None = None,
                          prior: Prior | str | Mapping | None = None, test_scale: bool = False) -> ModesLikelihood:
    """The joint likelihood of a specimen's tests in their loading modes (module docstring).

    Parameters
    ----------
    model : Model
        The base model in its energy form (:func:`hbm.spyrou_model` with ``form="energy"``); the thesis
        form only when every test is ``uniaxial_f``.
    data : Specimen or xarray.Dataset
        Tests with their modes (:func:`hbm.data.load_specimen` of a file with a ``mode`` column).
    collagen3d : {"cone", "gst"}, optional
        The collagen's 3-D reading (default ``"cone"``; refused with the thesis form).
    fix, bounds, prior
        As for :func:`hbm.likelihood.make_likelihood` (noise parameters are ``sigma_<mode>_<observable>``
        and, with ``test_scale``, ``scale_test<id>``).
    test_scale : bool
        A multiplicative factor per test on its predicted stresses, prior N(1, 0.05²).

    Returns
    -------
    ModesLikelihood

    Raises
    ------
    HbmError
        The thesis form outside ``uniaxial_f`` (with the reason), an unknown mode or reading, an effect
        in a mode where it is not defined (:class:`hbm.model.modes_effects.ModeEffects`), bad
        ``fix``/``bounds``/``prior``.
    """
    return ModesLikelihood(model, data, collagen3d=collagen3d, fix=fix, bounds=bounds, prior=prior,
                           test_scale=test_scale)
