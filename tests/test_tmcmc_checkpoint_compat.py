"""Checkpoints written before the TMCMC refactor (main at 287c749) still resume, bitwise.

``tests/data/tmcmc_checkpoint_{rw,local,manifold}.npz`` are runs interrupted inside stage 3, written
by the code of commit 287c749 (33-field ``TMCMCConfig``; recipe in ``tmcmc_checkpoints.json``).  The
refactored fingerprint folds the retired fields back in at their old defaults, so the stored
fingerprint matches, the run resumes at stage 2 and ends on the numbers the old code's uninterrupted
run gave (log-evidence, SE, evaluations; a hash of the posterior samples where the machine computes
like the one that wrote the files).  The last bits of exp/log differ between machines (the C library
picks its variants by CPU features): the stages stored in the files were computed on the machine
that wrote them, so elsewhere a resumed run and a fresh one agree to ~1e-14, not bit for bit.

Since the islands became chains (issue 29) the default resampling at β = 1 keeps each island
separate, where the old code pooled them: the old code's numbers are reproduced bitwise with
``final_resampling="pooled"``; with the default the resumed run reaches the same log-evidence and SE
(computed before the final resampling) and equals today's uninterrupted run bitwise.
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


def _resume_and_fresh(name, tmp_path, **kw):
    """The old checkpoint ``name`` resumed, and today's uninterrupted run of the same settings."""
    m = META[name]
    ck = tmp_path / "ck.npz"
    shutil.copy(DATA / f"tmcmc_checkpoint_{name}.npz", ck)
    extra = {"gradient_fim": _gf} if m["options"].get("kernel") == "manifold" else {}
    args = dict(seed=m["seed"], progress=False, **m["options"], **extra, **kw)
    return m, tmcmc(_ll, B, m["n_samples"], checkpoint=ck, **args), tmcmc(_ll, B, m["n_samples"], **args)


@pytest.mark.parametrize("name", sorted(META))
def test_checkpoint_of_the_old_code_resumes_bitwise(name, tmp_path):
    m, res, fresh = _resume_and_fresh(name, tmp_path, final_resampling="pooled")
    assert res.resumed_from_stage == m["stage"] == 2
    assert res.log_evidence == pytest.approx(m["log_evidence"], rel=1e-12)
    assert res.log_evidence_se == pytest.approx(m["log_evidence_se"], rel=1e-12)
    assert res.n_evaluations == m["n_evaluations"]
    bitwise = hashlib.sha256(np.ascontiguousarray(fresh.samples).tobytes()).hexdigest() == m["samples_sha256"]
    if bitwise:  # this machine computes like the one that wrote the files: the resumed run is bitwise too
        assert hashlib.sha256(np.ascontiguousarray(res.samples).tobytes()).hexdigest() == m["samples_sha256"]
    assert res.chains.n_chains == 1
    # and the fresh run of today's code agrees with the old one
    np.testing.assert_allclose(res.samples, fresh.samples, rtol=0, atol=1e-9)
    assert fresh.log_evidence == pytest.approx(res.log_evidence, rel=1e-12)


@pytest.mark.parametrize("name", sorted(META))
def test_checkpoint_of_the_old_code_resumes_into_island_chains(name, tmp_path):
    m, res, fresh = _resume_and_fresh(name, tmp_path)
    assert res.resumed_from_stage == 2
    # the evidence is computed before the final resampling: the old code's values
    assert res.log_evidence == pytest.approx(m["log_evidence"], rel=1e-12)
    assert res.log_evidence_se == pytest.approx(m["log_evidence_se"], rel=1e-12)
    np.testing.assert_allclose(res.samples, fresh.samples, rtol=0, atol=1e-9)
    assert fresh.n_evaluations == res.n_evaluations
    assert (res.chains.n_chains, res.chains.method) == (fresh.chains.n_chains, fresh.chains.method)
    assert res.chains.n_chains in (1, 4) and (res.chains.n_chains == 4) == (res.chains.spread <= res.chains.tolerance)


def test_finished_checkpoint_of_the_old_code_reports_one_pooled_chain(tmp_path):
    # a finished run checkpointed by the old code (3 counters, islands pooled at beta = 1): resuming
    # it returns its population as one chain and says why, whatever final_resampling is now
    m = META["rw"]
    ck = tmp_path / "ck.npz"
    res = tmcmc(_ll, B, m["n_samples"], seed=m["seed"], progress=False, checkpoint=ck, **m["options"],
                final_resampling="pooled")
    with np.load(ck) as z:
        arrays = {k: z[k] for k in z.files}
    arrays["counters"] = arrays["counters"][:3]
    with open(ck, "wb") as fh:
        np.savez(fh, **arrays)
    again = tmcmc(_ll, B, m["n_samples"], seed=m["seed"], progress=False, checkpoint=ck, **m["options"])
    assert np.array_equal(again.samples, res.samples) and again.chains.n_chains == 1
    assert again.chains.method == "pooled" and "always pooled" in again.chains.note


def test_old_checkpoint_with_other_settings_is_refused(tmp_path):
    m = META["rw"]
    ck = tmp_path / "ck.npz"
    shutil.copy(DATA / "tmcmc_checkpoint_rw.npz", ck)
    opts = {**m["options"], "max_steps": m["options"]["max_steps"] + 1}
    with pytest.raises(HbmError, match="different settings"):
        tmcmc(_ll, B, m["n_samples"], seed=m["seed"], progress=False, checkpoint=ck, **opts)
