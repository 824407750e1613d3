"""The seed table (hbm.runtime.seeds): named streams, no shared keys, compatibility with spawn()."""

import numpy as np
import pytest

from hbm.runtime import seeds


def test_no_two_streams_share_a_key():
    keys = seeds.run_keys(500)
    # every specimen stream, its four phases, refine, reference, layer_specimen, two organ streams, plus the
    # run-level streams (hierarchical, new_specimen, organ_new_specimen, grouped, joint, layer)
    assert len(keys) == 500 * (1 + len(seeds.PHASES) + 5) + 6


def test_run_keys_detects_a_collision(monkeypatch):
    monkeypatch.setitem(seeds.STREAMS, "new_specimen", lambda: (3,))  # = specimen 3's key
    with pytest.raises(ValueError, match="share spawn key"):
        seeds.run_keys(5)


def test_children_equal_spawn_of_a_fresh_sequence():
    # streams made before the table (SeedSequence(seed).spawn(n)) must be unchanged
    for seed in (0, 1, 12345):
        fresh = np.random.SeedSequence(seed).spawn(6)
        ours = seeds.children(seed, 6)
        for a, b in zip(fresh, ours):
            assert a.spawn_key == b.spawn_key
            assert np.array_equal(a.generate_state(4), b.generate_state(4))
        spec = seeds.stream(seed, "specimen", 4)
        assert np.array_equal(spec.generate_state(4), fresh[4].generate_state(4))


def test_children_do_not_depend_on_earlier_spawns():
    ss = np.random.SeedSequence(7)
    ss.spawn(3)  # a spawn() call would shift the next children; the table's keys do not move
    assert seeds.child_ints(ss, 2) == seeds.child_ints(7, 2)


def test_seed_int_is_the_63_bit_idiom():
    ss = np.random.SeedSequence(3, spawn_key=(10_000,))
    expected = int(ss.generate_state(1, np.uint64)[0] >> 1)
    assert seeds.seed_int(ss) == expected
    assert 0 <= expected < 2**63


def test_named_streams_match_the_documented_keys():
    assert seeds.stream(5, "hierarchical").spawn_key == (10_000,)
    assert seeds.stream(5, "refine", 2).spawn_key == (10_000, 3)
    assert seeds.stream(5, "organ_updated", 1).spawn_key == (20_000, 1, 1)
    assert seeds.stream(5, "joint").spawn_key == (10_002,)
    assert seeds.stream(5, "layer").spawn_key == (10_003,)
    assert seeds.stream(5, "layer_specimen", 7).spawn_key == (10_004, 7)
    with pytest.raises(KeyError, match="unknown seed stream"):
        seeds.stream(5, "nope")
    with pytest.raises(ValueError):
        seeds.stream(5, "specimen", 10_000)
