"""Identifiable combinations of the Spyrou model and their exact stage-1 prior density.

Uniaxial curves identify G = c·GF + (1−c)·GM, c·P1 and (1−c)·T1 (c = VOLF), not the five
parameters (VOLF, P1, T1, GF, GM) separately.  A hierarchical population over

    φ = (y3, y1, y2) = (log G, log c·P1, log (1−c)·T1)

reuses stage-1 samples drawn under the *uniform* box prior on (VOLF, P1, T1, GF, GM), so the
importance ratios need the density p0(φ) that this box prior induces on φ.  It is computed here.

Density
-------
Given c the three components are conditionally independent:

* y1 = log(c·P1), P1 ~ U(p_a, p_b):  p(y1|c) = e^{y1} / (c (p_b − p_a))  for p_a ≤ e^{y1}/c ≤ p_b;
* y2 = log((1−c)·T1), T1 ~ U(t_a, t_b): the same with 1 − c;
* G | c = c·GF + (1−c)·GM is the sum of U(c f_a, c f_b) and U((1−c) m_a, (1−c) m_b): a
  trapezoid, p_G(G|c) = max(0, min(x, w1 + w2 − x, w1, w2)) / (w1 w2) with
  x = G − c f_a − (1−c) m_a, w1 = c (f_b − f_a), w2 = (1−c)(m_b − m_a); y3 = log G has
  density G·p_G(G|c).

p0(φ) = ∫ p(c) p(y1|c) p(y2|c) p(y3|c) dc over c's box.  The integrand is smooth except at
analytic breakpoints in c (the two support limits of each of y1 and y2 and the five kinks of the
trapezoid: x = 0, w1, w2, w1 + w2 and w1 = w2, each linear in c), so the c box is split there
and every piece is integrated by Gauss–Legendre (``n_sub`` sub-pieces × ``n_nodes`` nodes).  The
integrand is rational with poles only at c = 0 and c = 1, outside the box, so the rule converges
geometrically (measured against scipy.integrate.quad on the default box: max relative error
2.7e-7 over 20 prior draws; about 30 µs per row).

Conditional draws
-----------------
:func:`sample_conditional` draws (VOLF, P1, T1, GF, GM) from p0(· | φ): c from the integrand
on the quadrature nodes (a node with probability ∝ weight × integrand, then uniform within its
Gauss–Legendre cell: the Chebyshev–Markov–Stieltjes separation theorem puts each node inside
the cell bounded by the cumulative weights, so the draw is a fine piecewise-constant
approximation of the exact conditional of c), then P1 = e^{y1}/c, T1 = e^{y2}/(1−c), and
(GF, GM) uniform on the segment c·GF + (1−c)·GM = G inside the box (the conditional of a
uniform pair given a linear combination).  The pushed-forward φ equals the given φ to rounding.

The parameters come by role from the model's spec (:class:`hbm.model.spec.MixtureRoles`:
fraction c, fibre and matrix amplitudes, the two shear moduli; ``roles=``, default the default
base's), so this module names none of them; the samplers never import it.
"""

from __future__ import annotations

from typing import Mapping, Sequence

import numpy as np

from ..errors import HbmError
from ..model.spec import MixtureRoles, base_spec
from ..runtime.seeds import as_generator

__all__ = ["COMBINATION_PARAMS", "FEATURES", "CombinationCoordinates", "combination_box", "combination_features",
           "fibre_point", "in_support", "support_constraints",
           "log_density", "onset_strain", "support_hull", "sample_conditional", "to_features"]

#: the default base's roles (:attr:`hbm.model.spec.ModelSpec.mixture`) where a caller gives none
DEFAULT_ROLES: MixtureRoles = base_spec().mixture
#: parameters entering the combinations, in the column order used by this module (the default roles')
COMBINATION_PARAMS = DEFAULT_ROLES.params
#: names of the combinations (natural units; the features φ are their logs), as in the default base's spec
FEATURES = base_spec().combination_names


