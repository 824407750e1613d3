"""dask.distributed execution: one task per specimen, seeded, retried, written atomically.

* :func:`dask_client` gives a ``Client``: an embedded ``LocalCluster`` (``workers`` processes,
  one thread each, BLAS limited to one thread) or, with ``scheduler=ADDRESS`` or the environment
  variable ``DASK_SCHEDULER_ADDRESS``, a connection to an existing scheduler (for SLURM/PBS use
  dask-jobqueue, see ``workflows/hpc_slurm.py``).
* :func:`map_specimens` submits ``func(item, seed=..., **kwargs)`` for every specimen, with a
  seed spawned from ``SeedSequence(seed)`` in sorted specimen order (so a specimen's result does
  not depend on how many workers run, or on which worker), task keys ``f"{prefix}-{id}"``,
  ``retries`` and ``pure=False``.  Each task writes its own file and returns its path.  A tqdm
  bar counts specimens done and shows the current TMCMC stage of the running ones (read from
  their checkpoint files, which every stage rewrites atomically).

``workers=0`` runs the same tasks serially in this process (no dask), for debugging.
"""

from __future__ import annotations

import contextlib
import logging
import os
import re
import time
from dataclasses import dataclass, field
from typing import Any, Callable, Iterator, Mapping

import numpy as np

from . import seeds
from .dask_worker import drop_dask_unraisables
from .blas import BLAS_ENV, single_thread_env
from .progress import progress_bar
from ..errors import HbmError, OutputError, OutputLockedError
from ..samplers.checkpoint import checkpoint_progress
from ..settings.rules import check_workers

__all__ = ["ALLOWED_FAILURES", "NO_WORKER_TIMEOUT", "NO_WORKER_TIMEOUT_EXTERNAL",
           "BLAS_ENV", "dask_client", "map_specimens", "submit_specimens", "PendingMap", "MapResult",
           "beside_this_process", "background_priority", "BACKGROUND_NICENESS", "spawn_specimen_seeds",
           "checkpoint_status"]

#: worker deaths the embedded cluster's scheduler allows a task before it fails it (KilledWorker):
#: a task that dies with its worker this often is killing it (out of memory), not unlucky
ALLOWED_FAILURES = 2
#: seconds a run waits for a cluster that has no worker at all: the embedded cluster's nannies
#: restart a dead worker within seconds, so after this long they have given up; an external
#: cluster (--scheduler, dask-jobqueue) may wait for its batch jobs much longer
NO_WORKER_TIMEOUT = 120.0
NO_WORKER_TIMEOUT_EXTERNAL = 1800.0

def spawn_specimen_seeds(seed: int, ids) -> dict[str, np.random.SeedSequence]:
    """The ``specimen`` stream of :mod:`hbm.runtime.seeds` for each id, numbered in sorted-id order."""
    return {sid: seeds.stream(int(seed), "specimen", k) for k, sid in enumerate(sorted(ids))}


#: loggers that report on a cluster being shut down (silenced once a run is interrupted)
_SHUTDOWN_LOGGERS = ("distributed", "tornado", "asyncio")


@contextlib.contextmanager
def _sigint_deferred() -> Iterator[None]:
    """Hold a Ctrl-C back while the cluster and client start, then raise it: an interrupted
    constructor would leave half-built objects whose finalizers print tracebacks at exit.

    (The worker processes of the ``hbm`` command ignore SIGINT: :mod:`hbm.runtime.process`.)
    """
    import signal
    import threading

    if (threading.current_thread() is not threading.main_thread()
            or signal.getsignal(signal.SIGINT) is not signal.default_int_handler):
        yield
        return
    received = []
    signal.signal(signal.SIGINT, lambda signum, frame: received.append(signum))
    try:
        yield
    except BaseException:
        if received:  # whatever failed meanwhile (a worker hit by the same Ctrl-C), the user interrupted
            raise KeyboardInterrupt from None
        raise
    finally:
        signal.signal(signal.SIGINT, signal.default_int_handler)
    if received:
        raise KeyboardInterrupt


@contextlib.contextmanager
def _quiet_shutdown() -> Iterator[None]:
    """Silence dask/tornado/asyncio while a failed or interrupted run closes its cluster
    (lost-worker warnings, cancelled-task and closed-comm tracebacks)."""
    loggers = [logging.getLogger(name) for name in _SHUTDOWN_LOGGERS]
    levels = [lg.level for lg in loggers]
    for lg in loggers:
        lg.setLevel(logging.CRITICAL + 1)
    # a Client garbage-collected after its event loop closed reports "IOLoop is closed" through
    # sys.unraisablehook (not logging), possibly after this block (the process is ending)
    drop_dask_unraisables()
    try:
        yield
    finally:
        for lg, level in zip(loggers, levels):
            lg.setLevel(level)


