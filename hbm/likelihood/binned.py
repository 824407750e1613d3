"""The noise of a reduced dense record: each point is the mean of a bin of raw readings.

A dense record reduced by :func:`hbm.data.reduction.reduce_record` holds, per point, the mean
of ``count`` raw readings (an *effective* count: the raw noise's correlation is accounted for).
:class:`BinnedNoise` wraps the noise model chosen for the raw readings and describes those
means, so every noise model of the registry applies unchanged:

* independent noise (iid, weighted, proportional, student_t): the mean of c readings of
  variance v has variance v/c, Gaussian (the central limit theorem; a Student-t reading
  enters through its variance, so ``student_t`` is no longer robust on a reduced record --
  the artefact screen runs on the raw rows first);
* AR(1): the residuals scaled to unit count, √c·r, follow the AR(1) of the raw readings' sd
  and a correlation ``rho`` between neighbouring bins.

Its noise parameters are those of the raw readings (``sigma`` is the sd of one reading), so a
fit of the reduced record reports the same noise as one of the full record, and its
log-likelihood is that of the bin means.  It keeps the wrapped model's name and parameters.
"""

from __future__ import annotations

import numpy as np

from ..errors import HbmError
from .noise import _LOG2PI, AR1Noise, NoiseModel

__all__ = ["BinnedNoise"]


class BinnedNoise(NoiseModel):
    """Noise of bin means (module docstring): ``inner`` describes one raw reading, ``counts`` (>0)
    the effective number of readings in each point."""

    def __init__(self, inner: NoiseModel, counts) -> None:
        counts = np.asarray(counts, dtype=float).ravel()
        if counts.size != inner.n_points or not np.all(counts > 0):
            raise HbmError(f"binned noise: {counts.size} positive counts expected for {inner.n_points} points")
        self.inner = inner
        self.name, self.names = inner.name, inner.names
        self.needs_model_stress = inner.needs_model_stress
        self.observed, self.history_starts, self.n_points = inner.observed, inner.history_starts, inner.n_points
        self.counts = counts
        self._root = np.sqrt(counts)
        self._half_log_counts = 0.5 * float(np.log(counts).sum())
        # AR(1) acts on the residuals scaled to unit count
        self._scaled = (AR1Noise(observed=None if inner.observed is None else inner.observed * self._root,
                                 history_starts=inner.history_starts) if isinstance(inner, AR1Noise) else None)

    def __repr__(self) -> str:
        return f"<BinnedNoise {self.inner!r}, {self.n_points} bin means of {self.counts.sum():.0f} readings>"

    def sigma_upper(self) -> float:
        return self.inner.sigma_upper()

    def default_box(self) -> dict[str, tuple[float, float]]:
        return self.inner.default_box()

    def box(self, sigma_bounds=None) -> dict[str, tuple[float, float]]:
        return self.inner.box(sigma_bounds)

    def sd(self, q, model_stress=None) -> np.ndarray:
        return self.inner.sd(q, model_stress) / self._root

    def variance(self, q, model_stress=None) -> np.ndarray:
        return self.inner.variance(q, model_stress) / self.counts

    def autocorrelation(self, q, lag) -> np.ndarray:
        return self.inner.autocorrelation(q, lag)

    def pointwise(self, q, model_stress) -> np.ndarray:
        if self._scaled is not None:
            return self._scaled.pointwise(q, model_stress * self._root) + np.log(self._root)
        r = self._need_observed() - model_stress
        v = self.variance(q, model_stress)
        return -0.5 * (_LOG2PI + np.log(v) + r * r / v)

    def loglik(self, q, model_stress, *, overwrite=False) -> np.ndarray:
        if self._scaled is not None:
            m = np.multiply(model_stress, self._root, out=model_stress if overwrite else None)
            return self._scaled.loglik(q, m, overwrite=True) + self._half_log_counts
        return self.pointwise(q, model_stress).sum(axis=1)

    def standard_draws(self, rng, q, n=None) -> np.ndarray:
        if isinstance(self.inner, AR1Noise):
            return self.inner.standard_draws(rng, q, n)
        return NoiseModel.standard_draws(self, rng, q, n)     # the mean of many readings: Gaussian

    def whiten_rows(self, a, q, *, sd=None, model_stress=None) -> np.ndarray:
        """The wrapped model's whitening with the sd of the bin means (σ/√count)."""
        if sd is None:
            sd = self.sd(np.atleast_2d(np.asarray(q, dtype=float)), model_stress)
        return self.inner.whiten_rows(a, q, sd=sd)

    def moment_guess(self, residual) -> dict[str, float]:
        return self.inner.moment_guess(np.asarray(residual, dtype=float) * self._root)

    def grad_fim(self, q, model_stress, jac):
        raise HbmError("a reduced dense record defines no Fisher information: use the 'rw' kernel")
