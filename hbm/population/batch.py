"""Specimens' likelihoods in the population sampler's coordinates, a shard of specimens at a time.

:class:`SpecimenLikelihoods` gives :class:`hbm.samplers.hierarchical.shards.ShardState` what it needs
(its ``SpecimenBatch`` protocol) for B specimens at once, every chain of every specimen in one array:

* **amplitude mode** (the default: ``--pool combinations``, a model with a linear structure
  (:mod:`hbm.model.linear`) and noise whose sd is a noise scale times fixed point weights, ``iid`` or
  ``weighted``): the coordinates hold u = log A of every amplitude column (``log_<column>``), and
  :meth:`prepare` evaluates the basis X(φ) once per row at the row's nonlinear parameters and keeps
  only its sufficient statistics — with W the point weights, X_w = X/W, d_w = data/W:

      G1 = X_wᵀX_w,  b1 = X_wᵀd_w,  d1 = d_wᵀd_w,

  so that for any amplitudes and noise scale σ the log-likelihood is
  −n log σ − Σ log W − n/2 log 2π − (d1 − 2Aᵀb1 + AᵀG1A)/(2σ²), a quadratic form in A
  (:meth:`quadratic`): no model evaluation for the amplitudes or the noise scale;
* **plain mode** (any other model, noise or pooling): every model parameter is a nonlinear column;
  :meth:`prepare` evaluates the stress and the noise model's log-likelihood follows it (closed form
  for a scaled-diagonal noise, the noise model's own ``loglik`` per specimen otherwise).

The basis and the stress are evaluated for the whole shard in one pass through the model's effects
when every effect is elastic (pointwise in the strain: the specimens' strains padded to a common
length, the padding masked), checked against the model's own ``basis`` at construction; a model with
other effects (history, kinematics) is evaluated specimen by specimen.  Each specimen's
log-likelihood is checked against its stage-1 :class:`hbm.likelihood.Likelihood` at its own stage-1
rows before the sampler starts.

This is muscle code (the model and the noise models); the samplers see only the protocol.
"""

from __future__ import annotations

from typing import Sequence

import numpy as np

from ..identifiability.combinations import in_support, support_constraints
from ..errors import HbmError
from ..model.core import State
from ..model.linear import structure_of
from ..likelihood.noise import IidNoise, WeightedNoise

__all__ = ["SpecimenLikelihoods", "amplitude_columns"]

_LOG2PI = np.log(2.0 * np.pi)
#: noise models whose sd is the noise scale times fixed per-point weights (exact classes)
_SCALED = (IidNoise, WeightedNoise)


def amplitude_columns(model, names_y: Sequence[str], noise) -> tuple[list[int] | None, str]:
    """y columns of the model's amplitude columns (in its structure's column order), or None and why not."""
    structure = structure_of(model)
    if structure is None:
        return None, "the model has no linear amplitudes"
    if type(noise) not in _SCALED:
        return None, f"noise model {noise.name!r} is not a scale times fixed weights"
    cols = [f"log_{c}" for c in structure.columns]
    missing = [c for c in cols if c not in names_y]
    if missing:
        return None, f"the layer's coordinates have no {', '.join(missing)} (pool the combinations)"
    idx = [list(names_y).index(c) for c in cols]
    if sorted(idx) != list(range(len(idx))):  # the combinations' coordinates lead y (PhiCoordinates)
        return None, "the amplitude columns are not the leading coordinates"
    return idx, ""


def _pad(arrays: Sequence[np.ndarray], n: int, fill: float = 0.0) -> np.ndarray:
    out = np.full((len(arrays), n), fill)
    for i, a in enumerate(arrays):
        out[i, : a.size] = a
    return out


