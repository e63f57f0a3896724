"""Optional native kernel for the online rule: one C loop per epoch over steps and maps.

The online rule is sequential (one sample per step), so with torch every step pays ~10 kernel
launches on small tensors. This kernel (``_native.c``) runs a whole epoch in one call on the
weights in blocks of units ``B x NB x C x L`` (:func:`lanes` units per block, unit axis innermost:
it vectorizes, and each block's weights are contiguous), the maps of the
batch in parallel on :func:`threads` OpenMP threads (one map per thread at a time: the same
numbers on any number of threads). It is compiled when the package is built or installed
(``setup.py``, portable flags, see :mod:`som_torch._prebuilt`); in a checkout without those
libraries, on first use with the system C compiler (flags in :data:`KERNEL`) into a private
per-user cache; loaded with ctypes (see :mod:`som_torch._cbuild`); nothing is downloaded. When
it cannot be loaded, :func:`kernel` returns ``None`` (after one warning) and training falls back
to the torch path.
``SOM_TORCH_NATIVE=0`` disables it (see :mod:`som_torch._config`).
"""

from __future__ import annotations

from functools import lru_cache
from pathlib import Path

import torch

from . import _config
from ._cbuild import CFunction, CheckedFunction, CKernel, CLibrary

KINDS = {"gaussian": 0, "bubble": 1, "cut_gaussian": 2, "epanechnikov": 3}

# -ffast-math lets gcc call glibc's vectorized expf/exp; the kernel sees no NaN/inf (NaN samples
# arrive zero-filled with a validity mask). The link step goes without it (see CKernel).
# Build facts as plain literals (``setup.py`` reads them without importing torch).
NAME, SOURCE = "som_torch_epoch", "_native.c"
FLAGS = ("-O3", "-march=native", "-ffast-math", "-fopenmp")
LINK_FLAGS = ("-fopenmp", "-lm", "-lmvec")

KERNEL = CKernel(
    name=NAME,
    source=Path(__file__).with_name(SOURCE),
    functions={
        "som_epoch": CFunction((
            "B: int", "U: int", "C: int", "N: int", "NB: int", "L: int",
            "w: REAL[B, NB, C, L]", "x: REAL[N, B, C]", "valid: REAL[N, B, C]?", "act: REAL[B, C]", "rows: int",
            "cols: int", "yr: REAL[rows]", "xc: REAL[2, cols]", "d2: REAL[U, U]?",
            "lr: REAL[N, B]", "sg: REAL[N, B]", "kind: int", "nthreads: int", "dist: REAL[B, NB, L]",
            "h: REAL[B, NB, L]", "bmus: int64[N, B]"), returns="int"),
        "som_lanes": CFunction((), returns="int")},
    flags=FLAGS,
    link_flags=LINK_FLAGS,
)


@lru_cache(maxsize=1)
def _library() -> CLibrary | None:
    return KERNEL.load(_config.cache_dir(), _config.compiler()) if _config.native_enabled() else None


def available() -> bool:
    """Whether the native kernel could be built and loaded here."""
    return _library() is not None


def library() -> str:
    """Which kernel :func:`kernel` calls: the prebuilt libraries' file names, or the run-time build's
    cache folder, or why none (for benchmark and bug reports)."""
    return "none (torch path)" if _library() is None else KERNEL.origin(_config.cache_dir())


def threads(maps: int) -> int:
    """Threads for an epoch of ``maps`` maps: :func:`som_torch._config.kernel_threads`, at most one per map."""
    return max(1, min(_config.kernel_threads(), maps))


def kernel(dtype: torch.dtype) -> CheckedFunction | None:
    """The checked epoch function for ``float32``/``float64``, or ``None`` when unavailable."""
    lib = _library()
    if lib is None or dtype not in (torch.float32, torch.float64):
        return None
    return lib.function("som_epoch", dtype)


def lanes(dtype: torch.dtype) -> int:
    """Units per block of the epoch function's weight layout (``B x NB x C x lanes``) for ``dtype``;
    the kernel must be available."""
    lib = _library()
    if lib is None:
        raise RuntimeError("som_torch native kernel: not available")
    return _lanes(lib, dtype)


@lru_cache(maxsize=None)
def _lanes(lib: CLibrary, dtype: torch.dtype) -> int:
    """:func:`lanes` of a loaded library (a build constant: asked once per library and dtype)."""
    return int(lib.function("som_lanes", dtype)())
