"""The collapsed likelihood: the amplitudes integrated out exactly, a function of φ only.

Given the nonlinear parameters φ (and the noise parameters) the model stress is X(φ)·A, with A
the column amplitudes of the model's linear structure (:mod:`hbm.model.linear`).  For Gaussian
noise whose covariance Σ does not depend on the stress (``iid``, ``weighted``, ``ar1``):

    log L_c(φ) = log ∫ p(A | φ) N(y; X(φ)A, Σ) dA
               = −½ n log 2π − ½ log|Σ| + log ∫ p(A | φ) exp(−½ ‖W(y − XA)‖²) dA

with W the whitening of :mod:`hbm.likelihood.noise` (1/sd, or the scaled AR(1) innovations) and p(A | φ)
the prior the columns inherit from the original parameters (:mod:`hbm.likelihood.collapsed.induced`).  The
integral is :class:`hbm.likelihood.collapsed.quadrature.BoxGaussianIntegral`.  Then

    Z = ∫ p(φ) L_c(φ) dφ

exactly, so a sampler over φ alone (TMCMC: the prior stays uniform on the φ box in the
likelihood's working coordinates) gives the same evidence as one over all parameters, and
:meth:`CollapsedLikelihood.complete` draws the amplitudes and the original parameters given φ.

``proportional`` noise (variance depends on the amplitudes) and models without a linear
structure are refused with the reason (:func:`collapse_reason`).
"""

from __future__ import annotations

import warnings
from typing import Any

import numpy as np

from ...errors import HbmError, SettingError
from ..core import Likelihood
from ...model.core import Model
from ...model.linear import structure_of, why_not_linear
from ...samplers.moves import needs_gradient
from ..noise import AR1Noise, IidNoise, WeightedNoise
from .induced import CollapseError, ColumnPrior, Term
from .quadrature import BoxGaussianIntegral

__all__ = ["CollapsedLikelihood", "collapse_reason", "choose_tier", "GAUSSIAN_NOISE", "TIERS"]

#: the likelihood tiers (the registry of ``FitSettings.tier`` / ``--tier``): auto, collapsed, full
TIERS = ("auto", "collapsed", "full")

#: noise models under which the amplitude integral stays Gaussian (their covariance does not
#: depend on the model stress); exact classes, since a subclass may change the covariance
GAUSSIAN_NOISE = (IidNoise, WeightedNoise, AR1Noise)


def collapse_reason(lik: Likelihood, structure) -> str | None:
    """Why the collapsed likelihood cannot be used for ``lik`` (None when it can).

    Parameters
    ----------
    lik : Likelihood
    structure : LinearStructure or None
        The model's linear structure (None: the model has none; :func:`why_not_linear` says why).
    """
    if structure is None:
        why = why_not_linear(lik.model) or "it declares no linear structure"
        return f"model {lik.model.name!r} has no linear amplitudes: {why}"
    if type(lik.noise_model) not in GAUSSIAN_NOISE:
        return (f"noise model {lik.noise!r}: its covariance is not fixed given the noise parameters "
                "(it depends on the amplitudes), so the integral over them is not Gaussian")
    free = [p for p in structure.amplitude_parameters if p not in lik.fixed]
    if not free:
        return "every amplitude parameter is held fixed: nothing to integrate"
    for col in structure.columns:
        terms = [p for p in structure.amplitude_parameters if structure.column_of[p] == col and p not in lik.fixed]
        if len(terms) > 2:
            return (f"column {col}: {len(terms)} free parameters ({', '.join(terms)}) feed one amplitude; "
                    "the induced prior is derived for sums of one or two")
    return None