def _drop_killed_worker_report(record: logging.LogRecord) -> bool:
    return "workers died while trying to run it" not in record.getMessage()


@contextlib.contextmanager
def dask_client(workers: int | None = None, scheduler: str | None = None, *,
                dashboard: bool = False, silence_logs: bool = True) -> Iterator[Any]:
    """A ``distributed.Client``; closes what it created on exit.

    A Ctrl-C while the cluster starts is raised once it is up (and then closed); when the body
    raises (KeyboardInterrupt included) the cluster is closed with dask's logging silenced, so
    that the caller's one-line message stays the last word.

    Parameters
    ----------
    workers : int, optional
        Worker processes of the embedded LocalCluster (default: number of cores).
    scheduler : str, optional
        Address of an existing scheduler (``tcp://host:8786``); default
        ``$DASK_SCHEDULER_ADDRESS``.  Then ``workers`` is ignored.
    dashboard : bool
        Serve the dask dashboard (port 8787) for the embedded cluster.
    """
    import dask
    from distributed import Client, LocalCluster

    address = scheduler or os.environ.get("DASK_SCHEDULER_ADDRESS")
    n = check_workers(workers) if workers else (os.cpu_count() or 1)  # the rule of --workers
    cluster = client = None
    failed = False
    try:
        if address:
            try:
                client = Client(address, timeout="30s")
            except OSError as exc:
                raise HbmError(f"cannot connect to dask scheduler {address}: {exc}") from None
        else:
            single_thread_env()  # also for anything spawned from this process
            # both objects exist before a Ctrl-C during startup is raised, so both get closed
            # the scheduler's own report of a KilledWorker would precede the run's one line
            logging.getLogger("distributed.scheduler").addFilter(_drop_killed_worker_report)
            # worker-saturation 1: a worker holds only the task it runs, so a task that kills its
            # worker does not count deaths against specimens merely queued there
            with _sigint_deferred(), dask.config.set({"distributed.scheduler.allowed-failures": ALLOWED_FAILURES,
                                                      "distributed.scheduler.worker-saturation": 1.0}):
                cluster = LocalCluster(n_workers=n, threads_per_worker=1, processes=True,
                                       dashboard_address=":8787" if dashboard else ":0",
                                       silence_logs=logging.ERROR if silence_logs else logging.WARNING,
                                       env=dict(BLAS_ENV), preload=["hbm.runtime.dask_worker"])
                client = Client(cluster)
            client.hbm_no_worker_timeout = NO_WORKER_TIMEOUT  # (read by map_specimens)
            client.hbm_embedded = True  # its workers share this machine's cores (beside_this_process)
        yield client
    except BaseException:
        failed = True
        raise
    finally:
        with _quiet_shutdown() if failed else contextlib.nullcontext():
            if client is not None:
                client.close()
            if cluster is not None:
                cluster.close()


def beside_this_process(client) -> bool:
    """Whether ``client``'s workers share this machine's cores with this process (the embedded cluster of
    :func:`dask_client`; an external cluster's workers run elsewhere, as far as hbm knows)."""
    return bool(getattr(client, "hbm_embedded", False))


#: the niceness of work that runs beside a computation of the command's own process
BACKGROUND_NICENESS = 10


def background_priority() -> None:
    """Lower the CPU priority of the calling worker thread (Linux; the process elsewhere) to
    :data:`BACKGROUND_NICENESS`, once.

    ``hbm run`` samples its population layer in its own process while the workers complete the specimens'
    optima and Sobol indices: on two cores two busy workers and the layer would share the cores three ways
    and the layer -- the run's longest part -- would take half again as long (66 s instead of 46 s for the
    shipped six).  At a lower priority the workers use what the layer leaves.  Irreversible (an unprivileged
    process cannot raise a priority again), so for the task thread of a worker of a cluster that lives for one
    run only; the worker's communication stays at its priority.
    """
    with contextlib.suppress(AttributeError, OSError):  # no os.nice (Windows) or not permitted
        current = os.nice(0)
        if current < BACKGROUND_NICENESS:
            os.nice(BACKGROUND_NICENESS - current)


def checkpoint_status(path: str | os.PathLike) -> str | None:
    """``"stage k β=..."`` from a TMCMC checkpoint file, or None if absent/unreadable."""
    progress = checkpoint_progress(path)
    if progress is None:
        return None
    stage, beta = progress
    return f"stage {stage} β={beta:.3g}"


