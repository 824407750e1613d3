"""Noise models of one stress-strain curve: one small class per model, in a registry.

A noise model describes the residual ``r = observed − model`` of one specimen.  An instance is
bound to one curve (its observed stress and its loading histories) and works on a population:
``q`` is always the ``(n, k)`` block of noise parameters (the last ``k`` columns of a
:class:`hbm.likelihood.Likelihood` theta) and model stress is ``(n, n_points)``.

=================  ====================  =====================================================
name               parameters            residual distribution
=================  ====================  =====================================================
``"iid"``          sigma                 r_i ~ N(0, sigma²) independent (thesis eq. 1.23)
``"weighted"``     scale                 r_i ~ N(0, (scale·σ_e,i)²), σ_e,i of eq. 1.20
``"proportional"`` sigma, sigma_rel      r_i ~ N(0, sigma² + (sigma_rel·model_i)²)
``"ar1"``          sigma, rho            stationary AR(1) along the points, restarted at each
                                         loading history (marginal sd sigma)
=================  ====================  =====================================================

Adding a noise model is one new :class:`NoiseModel` subclass passed to :func:`register_noise`
(usable as a class decorator); :func:`hbm.likelihood.make_likelihood` then accepts its name.
A subclass must set ``name`` and ``names`` and define :meth:`NoiseModel.default_box` and
:meth:`NoiseModel.sd`; everything else has a diagonal-Gaussian default built on ``sd``
(the Fisher information additionally needs :meth:`NoiseModel.variance_jacobian`).

The AR(1) recursion, its innovations and its whitening live here once (:class:`AR1Noise`);
the likelihood, the posterior predictive, the synthetic data and the diagnosis all call it.
"""

from __future__ import annotations

from typing import ClassVar

import numpy as np

from ..errors import HbmError

__all__ = ["NoiseModel", "IidNoise", "WeightedNoise", "ProportionalNoise", "AR1Noise", "NOISE_REGISTRY",
           "register_noise", "get_noise", "make_noise", "noise_model_names", "eq120_weights"]

_LOG2PI = float(np.log(2.0 * np.pi))


def eq120_weights(stress) -> np.ndarray:
    """Thesis weights σ_e,i = max(max|σ_exp|/10, |σ_exp,i|) (eq. 1.20).

    Parameters
    ----------
    stress : array (n_points,)
        Measured stress (MPa).

    Returns
    -------
    ndarray (n_points,)
    """
    stress = np.asarray(stress, dtype=float)
    return np.maximum(float(np.max(np.abs(stress))) / 10.0, np.abs(stress))


def _rows(q, n: int | None = None) -> np.ndarray:
    """Noise parameters as (n, k) rows; a single (k,) row is repeated ``n`` times (default 1)."""
    q = np.asarray(q, dtype=float)
    if q.ndim == 1:
        q = np.broadcast_to(q, (1 if n is None else int(n), q.size))
    if q.ndim != 2:
        raise HbmError(f"noise parameters must have shape (n, k) or (k,), got {q.shape}")
    return q