def _params(roles: MixtureRoles | None) -> tuple[str, ...]:
    return (roles or DEFAULT_ROLES).params


# --------------------------------------------------------------------------------------
# box handling
# --------------------------------------------------------------------------------------
def combination_box(bounds, names: Sequence[str] | None = None, *, roles: MixtureRoles | None = None) -> np.ndarray:
    """The (5, 2) box of the roles' parameters (fraction, fibre, matrix, the shear moduli) from ``bounds``.

    Parameters
    ----------
    bounds : mapping name -> (lo, hi), or array (len(names), 2) with ``names``, or array (5, 2)
        in :data:`COMBINATION_PARAMS` order.
    names : sequence of str, optional
        Row names of an array ``bounds``.

    Raises
    ------
    HbmError
        A parameter is missing (e.g. held fixed: the combinations then are not the identified
        quantities of a five-parameter box; pool the free parameters instead), or the box is
        not 0 < VOLF < 1 with non-negative lower bounds of the moduli.
    """
    if isinstance(bounds, Mapping):
        src = {str(k): v for k, v in bounds.items()}
    else:
        arr = np.asarray(bounds, float)
        if names is None:
            names = _params(roles)
        names = [str(n) for n in names]
        if arr.ndim != 2 or arr.shape != (len(names), 2):
            raise HbmError(f"combinations: bounds must have shape ({len(names)}, 2), got {arr.shape}")
        src = dict(zip(names, arr))
    params = _params(roles)
    missing = [p for p in params if p not in src]
    if missing:
        raise HbmError(f"combinations: need free parameters {list(params)}; {missing} missing "
                       f"(fixed parameters are not supported: use --pool auto or free them)")
    box = np.array([np.asarray(src[p], float).reshape(2) for p in params])
    if not np.all(np.isfinite(box)) or np.any(box[:, 0] >= box[:, 1]):
        raise HbmError(f"combinations: bounds must be finite with lo < hi, got {box.tolist()}")
    if not (0.0 < box[0, 0] and box[0, 1] < 1.0):
        raise HbmError(f"combinations: {params[0]} box must lie inside (0, 1), got {box[0].tolist()}")
    if np.any(box[1:, 0] < 0):
        raise HbmError(f"combinations: {', '.join(params[1:])} boxes must start at >= 0, got {box[1:].tolist()}")
    return box


def support_hull(bounds, names: Sequence[str] | None = None, *, floor: float = 1e-6,
                 roles: MixtureRoles | None = None) -> np.ndarray:
    """Box (3, 2) containing the support of (G, c·P1, (1−c)·T1) in natural units.

    The lower ends are the exact minima (linear in c, so attained at a box corner); a zero
    minimum (P1, T1 or both GF and GM starting at 0) is replaced by ``floor`` × the upper end
    so that the log transform has a finite box (the prior mass below it is O(floor)).
    """
    (ca, cb), (pa, pb), (ta, tb), (fa, fb), (ma, mb) = combination_box(bounds, names, roles=roles)
    g_lo = min(ca * fa + (1 - ca) * ma, cb * fa + (1 - cb) * ma)
    g_hi = max(ca * fb + (1 - ca) * mb, cb * fb + (1 - cb) * mb)
    hull = np.array([[g_lo, g_hi], [ca * pa, cb * pb], [(1 - cb) * ta, (1 - ca) * tb]])
    hull[:, 0] = np.where(hull[:, 0] > 0, hull[:, 0], floor * hull[:, 1])
    return hull


