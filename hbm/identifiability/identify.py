"""Identifiable parameter combinations and the VOLF–T1 manifold (thesis Appendix B, Fig. 3.61).

From uniaxial data only G = c·GF + (1−c)·GM, A_f = c·P1 and A_m = (1−c)·T1 are learnable
(with EOPT, T2, THETA; c = VOLF); when the collagen works in its near-linear regime (small
T2·(λ − 1)) only (1−c)·T1·T2 is, not (1−c)·T1 itself.  This module finds such combinations
*from the samples* rather than assuming them:

* :func:`identifiable_directions` — generalised eigen-analysis of the posterior covariance
  against the (uniform-box) prior covariance in a feature space: log θ_k for every parameter
  with a non-negative box, θ_k itself for parameters whose box reaches below zero, and
  additionally log(1 − θ_k) for volume fractions (``fractions``, default the spec's, VOLF for the Spyrou
  base).  (1 − c)
  is not a power of c, so with log(1 − c) as a feature the product (1 − c)·T1 is an exact
  linear direction log(1 − c) + log T1, found *without being told*.  A direction u is
  identified when its posterior/prior sd ratio sqrt(uᵀC_post u / uᵀC_prior u) is below
  ``threshold``; the number k of generalised eigenvalues below threshold² is the dimension
  of the identified subspace.

  The eigenvectors themselves are *not* reported: inside the identified subspace they are
  an arbitrary rotation (any mixture of two well-determined directions is well determined),
  so they come out as dense mixtures such as THETA·EOPT^0.1·T2^-0.6…, and pruning each of
  them term by term collapses every one of them onto the single best-determined parameter.
  Instead a **sparse basis** of the identified subspace is searched: supports (sets of
  feature columns) of size 1, 2, …, ``max_terms`` in increasing size; for each support the
  small generalised eigenproblem (C_post vs C_prior restricted to it) gives its best
  directions; within one size they are taken in order of increasing sd ratio, and a
  direction is accepted when its ratio is below ``threshold`` and it is linearly independent
  of the directions already accepted — measured in the prior-whitened metric (inner product
  C_prior, in which every feature has unit prior scale): the part orthogonal to the accepted
  span must keep at least ``independence_tol`` (0.3, i.e. ≳ 17° away from the span) of the
  direction's norm.  So a support {THETA, X} whose best direction is essentially THETA is
  rejected once THETA is in, while VOLF·P1 after EOPT and THETA is accepted.  The search
  stops at k accepted directions.  Smaller supports win over smaller ratios: the basis is
  the sparsest one (a parameter identified on its own is reported alone, not in a product).
  Accepted directions are reported as products of powers, exponents normalised so that the
  smallest exponent among the terms that matter (prior-whitened share ≥ ``min_coef`` of the
  largest) is ±1 and rounded to ``step``; the rounded combination's own ratio is re-checked
  and reported.  (Normalising the *largest* exponent to 1 would not do: THETA's box
  [55°, 60°] gives log THETA a prior sd of 0.025 against ≈ 1 for the other logs, so a
  direction T2·THETA^-6 would read THETA·T2^-0.16 and round to THETA.)
  Named candidates ((1−VOLF)·T1, (1−VOLF)·T1·T2, VOLF·P1, VOLF·GF + (1−VOLF)·GM) are checked
  explicitly by the same criterion (posterior/prior sd ratio of the log of the combination,
  prior = uniform draws from the box) with their posterior intervals.
* the VOLF–T1 manifold and its comparison across specimens live in :mod:`hbm.identifiability.manifolds`
  (:func:`volf_t1_manifold`, :func:`compare_manifolds`; also importable from here).

Only numpy/scipy; no sampler, no plotting, no file formats (``to_arrays`` hands plain arrays
to hbm.io).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from itertools import combinations
from typing import Callable, Sequence

import numpy as np
from scipy.linalg import eigh

from ..errors import HbmError
from .manifolds import ManifoldComparison, VolfT1Manifold, compare_manifolds, volf_t1_manifold  # their own module
from ..model.spec import ModelSpec, base_spec

__all__ = [
    "IdentifiabilityReport",
    "identifiable_directions",
    "candidate_combinations",
    "VolfT1Manifold",
    "volf_t1_manifold",
    "ManifoldComparison",
    "compare_manifolds",
]

# --------------------------------------------------------------------------------------
# (a) identifiable directions
# --------------------------------------------------------------------------------------
def _default_candidates(spec: ModelSpec | None = None) -> dict[str, tuple[tuple[str, ...], Callable]]:
    """The spec's named candidates (:attr:`hbm.model.spec.ModelSpec.candidates`) as name -> (needs, function)."""
    return {c.name: (c.parameters, c.compute) for c in (spec or base_spec()).candidates}