@dataclass
class MapResult:
    """Outcome of :func:`map_specimens`: paths of finished specimens (``values``: what each task returned,
    for tasks that return something else than a path), errors of failed ones."""

    paths: dict[str, str] = field(default_factory=dict)
    errors: dict[str, str] = field(default_factory=dict)
    values: dict[str, Any] = field(default_factory=dict)
    wall_time: float = 0.0
    task_times: dict[str, float] = field(default_factory=dict)


def _task_error(exc: BaseException) -> str:
    """One line for a failed specimen task (a KilledWorker says how often its worker died)."""
    if type(exc).__name__ == "KilledWorker":
        found = re.search(r"on (\d+) different workers", str(exc))
        deaths = found.group(1) if found else "several"
        return (f"its worker process died {deaths} times while running it (killed by the system, e.g. out of "
                "memory?); not retried")
    return f"{type(exc).__name__}: {exc}".splitlines()[0]


def _n_workers(client) -> int | None:
    try:
        return len(client.scheduler_info().get("workers", {}))
    except Exception:  # a scheduler that does not answer counts as unknown, not as empty
        return None


class PendingMap:
    """Specimen tasks submitted to a cluster and not yet collected (:func:`submit_specimens`).

    :meth:`wait` collects them as :func:`map_specimens` does (bounded deaths, bounded retries, bounded
    waits); meanwhile this process is free (``hbm run`` samples the population layer here while the
    specimens' optima and Sobol indices run on the workers).
    """

    def __init__(self, client, func, items, seeds, kwargs, prefix: str, retries: int) -> None:
        self.client, self.func, self.items, self.seeds, self.kwargs = client, func, items, seeds, kwargs
        self.prefix, self.retries = prefix, int(retries)
        self.attempts = {sid: 0 for sid in items}
        self.t0 = time.perf_counter()
        self.futures = {self._submit(sid): sid for sid in sorted(items)}

    def _submit(self, sid):
        key = f"{self.prefix}-{sid}" + (f"-retry{self.attempts[sid]}" if self.attempts[sid] else "")
        return self.client.submit(_timed_call, self.func, self.items[sid], self.seeds[sid], self.kwargs, key=key,
                                  pure=False)

    def wait(self, *, progress: bool = True, checkpoints: Mapping[str, str | os.PathLike] | None = None,
             poll: float = 0.5, no_worker_timeout: float | None = None) -> MapResult:
        """Collect every task (re-submitting failed ones within ``retries``) -> :class:`MapResult`."""
        res = MapResult()
        pending = set(self.futures)
        bar = progress_bar(len(pending), self.prefix, unit="specimen") if progress and pending else None
        try:
            self._collect(res, pending, bar, checkpoints or {}, poll, no_worker_timeout)
        finally:
            if bar is not None:
                bar.close()
        res.wall_time = time.perf_counter() - self.t0
        return res

    def _collect(self, res, pending, bar, checkpoints, poll, no_worker_timeout) -> None:
        client, futures, attempts = self.client, self.futures, self.attempts
        if no_worker_timeout is None:
            no_worker_timeout = getattr(client, "hbm_no_worker_timeout", NO_WORKER_TIMEOUT_EXTERNAL)
        timeout = float(no_worker_timeout)
        empty_since, last_check = None, 0.0
        while pending:
            for f in [f for f in pending if f.done()]:
                pending.discard(f)
                sid = futures.pop(f)
                try:
                    value, dt = f.result()
                    _store(res, sid, value, dt)
                except OutputLockedError as exc:  # another process writes this specimen's file
                    res.errors[sid] = str(exc)
                except OutputError:  # full disk, unwritable folder: every other task would fail too
                    raise
                except Exception as exc:  # keep going: report the failure at the end
                    killed = type(exc).__name__ == "KilledWorker"
                    if not killed and not isinstance(exc, HbmError) and attempts[sid] < self.retries:
                        attempts[sid] += 1
                        g = self._submit(sid)
                        futures[g] = sid
                        pending.add(g)
                        continue
                    res.errors[sid] = _task_error(exc)
                if bar is not None:
                    bar.update(1)
            if bar is not None and checkpoints:
                live = [f"{futures[f]}: {st}" for f in sorted(pending, key=lambda f: futures[f])
                        if futures[f] in checkpoints and (st := checkpoint_status(checkpoints[futures[f]]))]
                bar.set_postfix_str("; ".join(live)[:150], refresh=True)
            now = time.monotonic()
            if pending and now - last_check >= 2.0:  # a scheduler round trip: not at every poll
                last_check = now
                if _n_workers(client) == 0:
                    empty_since = empty_since or now
                    if now - empty_since > timeout:
                        left = sorted(futures[f] for f in pending)
                        failed = "".join(f"; {sid} failed: {msg}" for sid, msg in sorted(res.errors.items()))
                        raise HbmError(f"the dask cluster has had no workers for {timeout:.0f} s; "
                                       f"{len(left)} specimen(s) unfinished ({', '.join(left)}; their checkpoints are "
                                       f"kept: rerun to resume){failed}")
                else:
                    empty_since = None
            if pending:
                time.sleep(poll)