def to_features(names: Sequence[str], samples, *, roles: MixtureRoles | None = None) -> np.ndarray:
    """(G, c·P1, (1−c)·T1) in natural units (n, 3) from named parameter columns."""
    names = [str(n) for n in names]
    x = np.asarray(samples, float)
    if x.ndim != 2 or x.shape[1] != len(names):
        raise HbmError(f"combinations: samples must have shape (n, {len(names)}) for {names}, got {x.shape}")
    params = _params(roles)
    missing = [p for p in params if p not in names]
    if missing:
        raise HbmError(f"combinations: samples lack columns {missing} (fixed parameters are not supported)")
    c, p1, t1, gf, gm = (x[:, names.index(p)] for p in params)
    return np.column_stack([c * gf + (1 - c) * gm, c * p1, (1 - c) * t1])


# --------------------------------------------------------------------------------------
# quadrature
# --------------------------------------------------------------------------------------
def _nodes(phi: np.ndarray, box: np.ndarray, n_nodes: int, n_sub: int):
    """Quadrature nodes c (n, M), weights (n, M) and cell edges (n, M, 2) over c's box, split at
    the breakpoints of the integrand for each row of ``phi``."""
    (ca, cb), (pa, pb), (ta, tb), (fa, fb), (ma, mb) = box
    y3, y1, y2 = phi[:, 0], phi[:, 1], phi[:, 2]
    G, e1, e2 = np.exp(y3), np.exp(y1), np.exp(y2)
    with np.errstate(divide="ignore", invalid="ignore"):
        bp = [
            e1 / pb, e1 / pa if pa > 0 else np.full_like(e1, np.inf),  # y1 support
            1 - e2 / tb, 1 - e2 / ta if ta > 0 else np.full_like(e2, -np.inf),  # y2 support
            (G - ma) / (fa - ma), (G - ma) / (fb - ma), (G - mb) / (fa - mb), (G - mb) / (fb - mb),  # trapezoid
            np.full_like(G, (mb - ma) / ((fb - fa) + (mb - ma))),  # w1 = w2
        ]
    bp = np.column_stack(bp)
    bp = np.where(np.isfinite(bp), bp, ca)  # zero denominators: that kink does not depend on c
    edges = np.sort(np.column_stack([np.full_like(G, ca), np.clip(bp, ca, cb), np.full_like(G, cb)]), axis=1)
    if n_sub > 1:  # equal sub-pieces of every piece
        t = np.arange(n_sub) / n_sub
        lo, hi = edges[:, :-1, None], edges[:, 1:, None]
        edges = np.concatenate([(lo + (hi - lo) * t).reshape(len(G), -1), edges[:, -1:]], axis=1)
    x, w = np.polynomial.legendre.leggauss(n_nodes)
    cum = np.concatenate([[0.0], np.cumsum(w)]) / 2.0  # cell edges in [0, 1] (separation theorem)
    a, b = edges[:, :-1, None], edges[:, 1:, None]  # (n, S, 1)
    half = 0.5 * (b - a)
    c = (a + half * (x + 1.0)).reshape(len(G), -1)
    wt = (half * w).reshape(len(G), -1)
    cells = np.stack([(a + 2 * half * cum[:-1]).reshape(len(G), -1), (a + 2 * half * cum[1:]).reshape(len(G), -1)],
                     axis=-1)
    return c, wt, cells


def _integrand(phi: np.ndarray, c: np.ndarray, box: np.ndarray) -> np.ndarray:
    """p(c) p(y1|c) p(y2|c) p(y3|c) at nodes c (n, M) for rows of phi (n, 3)."""
    (ca, cb), (pa, pb), (ta, tb), (fa, fb), (ma, mb) = box
    y3, y1, y2 = (phi[:, k : k + 1] for k in range(3))
    G, e1, e2 = np.exp(y3), np.exp(y1), np.exp(y2)
    p1v, t1v = e1 / c, e2 / (1 - c)
    d1 = np.where((p1v >= pa) & (p1v <= pb), p1v / (pb - pa), 0.0)  # e^{y1}/(c Δp)
    d2 = np.where((t1v >= ta) & (t1v <= tb), t1v / (tb - ta), 0.0)
    w1, w2 = c * (fb - fa), (1 - c) * (mb - ma)
    x = G - c * fa - (1 - c) * ma
    d3 = G * np.maximum(0.0, np.minimum(np.minimum(x, w1 + w2 - x), np.minimum(w1, w2))) / (w1 * w2)
    return d1 * d2 * d3 / (cb - ca)


