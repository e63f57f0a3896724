"""Input checks shared by the signal-processing modules and the commands (one-line errors naming the input)."""

from __future__ import annotations

import math
import os
import shutil
from pathlib import Path
from typing import Any

import numpy as np

from training.errors import UserError


def as_signal(name: str, x: Any) -> np.ndarray:
    """``x`` as a float64 1-D array of finite values; ValueError/TypeError naming ``name`` otherwise."""
    if isinstance(x, (str, bytes)):
        raise TypeError(f"{name}: expected a 1-D array of numbers, received {type(x).__name__}")
    arr = np.asarray(x, dtype=np.float64)
    if arr.ndim != 1:
        raise ValueError(f"{name}: expected a 1-D array (N,), received shape {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise ValueError(f"{name}: expected finite values, received {int(np.sum(~np.isfinite(arr)))} NaN/inf")
    return arr


# --- command-line input checks (one-line UserErrors naming the option; shared by the commands) ---

#: RK4 substeps per sample above which a simulation is refused (:func:`check_sim_cost`). SPEC 3.1's
#: envelope needs at most about 20 (f_e 500 Hz at T_s 1 ms, or T_s / T_Ei = 10); 1000 allows eigen-
#: frequencies far beyond it (about 160 kHz on the reference drive) at 250 x the usual cost.
MAX_SUBSTEPS = 1000


def finite_number(option: str, value: float) -> float:
    """``value`` if finite and > 0; else a :class:`UserError` naming ``option``."""
    if not math.isfinite(value) or value <= 0:
        raise UserError(f"{option}: expected a finite number > 0, received {value!r}")
    return value


def seed(option: str, value: int) -> int:
    """``value`` if it is a usable seed (an integer >= 0); else a :class:`UserError` naming ``option``."""
    if value < 0:
        raise UserError(f"{option}: expected an integer >= 0, received {value}")
    return value


def record_name(source: str, name: str) -> str:
    """``name`` if it names a file inside the output folder (no path separator, no control character
    such as NUL or a line break, not ``.``/``..``)."""
    if name in ("", ".", "..") or any(sep in name for sep in ("/", "\\")) or not name.isprintable():
        from sim._values import shown

        raise UserError(f"{source}: record name {shown(name)}: expected a plain file name (no path separators "
                        "or control characters, not '.' or '..')")
    return name


#: Memory per system of a drawn population (parameters, their derived values, the sort by duration,
#: a dataset row) [bytes]: a generous estimate, for refusing sizes that cannot fit before numpy or
#: torch fail to allocate.
BYTES_PER_SYSTEM = 1024


#: Where Linux says how much memory a new allocation can get now: ``MemAvailable`` (free memory plus
#: the caches the kernel can drop), in kB.
MEMINFO = Path("/proc/meminfo")


def available_memory() -> int | None:
    """Memory this process can allocate now [bytes]: ``MemAvailable`` of :data:`MEMINFO`; where
    that is missing (not Linux, a kernel before 3.14), the machine's physical memory, the best bound
    known; ``None`` where neither is known (no check). A container's own limit (cgroup) is not seen."""
    try:
        with open(MEMINFO, encoding="ascii") as f:
            for line in f:
                key, _, value = line.partition(":")
                if key == "MemAvailable":
                    return int(value.split()[0]) * 1024
    except (OSError, ValueError, IndexError):
        pass
    try:
        return int(os.sysconf("SC_PAGE_SIZE")) * int(os.sysconf("SC_PHYS_PAGES"))
    except (AttributeError, ValueError, OSError):
        return None


def free_disk(folder: str | os.PathLike[str]) -> int:
    """Bytes free to an unprivileged user on the file system of ``folder`` (of its nearest existing
    parent where it does not exist yet)."""
    where = Path(folder).absolute()
    while not where.exists() and where != where.parent:
        where = where.parent
    return shutil.disk_usage(where).free


def _size(n_bytes: float) -> str:
    for unit in ("B", "KiB", "MiB", "GiB"):
        if n_bytes < 1024:
            return f"{n_bytes:.3g} {unit}"
        n_bytes /= 1024
    return f"{n_bytes:.3g} TiB"


def check_memory(what: str, n_bytes: float) -> None:
    """A :class:`UserError` where ``what`` needs more memory (an estimate, ``n_bytes``) than is
    available now (:func:`available_memory`), before any of it is allocated."""
    have = available_memory()
    if have is not None and n_bytes > have:
        raise UserError(f"{what}: needs about {_size(n_bytes)} of memory, {_size(have)} is available; ask for less")


def check_disk(what: str, folder: str | os.PathLike[str], n_bytes: float) -> None:
    """A :class:`UserError` where ``what`` would write more (an estimate, ``n_bytes``) into ``folder``
    than its file system has free (:func:`free_disk`), before anything is written."""
    free = free_disk(folder)
    if n_bytes > free:
        raise UserError(f"{what}: writes about {_size(n_bytes)} into {folder}, {_size(free)} is free there; "
                        "ask for less or free space")


def check_sim_cost(source: str, params: Any, drive: Any) -> None:
    """A :class:`UserError` naming ``f_e`` where simulating ``params`` (``sim.TwoMassParams``) on
    ``drive`` takes more than :data:`MAX_SUBSTEPS` RK4 substeps per sample (the cost grows with ``f_e``)."""
    from sim import default_substeps
    flat = params.reshape(-1)
    substeps = default_substeps(flat, drive)
    if substeps <= MAX_SUBSTEPS:
        return
    w_0 = flat.w_0
    i = int(w_0.argmax())
    f_e = float(flat.f_e[i])
    f_max = MAX_SUBSTEPS * 0.25 / drive.T_s * f_e / float(w_0[i])  # substeps ~ w_0 T_s / 0.25, w_0 ~ f_e
    raise UserError(f"{source}: f_e {f_e:g} Hz needs {substeps} RK4 substeps per "
                    f"sample (T_s {drive.T_s * 1e6:g} us); at most {MAX_SUBSTEPS} are allowed (f_e up to about "
                    f"{f_max:.3g} Hz on this drive)")