def _store(res: MapResult, sid: str, value, dt: float) -> None:
    """A finished task's value (its path, when it is one) and time."""
    res.values[sid], res.task_times[sid] = value, dt
    if isinstance(value, (str, os.PathLike)):
        res.paths[sid] = str(value)


def _timed_call(func, item, seed, kwargs):
    t = time.perf_counter()
    out = func(item, seed=seed, **kwargs)
    return out, time.perf_counter() - t


def map_specimens(func: Callable[..., str], items: Mapping[str, Any], *, seed: int, client=None,
                  kwargs: Mapping[str, Any] | None = None, prefix: str = "fit", retries: int = 1,
                  progress: bool = True, checkpoints: Mapping[str, str | os.PathLike] | None = None,
                  poll: float = 0.5, all_ids=None, no_worker_timeout: float | None = None) -> MapResult:
    """Run ``func(items[id], seed=<SeedSequence>, **kwargs) -> path`` for every specimen.

    Parameters
    ----------
    func : callable
        Importable (picklable) top-level function; writes one file, returns its path.
    items : mapping id -> argument
        Work to do (e.g. the specimen Datasets still lacking a complete result).
    seed : int
        Root seed; specimen seeds are spawned in sorted order of ``all_ids`` (default: the ids
        of ``items``) so that skipping finished specimens does not change the others' seeds.
    client : distributed.Client or None
        None runs serially in this process.
    retries : int
        Re-submissions of a task that raised (not for :class:`~hbm.errors.HbmError`, which would
        fail again).  A task whose worker dies is re-run by the scheduler (resuming from its
        checkpoint) at most :data:`ALLOWED_FAILURES` times on the embedded cluster; one more
        death fails that specimen (``KilledWorker``: "its worker died N times").
    no_worker_timeout : float, optional
        Seconds the cluster may have no worker at all before the run fails with one line
        (default :data:`NO_WORKER_TIMEOUT` for the cluster of :func:`dask_client`,
        :data:`NO_WORKER_TIMEOUT_EXTERNAL` for other clients): nothing waits without a deadline.
    checkpoints : mapping id -> path, optional
        TMCMC checkpoint files polled for the progress bar's stage display.

    Returns
    -------
    MapResult

    Raises
    ------
    OutputError
        As soon as one task cannot write its result (full disk, unwritable folder): the other
        tasks would fail the same way.  Other task errors are collected in ``errors``.
    HbmError
        When the cluster has had no worker for ``no_worker_timeout`` seconds.
    """
    kwargs = dict(kwargs or {})
    seeds = _seeds_for(seed, items, all_ids)
    if client is not None:
        return PendingMap(client, func, items, seeds, kwargs, prefix, retries).wait(
            progress=progress, checkpoints=checkpoints, poll=poll, no_worker_timeout=no_worker_timeout)
    order = sorted(items)
    res = MapResult()
    t0 = time.perf_counter()
    bar = None
    if progress and order:
        bar = progress_bar(len(order), prefix, unit="specimen")
    try:
        for sid in order:
            if bar is not None:
                bar.set_postfix_str(f"running {sid}")
            try:
                _store(res, sid, *_timed_call(func, items[sid], seeds[sid], kwargs))
            except OutputLockedError as exc:  # another process writes this specimen's file
                res.errors[sid] = str(exc)
            except OutputError:  # full disk, unwritable folder: every other task would fail too
                raise
            except HbmError as exc:
                res.errors[sid] = str(exc)
            if bar is not None:
                bar.update(1)
    finally:
        if bar is not None:
            bar.close()
    res.wall_time = time.perf_counter() - t0
    return res


def submit_specimens(func: Callable[..., Any], items: Mapping[str, Any], *, seed: int, client,
                     kwargs: Mapping[str, Any] | None = None, prefix: str = "fit", retries: int = 1,
                     all_ids=None) -> PendingMap:
    """Submit :func:`map_specimens`' tasks to ``client`` and return at once; ``wait()`` collects them."""
    seeds = _seeds_for(seed, items, all_ids)
    return PendingMap(client, func, items, seeds, dict(kwargs or {}), prefix, retries)


def _seeds_for(seed: int, items, all_ids) -> dict:
    seeds = spawn_specimen_seeds(seed, all_ids if all_ids is not None else items)
    missing = set(items) - set(seeds)
    if missing:
        raise HbmError(f"map_specimens: ids {sorted(missing)} not in all_ids")
    return seeds
