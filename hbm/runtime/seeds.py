"""The seed table: every random stream of hbm, derived from one root seed.

A run has one root seed ``S`` (``--seed``, default 0).  Every random thing draws from a
:class:`numpy.random.SeedSequence` ``SeedSequence(S, spawn_key=KEY)`` whose key is fixed here, so
results never depend on the number of workers, on the order in which tasks finish, or on which
other phases ran.  Specimens are numbered ``k = 0, 1, ...`` in sorted id order.

=========================  ========================  ==============================================
stream                     spawn key                 draws
=========================  ========================  ==============================================
``specimen`` k             ``(k,)``                  root of specimen k's analyses (below)
``phase`` (of a specimen)  ``(k, j)``                j = 0 CMA-ES optima, 1 TMCMC, 2 posterior
                                                     predictive, 3 Sobol (:data:`PHASES`)
``hierarchical``           ``(10000,)``              the population sampler (TMCMC over ψ,
                                                     updated individuals, new-specimen predictive)
``new_specimen``           ``(10000, 0)``            a new specimen's non-pooled parameters (drawn
                                                     given the population-predictive pooled ones)
``refine`` k               ``(10000, 1 + k)``        fresh TMCMC of specimen k under the population
``reference`` k            ``(10001, k)``            defensive reference draws of specimen k for the
                                                     population layer (hbm.population)
``joint``                  ``(10002,)``              the exact fallback of the population layer
                                                     before issue 37 (retired; its key stays taken)
``layer``                  ``(10003,)``              the population sampler (hbm.population.layer):
                                                     child 0 starting population, 1 ψ moves, 2
                                                     amplitude moves, 3 non-centred moves, 4 θ
                                                     given φ of the output, 5 new-specimen draws
``layer_specimen`` k       ``(10004, k)``            specimen k in the population sampler: child 0
                                                     its proposal fit, 1 its moves, 2 its chains'
                                                     starting rows
``organ_posterior`` k      ``(20000, 0, k)``         organ bands: subsample of specimen k's posterior
``organ_updated`` k        ``(20000, 1, k)``         organ bands: subsample of k's updated draws
``organ_new_specimen``     ``(20000, 2)``            organ bands: population-predictive draws
``detective``              ``(30000,)``              hbm.diagnose/extend: child j = 0 base fit,
                                                     1 + k greedy round k, 90 removal, 91 power
``detective_modes`` j      ``(30001, j)``            hbm.detective.modes: j = k the joint fit in
                                                     collagen reading k, 100 + m the fit without
                                                     mode m, 200 + m mode m's held-out replicates
``calibration`` k          ``(60000, k)``            hbm.diagnose: the null replicates of greedy round
                                                     k (the fitted model's own noise on the file's
                                                     design, :mod:`hbm.detective.calibration`)
``grouped``                ``(40000,)``              the grouped population sampler (population →
                                                     group → specimen, ``--group-by``/``# group:``);
                                                     used instead of ``hierarchical``
``prior`` (of a fit)       ``(50000,)`` after the    the ``prior`` group of a result file (draws from
                           fit's own key             the prior box, hbm.io.conventions)
=========================  ========================  ==============================================

A single ``hbm fit --seed S`` is specimen-free: its phases use keys ``(j,)`` of ``SeedSequence(S)``.

Keys are built explicitly (``spawn_key + (j,)``) rather than by ``SeedSequence.spawn``, whose
children depend on how often the same object was spawned before; for a fresh sequence the two
are identical, so streams made before this table existed are unchanged.
``tests/test_seeds.py`` checks that no two streams of a run share a key.
"""

from __future__ import annotations

from typing import Callable

import numpy as np

__all__ = ["PHASES", "STREAMS", "stream", "rng", "seed_int", "child", "children", "child_ints", "run_keys",
           "as_generator"]

#: Per-specimen phases, in spawn order (the j of a ``phase`` key).
PHASES: tuple[str, ...] = ("optima", "tmcmc", "predictive", "sobol")

_HIER = 10_000
_ORGAN = 20_000
_DETECTIVE = 30_000
_GROUPED = 40_000
_PRIOR = 50_000
_CALIBRATION = 60_000

#: name -> function of the stream's indices returning its spawn key (the table above).
def _specimen_key(k: int) -> tuple[int, ...]:
    if not 0 <= int(k) < _HIER:  # keys >= 10000 would collide with the population streams
        raise ValueError(f"specimen stream index must be in [0, {_HIER}), got {k}")
    return (int(k),)