def _cv(x: np.ndarray) -> float:
    m = np.mean(x)
    return float(np.std(x) / abs(m)) if m != 0 else float("inf")


def _sd_ratio_1d(post: np.ndarray, prior: np.ndarray) -> float:
    """Posterior/prior sd of log v when v > 0 in both sample sets, else of v itself."""
    post, prior = np.asarray(post, float), np.asarray(prior, float)
    ok = np.isfinite(post).all() and np.isfinite(prior).all()
    if not ok:
        return float("nan")
    if np.all(post > 0) and np.all(prior > 0):
        post, prior = np.log(post), np.log(prior)
    sp = np.std(prior)
    return float(np.std(post) / sp) if sp > 0 else float("inf")


def candidate_combinations(
    samples,
    names: Sequence[str],
    *,
    candidates=None,
    interval=(0.05, 0.95),
    shrink_threshold: float = 0.5,
    bounds=None,
    prior=None,
    threshold: float = 0.1,
    n_prior: int = 20000,
    seed=0,
    spec: ModelSpec | None = None,
) -> dict[str, dict]:
    """Posterior summaries of named parameter combinations, with an identification flag.

    A combination g(θ) > 0 is flagged ``identified`` when the posterior sd of log g is below
    ``threshold`` times its prior sd (prior = uniform draws from ``bounds``, or the draws
    given as ``prior``) — the same criterion :func:`identifiable_directions` applies to its
    directions.  Comparing with the *prior* sd of the same combination is what makes the
    criterion scale-free: a combination is learnt when the data shrink it, not when it is
    narrow to begin with.  (The older criterion — CV of the combination below
    ``shrink_threshold`` times the smallest CV of its constituents — penalises combinations
    containing a parameter with a narrow box: VOLF ∈ [0.5, 0.99] has a small CV whatever the
    data say, so VOLF·P1 at CV 0.07 failed it although log(VOLF·P1) has a prior sd ≈ 1.)
    Without ``bounds`` and ``prior`` the older criterion is used and ``sd_ratio`` is NaN.
    Combinations that are not positive on all draws are compared on the linear scale.

    Parameters
    ----------
    samples : array_like (n, d)
    names : sequence of str
    candidates : mapping name -> (required names, function(columns dict) -> array), optional
        Default: the spec's candidates (the Spyrou base: (1-VOLF)*T1, (1-VOLF)*T1*T2, VOLF*P1,
        VOLF*GF+(1-VOLF)*GM), those whose parameters exist.
    interval : (float, float)
        Quantiles of the reported interval.
    shrink_threshold : float
        CV-shrink criterion, used for ``identified`` only when neither ``bounds`` nor
        ``prior`` is given (``shrink`` is reported always).
    bounds : array_like (d, 2), optional
        Uniform prior box.
    prior : array_like (m, d), optional
        Prior draws (columns as ``samples``); overrides ``bounds``.
    threshold : float
        ``identified`` ⇔ sd_ratio < threshold.
    n_prior : int
        Prior draws from ``bounds``.
    seed : int or Generator

    Returns
    -------
    dict name -> {"median","lo","hi","mean","cv","naive_cv" (dict), "shrink", "sd_ratio",
    "identified"}
    """
    x = np.asarray(samples, float)
    names = list(names)
    cols = {n: x[:, i] for i, n in enumerate(names)}
    if prior is None and bounds is not None:
        b = np.asarray(bounds, float)
        if b.shape != (len(names), 2):
            raise HbmError(f"candidate_combinations: bounds must be ({len(names)}, 2), got {b.shape}")
        prior = np.random.default_rng(seed).uniform(b[:, 0], b[:, 1], (int(n_prior), len(names)))
    pcols = None
    if prior is not None:
        prior = np.asarray(prior, float)
        if prior.ndim != 2 or prior.shape[1] != len(names):
            raise HbmError(f"candidate_combinations: prior draws must be (m, {len(names)}), got {prior.shape}")
        pcols = {n: prior[:, i] for i, n in enumerate(names)}
    cands = _default_candidates(spec) if candidates is None else dict(candidates)
    out = {}
    for key, (req, fn) in cands.items():
        if not all(r in cols for r in req):
            continue
        v = np.asarray(fn(cols), float)
        lo, med, hi = np.quantile(v, [interval[0], 0.5, interval[1]])
        naive = {r: _cv(cols[r]) for r in req}
        cv = _cv(v)
        shrink = cv / min(naive.values()) if min(naive.values()) > 0 else float("inf")
        if pcols is not None:
            ratio = _sd_ratio_1d(v, np.asarray(fn(pcols), float))
            ident = bool(ratio < threshold)
        else:
            ratio, ident = float("nan"), bool(shrink < shrink_threshold)
        out[key] = {
            "median": float(med), "lo": float(lo), "hi": float(hi), "mean": float(v.mean()), "cv": cv,
            "naive_cv": naive, "shrink": float(shrink), "sd_ratio": ratio, "identified": ident,
        }
    return out


