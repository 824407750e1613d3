"""Vectorised log-likelihoods of a stress-strain curve under several noise models.

A :class:`Likelihood` maps a population ``theta`` of shape ``(n, d)`` -- the free model
parameters (model order) followed by the noise parameters -- to ``n`` log-likelihood values in
one call of the model.  Points outside the box, or whose evaluation is not finite, get
``-inf`` (never NaN, never an exception), so samplers and optimisers can use it blindly.

Noise models
------------
The noise model (``r = data − model``) is an object from :mod:`hbm.likelihood.noise` (``"iid"``,
``"weighted"``, ``"proportional"``, ``"ar1"`` or any registered one): it owns the noise
parameters' box, the marginal sd, the log-likelihood, the simulation and the noise part of the
gradient/Fisher information.  :class:`Likelihood` handles the parameters and the model calls.

Priors and working coordinates
------------------------------
The prior is uniform on :attr:`Likelihood.bounds` -- the thesis box, or a user
:class:`hbm.likelihood.prior.Prior` (``prior=``).  A *loguniform* parameter is handled by a coordinate
transform: ``theta`` rows (what samplers and optimisers see, the *working* coordinates) hold
``y = log θ`` in its column and ``bounds`` holds ``[log lo, log hi]``; the model gets ``exp(y)``.
A uniform prior in ``y`` is the loguniform prior in ``θ``, so TMCMC's evidence stays exact.
:meth:`Likelihood.to_natural` / :meth:`Likelihood.from_natural` convert rows; ``natural_bounds``
is the box in natural units.  With no loguniform parameter both coordinate systems coincide
(the transforms are the identity and every output is bitwise that of the plain box).

Gradients and Fisher information
--------------------------------
:meth:`Likelihood.gradient_fim` returns the exact gradient of the log-likelihood and the
expected Fisher information of the Gaussian noise model, built from the model Jacobian
(``model.stress_jacobian``, analytic for the base model) by the noise model's ``grad_fim``.
"""

from __future__ import annotations

from typing import Mapping, Sequence

import numpy as np

from ..data.reduction import bin_counts
from ..data.specimen import Specimen, as_specimen
from ..errors import DataError, HbmError
from ..model.core import Model
from ..model.spyrou import compression_check, model_form
from .binned import BinnedNoise
from .noise import NoiseModel, eq120_weights, get_noise, noise_model_names
from .prior import Prior, PriorError, load_prior


def __getattr__(name: str):
    # NOISE_MODELS is computed on access so that noise models registered later are listed
    if name == "NOISE_MODELS":
        return noise_model_names()
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def observed_stress(specimen: Specimen) -> np.ndarray:
    """The stress a likelihood fits: the specimen's main series, finite at every point."""
    stress = specimen.stress
    if not np.isfinite(stress).all():
        raise DataError(f"{specimen.id}: 'strain' and 'stress' must be finite numbers")
    return stress



def exp_columns(theta, mask: np.ndarray) -> np.ndarray:
    """Working rows -> natural units: exp of the log-uniform columns ``mask`` (any shape, last axis the
    parameters); ``theta`` itself when no column is log-uniform."""
    theta = np.asarray(theta, dtype=float)
    if not mask.any():
        return theta
    out = theta.copy()
    with np.errstate(over="ignore"):
        out[..., mask] = np.exp(theta[..., mask])
    return out


def log_columns(theta, mask: np.ndarray) -> np.ndarray:
    """Natural rows -> working coordinates: the inverse of :func:`exp_columns`."""
    theta = np.asarray(theta, dtype=float)
    if not mask.any():
        return theta
    out = theta.copy()
    with np.errstate(divide="ignore", invalid="ignore"):
        out[..., mask] = np.log(theta[..., mask])
    return out


def free_index(names: Sequence[str], name: str) -> int:
    """Column of free parameter ``name`` among ``names`` (one error text for every likelihood)."""
    try:
        return list(names).index(name)
    except ValueError:
        raise HbmError(f"{name!r} is not a free parameter; free parameters are {', '.join(names)}") from None

