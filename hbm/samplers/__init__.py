"""Samplers: Transitional MCMC by concept, and the hierarchical layer.

TMCMC: :mod:`.tmcmc` (pure ``init``/``step`` and the driver ``tmcmc``), :mod:`.types` (settings,
state, stage info, result), :mod:`.moves` (the Move protocol and registry: random walk,
manifold, local walk), :mod:`.coordinates`, :mod:`.resampling`, :mod:`.checkpoint`, :mod:`.linalg`,
:mod:`.chains` (the islands, or importance batches, as independent chains for R-hat).
Importance-sampling evidence: :mod:`.importance` (PSIS k̂: :mod:`.psis`); the mixture proposals
fitted to posterior draws, by weighted EM there and by k-means in the hierarchical exact fallback:
:mod:`.mixtures`.
``hbm.samplers.tmcmc`` is the module; the driver function is ``hbm.samplers.tmcmc.tmcmc`` (also
``hbm.tmcmc``).
"""

from ..runtime.lazy import attach

# a module that needs only the types (hbm.io) does not load the sampler and scipy (hbm.runtime.lazy)
__getattr__, __dir__ = attach(__name__, {
    ".checkpoint": ["checkpoint_progress"],
    ".moves": ["MOVES", "LocalWalk", "Manifold", "Move", "RandomWalk", "register_move"],
    ".tmcmc": ["init", "step"],
    ".types": ["DEFAULT_N_SAMPLES", "StageInfo", "TMCMCConfig", "TMCMCResult", "TMCMCState"],
})

__all__ = ["DEFAULT_N_SAMPLES", "StageInfo", "TMCMCConfig", "TMCMCResult", "TMCMCState", "checkpoint_progress",
           "init", "step", "MOVES", "Move", "RandomWalk", "Manifold", "LocalWalk", "register_move"]