class SpecimenLikelihoods:
    """B specimens' likelihoods as the shard sampler's ``SpecimenBatch`` (module docstring; picklable).

    Parameters
    ----------
    liks : sequence of Likelihood
        The specimens' stage-1 likelihoods (same model, parameters, boxes and noise model).
    coords : PhiCoordinates or PlainCoordinates
        The layer's coordinates (:mod:`hbm.population.pooling`): ``names_y``, ``box``, ``theta_of``.
    amplitude : bool
        Amplitude mode if it applies (:func:`amplitude_columns`); False: plain mode.
    """

    def __init__(self, liks: Sequence, coords, *, amplitude: bool = True) -> None:
        self.liks = list(liks)
        first = self.liks[0]
        self.model, self.coords = first.model, coords
        self.structure = structure_of(self.model)
        self.n_specimens = len(self.liks)
        names_y = list(coords.names_y)
        self.dy = len(names_y)
        self.box = np.asarray(coords.box, float)
        noise = first.noise_model
        amp, self.why_plain = amplitude_columns(self.model, names_y, noise) if amplitude else (None, "asked for")
        self.amplitude_cols = np.asarray(amp or [], int)
        self.noise_cols = np.array([names_y.index(n) for n in first.noise_names], int)
        self.nonlinear_cols = np.array([j for j in range(self.dy) if j not in self.amplitude_cols
                                        and j not in self.noise_cols], int)
        self.n_points = np.array([lik.n_points for lik in self.liks])
        n = int(self.n_points.max())
        self.mask = _pad([np.ones(k) for k in self.n_points], n)
        self.eps = _pad([lik.loading.strain for lik in self.liks], n)
        self.data = _pad([lik.observed for lik in self.liks], n)
        self.scaled = type(noise) in _SCALED and all(type(lik.noise_model) is type(noise) for lik in self.liks)
        if self.scaled:
            w = [np.asarray(lik.noise_model.sd(np.ones((1, 1)))[0], float) for lik in self.liks]
            self.iw = _pad([1.0 / x for x in w], n)   # zero on the padding
            self.logw = np.array([np.log(x).sum() for x in w])
            self.dw = self.data * self.iw
            self.d1 = np.sum(self.dw * self.dw, axis=1)
        self.batched = self.structure is not None and all(e.stage == "elastic" for e in self.model.effects)
        # the prior support of the amplitudes (the combinations' fibre exists), in amplitude-column order
        self.amplitude_constraints = None
        if self.amplitude_cols.size:
            P, Q, R = support_constraints(coords.cbox)
            self.amplitude_constraints = (P[:, self.amplitude_cols], Q, R)
        # the stage-1 columns that are y columns (by name) and a template row for the others
        self.stage1_names = list(first.names)
        self.cols_from_y = [(self.stage1_names.index(nm), j) for j, nm in enumerate(names_y) if nm in self.stage1_names]
        # the basis' rows: a fixed row with the nonlinear model columns of y (uniform priors: y holds them
        # in natural units), else the fibre's point of every row
        self._template = None
        model_names = list(self.model.parameter_names)
        nl = [j for j in self.nonlinear_cols if names_y[j] in model_names]
        if self.amplitude_cols.size and "loguniform" not in first.forms and len(nl) == len(self.nonlinear_cols):
            self._template = self.model.bounds.mean(axis=1)
            for name, v in first.fixed.items():
                self._template[model_names.index(name)] = v
            self._nl_y = np.array(nl, int)
            self._nl_model = np.array([model_names.index(names_y[j]) for j in nl], int)
        self._check_batched()

    # -- rows of the model ---------------------------------------------------------------------------
    def _stage1_rows(self, y: np.ndarray) -> np.ndarray:
        """Stage-1 columns (B*C, d) of rows ``y`` (B, C, dy): a point of the fibre (any point: the
        likelihood is the same on it)."""
        theta, _ = self.coords.theta_of(y.reshape(-1, self.dy))
        return theta

    def _model_rows(self, y: np.ndarray) -> np.ndarray:
        """Full model rows in natural units (B, C, n_params)."""
        B, C = y.shape[:2]
        return self.liks[0].model_theta(self._stage1_rows(y)).reshape(B, C, -1)

    def _noise(self, y: np.ndarray) -> np.ndarray:
        """Noise parameters in natural units (B, C, nq)."""
        lik = self.liks[0]
        rows = np.zeros(y.shape[:2] + (lik.d,))
        rows[..., lik.n_model:] = y[..., self.noise_cols]
        return lik.to_natural(rows)[..., lik.n_model:]

    def _basis(self, rows: np.ndarray) -> np.ndarray:
        """X (B, C, n, k) at model rows (B, C, n_params), padded points zero."""
        st = self.structure
        if self.batched:
            p = {q: rows[..., i, None] for i, q in enumerate(self.model.parameter_names)}
            state = State(self.eps[:, None, :], None)
            x = np.zeros(rows.shape[:-1] + (self.eps.shape[1], st.n_columns))
            with np.errstate(all="ignore"):
                for e in self.model.effects:
                    for col, u in e.unit_stress(state, p).items():
                        x[..., st.columns.index(col)] += u
            return x * self.mask[:, None, :, None]
        x = np.zeros(rows.shape[:-1] + (self.eps.shape[1], st.n_columns))
        for b, lik in enumerate(self.liks):  # history or kinematic effects: one specimen at a time
            with np.errstate(all="ignore"):
                x[b, :, : lik.n_points] = st.basis(lik.loading, rows[b])
        return x

    def _stress(self, rows: np.ndarray) -> np.ndarray:
        """Model stress (B, C, n) at model rows, padded points zero."""
        if self.structure is not None:
            return np.einsum("bcnk,bck->bcn", self._basis(rows), self.structure.amplitudes(rows))
        out = np.zeros(rows.shape[:-1] + (self.eps.shape[1],))
        for b, lik in enumerate(self.liks):
            with np.errstate(all="ignore"):
                out[b, :, : lik.n_points] = self.model.stress(lik.loading, rows[b])
        return out

    def _check_batched(self) -> None:
        """The one-pass basis must equal the model's own, specimen by specimen (else: one at a time)."""
        if not self.batched:
            return
        rng = np.random.default_rng(0)
        b = self.model.bounds
        rows = b[:, 0] + rng.random((self.n_specimens, 3, self.model.n_params)) * (b[:, 1] - b[:, 0])
        x = self._basis(rows)
        for i, lik in enumerate(self.liks):
            ref = self.structure.basis(lik.loading, rows[i])
            if not np.allclose(x[i, :, : lik.n_points], ref, rtol=1e-12, atol=1e-14 * max(1.0, np.abs(ref).max())):
                self.batched = False
                return

    # -- the protocol ----------------------------------------------------------------------------------
    def _basis_rows(self, y: np.ndarray) -> np.ndarray:
        """Model rows for the basis at ``y`` (B, C, n_params): the nonlinear columns of y in a fixed row
        (the basis does not depend on the amplitude parameters; :meth:`check` verifies that the
        likelihood is the specimens' at their own rows), or the fibre's point when a column is not in
        natural units."""
        if self._template is None:
            return self._model_rows(y)
        rows = np.broadcast_to(self._template, y.shape[:2] + self._template.shape).copy()
        rows[..., self._nl_model] = y[..., self._nl_y]
        return rows

    def prepare(self, y: np.ndarray) -> dict:
        """Sufficient statistics at rows ``y`` (B, C, dy): one model evaluation per row."""
        if self.amplitude_cols.size:
            rows = self._basis_rows(y)
            Xw = self._basis(rows) * self.iw[:, None, :, None]
            return {"G1": np.einsum("bcnk,bcnl->bckl", Xw, Xw), "b1": np.einsum("bcnk,bn->bck", Xw, self.dw)}
        s = self._stress(self._model_rows(y))
        if self.scaled:
            r = (self.data[:, None, :] - s) * self.iw[:, None, :]
            return {"d1": np.einsum("bcn,bcn->bc", r, r)}
        return {"stress": s}

    def quadratic(self, prep: dict, y: np.ndarray):
        """(ℓ0, G, b) of the amplitudes at ``y``'s noise scale (amplitude mode)."""
        s = self._noise(y)[..., 0]
        inv = 1.0 / (s * s)
        ll0 = (-self.n_points[:, None] * np.log(s) - self.logw[:, None] - 0.5 * self.n_points[:, None] * _LOG2PI
               - 0.5 * self.d1[:, None] * inv)
        return ll0, prep["G1"] * inv[..., None, None], prep["b1"] * inv[..., None]

    def loglik(self, prep: dict, y: np.ndarray) -> np.ndarray:
        """Log-likelihood (B, C) at ``y`` (its nonlinear columns those ``prep`` was made at)."""
        if self.amplitude_cols.size:
            s = self._noise(y)[..., 0]
            A = np.exp(y[..., self.amplitude_cols])
            rss = (self.d1[:, None] - 2.0 * np.einsum("bck,bck->bc", A, prep["b1"])
                   + np.einsum("bck,bckl,bcl->bc", A, prep["G1"], A))
            return (-self.n_points[:, None] * np.log(s) - self.logw[:, None] - 0.5 * self.n_points[:, None] * _LOG2PI
                    - 0.5 * rss / (s * s))
        if self.scaled:
            s = self._noise(y)[..., 0]
            return (-self.n_points[:, None] * np.log(s) - self.logw[:, None] - 0.5 * self.n_points[:, None] * _LOG2PI
                    - 0.5 * prep["d1"] / (s * s))
        q = self._noise(y)
        out = np.empty(y.shape[:2])
        for b, lik in enumerate(self.liks):  # a noise model without a closed form here: its own loglik
            with np.errstate(all="ignore"):
                out[b] = lik.noise_model.loglik(q[b], prep["stress"][b, :, : lik.n_points].copy())
        return np.where(np.isfinite(out), out, -np.inf)

    def select(self, prep: dict, new: dict, mask: np.ndarray) -> dict:
        """``new`` where ``mask`` (B, C), ``prep`` elsewhere."""
        return {k: np.where(mask.reshape(mask.shape + (1,) * (v.ndim - 2)), new[k], v) for k, v in prep.items()}

    def valid(self, y: np.ndarray) -> np.ndarray:
        """(B, C): inside the box and the support of the stage-1 prior (a point of the fibre exists)."""
        with np.errstate(invalid="ignore"):
            inside = np.all((y >= self.box[:, 0]) & (y <= self.box[:, 1]), axis=-1)
        _, ok = self.coords.theta_of(np.where(inside[..., None], y, self.box[:, 0]).reshape(-1, self.dy))
        return inside & ok.reshape(y.shape[:-1])

    def amplitudes_valid(self, u: np.ndarray) -> np.ndarray:
        """(...): amplitude columns u (..., k) inside their box and the prior support of the combinations
        (the other columns do not enter it)."""
        amp = self.amplitude_cols
        with np.errstate(invalid="ignore"):
            inside = np.all((u >= self.box[amp, 0]) & (u <= self.box[amp, 1]), axis=-1)
        phi = np.zeros(u.shape[:-1] + (3,))
        phi[..., amp] = np.where(inside[..., None], u, self.box[amp, 0])
        return inside & in_support(phi, self.coords.cbox)

    def check(self, rows: Sequence[np.ndarray], n: int = 8, tol: float = 1e-6) -> None:
        """Each specimen's log-likelihood here against its stage-1 likelihood at ``n`` of its rows ``rows``
        (HbmError if they differ: the batch would not be the specimens' likelihood)."""
        y = np.stack([np.asarray(r, float)[np.linspace(0, len(r) - 1, n).astype(int)] for r in rows])
        ll = self.loglik(self.prepare(y), y)
        for b, lik in enumerate(self.liks):
            ref = lik(self._stage1_rows(y[b:b + 1]))
            if not np.allclose(ll[b], ref, rtol=1e-9, atol=tol):
                bad = int(np.argmax(np.abs(ll[b] - ref)))
                raise HbmError(f"population layer: the batched likelihood of specimen {lik.label!r} gives "
                               f"{ll[b, bad]:.9g} where its own gives {ref[bad]:.9g}")
