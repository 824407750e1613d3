"""Checkpoints written before the TMCMC refactor (main at 287c749) still resume, bitwise.

``tests/data/tmcmc_checkpoint_{rw,local,manifold}.npz`` are runs interrupted inside stage 3, written
by the code of commit 287c749 (33-field ``TMCMCConfig``; recipe in ``tmcmc_checkpoints.json``).  The
refactored fingerprint folds the retired fields back in at their old defaults, so the stored
fingerprint matches, the run resumes at stage 2 and ends on the very numbers the old code's
uninterrupted run gave (log-evidence, SE, evaluations and a hash of the posterior samples).
"""

import hashlib
import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from hbm.errors import HbmError
from hbm.samplers.tmcmc import tmcmc

DATA = Path(__file__).parent / "data"
META = json.loads((DATA / "tmcmc_checkpoints.json").read_text())
D = 3
P = np.linalg.inv(np.array([[2.0, 0.5, 0.1], [0.5, 1.0, 0.3], [0.1, 0.3, 0.5]]))
MU = np.array([0.3, -0.2, 0.5])
B = np.array([[-4, 4]] * D, float)


def _ll(x):
    r = x - MU
    return -0.5 * np.einsum("ni,ij,nj->n", r, P, r)


def _gf(x):
    r = x - MU
    return -(r @ P), np.broadcast_to(P, (len(x), D, D)).copy()


@pytest.mark.parametrize("name", sorted(META))
def test_checkpoint_of_the_old_code_resumes_bitwise(name, tmp_path):
    m = META[name]
    ck = tmp_path / "ck.npz"
    shutil.copy(DATA / f"tmcmc_checkpoint_{name}.npz", ck)
    extra = {"gradient_fim": _gf} if m["options"].get("kernel") == "manifold" else {}
    res = tmcmc(_ll, B, m["n_samples"], seed=m["seed"], progress=False, checkpoint=ck, **m["options"], **extra)
    assert res.resumed_from_stage == m["stage"] == 2
    assert res.log_evidence == m["log_evidence"]
    assert res.log_evidence_se == m["log_evidence_se"]
    assert res.n_evaluations == m["n_evaluations"]
    assert hashlib.sha256(np.ascontiguousarray(res.samples).tobytes()).hexdigest() == m["samples_sha256"]
    # and the fresh run of today's code agrees with the old one
    fresh = tmcmc(_ll, B, m["n_samples"], seed=m["seed"], progress=False, **m["options"], **extra)
    assert np.array_equal(fresh.samples, res.samples) and fresh.log_evidence == res.log_evidence


def test_old_checkpoint_with_other_settings_is_refused(tmp_path):
    m = META["rw"]
    ck = tmp_path / "ck.npz"
    shutil.copy(DATA / "tmcmc_checkpoint_rw.npz", ck)
    opts = {**m["options"], "max_steps": m["options"]["max_steps"] + 1}
    with pytest.raises(HbmError, match="different settings"):
        tmcmc(_ll, B, m["n_samples"], seed=m["seed"], progress=False, checkpoint=ck, **opts)
