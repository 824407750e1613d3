"""Resampling of weighted particle populations (systematic or multinomial), whole or by island.

The one copy of the scheme for the package: TMCMC resamples between stages with it, the
hierarchical layer draws its equally weighted outputs with it.  Islands are contiguous blocks of
particles resampled separately, so each carries its own evidence estimate (their spread is the
TMCMC within-run standard error).
"""

from __future__ import annotations

import numpy as np

__all__ = ["SCHEMES", "resample", "islands", "resample_islands"]

#: resampling schemes: "systematic" (one uniform, lowest variance) or "multinomial" (n uniforms)
SCHEMES = ("systematic", "multinomial")


def resample(w: np.ndarray, n: int, rng: np.random.Generator, scheme: str = "systematic") -> np.ndarray:
    """Indices of ``n`` draws with probabilities proportional to ``w``.

    Parameters
    ----------
    w : ndarray (m,)
        Non-negative weights, normalised or not (at least one positive).
    n : int
        Number of draws.
    rng : numpy Generator
        Consumes one uniform ("systematic") or ``n`` ("multinomial").
    scheme : {"systematic", "multinomial"}

    Returns
    -------
    ndarray (n,) of int
    """
    c = np.cumsum(np.asarray(w, float))
    c /= c[-1]
    if scheme == "systematic":
        u = (rng.random() + np.arange(n)) / n
    else:
        u = rng.random(n)
    return np.minimum(np.searchsorted(c, u, side="right"), len(w) - 1)


def islands(n: int, k: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``k`` contiguous blocks of ``n`` particles: start index, size and island id of every particle."""
    starts = (np.arange(k) * n) // k
    sizes = np.diff(np.append(starts, n))
    return starts, sizes, np.repeat(np.arange(k), sizes)


def resample_islands(logw, m_k, starts, sizes, isl, rng, scheme) -> np.ndarray:
    """Resample each island from its own log weights ``logw`` (vectorised over islands).

    ``m_k`` is the largest log weight of each island; ``starts, sizes, isl`` come from
    :func:`islands`.  Every island keeps its size and draws only its own particles.
    """
    w = np.exp(logw - m_k[isl])
    tot = np.add.reduceat(w, starts)
    cum = np.cumsum(w / tot[isl])
    offset = np.concatenate([[0.0], cum[starts[1:] - 1]])
    cw = cum - offset[isl] + isl  # island k occupies (k, k + 1]
    n = len(logw)
    if scheme == "systematic":
        rank = np.arange(n) - starts[isl]
        u = isl + (rng.random(len(starts))[isl] + rank) / sizes[isl]
    else:
        u = isl + rng.random(n)
    idx = np.searchsorted(cw, u, side="right")
    return np.clip(idx, starts[isl], starts[isl] + sizes[isl] - 1)