@dataclass
class IdentifiabilityReport:
    """Result of :func:`identifiable_directions`.

    Attributes
    ----------
    directions : list of dict
        A sparse basis of the identified subspace, best (smallest ``sd_ratio``) first:
        ``label`` (e.g. "(1-VOLF)·T1"), ``exponents`` (feature label -> rounded exponent),
        ``raw`` (feature label -> unrounded exponent, same normalisation, 0 off the support),
        ``sd_ratio`` (posterior/prior sd along the raw direction), ``sd_ratio_rounded`` (same
        for the rounded exponents), ``median``, ``lo``, ``hi``, ``cv`` of the rounded
        combination on the θ scale (product of powers; linear features enter as exp).
    spectrum : ndarray
        All posterior/prior sd ratios of the full generalised eigenproblem (ascending).
    features : list of str
        Feature labels: "P" for log P, "(1-P)" for log(1−P), "lin:P" for a linear feature.
    candidates : dict
        :func:`candidate_combinations` output.
    threshold : float
    eigenvectors : ndarray
        Generalised eigenvectors of the full problem (columns, ascending ratio).
    n_identified : int
        k = number of spectrum values below ``threshold`` (dimension of the identified
        subspace).
    n_resolved : int
        Sparse basis directions found (≤ k).  Fewer than k: some identified directions need
        more than ``max_terms`` features.  It can exceed ``len(directions)``: a second
        direction on the same single parameter (VOLF and (1-VOLF) when VOLF itself is pinned)
        or with the same rounded exponents is counted but not listed again.
    """

    directions: list
    spectrum: np.ndarray
    features: list
    candidates: dict
    threshold: float
    eigenvectors: np.ndarray = field(repr=False, default=None)
    n_identified: int = 0
    n_resolved: int = 0

    def table(self) -> str:
        """Markdown table of the identified directions and the candidate checks."""
        lines = ["| combination | sd ratio post/prior | median | interval |", "|---|---|---|---|"]
        for d in self.directions:
            lines.append(f"| {d['label']} | {d['sd_ratio_rounded']:.3g} | {d['median']:.4g} | [{d['lo']:.4g}, {d['hi']:.4g}] |")
        if self.n_resolved < self.n_identified:
            lines.append(f"| ({self.n_identified - self.n_resolved} identified direction(s) without a sparse "
                         f"representation) | | | |")
        lines += ["", "| candidate | median | interval | CV | sd ratio post/prior | identified |",
                  "|---|---|---|---|---|---|"]
        for k, c in self.candidates.items():
            lines.append(f"| {k} | {c['median']:.4g} | [{c['lo']:.4g}, {c['hi']:.4g}] | {c['cv']:.3g} | "
                         f"{c.get('sd_ratio', float('nan')):.3g} | {'yes' if c['identified'] else 'no'} |")
        return "\n".join(lines)


