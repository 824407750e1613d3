"""``student_t``: heavy-tailed noise, for a fit that is robust to artefacts on purpose.

r_i ~ sigma · t_nu independent: a Student-t with scale ``sigma`` (MPa) and ``nu`` degrees of
freedom, ``nu`` in [1, 50] (1: Cauchy tails; large: Gaussian).  A single artefact row -- a
pre-test reading at six times the peak -- costs a Gaussian fit (r/σ)²/2 ≈ 10⁴ nats and bends
every parameter towards it; under t noise it costs (ν+1)/2·log(1 + r²/(νσ²)), a few tens of
nats whatever its size, so the rest of the curve decides the fit.  Registered like every noise
model (``--noise student_t`` in every command); it is never chosen by the detective on its own
(its default noise models are iid, proportional and AR(1)): robustness is the user's choice,
and the artefact screen (:mod:`hbm.data.artefacts`) names the rows it would down-weight.

``sd`` is the scale ``sigma`` (the marginal sd σ·√(ν/(ν−2)) exists only for ν > 2); simulation
draws t variates.  No Fisher information is defined: the manifold kernel refuses this model.
"""

from __future__ import annotations

import numpy as np
from scipy.special import gammaln

from .noise import NoiseModel, _constant_sd, _rows, register_noise

__all__ = ["StudentTNoise"]


@register_noise
class StudentTNoise(NoiseModel):
    """r_i ~ sigma · t_nu independent (module docstring)."""

    name = "student_t"
    names = ("sigma", "nu")
    robust = True

    def default_box(self) -> dict[str, tuple[float, float]]:
        return {"sigma": (1e-4, self.sigma_upper()), "nu": (1.0, 50.0)}

    def sd(self, q, model_stress=None) -> np.ndarray:
        return _constant_sd(q, self.n_points)

    def effective_sd(self, q, residual, model_stress=None) -> np.ndarray:
        """σ·√((ν + (r/σ)²)/(ν + 1)): the IRLS weight (ν + 1)/(ν + (r/σ)²) of a t residual as a sd."""
        s, nu = q[:, :1], q[:, 1:2]
        return s * np.sqrt((nu + (np.asarray(residual) / s) ** 2) / (nu + 1.0))

    def _terms(self, q, r) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        s, nu = q[:, :1], q[:, 1:2]
        const = gammaln(0.5 * (nu + 1.0)) - gammaln(0.5 * nu) - 0.5 * np.log(nu * np.pi) - np.log(s)
        return const, nu, np.log1p(r * r / (nu * s * s))

    def pointwise(self, q, model_stress) -> np.ndarray:
        r = self._need_observed() - model_stress
        const, nu, log1p = self._terms(q, r)
        return const - 0.5 * (nu + 1.0) * log1p

    def loglik(self, q, model_stress, *, overwrite=False) -> np.ndarray:
        r = np.subtract(self._need_observed(), model_stress, out=model_stress if overwrite else None)
        const, nu, log1p = self._terms(q, r)
        return self.n_points * const[:, 0] - 0.5 * (nu[:, 0] + 1.0) * log1p.sum(axis=1)

    def standard_draws(self, rng: np.random.Generator, q, n: int | None = None) -> np.ndarray:
        """t draws of scale 1 with each row's ``nu`` (variance ν/(ν−2), infinite for ν ≤ 2)."""
        q = _rows(q, n)
        return rng.standard_t(q[:, 1:2], (q.shape[0], self.n_points))

    def moment_guess(self, residual) -> dict[str, float]:
        """sigma from the median absolute residual (robust: an artefact does not inflate it), nu 4."""
        r = np.asarray(residual, dtype=float)
        mad = float(np.median(np.abs(r - np.median(r))))
        return {"sigma": 1.4826 * mad if mad > 0 else float(np.sqrt(np.mean(r * r))), "nu": 4.0}
