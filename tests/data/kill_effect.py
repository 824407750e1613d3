"""A test effect that kills the process evaluating it, as an out-of-memory kill does (tests/test_dask_failures.py).

It kills only a worker process (one started by multiprocessing, as dask's are; never the command's own
process) and only for the specimen whose largest strain is 0.4321, so the other specimens of a run finish.
"""

import multiprocessing
import os

import numpy as np

import hbm

KILL_STRAIN = 0.4321


class KillWorker(hbm.Effect):
    name = "kill_worker"
    stage = "output"
    parameters = ()
    description = "test only: kills the worker process that evaluates the specimen with the largest strain 0.4321"

    def modify(self, state, p, stress):
        if multiprocessing.parent_process() is not None and np.isclose(np.max(state.loading.strain), KILL_STRAIN):
            os.kill(os.getpid(), 9)
        return stress