def _feature_matrix(x, names, lo, hi, log, fractions):
    feats, labels, owner = [], [], []
    for i, n in enumerate(names):
        v = x[:, i]
        if log and lo[i] >= 0:
            # a lower bound of 0 (T1, EOPT) would give log 0: floor at 1e-9 of the box width
            floor = max(lo[i], 1e-9 * (hi[i] - lo[i]))
            feats.append(np.log(np.maximum(v, floor)))
            labels.append(n)
        else:
            feats.append(v)
            labels.append(f"lin:{n}")
        owner.append(i)
        if n in fractions and log and lo[i] >= 0 and hi[i] <= 1:
            feats.append(np.log(np.maximum(1.0 - v, 1e-9)))
            labels.append(f"(1-{n})")
            owner.append(i)
    return np.column_stack(feats), labels, owner


def _format_term(label: str, e: float) -> str:
    name = label[4:] if label.startswith("lin:") else label
    if label.startswith("lin:"):
        return f"exp({e:g}·{name})" if e != 1 else f"exp({name})"
    if e == 1:
        return name
    return f"{name}^{e:g}"


def _restricted_eigs(A: np.ndarray, B: np.ndarray, supports: np.ndarray):
    """Generalised eigenproblems A v = λ B v restricted to every support (rows of ``supports``).

    Batched: whitening by the Cholesky factor of each B block, then a symmetric eigh.
    Returns sd ratios sqrt(λ) (m, s), ascending per support, and eigenvectors (m, s, s) in
    columns, B-orthonormal.
    """
    r, c = supports[:, :, None], supports[:, None, :]
    As, Bs = A[r, c], B[r, c]
    Linv = np.linalg.inv(np.linalg.cholesky(Bs))
    M = Linv @ As @ np.swapaxes(Linv, 1, 2)
    w, U = np.linalg.eigh(0.5 * (M + np.swapaxes(M, 1, 2)))
    return np.sqrt(np.maximum(w, 0.0)), np.swapaxes(Linv, 1, 2) @ U