class NoiseModel:
    """Base class of the noise models of one curve (defaults: independent Gaussian noise).

    Parameters
    ----------
    observed : array (n_points,), optional
        Measured stress (MPa).  Needed by the log-likelihood, the prior box and models whose
        sd depends on the data; not by :meth:`simulate` for iid/AR(1) (synthetic data).
    history_starts : bool array (n_points,), optional
        True where a new loading history begins (:attr:`hbm.Loading.history_starts`); the first
        point must start one.  Default: one history.

    Attributes
    ----------
    name : str
        Registry name (class attribute).
    names : tuple of str
        Names of the noise parameters, in column order of ``q`` (class attribute).
    needs_model_stress : bool
        Whether :meth:`sd` depends on the model stress (class attribute).
    robust : bool
        Heavy-tailed, so robust to artefact rows (class attribute; :mod:`hbm.likelihood.student_t`).
    observed : ndarray or None
    history_starts : ndarray of bool
    n_points : int
    """

    name: ClassVar[str] = ""
    names: ClassVar[tuple[str, ...]] = ()
    needs_model_stress: ClassVar[bool] = False
    robust: ClassVar[bool] = False  # heavy-tailed: robust to artefact rows (kept, down-weighted)

    def __init__(self, *, observed=None, history_starts=None) -> None:
        if observed is None and history_starts is None:
            raise HbmError(f"noise model {self.name!r}: give the observed stress or the history starts")
        self.observed = None if observed is None else np.asarray(observed, dtype=float).ravel()
        if history_starts is None:
            starts = np.zeros(self.observed.size, dtype=bool)
            starts[:1] = True
        else:
            starts = np.asarray(history_starts, dtype=bool).ravel()
        if self.observed is not None and starts.size != self.observed.size:
            raise HbmError(f"noise model {self.name!r}: {starts.size} history flags for "
                           f"{self.observed.size} observed points")
        if starts.size == 0 or not starts[0]:
            raise HbmError(f"noise model {self.name!r}: the first point must start a loading history")
        self.history_starts = starts
        self.n_points = int(starts.size)

    def __repr__(self) -> str:
        return f"<{type(self).__name__} {self.name!r}: {', '.join(self.names)}; {self.n_points} points>"

    def _need_observed(self) -> np.ndarray:
        if self.observed is None:
            raise HbmError(f"noise model {self.name!r}: this needs the observed stress")
        return self.observed

    # -- prior box ---------------------------------------------------------------------------
    def sigma_upper(self) -> float:
        """Upper end of the default box of a stress-scale sd: max(0.05, 0.5·max|stress|) MPa."""
        return max(0.05, 0.5 * float(np.max(np.abs(self._need_observed()))))

    def default_box(self) -> dict[str, tuple[float, float]]:
        """``{name: (lo, hi)}`` of the uniform prior of each noise parameter, given the data."""
        raise NotImplementedError(f"{type(self).__name__} must define default_box()")

    def box(self, sigma_bounds: tuple[float, float] | None = None) -> dict[str, tuple[float, float]]:
        """Prior box of the noise parameters (in ``names`` order).

        Parameters
        ----------
        sigma_bounds : (lo, hi), optional
            Replaces the box of the first noise parameter (the scale: ``sigma`` or ``scale``).

        Returns
        -------
        dict
            ``{name: (lo, hi)}``.

        Raises
        ------
        HbmError
            ``sigma_bounds`` not finite with 0 < lo < hi.
        """
        nb = dict(self.default_box())
        if tuple(nb) != tuple(self.names):
            raise HbmError(f"noise model {self.name!r}: default_box() keys {tuple(nb)} differ from names "
                           f"{self.names}")
        if sigma_bounds is not None:
            lo, hi = map(float, sigma_bounds)
            if not (np.isfinite(lo) and np.isfinite(hi) and 0 < lo < hi):
                raise HbmError(f"sigma_bounds: need 0 < LO < HI, got {lo}:{hi}")
            nb[self.names[0]] = (lo, hi)
        return nb

    # -- marginal sd and variance --------------------------------------------------------------
    def sd(self, q, model_stress: np.ndarray | None = None) -> np.ndarray:
        """Marginal noise sd per point.

        Parameters
        ----------
        q : array (n, k)
            Noise parameters.
        model_stress : array (n, n_points), optional
            Model stress at each row (required when ``needs_model_stress``).

        Returns
        -------
        ndarray (n, n_points)
        """
        raise NotImplementedError(f"{type(self).__name__} must define sd()")

    def variance(self, q, model_stress: np.ndarray | None = None) -> np.ndarray:
        """Marginal variance per point (n, n_points) (default ``sd²``)."""
        return self.sd(q, model_stress) ** 2

    def effective_sd(self, q, residual, model_stress: np.ndarray | None = None) -> np.ndarray:
        """The sd of a point's weight at this residual (n, n_points): the marginal sd, larger for an
        outlier of a :attr:`robust` model (its IRLS weight; the detective's windows and screens)."""
        return self.sd(q, model_stress)

    def autocorrelation(self, q, lag) -> np.ndarray:
        """Correlation of the noise at points ``lag`` apart within one history (standardised).

        Parameters
        ----------
        q : array (k,)
            One row of noise parameters.
        lag : int or int array
            Non-negative lags.

        Returns
        -------
        ndarray (shape of ``lag``)
            1 at lag 0, 0 elsewhere for independent noise.
        """
        return np.where(np.asarray(lag) == 0, 1.0, 0.0)

    # -- log-likelihood ----------------------------------------------------------------------
    def pointwise(self, q, model_stress: np.ndarray) -> np.ndarray:
        """Pointwise log-likelihood (n, n_points) whose row sums are :meth:`loglik`.

        For independent noise the terms are the marginal Gaussian log-densities.
        """
        r = self._need_observed() - model_stress
        sd = self.sd(q, model_stress)
        return -0.5 * (_LOG2PI + 2 * np.log(sd) + (r / sd) ** 2)

    def loglik(self, q, model_stress: np.ndarray, *, overwrite: bool = False) -> np.ndarray:
        """Log-likelihood (n,) of the observed curve at each row.

        Parameters
        ----------
        q : array (n, k)
            Noise parameters (inside their box).
        model_stress : array (n, n_points)
            Model stress at each row.
        overwrite : bool
            The caller owns ``model_stress`` as scratch space (saves one (n, n_points) temporary).

        Returns
        -------
        ndarray (n,)
            May hold NaN/inf where the model stress is not finite (the caller maps them to −inf).
        """
        return self.pointwise(q, model_stress).sum(axis=1)

    # -- simulation ----------------------------------------------------------------------------
    def standard_draws(self, rng: np.random.Generator, q, n: int | None = None) -> np.ndarray:
        """Noise with unit marginal variance and this model's correlation, (n, n_points).

        Draws ``rng.standard_normal((n, n_points))`` once (so the stream is that of independent
        noise) and correlates it in place where the model has correlation.

        Parameters
        ----------
        rng : numpy.random.Generator
        q : array (n, k) or (k,)
            Noise parameters per replicate (a single row is used for all ``n`` replicates).
        n : int, optional
            Number of replicates when ``q`` is a single row.
        """
        q = _rows(q, n)
        return rng.standard_normal((q.shape[0], self.n_points))

    def simulate(self, rng: np.random.Generator, q, model_stress: np.ndarray | None = None) -> np.ndarray:
        """Noise draws sd · z (n, n_points): add them to the model stress for a replicate curve.

        Parameters
        ----------
        rng : numpy.random.Generator
        q : array (n, k) or (k,)
            Noise parameters, one replicate per row.
        model_stress : array (n, n_points), optional
            Model stress at each row (required when ``needs_model_stress``).
        """
        q = _rows(q)
        return self.sd(q, model_stress) * self.standard_draws(rng, q)

    # -- whitening -----------------------------------------------------------------------------
    def whiten(self, a, q, *, sd=None, model_stress=None) -> np.ndarray:
        """Map residuals or Jacobian columns to noise-whitened units (iid N(0, 1) noise).

        Parameters
        ----------
        a : array (n_points,) or (n_points, ...)
            Residuals, or Jacobian columns, with the points along the first axis.
        q : array (k,)
            One row of noise parameters.
        sd : array (n_points,), optional
            Marginal sd to use instead of the one implied by ``q`` (e.g. a model-free estimate).
        model_stress : array (n_points,), optional
            Model stress, when the sd implied by ``q`` depends on it.

        Returns
        -------
        ndarray (shape of ``a``)
            W a with W Σ Wᵀ = I for the noise covariance Σ; independent noise: a / sd.
        """
        m = None if model_stress is None else np.asarray(model_stress, dtype=float)[None, :]
        s = None if sd is None else np.asarray(sd, dtype=float)[None, :]
        return self.whiten_rows(np.asarray(a, dtype=float)[None], _rows(q), sd=s, model_stress=m)[0]

    def whiten_rows(self, a, q, *, sd=None, model_stress=None) -> np.ndarray:
        """:meth:`whiten` for a population: row i of ``a`` whitened with its own noise parameters.

        Parameters
        ----------
        a : array (n, n_points) or (n, n_points, ...)
            Residuals or Jacobian columns per row, the points along the second axis.
        q : array (n, k)
            Noise parameters, one row per row of ``a``.
        sd : array (n, n_points), optional
            Marginal sd per row instead of the one implied by ``q``.
        model_stress : array (n, n_points), optional
            Model stress per row, when the sd implied by ``q`` depends on it.

        Returns
        -------
        ndarray (shape of ``a``)
        """
        if sd is None:
            sd = self.sd(_rows(q), model_stress)
        sd = np.asarray(sd, dtype=float)
        a = np.asarray(a, dtype=float)
        return a / sd.reshape(sd.shape + (1,) * (a.ndim - 2))

    # -- starting values -----------------------------------------------------------------------
    def moment_guess(self, residual) -> dict[str, float]:
        """Moment estimates of the noise parameters from one residual curve (starting values).

        Parameters
        ----------
        residual : array (n_points,)
            observed − model at some fit.

        Returns
        -------
        dict
            ``{name: value}`` for the parameters this model can estimate in closed form.
        """
        r = np.asarray(residual, dtype=float)
        return {self.names[0]: float(np.sqrt(np.mean(r * r)))}

    # -- gradient and Fisher information --------------------------------------------------------
    def variance_jacobian(self, q, model_stress: np.ndarray, jac: np.ndarray) -> np.ndarray:
        """∂v_i/∂(model parameters, noise parameters), (n, n_points, k_model + k)."""
        raise HbmError(f"noise model {self.name!r} defines no variance_jacobian: no gradient/Fisher "
                       "information (use the 'rw' kernel)")

    def grad_fim(self, q, model_stress: np.ndarray, jac: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Gradient of the log-likelihood and expected Fisher information.

        Diagonal Gaussian with mean m(θ) and variance v(θ):
        F = Jmᵀ V⁻¹ Jm + ½ Σ_i ∇v_i ∇v_iᵀ / v_i².

        Parameters
        ----------
        q : array (n, k)
            Noise parameters.
        model_stress : array (n, n_points)
        jac : array (n, n_points, k_model)
            ∂model_stress/∂(free model parameters).

        Returns
        -------
        grad : ndarray (n, k_model + k)
        fim : ndarray (n, k_model + k, k_model + k)
        """
        n, P, k = jac.shape
        d = k + len(self.names)
        r = self._need_observed() - model_stress
        g = np.zeros((n, d))
        f = np.zeros((n, d, d))
        v = self.variance(q, model_stress)
        iv = 1.0 / v
        # mean part: Jᵀ V⁻¹ r and Jᵀ V⁻¹ J as batched matmuls (einsum with three operands is slow)
        g[:, :k] = np.matmul((r * iv)[:, None, :], jac)[:, 0, :]
        a = jac * np.sqrt(iv)[..., None]
        f[:, :k, :k] = np.matmul(np.swapaxes(a, 1, 2), a)
        # variance part: ½ Σ (r²/v² − 1/v) ∇v and ½ Σ ∇v ∇vᵀ / v²
        c = 0.5 * (r * r * iv * iv - iv)
        self._variance_terms(q, model_stress, jac, c, iv, g, f)
        return g, f

    def _variance_terms(self, q, m, jac, c, iv, g, f) -> None:
        """Add the variance part of the gradient and FIM (in place), from ∇v."""
        jv = self.variance_jacobian(q, m, jac)
        g += np.matmul(c[:, None, :], jv)[:, 0, :]
        b = jv * (iv / np.sqrt(2.0))[..., None]
        f += np.matmul(np.swapaxes(b, 1, 2), b)


def _constant_sd(q: np.ndarray, n_points: int) -> np.ndarray:
    return np.broadcast_to(q[:, :1], (q.shape[0], n_points)).copy()


class IidNoise(NoiseModel):
    """r_i ~ N(0, sigma²) independent (thesis eq. 1.23); ``sigma`` in MPa."""

    name = "iid"
    names = ("sigma",)

    def default_box(self) -> dict[str, tuple[float, float]]:
        return {"sigma": (1e-4, self.sigma_upper())}

    def sd(self, q, model_stress=None) -> np.ndarray:
        return _constant_sd(q, self.n_points)

    def variance(self, q, model_stress=None) -> np.ndarray:
        return np.broadcast_to(q[:, :1] ** 2, (q.shape[0], self.n_points))

    def loglik(self, q, model_stress, *, overwrite=False) -> np.ndarray:
        npt = self.n_points
        r = np.subtract(self._need_observed(), model_stress, out=model_stress if overwrite else None)
        s = q[:, 0]
        ssr = np.einsum("ij,ij->i", r, r)
        return -0.5 * npt * _LOG2PI - npt * np.log(s) - 0.5 * ssr / (s * s)

    def _variance_terms(self, q, m, jac, c, iv, g, f) -> None:
        k, sg = jac.shape[-1], q[:, 0]
        g[:, k] = (c * 2.0 * sg[:, None]).sum(axis=1)
        f[:, k, k] = 2.0 * self.n_points / (sg * sg)


class WeightedNoise(NoiseModel):
    """r_i ~ N(0, (scale·σ_e,i)²), σ_e,i = max(max|σ_exp|/10, |σ_exp,i|) (thesis eqs. 1.19–1.20).

    ``scale`` is dimensionless; its MAP is the weighted least-squares optimum of eq. 1.19.
    """

    name = "weighted"
    names = ("scale",)

    def __init__(self, *, observed=None, history_starts=None) -> None:
        super().__init__(observed=observed, history_starts=history_starts)
        self.weights = eq120_weights(self._need_observed())
        self._inv_weights = 1.0 / self.weights
        self._log_weights_sum = float(np.log(self.weights).sum())

    def default_box(self) -> dict[str, tuple[float, float]]:
        return {"scale": (1e-4, 10.0)}

    def sd(self, q, model_stress=None) -> np.ndarray:
        return q[:, :1] * self.weights

    def variance(self, q, model_stress=None) -> np.ndarray:
        return q[:, :1] ** 2 * self.weights ** 2

    def loglik(self, q, model_stress, *, overwrite=False) -> np.ndarray:
        npt = self.n_points
        s = q[:, 0]
        z = np.subtract(self.observed, model_stress, out=model_stress if overwrite else None)
        z *= self._inv_weights
        ssr = np.einsum("ij,ij->i", z, z)
        return (-0.5 * npt * _LOG2PI - npt * np.log(s) - self._log_weights_sum
                - 0.5 * ssr / (s * s))

    def moment_guess(self, residual) -> dict[str, float]:
        r = np.asarray(residual, dtype=float)
        return {"scale": float(np.sqrt(np.mean((r / self.weights) ** 2)))}

    def _variance_terms(self, q, m, jac, c, iv, g, f) -> None:
        k, sg = jac.shape[-1], q[:, 0]
        g[:, k] = (c * 2.0 * sg[:, None] * self.weights ** 2).sum(axis=1)
        f[:, k, k] = 2.0 * self.n_points / (sg * sg)


class ProportionalNoise(NoiseModel):
    """r_i ~ N(0, sigma² + (sigma_rel·model_i)²): an absolute floor plus a part growing with stress."""

    name = "proportional"
    names = ("sigma", "sigma_rel")
    needs_model_stress = True

    def default_box(self) -> dict[str, tuple[float, float]]:
        return {"sigma": (1e-4, self.sigma_upper()), "sigma_rel": (0.0, 0.5)}

    def sd(self, q, model_stress=None) -> np.ndarray:
        if model_stress is None:
            raise HbmError("noise model 'proportional': the sd needs the model stress")
        return np.sqrt(q[:, :1] ** 2 + (q[:, 1:2] * model_stress) ** 2)

    def variance(self, q, model_stress=None) -> np.ndarray:
        s, sr = q[:, :1], q[:, 1:2]
        return s * s + (sr * model_stress) ** 2

    def loglik(self, q, model_stress, *, overwrite=False) -> np.ndarray:
        m = model_stress
        r = self._need_observed() - m
        v = q[:, :1] ** 2 + (q[:, 1:2] * m) ** 2
        return -0.5 * (self.n_points * _LOG2PI + np.log(v).sum(axis=1) + (r * r / v).sum(axis=1))

    def moment_guess(self, residual) -> dict[str, float]:
        # the relative part is not identifiable from one residual curve: a small default
        return {**super().moment_guess(residual), "sigma_rel": 0.05}

    def variance_jacobian(self, q, model_stress, jac) -> np.ndarray:
        n, P, k = jac.shape
        s, sr, m = q[:, :1], q[:, 1:2], model_stress
        jv = np.empty((n, P, k + 2))
        jv[..., :k] = (2.0 * sr * sr * m)[..., None] * jac
        jv[..., k] = 2.0 * s
        jv[..., k + 1] = 2.0 * sr * m * m
        return jv


class AR1Noise(NoiseModel):
    """Stationary AR(1) noise along the points, restarted at the start of each loading history.

    r_1 ~ N(0, sigma²), r_t = rho·r_{t−1} + u_t, u_t ~ N(0, sigma²(1−rho²)): ``sigma`` is the
    marginal sd, ``rho`` in [0, 0.99] (the simulation and whitening accept (−1, 1)).  The exact
    likelihood is evaluated through the innovations u_t; its Fisher information uses the
    whitened Jacobian K_t = J_t − rho·J_{t−1} and the closed-form (sigma, rho) block
    F_σσ = 2n/σ², F_σρ = −2ρ(n−h)/(σ(1−ρ²)), F_ρρ = (n−h)(1+ρ²)/(1−ρ²)² (h histories).
    """

    name = "ar1"
    names = ("sigma", "rho")

    def __init__(self, *, observed=None, history_starts=None) -> None:
        super().__init__(observed=observed, history_starts=history_starts)
        self._cont = (~self.history_starts).astype(float)  # a_t: 1 where the AR(1) continues from t−1
        self._cont_index = np.flatnonzero(~self.history_starts)
        self._n_hist = int(self.history_starts.sum())

    def default_box(self) -> dict[str, tuple[float, float]]:
        return {"sigma": (1e-4, self.sigma_upper()), "rho": (0.0, 0.99)}

    def sd(self, q, model_stress=None) -> np.ndarray:
        return _constant_sd(q, self.n_points)

    def autocorrelation(self, q, lag) -> np.ndarray:
        return np.asarray(q, dtype=float)[1] ** lag

    def _innov(self, q, r) -> np.ndarray:
        u = r.copy()
        u[:, 1:] -= (q[:, 1][:, None] * self._cont[1:]) * r[:, :-1]
        return u

    def innovations(self, q, residual) -> tuple[np.ndarray, np.ndarray]:
        """Innovations u_t = r_t − rho·a_t·r_{t−1} and their variances sigma²(1 − rho²·a_t).

        a_t is 0 at a history start (u_t = r_t, variance sigma²), 1 elsewhere.

        Parameters
        ----------
        q : array (n, 2)
            sigma, rho per row.
        residual : array (n, n_points)

        Returns
        -------
        u, v : ndarray (n, n_points)
            Independent N(0, v) under the model.
        """
        s, rho = q[:, :1], q[:, 1:2]
        return self._innov(q, residual), s * s * (1.0 - rho * rho * self._cont)

    def loglik(self, q, model_stress, *, overwrite=False) -> np.ndarray:
        # var_t = sigma²(1 − rho²·a_t): the sums over t split into history starts (a=0) and
        # continued points (a=1), so only (n,) work remains after one pass over u
        npt = self.n_points
        s, rho = q[:, 0], q[:, 1]
        u = self._innov(q, self._need_observed() - model_stress)
        u2 = u * u
        start_ss = u2 @ (1.0 - self._cont)
        cont_ss = u2.sum(axis=1) - start_ss
        w = 1.0 - rho * rho
        nc = npt - self._n_hist
        return -0.5 * (npt * _LOG2PI + 2.0 * npt * np.log(s) + nc * np.log(w)
                       + (start_ss + cont_ss / w) / (s * s))

    def pointwise(self, q, model_stress) -> np.ndarray:
        """Conditional log-densities log p(r_t | r_{t−1}) of the innovations (exact factorisation
        of the joint Gaussian, as PSIS-LOO expects)."""
        u, v = self.innovations(q, self._need_observed() - model_stress)
        return -0.5 * (_LOG2PI + np.log(v) + u * u / v)

    def standard_draws(self, rng, q, n=None) -> np.ndarray:
        z = super().standard_draws(rng, q, n)
        rho = _rows(q, n)[:, 1]
        if np.any(rho != 0.0):
            innov = np.sqrt(1.0 - rho * rho)
            # loop over points (not samples): the recursion is sequential along the curve
            for t in self._cont_index:
                z[:, t] = rho * z[:, t - 1] + innov * z[:, t]
        return z

    def whiten_rows(self, a, q, *, sd=None, model_stress=None) -> np.ndarray:
        """Divide by the marginal sd, then take scaled innovations
        u_t = (z_t − ρ z_{t−1})/√(1−ρ²) (u = z at history starts), row by row with each row's ρ:
        iid N(0, 1) noise."""
        z = super().whiten_rows(a, q, sd=sd, model_stress=model_stress)
        rho = _rows(q)[:, 1]
        if not np.any(rho != 0.0):
            return z
        c = np.sqrt(np.maximum(1.0 - rho * rho, 1e-12))
        shape = (-1,) + (1,) * (z.ndim - 1)
        out = np.empty_like(z)
        out[:, 1:] = (z[:, 1:] - rho.reshape(shape) * z[:, :-1]) / c.reshape(shape)
        out[:, self.history_starts] = z[:, self.history_starts]
        return out

    def moment_guess(self, residual) -> dict[str, float]:
        """sigma from the mean square; rho from the lag-1 autocorrelation within histories,
        clipped to [0.05, 0.9] (a start on the box edge rho = 0 tends to stay there)."""
        r = np.asarray(residual, dtype=float)
        cont = ~self.history_starts[1:]
        r1 = float(np.sum(r[1:][cont] * r[:-1][cont]) / max(np.sum(r * r), 1e-300))
        return {**super().moment_guess(r), "rho": float(np.clip(r1, 0.05, 0.9))}

    def grad_fim(self, q, model_stress, jac) -> tuple[np.ndarray, np.ndarray]:
        n, P, k = jac.shape
        r = self._need_observed() - model_stress
        g = np.zeros((n, k + 2))
        f = np.zeros((n, k + 2, k + 2))
        s, rho = q[:, :1], q[:, 1:2]
        a = self._cont
        u, v = self.innovations(q, r)
        jprev = np.zeros_like(jac)
        jprev[:, 1:] = jac[:, :-1]
        kk = jac - (rho * a)[..., None] * jprev  # whitened Jacobian K_t
        w = u / v
        g[:, :k] = np.einsum("np,npk->nk", w, kk)
        rprev = np.zeros_like(r)
        rprev[:, 1:] = r[:, :-1]
        z = u * u / v
        g[:, k] = ((z - 1.0).sum(axis=1)) / s[:, 0]
        g[:, k + 1] = (w * a * rprev).sum(axis=1) + ((z - 1.0) / v * (-rho * a * s * s)).sum(axis=1)
        a = kk / np.sqrt(v)[..., None]
        f[:, :k, :k] = np.matmul(np.swapaxes(a, 1, 2), a)
        nc = P - self._n_hist  # number of continued (t ≥ 2) points
        s0, r0 = s[:, 0], rho[:, 0]
        f[:, k, k] = 2.0 * P / (s0 * s0)
        f[:, k, k + 1] = f[:, k + 1, k] = -2.0 * r0 * nc / (s0 * (1.0 - r0 * r0))
        f[:, k + 1, k + 1] = nc * (1.0 + r0 * r0) / (1.0 - r0 * r0) ** 2
        return g, f


# -----------------------------------------------------------------------------------------
# registry
# -----------------------------------------------------------------------------------------
#: noise model name -> NoiseModel subclass
NOISE_REGISTRY: dict[str, type[NoiseModel]] = {}


def register_noise(cls: type[NoiseModel], *, replace: bool = False) -> type[NoiseModel]:
    """Register a :class:`NoiseModel` subclass under ``cls.name`` (usable as a decorator).

    Parameters
    ----------
    cls : type
        Subclass with ``name``, ``names``, ``default_box`` and ``sd``.
    replace : bool
        Allow replacing a different class already registered under the same name.

    Returns
    -------
    type
        ``cls`` (so that ``@register_noise`` leaves the class usable).

    Raises
    ------
    HbmError
        Not a NoiseModel subclass, empty/duplicate names, or the name is taken.
    """
    if not (isinstance(cls, type) and issubclass(cls, NoiseModel)):
        raise HbmError(f"register_noise: {cls!r} is not a subclass of hbm.likelihood.noise.NoiseModel")
    name, names = cls.name, cls.names
    if not (isinstance(name, str) and name):
        raise HbmError(f"register_noise: {cls.__name__} needs a non-empty class attribute 'name'")
    if not (isinstance(names, tuple) and names and all(isinstance(p, str) and p for p in names)
            and len(set(names)) == len(names)):
        raise HbmError(f"register_noise: {cls.__name__}.names must be a non-empty tuple of distinct "
                       f"parameter names, got {names!r}")
    old = NOISE_REGISTRY.get(name)
    if old is not None and old is not cls and not replace:
        raise HbmError(f"register_noise: noise model {name!r} is already registered ({old.__name__})")
    NOISE_REGISTRY[name] = cls
    return cls


for _cls in (IidNoise, WeightedNoise, ProportionalNoise, AR1Noise):
    register_noise(_cls)


def noise_model_names() -> tuple[str, ...]:
    """Names of the registered noise models (registration order)."""
    return tuple(NOISE_REGISTRY)


def get_noise(name: str) -> type[NoiseModel]:
    """The registered noise model class called ``name``.

    Raises
    ------
    HbmError
        Unknown name.
    """
    try:
        return NOISE_REGISTRY[name]
    except (KeyError, TypeError):
        raise HbmError(f"noise model must be one of {', '.join(NOISE_REGISTRY)}, got {name!r}") from None


def make_noise(name: str, *, observed=None, history_starts=None) -> NoiseModel:
    """Instance of the registered noise model ``name`` bound to one curve (see :class:`NoiseModel`)."""
    return get_noise(name)(observed=observed, history_starts=history_starts)
