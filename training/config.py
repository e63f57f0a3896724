"""Process-wide settings of :mod:`training` and the environment variables it reads (one place).

Environment variables (those of :mod:`sim` and :mod:`som_torch` are read in their own
``_config`` modules; ``docs/design.md`` lists all of them):

- ``TWOMASS_CHECKPOINTS``: folder of the maps ``Identifier.load()`` uses (default: the shipped ones).
- ``OPENBLAS_NUM_THREADS``, ``MKL_NUM_THREADS``, ``OMP_WAIT_POLICY``: set by :func:`apply_process_defaults`
  unless the user has set them.

Thread policy of the ``twomass`` command: BLAS on one thread (:data:`BLAS_THREADS`), the
simulator's C kernel on every usable CPU. The kernel takes its thread count from its own setting
(``TWOMASS_SIM_THREADS``, else ``OMP_NUM_THREADS``, else all CPUs: :mod:`sim._config`), not from
torch, which reports one thread once ``MKL_NUM_THREADS=1`` is set. ``OMP_NUM_THREADS`` is left
alone here for that reason; the pool workers (:mod:`training._pool`) set it to 1 (one worker per core).
"""

from __future__ import annotations

import contextlib
import functools
import importlib.resources
import os
from collections.abc import Iterator
from pathlib import Path
from typing import Any

#: Where the maps live in a checkout (the repository's top-level ``checkpoints/``).
_CHECKOUT_CHECKPOINTS = Path(__file__).resolve().parents[1] / "checkpoints"


def shipped_checkpoints() -> Path:
    """The maps shipped with the toolkit: in an installed wheel the package data of
    ``training.checkpoints`` (``pyproject.toml`` maps the repository's ``checkpoints/`` there);
    in a checkout or an editable install, which do not map that package, the checkout's
    ``checkpoints/``."""
    try:
        manifest = importlib.resources.files("training.checkpoints").joinpath("manifest.json")
    except ModuleNotFoundError:
        return _CHECKOUT_CHECKPOINTS
    return Path(str(manifest)).parent  # installed unzipped: a real folder


#: BLAS threads while identifying: the work is many small least-squares and FFT problems, where
#: several BLAS threads per process thrash (measured 10x slower on 2 busy cores).
BLAS_THREADS = 1

# Not OMP_NUM_THREADS: the simulator kernel uses OpenMP. OpenMP threads that spin after each of
# the many short kernel calls take the cores from the analysis (identify of 100 records: 9.2-9.7 s
# passive against 9.6-10.2 s spinning).
_PROCESS_DEFAULTS = {"OPENBLAS_NUM_THREADS": str(BLAS_THREADS), "MKL_NUM_THREADS": str(BLAS_THREADS),
                     "OMP_WAIT_POLICY": "PASSIVE"}


def checkpoints_folder() -> Path:
    """``$TWOMASS_CHECKPOINTS``, else the shipped maps (:func:`shipped_checkpoints`)."""
    env = os.environ.get("TWOMASS_CHECKPOINTS")
    return Path(env) if env else shipped_checkpoints()


def apply_process_defaults() -> None:
    """Set the thread environment of this process where the user has not (effective only before
    numpy and torch are imported: the command line calls it first thing)."""
    for var, value in _PROCESS_DEFAULTS.items():
        os.environ.setdefault(var, value)


@functools.lru_cache(maxsize=1)
def _thread_pools() -> Any:
    """The process's thread pools, found once: finding them walks every loaded library (1-2 ms,
    paid per record before). The BLAS libraries are numpy's, scipy's and torch's, all loaded by
    the toolkit's own imports before the first call."""
    from threadpoolctl import ThreadpoolController

    return ThreadpoolController()


@contextlib.contextmanager
def blas_threads(n: int = BLAS_THREADS) -> Iterator[None]:
    """Limit the BLAS thread pools to ``n`` threads inside the block, also in a process whose numpy
    was imported before the toolkit (an app calling :class:`training.Identifier`)."""
    with _thread_pools().limit(limits=n, user_api="blas"):
        yield
