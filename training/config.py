"""Process-wide settings of :mod:`training` and the environment variables it reads (one place).

Environment variables (those of :mod:`sim` and :mod:`som_torch` are read in their own
``_config`` modules; ``docs/design.md`` lists all of them):

- ``TWOMASS_CHECKPOINTS``: folder of the maps ``Identifier.load()`` uses (default: the shipped ones).
- ``OPENBLAS_NUM_THREADS``, ``MKL_NUM_THREADS``, ``OMP_WAIT_POLICY``: set by :func:`apply_process_defaults`
  unless the user has set them.
"""

from __future__ import annotations

import contextlib
import os
from collections.abc import Iterator
from pathlib import Path

#: The maps shipped with the toolkit.
SHIPPED_CHECKPOINTS = Path(__file__).resolve().parents[1] / "checkpoints"

#: BLAS threads while identifying: the work is many small least-squares and FFT problems, where
#: several BLAS threads per process thrash (measured 10x slower on 2 busy cores).
BLAS_THREADS = 1

# Not OMP_NUM_THREADS: the simulator kernel uses OpenMP. OpenMP threads that spin after each of
# the many short kernel calls take the cores from the analysis (identify of 100 records: 9.2-9.7 s
# passive against 9.6-10.2 s spinning).
_PROCESS_DEFAULTS = {"OPENBLAS_NUM_THREADS": str(BLAS_THREADS), "MKL_NUM_THREADS": str(BLAS_THREADS),
                     "OMP_WAIT_POLICY": "PASSIVE"}


def checkpoints_folder() -> Path:
    """``$TWOMASS_CHECKPOINTS``, else the shipped maps."""
    env = os.environ.get("TWOMASS_CHECKPOINTS")
    return Path(env) if env else SHIPPED_CHECKPOINTS


def apply_process_defaults() -> None:
    """Set the thread environment of this process where the user has not (effective only before
    numpy and torch are imported: the command line calls it first thing)."""
    for var, value in _PROCESS_DEFAULTS.items():
        os.environ.setdefault(var, value)


@contextlib.contextmanager
def blas_threads(n: int = BLAS_THREADS) -> Iterator[None]:
    """Limit the BLAS thread pools to ``n`` threads inside the block, also in a process whose numpy
    was imported before the toolkit (an app calling :class:`training.Identifier`)."""
    from threadpoolctl import threadpool_limits

    with threadpool_limits(limits=n, user_api="blas"):
        yield