def _check_phi(phi) -> np.ndarray:
    phi = np.asarray(phi, float)
    if phi.ndim == 1 and phi.shape[0] == 3:
        phi = phi[None, :]
    if phi.ndim != 2 or phi.shape[1] != 3:
        raise HbmError(f"combinations: phi must have shape (n, 3) (log G, log c*P1, log (1-c)*T1), got {phi.shape}")
    return phi


def log_density(phi, bounds, names: Sequence[str] | None = None, *, n_nodes: int = 16, n_sub: int = 2,
                roles: MixtureRoles | None = None,
                chunk: int = 20_000) -> np.ndarray:
    """log p0(φ): density of φ = (log G, log c·P1, log (1−c)·T1) under the uniform box prior.

    Parameters
    ----------
    phi : array (n, 3)
    bounds, names
        Box of (VOLF, P1, T1, GF, GM), see :func:`combination_box`.
    n_nodes, n_sub : int
        Gauss–Legendre nodes per sub-piece and sub-pieces per breakpoint interval.
    chunk : int
        Rows per vectorised block (bounds memory).

    Returns
    -------
    ndarray (n,)
        −inf outside the support.
    """
    phi = _check_phi(phi)
    box = combination_box(bounds, names, roles=roles)
    out = np.empty(phi.shape[0])
    for s in range(0, phi.shape[0], chunk):  # blocks of rows, vectorised inside
        ph = phi[s : s + chunk]
        c, w, _ = _nodes(ph, box, n_nodes, n_sub)
        with np.errstate(divide="ignore"):
            out[s : s + chunk] = np.log(np.sum(w * _integrand(ph, c, box), axis=1))
    return out


def combination_features(names: Sequence[str], samples, bounds, *, roles: MixtureRoles | None = None,
                         density: bool = True, **quadrature) -> tuple[np.ndarray, np.ndarray | None]:
    """Features φ and their stage-1 prior log density for named parameter samples.

    Parameters
    ----------
    names : sequence of str
        Column names of ``samples`` (must include VOLF, P1, T1, GF, GM; extra columns ignored).
    samples : array (n, len(names))
    bounds : array (len(names), 2) aligned with ``names``, or mapping name -> (lo, hi)
        The uniform prior box the samples were drawn under (a narrowed box works).
    density : bool
        Compute ``log_p0`` (a quadrature per row); False: None in its place.
    **quadrature
        ``n_nodes``, ``n_sub`` of :func:`log_density`.

    Returns
    -------
    phi : ndarray (n, 3)
        (log G, log c·P1, log (1−c)·T1).
    log_p0 : ndarray (n,) or None
        log density of φ under the uniform prior on the box of (VOLF, P1, T1, GF, GM).

    Raises
    ------
    HbmError
        Missing (fixed) parameters, a bad box, or samples with a zero combination.
    """
    names = [str(n) for n in names]
    box_names = None if isinstance(bounds, Mapping) else names
    box = combination_box(bounds, box_names, roles=roles)
    f = to_features(names, samples, roles=roles)
    if np.any(f <= 0):
        raise HbmError("combinations: samples with G, c*P1 or (1-c)*T1 <= 0 have no log feature")
    phi = np.log(f)
    return phi, log_density(phi, box, **quadrature) if density else None