class Likelihood:
    """Log-likelihood of one specimen curve; built by :func:`make_likelihood`.

    Attributes
    ----------
    names : tuple of str
        Free parameters: free model parameters in model order, then the noise parameters.
    bounds : ndarray (d, 2)
        Box of the free parameters in working coordinates (the sampler's uniform prior support;
        ``[log lo, log hi]`` for loguniform parameters).
    natural_bounds : ndarray (d, 2)
        The same box in natural units.
    forms : tuple of str
        Prior form per free parameter ("uniform" or "loguniform").
    prior : Prior
        The effective prior: natural box and form of every model parameter (fixed ones
        included) and noise parameter.
    model : Model
    data : Specimen
        The specimen (a Dataset given to :func:`make_likelihood` is converted once).
    noise : str
        Name of the noise model.
    noise_model : NoiseModel
        The noise model bound to this curve (:mod:`hbm.likelihood.noise`).
    fixed : dict
        Fixed model parameters and their values.
    loading : Loading
        Strain/time/test passed to the model (history effects see the whole path).
    observed : ndarray (n_points,)
        Measured stress (MPa).
    weights : ndarray (n_points,)
        σ_e,i = max(max|σ_exp|/10, |σ_exp,i|) of thesis eq. 1.20 (used by "weighted" and by
        :meth:`wls`).
    """

    def __init__(self, model: Model, data, *, noise: str = "iid",
                 fix: Mapping[str, float] | None = None,
                 bounds: Mapping[str, tuple[float, float]] | None = None,
                 sigma_bounds: tuple[float, float] | None = None,
                 prior: Prior | str | Mapping | None = None) -> None:
        noise_cls = get_noise(noise)
        data = as_specimen(data)
        if data.key_extras():  # tests in other modes or further series: never fitted as along-fibre stress
            raise DataError(f"{data.id}: tests in loading modes {', '.join(data.load_cases)} with series "
                            f"{', '.join(data.observed)}: this likelihood fits along-fibre stress only; fit the "
                            "file with 'hbm fit' (hbm.fit.modes.fit_modes), which predicts every mode")
        stress = observed_stress(data)
        self.loading = data.loading
        self.model = model
        self.data = data
        self.noise = noise_cls.name
        self.label = data.id
        self.observed = stress
        self.n_points = stress.size
        self.weights = eq120_weights(stress)
        if not np.all(self.weights > 0):
            raise DataError(f"{self.label}: stress is identically zero; the weights of eq. 1.20 are undefined")
        self.noise_model: NoiseModel = noise_cls(observed=stress, history_starts=self.loading.history_starts)
        counts = bin_counts(data)
        if counts is not None:
            # a reduced dense record: each point is a bin mean of ``counts`` readings (hbm.data.reduction)
            self.noise_model = BinnedNoise(self.noise_model, counts)

        names = model.parameter_names
        box = model.bounds.copy()
        user_prior = load_prior(prior)
        forms = {n: "uniform" for n in names}
        if user_prior is not None:  # the user's prior replaces the thesis box (it may widen it)
            for n in names:
                if n in user_prior:
                    box[model.index(n)] = user_prior[n].lo, user_prior[n].hi
                    forms[n] = user_prior[n].form
        fix = dict(fix or {})
        bounds = dict(bounds or {})
        for kind, d in (("fix", fix), ("bounds", bounds)):
            unknown = [k for k in d if k not in names]
            if unknown:
                raise HbmError(f"{kind}: unknown parameter(s) {', '.join(unknown)}; "
                               f"the model has {', '.join(names)}")
        for k, (lo, hi) in bounds.items():
            lo, hi = float(lo), float(hi)
            i = model.index(k)
            if not (np.isfinite(lo) and np.isfinite(hi) and lo < hi):
                raise HbmError(f"bounds: {k} needs finite LO < HI, got {lo}:{hi}")
            if lo < box[i, 0] or hi > box[i, 1]:
                raise HbmError(f"bounds: {k}={lo}:{hi} is outside the prior box "
                               f"[{box[i, 0]:g}, {box[i, 1]:g}]")
            if forms[k] == "loguniform" and lo <= 0:
                raise PriorError(f"bounds: {k} is loguniform and needs LO > 0, got {lo:g}")
            box[i] = lo, hi
        for k, v in fix.items():
            v = float(v)
            i = model.index(k)
            if not (np.isfinite(v) and box[i, 0] <= v <= box[i, 1]):
                raise HbmError(f"fix: {k}={v} is outside its box [{box[i, 0]:g}, {box[i, 1]:g}]")
            fix[k] = v
        self.fixed = fix
        self.free_index = np.array([i for i, n in enumerate(names) if n not in fix], dtype=int)
        self.model_names = tuple(names[i] for i in self.free_index)
        self.n_model = len(self.model_names)
        self._fixed_row = np.array([fix.get(n, np.nan) for n in names], dtype=float)
        self._model_box = box  # all model parameters (fixed ones keep their box)

        nb = self.noise_model.box(sigma_bounds)
        clash = [p for p in nb if p in names]
        if clash:
            raise HbmError(f"noise model {self.noise!r}: parameter(s) {', '.join(clash)} "
                           "clash with model parameters")
        if user_prior is not None:
            user_prior.check_names(list(names) + list(nb), what=f"the model with {self.noise!r} noise")
            for n in nb:
                if n in user_prior:
                    nb[n] = (user_prior[n].lo, user_prior[n].hi)
                    forms[n] = user_prior[n].form
        self.noise_names = tuple(nb)
        self.names = self.model_names + self.noise_names
        self.natural_bounds = np.vstack([box[self.free_index].reshape(-1, 2), np.array(list(nb.values()), float)])
        self.forms = tuple(forms.get(n, "uniform") for n in self.names)
        self._log = np.array([f == "loguniform" for f in self.forms], dtype=bool)
        self._any_log = bool(self._log.any())
        self.bounds = self.from_natural(self.natural_bounds.T).T if self._any_log else self.natural_bounds
        self.d = len(self.names)
        allb = {n: tuple(box[i]) for i, n in enumerate(names)}
        allb.update({n: tuple(self.natural_bounds[self.n_model + j]) for j, n in enumerate(self.noise_names)})
        self.prior = Prior({n: (*allb[n], forms.get(n, "uniform")) for n in allb}, source="likelihood")

    # -- parameter handling ----------------------------------------------------------------
    def __repr__(self) -> str:
        return (f"<Likelihood {self.label}: {self.model.name}, noise={self.noise}, "
                f"{self.n_points} points, free={', '.join(self.names)}>")

    def index(self, name: str) -> int:
        """Column of free parameter ``name`` in theta."""
        return free_index(self.names, name)

    def with_bounds(self, **bounds: tuple[float, float]) -> "Likelihood":
        """A copy with some model-parameter boxes replaced (natural units; forms and noise boxes kept).

        Narrowing inside the current box is the common use (bound sweeps); a box outside it is
        accepted too and replaces it (a user prior may widen the thesis box).
        """
        unknown = [k for k in bounds if k not in self.model.parameter_names]
        if unknown:
            raise HbmError(f"bounds: unknown parameter(s) {', '.join(unknown)}; "
                           f"the model has {', '.join(self.model.parameter_names)}")
        new = Likelihood(self.model, self.data, noise=self.noise, fix=self.fixed,
                         prior=self.prior.override(bounds))
        return new

    def _as2d(self, theta) -> tuple[np.ndarray, bool]:
        theta = np.asarray(theta, dtype=float)
        single = theta.ndim == 1
        theta = np.atleast_2d(theta)
        if theta.ndim != 2 or theta.shape[1] != self.d:
            raise HbmError(f"theta must have shape (n, {self.d}) for parameters {', '.join(self.names)}, "
                           f"got {np.shape(theta)}")
        return theta, single

    def to_natural(self, theta) -> np.ndarray:
        """Working rows (sampler/optimiser coordinates) -> natural units (exp of loguniform columns).

        Any shape whose last axis has length ``d``; the identity (same values) without
        loguniform parameters.
        """
        return exp_columns(theta, self._log)

    def from_natural(self, theta) -> np.ndarray:
        """Natural-unit rows -> working coordinates (log of loguniform columns); inverse of :meth:`to_natural`."""
        return log_columns(theta, self._log)

    def _model_rows(self, nat: np.ndarray) -> np.ndarray:
        out = np.empty((nat.shape[0], self.model.n_params))
        out[:] = self._fixed_row
        out[:, self.free_index] = nat[:, : self.n_model]
        return out

    def model_theta(self, theta) -> np.ndarray:
        """Full model parameter rows (n, model.n_params) in natural units: free columns plus fixed values.

        ``theta`` is in working coordinates (see :meth:`to_natural`).
        """
        theta, _ = self._as2d(theta)
        return self._model_rows(self.to_natural(theta))

    def predict(self, theta) -> np.ndarray:
        """Model stress (n, n_points) at each parameter row."""
        with np.errstate(all="ignore"):
            return self.model.stress(self.loading, self.model_theta(theta))

    def in_box(self, theta) -> np.ndarray:
        """Boolean (n,): row finite and inside the box (NaN compares False)."""
        theta, _ = self._as2d(theta)
        return ((theta >= self.bounds[:, 0]) & (theta <= self.bounds[:, 1])).all(axis=1)

    def noise_sd(self, theta, model_stress: np.ndarray | None = None) -> np.ndarray:
        """Marginal noise sd per point, (n, n_points).

        ``model_stress`` (the prediction at ``theta``) is used by noise models whose sd depends
        on it; it is computed when needed and not given.
        """
        theta, _ = self._as2d(theta)
        m = model_stress
        if m is None and self.noise_model.needs_model_stress:
            m = self.predict(theta)
        return self.noise_model.sd(self.to_natural(theta)[:, self.n_model:], m)

    # -- log-likelihood ----------------------------------------------------------------------
    def __call__(self, theta) -> np.ndarray:
        """Log-likelihood of each row of ``theta`` (n, d) -> (n,); -inf out of box / non-finite."""
        theta, single = self._as2d(theta)
        out = np.full(theta.shape[0], -np.inf)
        ok = self.in_box(theta)
        if ok.all():
            sub = theta
        elif ok.any():
            sub = theta[ok]
        else:
            return out[0] if single else out
        nat = self.to_natural(sub)
        with np.errstate(all="ignore"):
            m = self.model.stress(self.loading, self._model_rows(nat))
            # overwrite: m is a temporary of ours, the residual may reuse its memory
            val = self.noise_model.loglik(nat[:, self.n_model:], m, overwrite=True)
        val = np.where(np.isfinite(val), val, -np.inf)  # NaN/inf from the model -> -inf
        if sub is theta:
            out = val
        else:
            out[ok] = val
        return out[0] if single else out

    def log_density(self, theta) -> np.ndarray:
        """Alias of ``__call__`` (the prior is uniform in working coordinates: a constant on the box)."""
        return self(theta)

    # -- weighted least squares (thesis eq. 1.19) --------------------------------------------
    def wls(self, theta_model) -> np.ndarray:
        """Er = Σ ((model_i − σ_exp,i)/σ_e,i)² (eq. 1.19) for rows of free *model* parameters.

        ``theta_model`` is (n, n_model) or (n, d) (noise columns ignored).  +inf out of box.
        """
        t = np.atleast_2d(np.asarray(theta_model, dtype=float))
        if t.shape[1] not in (self.n_model, self.d):
            raise HbmError(f"wls: theta must have {self.n_model} (or {self.d}) columns, got {t.shape[1]}")
        t = t[:, : self.n_model]
        box = self.bounds[: self.n_model]
        ok = np.isfinite(t).all(1) & (t >= box[:, 0]).all(1) & (t <= box[:, 1]).all(1)
        out = np.full(t.shape[0], np.inf)
        if ok.any():
            full = np.empty((int(ok.sum()), self.d))
            full[:, : self.n_model] = t[ok]
            full[:, self.n_model:] = self.bounds[self.n_model:].mean(axis=1)
            with np.errstate(all="ignore"):
                z = (self.predict(full) - self.observed) / self.weights
                e = np.einsum("ij,ij->i", z, z)
            out[ok] = np.where(np.isfinite(e), e, np.inf)
        return out

    # -- gradient and Fisher information -------------------------------------------------------
    def gradient_fim(self, theta) -> tuple[np.ndarray, np.ndarray]:
        """Gradient (n, d) of the log-likelihood and Fisher information (n, d, d).

        Exact gradient; expected (Gaussian) Fisher information, both with respect to the working
        coordinates (chain rule dθ/dy = θ for loguniform columns).  Rows that are out of the box
        or not finite get NaN so that callers (e.g. the manifold kernel) can fall back.
        """
        theta, _ = self._as2d(theta)
        n, d = theta.shape[0], self.d
        grad = np.full((n, d), np.nan)
        fim = np.full((n, d, d), np.nan)
        ok = self.in_box(theta)
        if not ok.any():
            return grad, fim
        t = self.to_natural(theta[ok])
        full = self._model_rows(t)
        with np.errstate(all="ignore"):
            m = self.model.stress(self.loading, full)
            jac = self.model.stress_jacobian(self.loading, full)[..., self.free_index]  # (n, P, k)
            g, f = self.noise_model.grad_fim(t[:, self.n_model:], m, jac)
            if self._any_log:  # d/dy = θ d/dθ for y = log θ
                s = np.where(self._log, t, 1.0)
                g = g * s
                f = f * s[:, :, None] * s[:, None, :]
        bad = ~(np.isfinite(g).all(1) & np.isfinite(f).all((1, 2)))
        g[bad] = np.nan
        f[bad] = np.nan
        grad[ok], fim[ok] = g, f
        return grad, fim

    # -- unit-box transforms (optimisers) ----------------------------------------------------
    def to_unit(self, theta) -> np.ndarray:
        lo, hi = self.bounds[:, 0], self.bounds[:, 1]
        return (np.asarray(theta, dtype=float) - lo) / (hi - lo)

    def from_unit(self, x) -> np.ndarray:
        lo, hi = self.bounds[:, 0], self.bounds[:, 1]
        return lo + np.asarray(x, dtype=float) * (hi - lo)

    def as_dict(self, row) -> dict[str, float]:
        """Free parameters of one (working-coordinate) row plus the fixed ones, as {name: natural value}.

        Model order, then noise parameters.
        """
        row = self.to_natural(np.asarray(row, dtype=float).ravel())
        full = self._model_rows(row[None])[0]
        out = {n: float(full[i]) for i, n in enumerate(self.model.parameter_names)}
        out.update({n: float(row[self.n_model + j]) for j, n in enumerate(self.noise_names)})
        return out