def identifiable_directions(
    samples,
    names: Sequence[str],
    *,
    bounds=None,
    log: bool = True,
    threshold: float = 0.1,
    fractions: Sequence[str] | None = None,
    step: float = 0.5,
    min_coef: float = 0.2,
    max_terms: int = 3,
    independence_tol: float = 0.3,
    n_prior: int = 20000,
    seed=0,
    interval: tuple[float, float] = (0.05, 0.95),
    candidates=None,
    spec: ModelSpec | None = None,
) -> IdentifiabilityReport:
    """Combinations of parameters that the data identify, found from the posterior samples.

    A sparse basis of the identified subspace of the generalised eigenproblem
    C_post v = λ C_prior v in feature space (see the module docstring for why the
    eigenvectors themselves are not reported):

    1. k = number of sd ratios sqrt(λ) below ``threshold``.
    2. For support sizes s = 1, …, ``max_terms``: solve the eigenproblem restricted to every
       set of s feature columns; take all its directions with ratio < ``threshold`` in order
       of increasing ratio; accept a direction when, in the prior-whitened metric (inner
       product C_prior), its part orthogonal to the span of the directions accepted so far
       has relative norm > ``independence_tol``.  Stop at k accepted.
    3. Normalise the exponents of each accepted direction (the smallest |exponent| among
       terms with a prior-whitened share ≥ ``min_coef`` of the largest becomes 1, the
       largest share positive), round to ``step`` and re-check the ratio of the rounded
       combination.

    Parameters
    ----------
    samples : array_like (n, d)
        Posterior samples (equal weights).
    names : sequence of str
    bounds : array_like (d, 2), optional
        Prior box (uniform).  Default: the range spanned by the samples (then "prior" means
        that range, ratios are less meaningful, and the candidates use the CV-shrink
        criterion of :func:`candidate_combinations`).
    log : bool
        Use log features for parameters with a non-negative box (products of powers).
    threshold : float
        A direction is identified when its posterior sd is below ``threshold`` times its prior
        sd (generalised eigenvalue λ = var_post/var_prior < threshold²).
    fractions : sequence of str, optional
        Parameters in [0, 1] that also get a log(1 − θ) feature (default: the spec's volume fractions).
    step : float
        Rounding step of the exponents.
    min_coef : float
        Terms whose prior-whitened share |u_j|·sd_prior,j is below ``min_coef`` times the
        largest do not set the exponent scale (they stay in the label if their rounded
        exponent is non-zero).
    max_terms : int
        Largest support searched (number of features in one reported combination).
    independence_tol : float
        Minimum relative norm, in the prior-whitened metric, of the part of a candidate
        direction orthogonal to the directions already accepted (0.3 ≈ 17.5° from their
        span).  Too small admits near-copies (P1·(1-VOLF)^-0.1 next to VOLF·P1: VOLF's
        narrow box puts them only ≈ 0.2 apart); too large rejects genuinely new directions
        that are oblique to the accepted ones.
    n_prior : int
        Uniform draws from the box used for the prior covariance of the features.
    seed : int or Generator
    interval : (float, float)
    candidates : see :func:`candidate_combinations`.
    spec : ModelSpec, optional
        The model's vocabulary (fractions, candidates); default the default base's.

    Returns
    -------
    IdentifiabilityReport
    """
    x = np.asarray(samples, float)
    names = list(names)
    if x.ndim != 2 or x.shape[1] != len(names) or x.shape[0] < len(names) + 2:
        raise HbmError(f"identifiable_directions: samples must be (n > d+1, {len(names)}), got {x.shape}")
    if int(max_terms) < 1:
        raise HbmError(f"identifiable_directions: max_terms must be >= 1, got {max_terms}")
    if bounds is None:
        b = np.column_stack([x.min(0), x.max(0)])
        flat = b[:, 1] <= b[:, 0]  # a constant column: give it a tiny box so C_prior stays regular
        b[flat, 1] = b[flat, 0] + np.maximum(1e-12, 1e-9 * np.abs(b[flat, 0]))
    else:
        b = np.asarray(bounds, float)
        if b.shape != (len(names), 2) or np.any(b[:, 1] <= b[:, 0]):
            raise HbmError(f"identifiable_directions: bounds must be ({len(names)}, 2) with lower < upper")
    lo, hi = b[:, 0], b[:, 1]
    fractions = (spec or base_spec()).fractions if fractions is None else fractions
    rng = np.random.default_rng(seed)
    prior = rng.uniform(lo, hi, (int(n_prior), len(names)))
    Fp, labels, owner = _feature_matrix(x, names, lo, hi, log, set(fractions))
    Fq, _, _ = _feature_matrix(prior, names, lo, hi, log, set(fractions))
    Cpost = np.cov(Fp, rowvar=False)
    Cprior = np.cov(Fq, rowvar=False)
    # Parameters that do not vary in the samples would make C_post singular; the tiny ridge
    # keeps the restricted problems well posed (a degenerate prior is excluded above).
    Cpost_r = Cpost + 1e-14 * np.diag(np.diag(Cprior))
    lam, V = eigh(Cpost_r, Cprior)
    sd_ratio = np.sqrt(np.maximum(lam, 0.0))
    k = int(np.count_nonzero(sd_ratio < threshold))
    p = len(labels)
    prior_sd = np.sqrt(np.diag(Cprior))

    def ratio(u):
        return float(np.sqrt(max(u @ Cpost @ u, 0.0) / (u @ Cprior @ u))) if np.any(u) else float("inf")

    basis = np.zeros((0, p))  # accepted directions, C_prior-orthonormalised (Gram–Schmidt)
    accepted = []  # (raw ratio, direction u)
    for s in range(1, min(int(max_terms), p) + 1):
        if len(accepted) >= k:
            break
        S = np.array(list(combinations(range(p), s)))
        rat, vec = _restricted_eigs(Cpost_r, Cprior, S)
        si, ei = np.nonzero(rat < threshold)
        if si.size == 0:
            continue
        order = np.argsort(rat[si, ei], kind="stable")
        si, ei = si[order], ei[order]
        U = np.zeros((si.size, p))
        U[np.arange(si.size)[:, None], S[si]] = vec[si, :, ei]
        norms = np.sqrt(np.einsum("ij,jk,ik->i", U, Cprior, U))
        R = U - (U @ Cprior @ basis.T) @ basis  # parts orthogonal to the accepted span
        for i in range(si.size):
            rn = float(np.sqrt(max(R[i] @ Cprior @ R[i], 0.0)))
            if rn <= independence_tol * norms[i]:
                continue
            bvec = R[i] / rn
            basis = np.vstack([basis, bvec])
            R[i + 1:] -= np.outer(R[i + 1:] @ Cprior @ bvec, bvec)
            accepted.append((float(rat[si[i], ei[i]]), U[i]))
            if len(accepted) >= k:
                break

    directions, seen_keys, single_params = [], set(), set()
    for raw_ratio, u in accepted:
        share = np.abs(u) * prior_sd
        lead = int(np.argmax(share))
        big = share >= min_coef * share[lead]
        v = u / np.min(np.abs(u[big])) * np.sign(u[lead])
        r = np.round(v / step) * step
        key = tuple(r)
        params = {owner[j] for j in np.flatnonzero(r)}
        if key in seen_keys or (len(params) == 1 and params <= single_params):
            continue  # counted in n_resolved, not listed twice
        seen_keys.add(key)
        if len(params) == 1:
            single_params |= params
        expo = {labels[j]: float(r[j]) for j in range(p) if r[j] != 0}
        label = "·".join(_format_term(lb, e) for lb, e in expo.items())
        val = np.exp(Fp @ r)
        qlo, med, qhi = np.quantile(val, [interval[0], 0.5, interval[1]])
        directions.append({
            "label": label, "exponents": expo, "raw": {labels[j]: float(v[j]) for j in range(p)},
            "sd_ratio": raw_ratio, "sd_ratio_rounded": ratio(r),
            "median": float(med), "lo": float(qlo), "hi": float(qhi), "cv": _cv(val),
        })
    directions.sort(key=lambda d: d["sd_ratio"])
    cands = candidate_combinations(x, names, candidates=candidates, interval=interval, threshold=threshold,
                                   prior=prior if bounds is not None else None, spec=spec)
    return IdentifiabilityReport(directions=directions, spectrum=np.sort(sd_ratio), features=labels,
                                 candidates=cands, threshold=float(threshold), eigenvectors=V,
                                 n_identified=k, n_resolved=len(accepted))
