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
from pathlib import Path

from som_torch import CKernel, CLibrary, env_threads


def c_kernel_enabled() -> bool:
    """Whether the fused C kernel may be used (``TWOMASS_NO_C_KERNEL`` unset or empty)."""
    return not os.environ.get("TWOMASS_NO_C_KERNEL")


def cache_dir() -> Path:
    """``$TWOMASS_CACHE``, else ``~/.cache/twomass-som``."""
    return Path(os.environ.get("TWOMASS_CACHE") or Path.home() / ".cache" / "twomass-som")


def compiler() -> str | None:
    """``$CC``, or None (the default compiler)."""
    return os.environ.get("CC") or None


def kernel_threads() -> int:
    """``$TWOMASS_SIM_THREADS``, else the first value of ``$OMP_NUM_THREADS``, else the usable CPUs."""
    return env_threads("TWOMASS_SIM_THREADS", "OMP_NUM_THREADS")


def load_c_kernel(kernel: CKernel) -> CLibrary | None:
    """The toolkit's C ``kernel`` (a :class:`som_torch.CKernel`) loaded with these settings (its
    :class:`som_torch.CLibrary`), or None when ``TWOMASS_NO_C_KERNEL`` is set or (after one
    warning) it cannot be built: its caller then runs its reference path."""
    return kernel.load(cache_dir(), compiler()) if c_kernel_enabled() else None
