"""Resampling of weighted particle populations (systematic or multinomial), whole or by island.

The one copy of the scheme for the package: TMCMC resamples between stages with it, the
hierarchical layer draws its equally weighted outputs with it, and the importance finish resamples
its batches into chains with it (:func:`hbm.samplers.chains.importance_batches`).  Islands are
contiguous blocks of particles resampled separately, so each carries its own evidence estimate
(their spread is the TMCMC within-run standard error).
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


def resample_islands(logw, m_k, starts, sizes, isl, rng, scheme, n_per: int | None = None) -> np.ndarray:
    """Resample each island from its own log weights ``logw`` (vectorised over islands).

    ``m_k`` is the largest log weight of each island (finite); ``starts, sizes, isl`` describe
    contiguous islands (from :func:`islands`, or any other split into contiguous blocks).  Every
    island draws only its own particles: as many as it has (``n_per`` None), or ``n_per`` each,
    returned island-major (the importance batches of :func:`hbm.samplers.chains.importance_batches`).
    """
    w = np.exp(logw - m_k[isl])
    tot = np.add.reduceat(w, starts)
    cum = np.cumsum(w / tot[isl])
    offset = np.concatenate([[0.0], cum[starts[1:] - 1]])
    cw = cum - offset[isl] + isl  # island k occupies (k, k + 1]
    if n_per is None:  # each island keeps its size
        out_starts, out_sizes, out_isl = starts, sizes, isl
    else:
        k, per = len(starts), int(n_per)
        out_starts, out_sizes, out_isl = np.arange(k) * per, np.full(k, per), np.repeat(np.arange(k), per)
    n = len(out_isl)
    if scheme == "systematic":
        rank = np.arange(n) - out_starts[out_isl]
        u = out_isl + (rng.random(len(starts))[out_isl] + rank) / out_sizes[out_isl]
    else:
        u = out_isl + rng.random(n)
    idx = np.searchsorted(cw, u, side="right")
    return np.clip(idx, starts[out_isl], starts[out_isl] + sizes[out_isl] - 1)