def _volf_interval(phi: np.ndarray, box: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The interval (lo, hi) of c = VOLF compatible with φ (..., 3) inside ``box`` and whether it is
    not empty: each box limit of P1 = e^{y1}/c, T1 = e^{y2}/(1−c) and of G = c·GF + (1−c)·GM is a
    half-line in c."""
    (ca, cb), (pa, pb), (ta, tb), (fa, fb), (ma, mb) = box
    with np.errstate(over="ignore"):
        G, a, b = np.exp(phi[..., 0]), np.exp(phi[..., 1]), np.exp(phi[..., 2])
    lo = np.maximum(ca, a / pb)
    hi = np.minimum(cb, 1.0 - b / tb)
    if pa > 0:
        hi = np.minimum(hi, a / pa)
    if ta > 0:
        lo = np.maximum(lo, 1.0 - b / ta)
    ok = np.ones(G.shape, bool)
    # G >= ma + c (fa − ma) and G <= mb + c (fb − mb): each a half-line in c
    for base, slope, below in ((ma, fa - ma, True), (mb, fb - mb, False)):
        if slope == 0:
            ok &= (G >= base) if below else (G <= base)
            continue
        t = (G - base) / slope
        if below == (slope > 0):
            hi = np.minimum(hi, t)
        else:
            lo = np.maximum(lo, t)
    return lo, hi, ok & (lo < hi)


def support_constraints(box: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The support of p0 as linear constraints with one latent scalar: φ is in it iff some c satisfies
    P·(G, c·P1, (1−c)·T1) + Q·c ≤ R row by row (strictly, as :func:`in_support`: the interval of c is not
    a point).  The rows are the box limits of c, P1 = a/c, T1 = b/(1 − c) and G = c·GF + (1−c)·GM of
    :func:`_volf_interval` (for a compiled sampler: :mod:`hbm.samplers.hierarchical.amplitudes`)."""
    (ca, cb), (pa, pb), (ta, tb), (fa, fb), (ma, mb) = np.asarray(box, float)
    rows = [((0, 0, 0), -1.0, -ca), ((0, 0, 0), 1.0, cb),             # ca <= c <= cb
            ((0, 1, 0), -pb, 0.0),                                     # a <= pb c
            ((0, 0, 1), tb, tb),                                       # b <= tb (1 - c)
            ((-1, 0, 0), fa - ma, -ma), ((1, 0, 0), -(fb - mb), mb)]   # G between the two moduli
    if pa > 0:
        rows.append(((0, -1, 0), pa, 0.0))                             # a >= pa c
    if ta > 0:
        rows.append(((0, 0, -1), -ta, -ta))                            # b >= ta (1 - c)
    return (np.array([r[0] for r in rows], float), np.array([r[1] for r in rows]), np.array([r[2] for r in rows]))


def in_support(phi, box: np.ndarray) -> np.ndarray:
    """Whether φ (..., 3) lies in the support of p0 (a point of its fibre exists) for a built
    :func:`combination_box` ``box``: exactly where :func:`log_density` is finite."""
    return _volf_interval(np.asarray(phi, float), box)[2]


def fibre_point(phi, bounds, names: Sequence[str] | None = None, *,
                box: np.ndarray | None = None, roles: MixtureRoles | None = None) -> tuple[np.ndarray, np.ndarray]:
    """One (VOLF, P1, T1, GF, GM) with combinations φ, and whether φ is in the support of p0.

    Each box limit of P1 = e^{y1}/c, T1 = e^{y2}/(1−c) and of G = c·GF + (1−c)·GM is a half-line
    in c; φ lies in the support iff their intersection with c's box is not empty.  The point
    takes c mid-way in that interval and GF, GM at the same fraction of their boxes (a
    deterministic point of the fibre: the likelihood is the same anywhere on it).

    Parameters
    ----------
    phi : array (n, 3)
        log G, log c·P1, log (1−c)·T1.
    bounds, names
        As in :func:`combination_box`.
    box : array (5, 2), optional
        That box, already built: callers that call this in a sampler's inner loop pass it once-built
        (validating the box each call cost ~10 % of the hierarchical exact fallback's CPU).

    Returns
    -------
    parts : array (n, 5)
        (VOLF, P1, T1, GF, GM), clipped to the box (meaningless where ``ok`` is False).
    ok : bool array (n,)
        Exactly where :func:`log_density` is finite.
    """
    phi = _check_phi(phi)
    box = combination_box(bounds, names, roles=roles) if box is None else box
    (ca, cb), (pa, pb), (ta, tb), (fa, fb), (ma, mb) = box
    lo, hi, ok = _volf_interval(phi, box)
    G, a, b = np.exp(phi[:, 0]), np.exp(phi[:, 1]), np.exp(phi[:, 2])
    c = np.where(ok, 0.5 * (lo + hi), 0.5 * (ca + cb))
    span = c * (fb - fa) + (1 - c) * (mb - ma)
    frac = np.clip((G - c * fa - (1 - c) * ma) / span, 0.0, 1.0)
    parts = np.column_stack([c, a / c, b / (1 - c), fa + frac * (fb - fa), ma + frac * (mb - ma)])
    return np.clip(parts, box[:, 0], box[:, 1]), ok


def sample_conditional(phi, bounds, rng, names: Sequence[str] | None = None, *, n_nodes: int = 16,
                       n_sub: int = 2, roles: MixtureRoles | None = None) -> np.ndarray:
    """Draw (VOLF, P1, T1, GF, GM) from the uniform box prior conditioned on φ.

    Parameters
    ----------
    phi : array (n, 3)
        (log G, log c·P1, log (1−c)·T1), each row inside the support of p0.
    bounds, names
        Box of (VOLF, P1, T1, GF, GM), see :func:`combination_box`.
    rng : numpy Generator or seed
    n_nodes, n_sub : int
        Quadrature of c (see the module docstring).

    Returns
    -------
    ndarray (n, 5)
        Columns in the roles' order (:attr:`~hbm.model.spec.MixtureRoles.params`); their combinations
        reproduce φ to rounding.
    """
    rng = as_generator(rng)
    phi = _check_phi(phi)
    box = combination_box(bounds, names, roles=roles)
    n = phi.shape[0]
    c_nodes, w, cells = _nodes(phi, box, n_nodes, n_sub)
    mass = w * _integrand(phi, c_nodes, box)
    cum = np.cumsum(mass, axis=1)
    tot = cum[:, -1]
    if np.any(~(tot > 0)):
        bad = int(np.argmax(~(tot > 0)))
        raise HbmError(f"combinations: phi row {bad} ({phi[bad].tolist()}) is outside the prior support")
    k = np.minimum((cum < (rng.random(n) * tot)[:, None]).sum(axis=1), cum.shape[1] - 1)
    rows = np.arange(n)
    lo, hi = cells[rows, k, 0], cells[rows, k, 1]
    c = lo + (hi - lo) * rng.random(n)
    (ca, cb), (pa, pb), (ta, tb), (fa, fb), (ma, mb) = box
    c = np.clip(c, ca, cb)
    G, e1, e2 = np.exp(phi[:, 0]), np.exp(phi[:, 1]), np.exp(phi[:, 2])
    p1 = e1 / c
    t1 = e2 / (1 - c)
    # (GF, GM) uniform on the segment c·GF + (1−c)·GM = G inside the box, parametrised by GF
    gf_lo = np.maximum(fa, (G - (1 - c) * mb) / c)
    gf_hi = np.minimum(fb, (G - (1 - c) * ma) / c)
    gf = gf_lo + (np.maximum(gf_hi, gf_lo) - gf_lo) * rng.random(n)
    gm = (G - c * gf) / (1 - c)
    out = np.column_stack([c, p1, t1, gf, gm])
    # rounding only (c lies inside the support interval): keep the draws in the box
    return np.clip(out, box[:, 0], box[:, 1])


# --------------------------------------------------------------------------------------
# sampling coordinates for TMCMC
# --------------------------------------------------------------------------------------
#: the fibre angle (degrees) below which the collagen term has no onset strain (cos²θ = 1/3)
_MAGIC_ANGLE = float(np.degrees(np.arccos(np.sqrt(1.0 / 3.0))))


def onset_strain(theta_deg) -> np.ndarray:
    """Strain ε* > 0 at which λH = 1 again, i.e. where the collagen term switches on.

    λH² = cos²θ·λ² + sin²θ/λ = 1 has the roots λ = 1 and the positive root of
    cos²θ·(λ² + λ) = sin²θ; ε* = λ − 1 (0.3028 at 60°, 0 at the magic angle 54.74°).
    """
    c2 = np.cos(np.deg2rad(np.asarray(theta_deg, float))) ** 2
    return (np.sqrt(c2 * c2 + 4.0 * c2 * (1.0 - c2)) - c2) / (2.0 * c2) - 1.0


def _theta_from_onset(eps) -> tuple[np.ndarray, np.ndarray]:
    """Inverse of :func:`onset_strain` and log dθ/dε* (θ in degrees): cos²θ = 1/(λ² + λ + 1)."""
    lam = 1.0 + np.asarray(eps, float)
    c2 = 1.0 / (lam * lam + lam + 1.0)
    theta = np.degrees(np.arccos(np.sqrt(c2)))
    # dθ/dλ = (2λ + 1)·c2² / (2 √(c2 (1 − c2))) radians
    log_d = np.log((2.0 * lam + 1.0) * c2 * c2 / (2.0 * np.sqrt(c2 * (1.0 - c2))) * (180.0 / np.pi))
    return theta, log_d


class CombinationCoordinates:
    """TMCMC sampling coordinates that straighten the Spyrou model's degeneracies.

    Every parameter starts from the sampler's default logit coordinate
    ℓ_j = logit((θ_j − lo_j)/(hi_j − lo_j)); then

    * P1 and GF are sheared by log c and T1 and GM by log(1 − c) (c = VOLF): u = ℓ + log c, so
      the hyperbolas c·P1 = const that the curve identifies (and (1 − c)·T1 = const) become
      nearly straight lines in (ℓ_c, u) wherever P1 lies well inside its box.  The shear is unit
      triangular: the Jacobian is that of the logit alone;
    * THETA (if its box lies above the magic angle 54.74°) becomes u = log ε*(THETA), the log
      onset strain of the collagen term (:func:`onset_strain`) on its box [log ε*(lo), log ε*(hi)]
      — *not* a logit: the posterior piles up at the 60° face, where a logit would stretch it
      into a long tail whose local scale changes exponentially (a turning thin direction).

    Measured on the shared benchmark posterior (workflows/benchmarks/evaluations_to_accuracy.py
    ``--geometry``): the largest eigenvalue of the Fisher information whitened by the
    posterior covariance falls from a median ~8000 (logit) to ~1400 and the β = 1 random walk's
    step scale rises 1.8×, but TMCMC does not reach the benchmark's accuracy with fewer
    evaluations in these coordinates (results/benchmarks/evaluations_to_accuracy.md): the
    remaining thin direction is not a smooth function of the others.  Exact (tested), optional.

    Parameters
    ----------
    names : sequence of str
        Parameter names in the sampler's column order (absent VOLF: no shear; absent THETA:
        no onset coordinate; other parameters keep the logit).
    bounds : array (len(names), 2)
        The uniform prior box.
    theta : {"onset", "linear", "logit"}
        Coordinate of THETA: log onset strain (default), THETA itself, or the plain logit.
    shear : bool
        Apply the log c / log(1 − c) shear.
    """

    def __init__(self, names: Sequence[str], bounds, *, theta: str = "onset", shear: bool = True,
                 roles: MixtureRoles | None = None):
        roles = roles or DEFAULT_ROLES
        self.names = [str(n) for n in names]
        b = np.asarray(bounds, float)
        if b.shape != (len(self.names), 2) or not np.all(np.isfinite(b)) or np.any(b[:, 0] >= b[:, 1]):
            raise HbmError(f"combinations: bounds must be a finite ({len(self.names)}, 2) box with lo < hi")
        if theta not in ("onset", "linear", "logit"):
            raise HbmError(f"combinations: theta must be 'onset', 'linear' or 'logit', got {theta!r}")
        self.lo, self.width = b[:, 0].copy(), b[:, 1] - b[:, 0]
        ix = {n: j for j, n in enumerate(self.names)}
        self._c = ix.get(roles.fraction) if shear else None
        if self._c is not None and not (0.0 < b[self._c, 0] and b[self._c, 1] < 1.0):
            raise HbmError(f"combinations: {roles.fraction} box must lie inside (0, 1), got {b[self._c].tolist()}")
        self._up = [ix[p] for p in (roles.fibre, roles.shear[0]) if p in ix and self._c is not None]
        self._down = [ix[p] for p in (roles.matrix, roles.shear[1]) if p in ix and self._c is not None]
        self._th = ix.get(roles.angle) if theta != "logit" and roles.angle else None
        self._theta_kind = theta
        if self._th is not None and theta == "onset" and not b[self._th, 0] > _MAGIC_ANGLE:
            raise HbmError(f"combinations: theta='onset' needs a {roles.angle} box above {_MAGIC_ANGLE:.2f} deg, "
                           f"got {b[self._th].tolist()}")
        self._logit = np.ones(len(self.names), dtype=bool)
        sup = np.array([[-np.inf, np.inf]] * len(self.names))
        if self._th is not None:
            self._logit[self._th] = False
            sup[self._th] = np.log(onset_strain(b[self._th])) if theta == "onset" else b[self._th]
        self.support = sup
        self.name = f"combinations(theta={theta},shear={bool(shear)},names={','.join(self.names)})"

    def _shift(self, c: np.ndarray) -> np.ndarray:
        """(n, d) shear added to the logit coordinates."""
        s = np.zeros((len(c), len(self.names)))
        s[:, self._up] = np.log(c)[:, None]
        s[:, self._down] = np.log1p(-c)[:, None]
        return s

    def forward(self, theta: np.ndarray) -> np.ndarray:
        """θ (n, d) → u (n, d)."""
        x = np.asarray(theta, float)
        f = np.clip((x - self.lo) / self.width, 1e-15, 1.0 - 1e-15)
        u = np.log(f) - np.log1p(-f)
        if self._c is not None:
            u = u + self._shift(x[:, self._c])
        if self._th is not None:
            t = x[:, self._th]
            u[:, self._th] = np.log(onset_strain(t)) if self._theta_kind == "onset" else t
        return u

    def inverse(self, u: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """u (n, d) → (θ (n, d), log|det ∂θ/∂u| (n,))."""
        u = np.asarray(u, float)
        ell = u.copy()
        if self._c is not None:  # VOLF is itself a plain logit: undo the shear with its c
            a = np.abs(u[:, self._c])
            e = np.exp(-a)
            fc = np.where(u[:, self._c] >= 0, 1.0, e) / (1.0 + e)
            ell = ell - self._shift(self.lo[self._c] + fc * self.width[self._c])
        a = np.abs(ell)
        e = np.exp(-a)  # stable logistic
        f = np.where(ell >= 0, 1.0, e) / (1.0 + e)
        x = self.lo + f * self.width
        # logit Jacobian: dθ/dℓ = width·f(1 − f) = width·e^{−|ℓ|}/(1 + e^{−|ℓ|})²; the shear has det 1
        log_j = np.log(self.width) - a - 2.0 * np.log1p(e)
        if self._th is not None:
            t = u[:, self._th]
            if self._theta_kind == "onset":
                x[:, self._th], log_d = _theta_from_onset(np.exp(t))
                log_j[:, self._th] = t + log_d
            else:
                x[:, self._th] = t
                log_j[:, self._th] = 0.0
        return x, log_j.sum(axis=1)