STREAMS: dict[str, Callable[..., tuple[int, ...]]] = {
    "specimen": _specimen_key,
    "hierarchical": lambda: (_HIER,),
    "new_specimen": lambda: (_HIER, 0),
    "refine": lambda k: (_HIER, 1 + int(k)),
    "reference": lambda k: (_HIER + 1, int(k)),
    "joint": lambda: (_HIER + 2,),
    "layer": lambda: (_HIER + 3,),
    "layer_specimen": lambda k: (_HIER + 4, int(k)),
    "organ_posterior": lambda k: (_ORGAN, 0, int(k)),
    "organ_updated": lambda k: (_ORGAN, 1, int(k)),
    "organ_new_specimen": lambda: (_ORGAN, 2),
    "detective": lambda: (_DETECTIVE,),
    "detective_modes": lambda j: (_DETECTIVE + 1, int(j)),
    "grouped": lambda: (_GROUPED,),
    "prior": lambda: (_PRIOR,),
    "calibration": lambda k: (_CALIBRATION, int(k)),
}


def _root(seed: int | np.random.SeedSequence) -> np.random.SeedSequence:
    if isinstance(seed, np.random.SeedSequence):
        return seed
    return np.random.SeedSequence(int(seed))


def stream(seed: int | np.random.SeedSequence, name: str, *index: int) -> np.random.SeedSequence:
    """The ``SeedSequence`` of a named stream of the table (module docstring).

    Parameters
    ----------
    seed : int or SeedSequence
        The run's root seed (an int), or a root sequence whose key the stream's key extends.
    name : str
        A key of :data:`STREAMS`.
    *index : int
        The stream's indices (e.g. the specimen number ``k``).
    """
    try:
        make = STREAMS[name]
    except KeyError:
        raise KeyError(f"unknown seed stream {name!r}; known: {', '.join(STREAMS)}") from None
    root = _root(seed)
    return np.random.SeedSequence(root.entropy, spawn_key=tuple(root.spawn_key) + make(*index))


def rng(seed: int | np.random.SeedSequence, name: str, *index: int) -> np.random.Generator:
    """A ``numpy.random.Generator`` on a named stream (see :func:`stream`)."""
    return np.random.default_rng(stream(seed, name, *index))


def seed_int(ss: np.random.SeedSequence) -> int:
    """A non-negative 63-bit integer seed from a sequence (for APIs that take an int seed)."""
    return int(ss.generate_state(1, dtype=np.uint64)[0] >> np.uint64(1))


def child(seed: int | np.random.SeedSequence, j: int) -> np.random.SeedSequence:
    """Child ``j`` of a sequence: key ``spawn_key + (j,)`` (= ``spawn(j + 1)[j]`` of a fresh one)."""
    root = _root(seed)
    return np.random.SeedSequence(root.entropy, spawn_key=tuple(root.spawn_key) + (int(j),))


def children(seed: int | np.random.SeedSequence, n: int) -> list[np.random.SeedSequence]:
    """Children ``0 .. n-1`` of a sequence (independent of earlier ``spawn`` calls on it)."""
    return [child(seed, j) for j in range(int(n))]


def child_ints(seed: int | np.random.SeedSequence, n: int) -> list[int]:
    """``n`` independent 63-bit integer seeds: :func:`seed_int` of :func:`children`."""
    return [seed_int(c) for c in children(seed, n)]


def run_keys(n_specimens: int) -> dict[tuple[int, ...], str]:
    """Every spawn key a run over ``n_specimens`` draws from, mapped to a readable stream name.

    Raises ``ValueError`` if two streams share a key (tested in ``tests/test_seeds.py``).
    """
    named: list[tuple[str, tuple[int, ...]]] = []
    for k in range(int(n_specimens)):
        named.append((f"specimen {k}", STREAMS["specimen"](k)))
        named += [(f"specimen {k} {p}", STREAMS["specimen"](k) + (j,)) for j, p in enumerate(PHASES)]
        named.append((f"refine {k}", STREAMS["refine"](k)))
        named.append((f"reference {k}", STREAMS["reference"](k)))
        named.append((f"layer_specimen {k}", STREAMS["layer_specimen"](k)))
        named.append((f"organ_posterior {k}", STREAMS["organ_posterior"](k)))
        named.append((f"organ_updated {k}", STREAMS["organ_updated"](k)))
    for name in ("hierarchical", "new_specimen", "organ_new_specimen", "grouped", "joint", "layer"):
        named.append((name, STREAMS[name]()))
    out: dict[tuple[int, ...], str] = {}
    for name, key in named:
        if key in out:
            raise ValueError(f"seed streams {out[key]!r} and {name!r} share spawn key {key}")
        out[key] = name
    return out


def as_generator(seed) -> np.random.Generator:
    """A numpy Generator from an int, SeedSequence, Generator or None."""
    if isinstance(seed, np.random.Generator):
        return seed
    return np.random.default_rng(seed)
