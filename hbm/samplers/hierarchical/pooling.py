"""Which parameters to pool: the parameters the stage-1 data inform in most specimens.

When the sample reuse fails, and what to pool
---------------------------------------------
The ESS of the ratios is a product over the pooled parameters (one factor per dimension for
a diagonal population), and a factor is small in two situations:

* *wide populations of prior-like parameters*: for a parameter the data do not inform, the
  stage-1 samples follow the uniform prior, whose density in the transformed space has
  exponential tails (logistic for logit, e^z for log), while p(d_i|ψ) is flat in its (mu, sd),
  so the hyper-posterior returns the hyperprior, which reaches |mu| near ``logit_range`` and
  sd of several units.  Such a population puts its mass where the samples are exponentially
  rare and one or two extreme samples carry all the weight.  On the six shipped specimens
  (2000 samples each, all eight parameters pooled) this is what collapses the ESS (min ≈ 1,
  10 % quantile 1.8–31): per parameter the ESS falls as sd_k grows (correlation of log ESS_k
  with log sd_k −0.5 to −0.8 for VOLF, EOPT, P1, GF, GM), VOLF/EOPT/GM alone keep a median of
  300–600 of 2000, and eight such factors multiply to a handful.  Capping sd at the prior's
  sd does not help: the populations then become narrower than the prior-like posteriors and
  the factors stay ≈ 0.5 each.
* *narrow populations*: a population much narrower than a specimen's posterior leaves few
  samples in its support (the kernel estimator below addresses this).

Hence :func:`auto_pool`: pool only parameters whose stage-1 posterior sd in the transformed
space is below ``max_sd_ratio`` (2/3) of the uniform prior's sd there
(:func:`prior_sd_transformed`) in at least half of the specimens (``max_needed`` caps that count for a
sampler without importance weights); the others keep their stage-1 prior and cost nothing.  On the shipped
specimens it selects T2 and THETA (VOLF, T1 and GM are prior-like everywhere, EOPT, P1 and GF informed in
one or two specimens) and the ESS 10 % quantile becomes 174–987 with a minimum of 121.

This module is sampler-layer code: it knows nothing about muscles.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Mapping, Sequence

import numpy as np

from ...errors import HbmError
from .model import TRANSFORMS, HierarchicalModel

__all__ = ["PoolChoice", "auto_pool", "prior_sd_transformed"]


def prior_sd_transformed(kind: str, lo: float, hi: float) -> float:
    """sd of z = g(θ) when θ is uniform on [lo, hi] (the stage-1 prior seen in the transformed space).

    identity: (hi − lo)/√12; logit: π/√3 (the standard logistic); log: sd of log θ, whose density
    is e^z/(hi − lo) on [log lo, log hi] (64-point Gauss–Legendre, exact to rounding for any box).
    """
    if kind == "identity":
        return float((hi - lo) / np.sqrt(12.0))
    if kind == "logit":
        return float(np.pi / np.sqrt(3.0))
    if kind == "log":
        if not lo > 0:
            raise HbmError(f"hierarchical: transform 'log' needs a positive lower bound, got {lo:g}")
        a, b = np.log(lo), np.log(hi)
        x, w = np.polynomial.legendre.leggauss(64)
        z = 0.5 * (b - a) * x + 0.5 * (a + b)
        p = w * np.exp(z - b)  # density ∝ e^z; scaled by e^−b against overflow
        p /= p.sum()
        m = np.sum(p * z)
        return float(np.sqrt(np.sum(p * (z - m) ** 2)))
    raise HbmError(f"hierarchical: transform must be one of {TRANSFORMS}, got {kind!r}")


@dataclass
class PoolChoice:
    """Result of :func:`auto_pool`: the chosen names (also iterable as ``pooled, reasons = ...``).

    Attributes
    ----------
    pooled : list of str
        Parameters to pool, in column order.
    reasons : dict name -> dict
        Per candidate: ``sd_ratio`` (per specimen, posterior sd / prior sd in the transformed
        space), ``informative`` (per specimen, bool), ``n_informative``, ``n_specimens``,
        ``pooled`` (bool) and a one-line ``reason``.
    """

    pooled: list
    reasons: dict

    def __iter__(self):
        return iter((self.pooled, self.reasons))


def auto_pool(
    samples_by_specimen: Mapping[str, np.ndarray],
    names: Sequence[str],
    bounds,
    transforms: Mapping[str, str] | None = None,
    *,
    candidates: Sequence[str] | None = None,
    max_sd_ratio: float = 2.0 / 3.0,
    min_fraction: float = 0.5,
    min_pooled: int = 1,
    max_needed: int | None = None,
) -> PoolChoice:
    """Choose the parameters worth pooling: those the stage-1 data inform in most specimens.

    A parameter is *informative* for a specimen when its stage-1 posterior sd in the
    transformed space (the space of the population model) is below ``max_sd_ratio`` times the
    sd of the stage-1 uniform prior in that space (:func:`prior_sd_transformed`); the default
    2/3 means a variance contraction 1 − σ²_post/σ²_prior of at least 5/9.  It is pooled when it
    is informative in at least ``min_fraction`` of the specimens.

    Why: for a parameter whose posteriors are prior-like, p(d_i|ψ) is flat in its (mu, sd), the
    hyper-posterior returns the hyperprior, and that hyperprior reaches populations whose mass
    lies in the transformed tails (|mu| near logit_range, sd of several logit units) where the
    stage-1 samples, drawn under a uniform prior, are exponentially rare: the importance ratios
    are then dominated by one or two extreme samples and the ESS collapses, multiplicatively
    over such parameters.  Pooling them adds nothing but noise; they keep their stage-1 prior.

    Parameters
    ----------
    samples_by_specimen : mapping specimen -> ndarray (N_i, len(names))
        Stage-1 posterior samples.
    names : sequence of str
        Column names.
    bounds : array_like (len(names), 2)
        Stage-1 uniform prior box.
    transforms : mapping name -> {"identity","log","logit"}, optional
        Transform of each candidate (default identity), as passed to :func:`hierarchical`.
    candidates : sequence of str, optional
        Names that may be pooled (default all), e.g. the model parameters without ``sigma``.
    max_sd_ratio : float
        Posterior/prior sd ratio below which a specimen counts as informed.
    min_fraction : float
        Fraction of specimens that must be informed.
    max_needed : int, optional
        At most this many informed specimens are needed, whatever ``min_fraction`` of them that is (None:
        no cap).  For a sampler that evaluates every specimen's likelihood (no importance weights to collapse),
        enough informed specimens estimate a population's spread however many others the data leave at their
        prior.
    min_pooled : int
        If fewer candidates pass, the best-informed ones (most informed specimens, then the
        smallest median ratio) are added up to this number, with a reason saying so, so that a
        hierarchical layer can always run; 0 allows an empty choice.

    Returns
    -------
    PoolChoice
        ``pooled`` and per-candidate ``reasons``.
    """
    names = [str(n) for n in names]
    candidates = list(names) if candidates is None else [str(c) for c in candidates]
    bad = [c for c in candidates if c not in names]
    if bad:
        raise HbmError(f"auto_pool: candidates {bad} are not among names {names}")
    if not samples_by_specimen:
        raise HbmError("auto_pool: samples_by_specimen is empty")
    if not (0 < max_sd_ratio) or not (0 < min_fraction <= 1):
        raise HbmError(f"auto_pool: need max_sd_ratio > 0 and 0 < min_fraction <= 1, got {max_sd_ratio}, {min_fraction}")
    tr = {c: dict(transforms or {}).get(c, "identity") for c in candidates}
    model = HierarchicalModel(names, bounds, pooled=candidates, transforms=tr)
    prior_sd = np.array([prior_sd_transformed(k, lo, hi) for k, lo, hi in zip(model.kinds, model.lo, model.hi)])
    ratios = []
    for key, x in samples_by_specimen.items():
        x = np.asarray(x, float)
        if x.ndim != 2 or x.shape[1] != len(names) or x.shape[0] < 2:
            raise HbmError(f"auto_pool: samples of {key!r} must be (N>=2, {len(names)}), got {x.shape}")
        z, _ = model.to_z(x)
        ratios.append(z.std(axis=0, ddof=1) / prior_sd)
    ratios = np.array(ratios)  # (n_specimens, n_candidates)
    informative = ratios < max_sd_ratio
    n_spec = ratios.shape[0]
    need = int(np.ceil(min_fraction * n_spec - 1e-9))
    if max_needed is not None:
        need = min(need, int(max_needed))
    pooled, reasons = [], {}
    for k, c in enumerate(candidates):
        n_inf = int(informative[:, k].sum())
        ok = n_inf >= need
        if ok:
            pooled.append(c)
        reasons[c] = {
            "sd_ratio": ratios[:, k].tolist(), "informative": informative[:, k].tolist(),
            "n_informative": n_inf, "n_specimens": n_spec, "pooled": ok, "transform": tr[c],
            "reason": (f"{c}: posterior sd < {max_sd_ratio:.2f} x prior sd ({tr[c]} space) in {n_inf}/{n_spec} "
                       f"specimens (need {need}); median ratio {np.median(ratios[:, k]):.2f} -> "
                       + ("pooled" if ok else "not pooled (keeps its stage-1 prior)")),
        }
    if len(pooled) < min_pooled:
        # rank the rest: most informed specimens first, then the smallest median sd ratio
        rest = sorted((c for c in candidates if c not in pooled),
                      key=lambda c: (-reasons[c]["n_informative"], float(np.median(reasons[c]["sd_ratio"]))))
        for c in rest[: min_pooled - len(pooled)]:
            pooled.append(c)
            reasons[c]["pooled"] = True
            reasons[c]["reason"] = reasons[c]["reason"].replace(
                "not pooled (keeps its stage-1 prior)", f"pooled anyway: best informed of the candidates (min_pooled={min_pooled})")
    pooled = [n for n in names if n in pooled]
    return PoolChoice(pooled=pooled, reasons=reasons)
