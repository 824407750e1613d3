"""TMCMC checkpoints: an atomic ``.npz`` after every stage, and the settings fingerprint that guards resuming.

A run resumes only from a checkpoint written with the same settings.  The fingerprint is the
SHA-256 of the settings in the layout of checkpoint version 1 (the 33-field ``TMCMCConfig`` of
commit 287c749): fields retired since are folded in at the values they had by default, and the
move contributes its settings under the old field names (:meth:`~hbm.samplers.moves.Move.fingerprint`),
so a checkpoint written before the refactor resumes after it, bitwise (tests/data/).
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import os
from pathlib import Path
from typing import Optional

import numpy as np

from ..errors import HbmError
from ..runtime.files import atomic_path
from .types import StageInfo, TMCMCConfig, TMCMCState

__all__ = ["fingerprint", "save_checkpoint", "load_checkpoint", "checkpoint_progress"]

CHECKPOINT_VERSION = 1

#: fields of the version-1 config that are no longer settings, at the values every run of today has
#: (differential evolution off, the max-correlation mixing measure evaluated every step)
RETIRED_FIELDS = {"de_fraction": 0.0, "de_gamma": None, "de_jump": 0.1, "de_noise": 0.05, "mixing": "max_corr",
                  "mixing_every": 1}

#: fields added after version 1: left out of the fingerprint while at these values, so checkpoints of
#: the runs before them still resume (recycling, the fitted mixture and persistent sampling are
#: retired: their values here are the only ones a run of today has)
LATE_FIELDS = {"max_evaluations": None, "recycle": False, "proposal": "rw", "mixture_components": 4,
               "independence_fraction": 0.5, "mixture_df": 5.0, "local_neighbours": 30, "local_ridge": 0.01,
               "persistent": False, "persistent_ess": 2.0}

#: fields never in the fingerprint: the final resampling changes nothing before β = 1, and the state
#: records what the last stage did (``n_chains``), so a checkpoint resumes under either value
UNFINGERPRINTED = {"final_resampling"}

#: stage keys of checkpoints written before :class:`StageInfo` (renamed fields)
LEGACY_STAGE_KEYS = {"cov": "cov_weights", "scale": "proposal_scale"}


def fingerprint(config: TMCMCConfig, bounds: np.ndarray, seed, bijection: Optional[str] = None) -> str:
    """SHA-256 of the settings of a run (version-1 layout; see the module docstring)."""
    cfg = {f.name: getattr(config, f.name) for f in dataclasses.fields(config)
           if f.name != "move" and f.name not in UNFINGERPRINTED}
    cfg.update(RETIRED_FIELDS)
    cfg.update(config.move.fingerprint())
    cfg = {k: v for k, v in cfg.items() if not (k in LATE_FIELDS and v == LATE_FIELDS[k])}
    payload = {"config": cfg, "bounds": bounds.tolist(), "seed": repr(seed), "version": CHECKPOINT_VERSION}
    if bijection is not None:  # absent without one: older checkpoints still resume
        payload["bijection"] = bijection
    return hashlib.sha256(json.dumps(payload, sort_keys=True).encode()).hexdigest()


def save_checkpoint(path: Path, state: TMCMCState, stages: list[StageInfo], fingerprint: str,
                    settings: dict) -> None:
    """Write ``state`` and the stage records atomically (a reader never sees a half-written file)."""
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as fh:  # file handle: np.savez would append ".npz" to a name
            np.savez(fh, samples=state.samples, log_likelihood=state.log_likelihood,
                     island_log_evidence=state.island_log_evidence,
                     scalars=np.array([state.beta, state.log_evidence, state.log_evidence_var,
                                       state.scale, state.epsilon]),
                     counters=np.array([state.stage, state.n_evaluations, int(state.budget_bound),
                                        int(state.n_chains)], dtype=np.int64),
                     meta=np.array(json.dumps({"rng_state": state.rng_state,
                                               "stages": [s._asdict() for s in stages],
                                               "fingerprint": fingerprint, "settings": settings})))


def load_checkpoint(path: Path, fingerprint: str) -> tuple[TMCMCState, list[StageInfo]]:
    """State and stage records of a checkpoint; :class:`HbmError` if unreadable or of other settings."""
    try:
        with np.load(path, allow_pickle=False) as z:
            meta = json.loads(str(z["meta"]))
            sc, ct = z["scalars"], z["counters"]
            state = TMCMCState(z["samples"].copy(), z["log_likelihood"].copy(), z["island_log_evidence"].copy(),
                               float(sc[0]), float(sc[1]), float(sc[2]), int(ct[0]), float(sc[3]),
                               float(sc[4]), int(ct[1]), meta["rng_state"],
                               bool(ct[2]) if len(ct) > 2 else False,
                               # before chains were recorded a finished run had always pooled its islands
                               int(ct[3]) if len(ct) > 3 else int(float(sc[0]) >= 1.0))
    except Exception as exc:  # corrupt / foreign file
        raise HbmError(f"tmcmc: cannot read checkpoint {path}: {exc}") from None
    if meta.get("fingerprint") != fingerprint:
        raise HbmError(f"tmcmc: checkpoint {path} was made with different settings "
                       f"({meta.get('settings')}); delete it or use another path")
    stages = [StageInfo.from_record({LEGACY_STAGE_KEYS.get(k, k): v for k, v in rec.items()})
              for rec in meta["stages"]]
    return state, stages


def checkpoint_progress(path: str | os.PathLike) -> Optional[tuple[int, float]]:
    """Progress recorded in a checkpoint written by :func:`hbm.samplers.tmcmc.tmcmc`.

    Parameters
    ----------
    path : path
        The ``checkpoint`` file of a (possibly running) run.

    Returns
    -------
    (stage, beta) or None
        Completed stages and the tempering exponent reached; None if the file is absent or
        unreadable (e.g. being replaced at this moment, or not a checkpoint).
    """
    try:
        with np.load(Path(path), allow_pickle=False) as z:
            return int(z["counters"][0]), float(z["scalars"][0])
    except Exception:  # absent, mid-replacement or foreign: no progress to report
        return None
