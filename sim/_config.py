"""The environment variables ``sim`` reads (here and nowhere else).

``TWOMASS_NO_C_KERNEL``
    Any non-empty value disables the fused C kernel; the simulator then runs its torch eager
    twin (same numbers, slower).
``TWOMASS_CACHE``
    The folder of the compiled kernel; default ``~/.cache/twomass-som``.
``CC``
    The C compiler (a name on ``PATH`` or a path); default ``cc``, else ``gcc``.
``TWOMASS_SIM_THREADS``
    Threads of the fused C kernel (a positive integer); default ``OMP_NUM_THREADS`` where set
    (the pool workers of ``training`` set it to 1), else every CPU this process may run on. Not
    torch's thread count: a process that limits BLAS (``MKL_NUM_THREADS=1``, as the ``twomass``
    command does) makes torch report one thread.
"""

from __future__ import annotations

import os
from functools import lru_cache
from pathlib import Path


def c_kernel_enabled() -> bool:
    """Whether the fused C kernel may be used (``TWOMASS_NO_C_KERNEL`` unset or empty)."""
    return not os.environ.get("TWOMASS_NO_C_KERNEL")


def cache_dir() -> Path:
    """``$TWOMASS_CACHE``, else ``~/.cache/twomass-som``."""
    return Path(os.environ.get("TWOMASS_CACHE") or Path.home() / ".cache" / "twomass-som")


def compiler() -> str | None:
    """``$CC``, or None (the default compiler)."""
    return os.environ.get("CC") or None


@lru_cache(maxsize=1)
def _usable_cpus() -> int:
    """The CPUs this process may run on (its affinity mask where the OS has one)."""
    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1


def kernel_threads() -> int:
    """``$TWOMASS_SIM_THREADS``, else the first value of ``$OMP_NUM_THREADS``, else the usable CPUs."""
    for var in ("TWOMASS_SIM_THREADS", "OMP_NUM_THREADS"):
        text = os.environ.get(var, "").split(",")[0].strip()
        if not text:
            continue
        if not text.isdigit() or int(text) < 1:
            raise ValueError(f"{var}: expected a positive integer, received {os.environ[var]!r}")
        return int(text)
    return _usable_cpus()