def make_likelihood(model: Model, data, *, noise: str = "iid", fix: Mapping[str, float] | None = None,
                    bounds: Mapping[str, tuple[float, float]] | None = None,
                    sigma_bounds: tuple[float, float] | None = None,
                    prior: Prior | str | Mapping | None = None) -> Likelihood:
    """Build the vectorised log-likelihood of one specimen.

    Parameters
    ----------
    model : Model
        Constitutive model (``model.stress`` receives the specimen's :class:`Loading`).
    data : Specimen or xarray.Dataset
        The specimen (:func:`hbm.data.load_specimen`); a Dataset with ``strain``, ``stress`` (MPa)
        along dim ``point`` and optional ``time``, ``test`` is converted once.
    noise : str
        Name of a registered noise model: "iid", "weighted", "proportional", "ar1" (see
        :mod:`hbm.likelihood.noise`) or one added with :func:`hbm.likelihood.noise.register_noise`.
    fix : dict, optional
        ``{name: value}`` model parameters held fixed (removed from the free set).
    bounds : dict, optional
        ``{name: (lo, hi)}`` narrowed boxes (must lie inside the prior box: the model's, or
        ``prior``'s).  To widen the thesis box use ``prior`` (:func:`hbm.likelihood.prior.resolve_prior`).
    sigma_bounds : (lo, hi), optional
        Box of the first noise parameter (``sigma``, or ``scale`` for "weighted").  Default for
        ``sigma``: [1e-4, max(0.05, 0.5·max|stress|)] MPa; for ``scale``: [1e-4, 10].
        A noise parameter named in ``prior`` takes the prior's box instead.
    prior : Prior, TOML path or mapping, optional
        User prior (:mod:`hbm.likelihood.prior`): boxes (may be wider than the thesis box) and forms; a
        loguniform parameter is sampled in log coordinates (module docstring).

    Returns
    -------
    Likelihood

    Raises
    ------
    HbmError
        Unknown noise model or parameter names, values outside the box.
    DataError
        Missing/non-finite data, or substantially compressive data for the thesis form of the
        Spyrou collagen (which turns tensile under axial compression, see
        :func:`hbm.model.spyrou.compression_check`).
    """
    data = as_specimen(data)
    if model_form(model) == "thesis":
        msg = compression_check(data.loading, "thesis", name=data.id)
        if msg is not None:
            raise DataError(msg)
    return Likelihood(model, data, noise=noise, fix=fix, bounds=bounds, sigma_bounds=sigma_bounds, prior=prior)