class CollapsedLikelihood:
    """log L_c(φ) of one specimen (module docstring), vectorised over a population of φ.

    Parameters
    ----------
    lik : Likelihood
        The full likelihood (model, data, noise, fixed parameters and prior are taken from it).
    structure : LinearStructure, optional
        The model's linear structure; default :func:`hbm.model.linear.structure_of` of the model.
    nodes : int
        Gauss–Legendre nodes per panel of each outer amplitude column.
    width : float
        Quadrature window half-width in conditional sd.

    Attributes
    ----------
    names : tuple of str
        Sampled parameters: the free nonlinear model parameters (model order), then the noise
        parameters.
    bounds : ndarray (d, 2)
        Their box in the full likelihood's working coordinates (log for loguniform).
    n_evaluations : int
        Rows evaluated so far (each one evaluation of the model's basis).

    Raises
    ------
    CollapseError
        :func:`collapse_reason` says why not; or a weight of an amplitude parameter can vanish
        inside the φ box.
    """

    def __init__(self, lik: Likelihood, structure=None, *, nodes: int = 6, width: float = 5.0) -> None:
        if structure is None:
            structure = structure_of(lik.model)
        why = collapse_reason(lik, structure)
        if why is not None:
            raise CollapseError(f"collapsed likelihood not available: {why}")
        self.lik = lik
        self.structure = structure
        self.nodes, self.width = int(nodes), float(width)
        amp = tuple(structure.amplitude_parameters)
        self.amplitude_parameters = amp
        self.amp_index = np.array([lik.index(p) if p in lik.names else -1 for p in amp], dtype=int)
        self.phi_index = np.array([i for i, n in enumerate(lik.names) if n not in amp], dtype=int)
        self.names = tuple(lik.names[i] for i in self.phi_index)
        self.bounds = np.asarray(lik.bounds, float)[self.phi_index]
        self.d = len(self.names)
        self.n_evaluations = 0
        # working-coordinate row template: amplitude columns at their box middle (ignored by the basis)
        self._template = np.asarray(lik.bounds, float).mean(axis=1)
        self.columns = tuple(structure.columns)
        self.terms: dict[str, list[Term]] = {}
        self.fixed_terms: dict[str, list[tuple[int, float]]] = {}
        for c in self.columns:
            self.terms[c], self.fixed_terms[c] = [], []
        for i, p in enumerate(amp):
            c = structure.column_of[p]
            if p in lik.fixed:
                self.fixed_terms[c].append((i, float(lik.fixed[p])))
            else:
                e = lik.prior[p]
                self.terms[c].append(Term.of(p, e.lo, e.hi, e.form))
        self._term_index = {c: [amp.index(t.name) for t in self.terms[c]] for c in self.columns}
        # columns whose parameters are all fixed are known curves: moved into the data
        self.free_columns = tuple(c for c in self.columns if self.terms[c])
        self._check_weights()

    def __repr__(self) -> str:
        return (f"<CollapsedLikelihood {self.lik.label}: sample {', '.join(self.names)}; integrate "
                f"{', '.join(self.free_columns)}>")

    # -- rows ---------------------------------------------------------------------------------
    def full_rows(self, theta) -> np.ndarray:
        """Rows of the full likelihood (working coordinates) with the amplitude columns at their
        box middle; ``theta`` (n, d) holds the sampled parameters."""
        theta = np.atleast_2d(np.asarray(theta, float))
        out = np.tile(self._template, (theta.shape[0], 1))
        out[:, self.phi_index] = theta
        return out

    def _check_weights(self) -> None:
        """Refuse when an amplitude's weight can vanish inside the φ box (corners and random points)."""
        lo, hi = self.bounds[:, 0], self.bounds[:, 1]
        rng = np.random.default_rng(0)  # a fixed probe of the box, not a random result
        corners = np.array(np.meshgrid(*[[0.0, 1.0]] * min(self.d, 10), indexing="ij")).reshape(min(self.d, 10), -1).T
        probe = np.vstack([rng.random((64, self.d)),
                           np.hstack([corners, np.full((corners.shape[0], self.d - corners.shape[1]), 0.5)])])
        w = self.structure.coefficients(self.lik.model_theta(self.full_rows(lo + probe * (hi - lo))))
        for c in self.free_columns:
            ww = w[:, self._term_index[c]]
            if not np.all(ww > 0):
                raise CollapseError(f"collapsed likelihood not available: the weight of "
                                    f"{', '.join(t.name for t in self.terms[c])} in column {c} reaches "
                                    f"{ww.min():.3g} in the prior box (must stay > 0)")

    # -- the integral -------------------------------------------------------------------------
    def _setup(self, theta: np.ndarray) -> tuple[BoxGaussianIntegral, np.ndarray]:
        """The whitened problem of rows ``theta`` (all in the box): integral object and log-det term."""
        lik = self.lik
        full = self.full_rows(theta)
        model_rows = lik.model_theta(full)
        q = lik.to_natural(full)[:, lik.n_model:]
        X = np.asarray(self.structure.basis(lik.loading, model_rows), float)  # (n, P, k)
        self.n_evaluations += theta.shape[0]
        w = np.asarray(self.structure.coefficients(model_rows), float)
        n = theta.shape[0]
        y = np.broadcast_to(lik.observed, (n, lik.n_points)).copy()
        priors, cols = [], []
        for j, c in enumerate(self.columns):
            off = np.zeros(n)
            for i, v in self.fixed_terms[c]:
                off += w[:, i] * v
            if not self.terms[c]:
                y -= X[:, :, j] * off[:, None]
                continue
            priors.append(ColumnPrior(c, self.terms[c], w[:, self._term_index[c]], off))
            cols.append(j)
        X = X[:, :, cols]
        noise = lik.noise_model
        # −½ n log 2π − ½ log|Σ|: the noise log-likelihood at a zero residual
        logdet = noise.loglik(q, np.broadcast_to(noise.observed, y.shape).copy())
        Xw, yw = self._whiten(q, X, y)
        H = np.einsum("npi,npj->nij", Xw, Xw)
        b = np.einsum("npi,np->ni", Xw, yw)
        yy = np.einsum("np,np->n", yw, yw)
        return BoxGaussianIntegral(H, b, yy, priors, nodes=self.nodes, width=self.width), logdet

    def _whiten(self, q: np.ndarray, X: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """W·X and W·y per row (W Σ Wᵀ = I), batched over rows with their own noise parameters
        (:meth:`hbm.likelihood.noise.NoiseModel.whiten_rows`)."""
        noise = self.lik.noise_model
        sd = noise.sd(q)  # (n, P): none of the Gaussian models needs the model stress
        return noise.whiten_rows(X, q, sd=sd), noise.whiten_rows(y, q, sd=sd)

    def log_likelihood(self, theta, *, refine: bool = False) -> tuple[np.ndarray, np.ndarray | None]:
        """log L_c per row and (``refine``) the quadrature's error estimate per row.

        Parameters
        ----------
        theta : array (n, d)
            Sampled parameters (working coordinates, ``names`` order).
        refine : bool
            Also return |log L_c − log L_c'| with 1.5× the nodes (costs a second integral).

        Returns
        -------
        value : ndarray (n,)
            −inf outside the box or where the basis is not finite.
        error : ndarray (n,) or None
        """
        theta = np.atleast_2d(np.asarray(theta, float))
        if theta.shape[1] != self.d:
            raise HbmError(f"theta must have shape (n, {self.d}) for {', '.join(self.names)}, got {theta.shape}")
        out = np.full(theta.shape[0], -np.inf)
        err = np.full(theta.shape[0], np.nan) if refine else None
        ok = ((theta >= self.bounds[:, 0]) & (theta <= self.bounds[:, 1])).all(axis=1)
        if not ok.any():
            return out, err
        with np.errstate(all="ignore"):
            integral, logdet = self._setup(theta[ok])
            v, e = integral.log_integral(refine=refine)
        v = logdet + v
        out[ok] = np.where(np.isfinite(v), v, -np.inf)
        if refine:
            err[ok] = e
        return out, err

    def __call__(self, theta) -> np.ndarray:
        """log L_c of each row (n,) (the sampler's log-likelihood)."""
        return self.log_likelihood(theta)[0]

    # -- the full posterior -----------------------------------------------------------------
    def complete(self, theta, rng: np.random.Generator) -> np.ndarray:
        """Full-likelihood rows (working coordinates): φ as given, amplitudes drawn given φ and y.

        Draws A ~ p(A | φ, y) (a box-truncated Gaussian times the induced prior,
        :meth:`BoxGaussianIntegral.draw`), then the original parameters of each column given its
        amplitude from their prior on the feasible segment (:meth:`ColumnPrior.split`).

        Parameters
        ----------
        theta : array (n, d)
            Posterior draws of the sampled parameters.
        rng : numpy.random.Generator

        Returns
        -------
        ndarray (n, lik.d)
        """
        theta = np.atleast_2d(np.asarray(theta, float))
        with np.errstate(all="ignore"):
            integral, _ = self._setup(theta)
            amps = integral.draw(rng)
        full = self.full_rows(theta)
        nat = self.lik.to_natural(full)
        for j, pr in enumerate(integral.column_priors):
            for name, vals in pr.split(amps[:, j], rng).items():
                nat[:, self.lik.index(name)] = vals
        return self.lik.from_natural(nat)

    def info(self) -> dict[str, Any]:
        """JSON-able description: tier, sampled parameters, integrated columns, quadrature."""
        return {"likelihood_tier": "collapsed", "sampled": list(self.names),
                "integrated_columns": {c: [t.name for t in self.terms[c]] for c in self.free_columns},
                "quadrature": {"nodes_per_panel": self.nodes, "window_sd": self.width}}


def choose_tier(lik: Likelihood, tier: str = "auto", *, move: str = "rw",
                kernel: str | None = None) -> tuple[CollapsedLikelihood | None, str]:
    """The likelihood tier of a fit: the collapsed likelihood when it applies, else the full one.

    Parameters
    ----------
    lik : Likelihood
    tier : {"auto", "collapsed", "full"}
        One of :data:`TIERS`.  "auto": collapsed when the model has a linear structure (verified
        numerically at 8 points of the prior box), the noise model keeps the amplitude integral
        Gaussian and the move is the random walk; "collapsed": the same, but an error when it does
        not apply; "full": today's full-space likelihood.
    move : str
        The fit's TMCMC move (the collapsed tier runs the random walk "rw"; "manifold" needs the
        full likelihood's gradient).
    kernel : str, optional
        Deprecated name of ``move``.

    Returns
    -------
    collapsed : CollapsedLikelihood or None
        None for the full tier.
    note : str
        One line for the outputs: which tier and why.

    Raises
    ------
    SettingError
        Unknown ``likelihood``, or "collapsed" where it does not apply (the reason is named).
    """
    if kernel is not None:
        warnings.warn("choose_tier(kernel=...) is deprecated; use move=", DeprecationWarning, stacklevel=2)
        move = kernel
    if tier not in TIERS:
        raise SettingError(f"tier must be one of {', '.join(TIERS)}, got {tier!r}")
    if tier == "full":
        return None, "full likelihood (requested)"
    why = None
    cl = None
    if move != "rw":
        why = (f"the {move!r} move needs the gradient of the full likelihood" if needs_gradient(move)
               else f"the collapsed tier samples with the random walk ('rw'), not the {move!r} move")
    elif not isinstance(lik.model, Model):
        why = f"{type(lik.model).__name__} is not an hbm Model built from effects (a black box declares no amplitudes)"
    else:
        structure = structure_of(lik.model)
        why = collapse_reason(lik, structure)
        if why is None:
            try:
                # a declaration is checked before it is used (a user's effect may be wrong);
                # fixed probe points, not a random result
                structure.verify(lik.loading, np.random.default_rng(0))
                cl = CollapsedLikelihood(lik, structure)
            except HbmError as exc:
                why = str(exc)
    if cl is None:
        if tier == "collapsed":
            raise SettingError(f"tier 'collapsed' is not available: {why}")
        return None, f"full likelihood ({why})"
    return cl, ("collapsed likelihood: amplitudes " + ", ".join(cl.free_columns)
                + " integrated exactly; sampled " + ", ".join(cl.names))
