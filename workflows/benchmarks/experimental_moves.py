"""TMCMC moves measured on the muscle benchmark and not shipped: differential evolution.

Until commit 287c749 these lived in ``hbm/samplers/tmcmc.py`` as ``TMCMCConfig`` fields
(``de_fraction``, ``de_gamma``, ``de_jump``, ``de_noise``) with branches in ``step()``.  The
measurements (``results/benchmarks/muscle_posterior.md``, ``evaluations_to_accuracy.md``) found no
gain: DE did not reduce the steps per stage and made log Ẑ less accurate.  Here the move is a
:class:`hbm.samplers.moves.Move` built on the public API only, so the benchmark can still run it::

    tmcmc(lik, lik.bounds, 2000, seed=0, move=DifferentialEvolution(fraction=0.5))

It reproduces the old ``de_fraction`` runs bitwise (same random stream).  The other experiments of
287c749 (fitted t-mixture independence moves, recycling/MBAR, persistent sampling, the "pca",
"ll_rank" and "max_corr_ll" mixing measures, the ``frugal`` preset) are not ported: no benchmark
setting kept uses them; ``git show 287c749:hbm/samplers/tmcmc.py`` has the code.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any, Optional

import numpy as np

from hbm.samplers.moves import MoveStep, RandomWalk, StageSetup, Tuning, Walkers, metropolis


def pairs_excluding_self(n: int, m: int, rng: np.random.Generator, rows: np.ndarray):
    """Two distinct indices a ≠ b in [0, n), both ≠ rows[i], uniform over ordered pairs."""
    a = rng.integers(0, n - 1, m)
    a += a >= rows
    b = rng.integers(0, n - 2, m)
    lo, hi = np.minimum(rows, a), np.maximum(rows, a)
    b += b >= lo
    b += b >= hi
    return a, b


@dataclass(frozen=True)
class DifferentialEvolution(RandomWalk):
    """Random walk mixed with differential-evolution proposals (ter Braak 2006).

    Each particle independently (probability ``fraction``; a choice that does not depend on its
    position, so the step is a mixture of MH kernels each leaving the tempered target invariant)
    proposes u′ = u + γ·(P_a − P_b) + noise·L z with P the stage-start population held fixed during
    the stage and a ≠ b two particles not descended from the particle's own ancestor — the
    increment is then symmetric and independent of u, so the plain Metropolis ratio is exact;
    γ = 1 with probability ``jump`` (jumps between modes), else ``gamma`` (None = 2.38/√(2d)).
    Otherwise (or when no valid pair is found in a few redraws) the Gaussian random walk.  DE pairs
    span the islands, so the island SE can be optimistic.  The acceptance of the DE proposals of each
    step is appended to ``de_acceptance`` (the sampler's per-stage statistics do not know this move).
    """

    fraction: float = 0.5
    gamma: Optional[float] = None
    jump: float = 0.1
    noise: float = 0.05
    de_acceptance: list = field(default_factory=list, compare=False, repr=False)

    name = "de"

    def step(self, kernel: StageSetup, walkers: Walkers, beta: float, tuning: Tuning,
             rng: np.random.Generator) -> MoveStep:
        x, pop, anc = walkers.x, kernel.walkers.x, kernel.ancestors
        n, d = x.shape
        zl = rng.standard_normal((n, d)) @ kernel.chol.T
        log_u = np.log(rng.random(n))
        prop = x + tuning.scale * zl
        is_de = np.zeros(n, dtype=bool)
        if self.fraction > 0 and n >= 4:
            rows = np.flatnonzero(rng.random(n) < self.fraction)
            a = np.empty(len(rows), dtype=np.int64)
            b = np.empty(len(rows), dtype=np.int64)
            todo = np.arange(len(rows))
            for _ in range(8):  # vectorised redraws of the few pairs hitting a relative of the particle
                if not len(todo):
                    break
                ai, bi = pairs_excluding_self(n, len(todo), rng, rows[todo])
                a[todo], b[todo] = ai, bi
                own = anc[rows[todo]]
                bad = (anc[ai] == own) | (anc[bi] == own) | (anc[ai] == anc[bi])
                todo = todo[bad]
            ok = np.ones(len(rows), dtype=bool)
            ok[todo] = False  # no valid pair found: this particle keeps its random-walk proposal
            rows, a, b = rows[ok], a[ok], b[ok]
            gamma = self.gamma if self.gamma is not None else 2.38 / math.sqrt(2.0 * d)
            g = np.where(rng.random(len(rows)) < self.jump, 1.0, gamma)
            prop[rows] = x[rows] + g[:, None] * (pop[a] - pop[b]) + self.noise * zl[rows]
            is_de[rows] = True
        new, accept, n_eval = metropolis(walkers, prop, log_u, beta, kernel.evaluate, kernel.box)
        if is_de.any():
            self.de_acceptance.append(float(accept[is_de].mean()))
        return MoveStep(new, accept, n_eval, alternative=is_de)

    def fingerprint(self) -> dict[str, Any]:
        return {"move": self.name, "de_fraction": self.fraction, "de_gamma": self.gamma, "de_jump": self.jump,
                "de_noise": self.noise}
