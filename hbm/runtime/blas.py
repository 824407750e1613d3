"""One BLAS/OpenMP thread per process: the environment for worker processes and a runtime switch.

The package's parallelism is its worker processes (dask) and its vectorised populations; BLAS
threads on top of that only compete for the cores.  Two levers, one home:

* :data:`BLAS_ENV` / :func:`single_thread_env` — environment variables read when a BLAS library
  loads: set for every worker process that is started (and anything it spawns);
* :class:`single_thread_blas` — a context manager that switches an already loaded OpenBLAS to
  one thread for a hot loop and restores it afterwards (no-op for other BLAS builds).
"""

from __future__ import annotations

import os

__all__ = ["BLAS_ENV", "single_thread_env", "single_thread_blas", "one_blas_thread"]

#: environment of the worker processes: one BLAS/OpenMP thread each (workers are the parallelism)
BLAS_ENV = {"OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1", "OPENBLAS_NUM_THREADS": "1",
            "VECLIB_MAXIMUM_THREADS": "1", "NUMEXPR_NUM_THREADS": "1"}


def single_thread_env() -> None:
    """Set :data:`BLAS_ENV` in ``os.environ`` where the user has not set a value (children inherit it)."""
    for k, v in BLAS_ENV.items():
        os.environ.setdefault(k, v)


_BLAS_API: list | None = None


def _blas_api() -> list:
    """(set, get) pairs of OpenBLAS thread controls of the loaded BLAS libraries (Linux)."""
    global _BLAS_API
    if _BLAS_API is None:
        import ctypes

        found = []
        try:
            with open("/proc/self/maps") as fh:
                libs = sorted({ln.split()[-1] for ln in fh if "openblas" in ln.lower() and "/" in ln})
        except OSError:
            libs = []
        for path in libs:
            try:
                lib = ctypes.CDLL(path)
            except OSError:
                continue
            for prefix, suffix in (("openblas", ""), ("scipy_openblas", "64_"), ("openblas", "64_")):
                setter = getattr(lib, f"{prefix}_set_num_threads{suffix}", None)
                getter = getattr(lib, f"{prefix}_get_num_threads{suffix}", None)
                if setter is not None and getter is not None:
                    found.append((setter, getter))
                    break
        _BLAS_API = found
    return _BLAS_API


def one_blas_thread() -> list[tuple]:
    """Switch every loaded OpenBLAS to one thread (e.g. in a forked worker process, whose BLAS is
    already loaded so the environment no longer counts); returns the previous (setter, threads)."""
    old = []
    for setter, getter in _blas_api():
        try:
            old.append((setter, int(getter())))
            setter(1)
        except Exception:  # pragma: no cover - exotic BLAS builds
            pass
    return old


class single_thread_blas:
    """Run a hot loop with one BLAS thread.

    Thin GEMMs (e.g. the hierarchical layer's K = 2d+2 columns) gain nothing from OpenBLAS
    threads and, on a loaded machine or inside several dask workers, spin-waiting threads made
    one likelihood call 3× slower (measured).  Restores the previous setting; no-op if the BLAS
    is not OpenBLAS.
    """

    def __enter__(self):
        self._old = one_blas_thread()
        return self

    def __exit__(self, *exc):
        for setter, n in self._old:
            setter(n)
        return False
