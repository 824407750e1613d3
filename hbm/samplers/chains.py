"""Independent chains of an equally weighted posterior population, or the reason there are none.

R-hat (Vehtari et al. 2021, what ``arviz.summary`` reports) compares several chains that were
produced independently; a single chain gives NaN.  hbm's samplers are not MCMC chains, but two of
their products split into independent blocks:

* **TMCMC islands** (:func:`hbm.samplers.tmcmc.step`): the population is K contiguous islands,
  each resampled only from its own particles at every stage, the final β = 1 included, and moved
  by Metropolis–Hastings steps that keep a particle in its island.  Each island is therefore an
  SMC sampler of its own and its block of the final population a posterior sample.  The islands
  are *not* fully independent: they share the β schedule (chosen from the whole population) and
  the proposal covariance and step scale (adapted from the whole population; the local walk's
  neighbourhood covariances also come from other islands' particles) -- the same
  adaptation dependency as the chains of multi-chain adaptive MCMC, whose R-hat is read the same
  way.  Stored in every result file (``chains_note``).
* **Importance batches** (:func:`importance_batches`): the importance draws are iid, so K
  contiguous batches are independent; each is resampled from its own normalised weights into a
  chain of equal length (the evidence still uses all draws).

**When blocks are not kept as chains.**  Pooling the blocks, each weighted by its own evidence
estimate Ẑ_k, is the correct combination; weighting them equally (what separate chains of equal
length mean) agrees with it only while the Ẑ_k agree up to their noise.  A block whose Ẑ_k is
negligible next to the others (an island stuck in a minor mode, a batch without the draw that
dominates the weights) would get 1/K of the posterior mass it does not deserve.  So the blocks
become chains only when the spread max_k log Ẑ_k − min_k log Ẑ_k is within :func:`spread_tolerance`;
otherwise the population is pooled as before, stored as one chain, and the reason recorded (ArviZ
then reports NaN R-hat, the truthful outcome).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from .resampling import resample_islands

__all__ = ["Chains", "POOLED", "spread_tolerance", "block_chains", "importance_batches",
           "MIN_SPREAD", "MAX_SPREAD", "SPREAD_SDS"]

#: the spread of the K blocks' log Ẑ_k allowed as noise, in per-block delta-method sd: on the analytic
#: targets of tests/test_tmcmc.py (Gaussian 9-D, banana, mixture, 1-D; N = 500 and 2000, 20 seeds
#: each) the spread was 1.8–2.6 sd (median) and at most 5.1 sd; the range of 4 normal draws exceeds
#: 5 sd with probability ~0.3 %
SPREAD_SDS = 5.0
#: nats: below this, the blocks' evidence shares differ by less than a factor e -- kept as chains
#: whatever the sd (the delta-method sd is small when every stage was easy)
MIN_SPREAD = 1.0
#: nats: above this (a share 20× smaller than another's) a block counts as dead whatever the sd
MAX_SPREAD = math.log(20.0)


@dataclass(frozen=True)
class Chains:
    """How a population of ``n`` rows splits into chains (chain-major: rows of chain c are contiguous).

    Attributes
    ----------
    n_chains : int
        1 when the population was pooled (no R-hat).
    method : str
        ``"tmcmc_islands"``, ``"importance_batches"`` or ``"pooled"``.
    note : str
        What the chains are and how independent, or why the population is one chain.
    spread : float
        max − min of the blocks' log-evidence estimates (NaN when not computed).
    tolerance : float
        The spread allowed (:func:`spread_tolerance`; NaN when not computed).
    """

    n_chains: int
    method: str
    note: str
    spread: float = float("nan")
    tolerance: float = float("nan")

    def to_attrs(self) -> dict:
        """netCDF attributes (strings and floats only)."""
        return {"chains": self.method, "chains_note": self.note, "chains_spread_log_evidence": float(self.spread),
                "chains_tolerance_log_evidence": float(self.tolerance)}

    @classmethod
    def from_attrs(cls, attrs: dict, n_chains: int) -> "Chains":
        """Inverse of :meth:`to_attrs`; files written before chains were stored are one pooled chain."""
        if "chains" not in attrs:
            return cls(n_chains, "pooled" if n_chains == 1 else "unknown",
                       "written by an hbm version that pooled the population into one chain")
        return cls(n_chains, str(attrs["chains"]), str(attrs.get("chains_note", "")),
                   float(attrs.get("chains_spread_log_evidence", np.nan)),
                   float(attrs.get("chains_tolerance_log_evidence", np.nan)))


#: one chain, nothing recorded (results built by callers that do not track chains)
POOLED = Chains(1, "pooled", "one pooled population (its sampler did not record independent chains)")

ISLAND_NOTE = ("{k} TMCMC islands, each resampled only from its own particles at every stage (beta = 1 included) "
               "and moved by Metropolis-Hastings steps of its own particles; they share the beta schedule and the "
               "proposal's covariance and scale (adapted from the whole population; the local walk's neighbourhoods "
               "too), so they are independent up to that adaptation, like the chains of multi-chain adaptive MCMC")
BATCH_NOTE = ("{k} independent batches of the iid importance draws, each resampled from its own normalised "
              "weights; the evidence uses all draws")


def spread_tolerance(block_sd: float) -> float:
    """Largest spread (nats) of the blocks' log Ẑ_k that counts as noise.

    ``SPREAD_SDS`` per-block delta-method sd, at least :data:`MIN_SPREAD` and at most
    :data:`MAX_SPREAD` (module docstring; the constants say what they rest on).
    """
    sd = float(block_sd) if np.isfinite(block_sd) else 0.0
    return float(min(MAX_SPREAD, max(MIN_SPREAD, SPREAD_SDS * sd)))


def block_chains(block_log_evidence, block_sd: float, n: int, method: str, note: str) -> Chains:
    """Keep K blocks of a population of ``n`` as chains, or pool them (and say why).

    Parameters
    ----------
    block_log_evidence : array (K,)
        Each block's own log-evidence estimate.
    block_sd : float
        Per-block sd of log Ẑ_k by the delta method (noise of one block's estimate).
    n : int
        Rows of the population (must split into K equal chains).
    method, note : str
        What to record when the blocks are kept (``note`` may use ``{k}``).

    Returns
    -------
    Chains
    """
    z = np.asarray(block_log_evidence, float)
    k = len(z)
    if k < 2:
        return Chains(1, "pooled", "one block only (n_islands = 1, or fewer than 40 particles or draws): no R-hat")
    if n % k:
        return Chains(1, "pooled", f"{n} draws do not split into {k} equal chains: pooled, no R-hat")
    if not np.isfinite(z).all():
        return Chains(1, "pooled", f"a block of {k} lost all its weight (zero likelihood everywhere it looked): "
                                   "pooled by evidence, no R-hat")
    spread, tol = float(z.max() - z.min()), spread_tolerance(block_sd)
    if spread > tol:
        return Chains(1, "pooled", f"the {k} blocks' log-evidences differ by {spread:.2f} nats (more than the "
                                   f"{tol:.2f} their noise explains): pooled, each weighted by its evidence; "
                                   "equal-weight chains would bias the posterior, so no R-hat",
                      spread, tol)
    return Chains(k, method, note.format(k=k), spread, tol)


def importance_batches(log_weights: np.ndarray, n_out: int, k: int,
                       rng: np.random.Generator) -> tuple[np.ndarray, Chains]:
    """Rows of ``n_out`` draws resampled batch-wise from iid importance draws: K chains, or None to pool.

    The draws are split into ``k`` interleaved batches (row i belongs to batch i mod k); if
    :func:`block_chains` keeps them, each batch is resampled systematically from its own normalised
    weights into ``n_out // k`` rows (chain-major; :func:`~hbm.samplers.resampling.resample_islands`).  Otherwise the indices are None and the caller
    resamples the pooled draws.  Interleaved, not contiguous: when the finish combined rounds from
    two proposals (balance-heuristic weights against their draw-count mixture), every batch holds
    both rounds in the mixture's proportions, so each batch's weights remain valid for its own draws.

    Parameters
    ----------
    log_weights : array (m,)
        Log importance weights (any normalisation; −inf allowed).
    n_out : int
        Rows wanted.
    k : int
        Batches.
    rng : numpy Generator
        Consumes ``k`` uniforms when the batches are kept, nothing otherwise.

    Returns
    -------
    idx : ndarray (n_out,) of int, or None
    chains : Chains
    """
    lw_rows = np.asarray(log_weights, float)
    m = len(lw_rows)
    k = max(1, min(int(k), m // 20))
    order = np.argsort(np.arange(m) % k, kind="stable")  # batch j = rows j, j + k, j + 2k, ...
    lw = lw_rows[order]
    sizes = np.bincount(np.arange(m) % k, minlength=k)
    starts = np.concatenate([[0], np.cumsum(sizes)[:-1]])
    isl = np.repeat(np.arange(k), sizes)
    top = np.maximum.reduceat(lw, starts)
    with np.errstate(divide="ignore", invalid="ignore"):
        w = np.exp(lw - np.where(np.isfinite(top), top, 0.0)[isl])
        mean, sq = np.add.reduceat(w, starts) / sizes, np.add.reduceat(w * w, starts) / sizes
        z = np.where(np.isfinite(top), top + np.log(mean), -np.inf)  # each batch's log Ẑ_k
        cov2 = np.where(mean > 0, sq / np.where(mean > 0, mean, 1.0) ** 2 - 1.0, np.inf)
    # delta method: Var(log mean w) = CoV²/m per batch; the largest is the noise of the spread
    sd = float(np.sqrt(np.max(np.maximum(cov2, 0.0) / sizes)))
    chains = block_chains(z, sd, int(n_out), "importance_batches", BATCH_NOTE)
    if chains.n_chains == 1:
        return None, chains
    # every top is finite here (block_chains pooled otherwise)
    return order[resample_islands(lw, top, starts, sizes, isl, rng, "systematic", n_per=int(n_out) // k)], chains
