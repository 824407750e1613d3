"""Run the six-rat workflow on a SLURM cluster with dask-jobqueue (``pip install 'hbm[hpc]'``).

Each specimen is one dask task; dask-jobqueue submits SLURM jobs that each start dask workers,
and the same hbm code that runs on a laptop's LocalCluster runs on them.  Results are identical
to a local run with the same seed (every task carries its own seed).  The output folder must be
on a filesystem shared by the login node and the compute nodes (each task writes its own
netCDF file there, and TMCMC checkpoints go to <out>/checkpoints so a pre-empted job resumes).

Usage (on the login node, inside the environment where hbm is installed)::

    python workflows/hpc_slurm.py --queue short --account myproj --jobs 3 --out /scratch/$USER/six

Options map to ``dask_jobqueue.SLURMCluster``: one job = ``--cores`` worker processes with one
thread each (the model is vectorised numpy; BLAS is limited to one thread per worker).  For PBS
use ``dask_jobqueue.PBSCluster`` with the same arguments (``--account`` -> ``account``).

Alternatively start the cluster yourself (``dask scheduler`` + ``dask worker`` in job scripts)
and point hbm at it: ``hbm run --scheduler tcp://HOST:8786`` or ``DASK_SCHEDULER_ADDRESS``.

This file imports dask-jobqueue only inside :func:`main`, so it stays importable without it.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path


def make_cluster(*, queue: str, account: str | None, cores: int, memory: str, walltime: str, jobs: int):
    """A started ``SLURMCluster`` scaled to ``jobs`` jobs (requires dask-jobqueue)."""
    try:
        from dask_jobqueue import SLURMCluster
    except ImportError:  # pragma: no cover - depends on the optional extra
        raise SystemExit("dask-jobqueue is not installed: pip install 'hbm[hpc]'") from None
    cluster = SLURMCluster(
        queue=queue, account=account, cores=cores, processes=cores, memory=memory, walltime=walltime,
        job_script_prologue=["export OMP_NUM_THREADS=1 OPENBLAS_NUM_THREADS=1 MKL_NUM_THREADS=1"],
    )
    cluster.scale(jobs=jobs)
    return cluster


def main(argv=None) -> int:
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
    from distributed import Client

    from hbm.workflow import RunConfig, run_workflow

    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--queue", required=True, help="SLURM partition")
    ap.add_argument("--account", default=None, help="SLURM account")
    ap.add_argument("--cores", type=int, default=4, help="worker processes per job (default 4)")
    ap.add_argument("--memory", default="8GB", help="memory per job (default 8GB)")
    ap.add_argument("--walltime", default="01:00:00", help="walltime per job (default 1 h)")
    ap.add_argument("--jobs", type=int, default=2, help="number of SLURM jobs (default 2)")
    ap.add_argument("--data", default="data/specimens")
    ap.add_argument("--out", default="results")
    ap.add_argument("--samples", type=int, default=10000, help="TMCMC N (a cluster affords more)")
    ap.add_argument("--seed", type=int, default=0)
    a = ap.parse_args(argv)

    cluster = make_cluster(queue=a.queue, account=a.account, cores=a.cores, memory=a.memory,
                           walltime=a.walltime, jobs=a.jobs)
    try:
        with Client(cluster) as client:
            client.wait_for_workers(1, timeout=600)  # queue wait
            cfg = RunConfig(data=a.data, out=a.out, samples=a.samples, seed=a.seed, retries=2)
            res = run_workflow(cfg, client=client)
    finally:
        cluster.close()
    print(f"report: {res.report_path}")
    return 0 if not res.errors else 1


if __name__ == "__main__":
    sys.exit(main())
