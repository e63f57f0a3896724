"""The process pool of the long runs (dataset generation, evaluation): spawned workers with one
BLAS/OpenMP thread each, set in the workers only (this process's environment is left alone).

The workers end with the work: an exception or an interruption (Ctrl-C, SIGTERM as the command
line raises it) inside the ``with`` block cancels the queued tasks and terminates the workers before
it goes on, so that none is left computing (or holding its memory) after this process. A worker
ignores SIGINT from its start: Ctrl-C reaches the whole process group, and this process, not each
worker, decides (it ends the pool); SIGTERM keeps its default action, which ends a worker at once.
"""

from __future__ import annotations

import multiprocessing.context
import os
import signal
import threading
from collections.abc import Iterator
from concurrent.futures import ProcessPoolExecutor
from contextlib import contextmanager

from training.config import BLAS_THREADS

#: Thread limits of a worker: the analysis is many small least-squares problems, and several BLAS
#: threads per worker on a few cores thrash (10x slower, measured); OMP too: one worker per core.
_WORKER_THREADS = {var: str(BLAS_THREADS) for var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS")}


#: Memory a worker holds once it has imported torch, numpy, scipy and the simulator [bytes]: about
#: 360 MB resident measured; for the memory checks of the commands that start a pool.
WORKER_MEMORY = 384 * 2**20


class _WorkerProcess(multiprocessing.context.SpawnProcess):
    """A spawned worker that starts with SIGINT ignored (an ignored signal stays ignored across
    ``exec``, and Python then installs no ``KeyboardInterrupt`` handler): a Ctrl-C while it imports
    torch prints no traceback either. The parent ignores SIGINT for the moment of the start only,
    and only from its main thread (the only one that may set handlers)."""

    def start(self) -> None:
        if threading.current_thread() is not threading.main_thread():
            super().start()
            return
        previous = signal.signal(signal.SIGINT, signal.SIG_IGN)
        try:
            super().start()
        finally:
            signal.signal(signal.SIGINT, signal.SIG_DFL if previous is None else previous)


class _WorkerContext(multiprocessing.context.SpawnContext):
    Process = _WorkerProcess


def _limit_worker_threads() -> None:
    """Pool initializer (runs in each worker): the environment for the libraries the worker loads
    later, threadpoolctl for those already loaded (e.g. by the parent's main module, re-imported)."""
    from threadpoolctl import threadpool_limits

    signal.signal(signal.SIGINT, signal.SIG_IGN)  # a worker started outside the main thread too
    os.environ.update(_WORKER_THREADS)
    threadpool_limits(limits=BLAS_THREADS)


def _terminate(pool: ProcessPoolExecutor) -> None:
    """Cancel ``pool``'s queued tasks and end its workers now (SIGTERM), waiting until they have.
    Python 3.14 has ``terminate_workers``; before it the executor's process table is the only handle."""
    workers = list((getattr(pool, "_processes", None) or {}).values())  # to wait for them
    manager = getattr(pool, "_executor_manager_thread", None)  # shutdown() forgets it
    # Before Python 3.12 the pool's manager thread, seeing its workers gone, joins the thread that
    # feeds their task pipe; that thread can sit in a write to the full pipe forever, and the process
    # never exits (seen with tasks queued at the signal). Nothing will read the pipe: do not wait for
    # it, and say so before the workers end (the manager thread acts as soon as they do).
    call_queue = getattr(pool, "_call_queue", None)
    if call_queue is not None:
        call_queue.cancel_join_thread()
    if hasattr(pool, "terminate_workers"):
        pool.terminate_workers()
    else:
        pool.shutdown(wait=False, cancel_futures=True)
        for p in workers:
            p.terminate()
    for p in workers:
        p.join()
    # Before Python 3.12 the manager thread closes its wake-up pipe while the interpreter's exit hook
    # may still write to it ("OSError: [Errno 9] Bad file descriptor" after the command's last line):
    # let it finish first (bounded: a manager that hangs must not hold the exit).
    if manager is not None:
        manager.join(timeout=5.0)


@contextmanager
def worker_pool(workers: int) -> Iterator[ProcessPoolExecutor]:
    """``workers`` spawned processes with :data:`training.config.BLAS_THREADS` thread each; they are
    terminated when the block raises (an interruption too), else waited for."""
    if workers < 1:
        raise ValueError(f"worker_pool: expected workers >= 1, received {workers}")
    pool = ProcessPoolExecutor(max_workers=workers, mp_context=_WorkerContext(), initializer=_limit_worker_threads)
    try:
        yield pool
    except BaseException:
        _terminate(pool)
        raise
    pool.shutdown(wait=True)
