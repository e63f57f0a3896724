"""The process pool of the long runs (dataset generation, evaluation): spawned workers with one
BLAS/OpenMP thread each, set in the workers only (this process's environment is left alone)."""

from __future__ import annotations

import multiprocessing
import os
from collections.abc import Iterator
from concurrent.futures import ProcessPoolExecutor
from contextlib import contextmanager

from training.config import BLAS_THREADS

#: Thread limits of a worker: the analysis is many small least-squares problems, and several BLAS
#: threads per worker on a few cores thrash (10x slower, measured); OMP too: one worker per core.
_WORKER_THREADS = {var: str(BLAS_THREADS) for var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS")}


def _limit_worker_threads() -> None:
    """Pool initializer (runs in each worker): the environment for the libraries the worker loads
    later, threadpoolctl for those already loaded (e.g. by the parent's main module, re-imported)."""
    from threadpoolctl import threadpool_limits

    os.environ.update(_WORKER_THREADS)
    threadpool_limits(limits=BLAS_THREADS)


@contextmanager
def worker_pool(workers: int) -> Iterator[ProcessPoolExecutor]:
    """``workers`` spawned processes with :data:`training.config.BLAS_THREADS` thread each."""
    if workers < 1:
        raise ValueError(f"worker_pool: expected workers >= 1, received {workers}")
    with ProcessPoolExecutor(max_workers=workers, mp_context=multiprocessing.get_context("spawn"),
                             initializer=_limit_worker_threads) as pool:
        yield pool
