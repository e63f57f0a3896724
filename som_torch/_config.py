"""The environment variables ``som_torch`` reads (here and nowhere else).

``SOM_TORCH_NATIVE``
    ``0`` disables the native C kernel of ``method="native"`` / ``"fast"`` (training then uses
    the torch path); any other value, or unset, lets it build and load.
``SOM_TORCH_CACHE``
    The folder of the compiled kernel; default ``$XDG_CACHE_HOME/som_torch``.
``XDG_CACHE_HOME``
    The user's cache folder (default ``~/.cache``), used when ``SOM_TORCH_CACHE`` is unset.
``CC``
    The C compiler (a name on ``PATH`` or a path); default ``cc``, else ``gcc``.
``SOM_TORCH_THREADS``
    Threads of the native kernel (a positive integer; it trains the maps of a batch in parallel,
    one map per thread); default ``OMP_NUM_THREADS`` where set (the pool workers of ``training``
    set it to 1), else every CPU this process may run on. Not torch's thread count, which a
    process that limits BLAS (``MKL_NUM_THREADS=1``) reports as one.
"""

from __future__ import annotations

import os
from functools import lru_cache
from pathlib import Path


def native_enabled() -> bool:
    """Whether the native kernel may be used (``SOM_TORCH_NATIVE`` is not ``0``)."""
    return os.environ.get("SOM_TORCH_NATIVE", "1") != "0"


def cache_dir() -> Path:
    """``$SOM_TORCH_CACHE``, else ``$XDG_CACHE_HOME/som_torch``, else ``~/.cache/som_torch``."""
    base = os.environ.get("SOM_TORCH_CACHE")
    if base:
        return Path(base)
    xdg = os.environ.get("XDG_CACHE_HOME")
    return (Path(xdg) if xdg else Path.home() / ".cache") / "som_torch"


def compiler() -> str | None:
    """``$CC``, or None (the default compiler)."""
    return os.environ.get("CC") or None


@lru_cache(maxsize=1)
def _usable_cpus() -> int:
    """The CPUs this process may run on (its affinity mask where the OS has one)."""
    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1


def env_threads(*variables: str) -> int:
    """The first of ``variables`` that is set (its first comma-separated value, a positive integer),
    else the usable CPUs: the one rule for every C kernel's thread setting (``sim`` uses it with
    ``TWOMASS_SIM_THREADS``)."""
    for var in variables:
        text = os.environ.get(var, "").split(",")[0].strip()
        if not text:
            continue
        if not text.isdigit() or int(text) < 1:
            raise ValueError(f"{var}: expected a positive integer, received {os.environ[var]!r}")
        return int(text)
    return _usable_cpus()


def kernel_threads() -> int:
    """``$SOM_TORCH_THREADS``, else the first value of ``$OMP_NUM_THREADS``, else the usable CPUs."""
    return env_threads("SOM_TORCH_THREADS", "OMP_NUM_THREADS")
