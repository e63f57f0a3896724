"""Build and load the fused C kernel (``_kernel_src.c``) with the system C compiler.

The shared library is compiled once per source/compiler/flags into a cache folder
(``$TWOMASS_CACHE`` or ``~/.cache/twomass-som``; about one second) and loaded with ctypes.
When no compiler is available, :func:`load_kernel` returns ``None`` and the simulator uses its
torch eager twin (same arithmetic, slower).
"""

from __future__ import annotations

import ctypes
import hashlib
import os
import platform
import shutil
import subprocess
import sys
import tempfile
import warnings
from functools import lru_cache
from pathlib import Path

_SRC = Path(__file__).with_name("_kernel_src.c")
_FLAGS = ["-O3", "-march=native", "-fopenmp", "-ffp-contract=off", "-fno-trapping-math",
          "-fPIC", "-shared", "-std=c99"]

_R = {"f32": ctypes.c_float, "f64": ctypes.c_double}
_P = ctypes.c_void_p
_I64, _I32, _INT, _D = ctypes.c_int64, ctypes.c_int32, ctypes.c_int, ctypes.c_double


def _cache_dir() -> Path:
    return Path(os.environ.get("TWOMASS_CACHE", Path.home() / ".cache" / "twomass-som"))


def _source() -> str:
    body = _SRC.read_text()
    parts = []
    for real, sfx in (("float", "_f32"), ("double", "_f64")):
        b = body.replace("REAL", real).replace("_SFX", sfx)
        for name in ("block_t", "rhs", "advance_block", "load_block", "store_block"):
            b = b.replace(name, name + sfx)
        parts.append(b)
    return "\n".join(parts)


def _cpu_id() -> str:
    """The CPU's model and flags (``-march=native`` code must not be reused on another CPU)."""
    try:
        info = Path("/proc/cpuinfo").read_text()
        return "".join(sorted({ln for ln in info.splitlines() if ln.startswith(("model name", "flags"))}))
    except OSError:
        return platform.processor() + platform.machine()


def _build() -> Path:
    cc = os.environ.get("CC") or shutil.which("gcc") or shutil.which("cc")
    if cc is None:
        raise OSError("no C compiler (gcc/cc) found")
    src = _source()
    key = hashlib.sha256((src + " ".join(_FLAGS) + cc + sys.platform + _cpu_id()).encode()).hexdigest()[:16]
    out = _cache_dir() / f"twomass_kernel_{key}.so"
    if out.exists():
        return out
    out.parent.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory(dir=out.parent) as tmp:
        c_path = Path(tmp) / "kernel.c"
        c_path.write_text(src)
        so_tmp = Path(tmp) / "kernel.so"
        res = subprocess.run([cc, *_FLAGS, str(c_path), "-o", str(so_tmp), "-lm"],
                             capture_output=True, text=True)
        if res.returncode != 0:
            raise OSError(f"C kernel build failed: {res.stderr.strip().splitlines()[-1:]}")
        os.replace(so_tmp, out)  # atomic
    return out


@lru_cache(maxsize=1)
def load_kernel() -> ctypes.CDLL | None:
    """The compiled kernel library, or ``None`` (with one warning) when it cannot be built."""
    if os.environ.get("TWOMASS_NO_C_KERNEL"):
        return None
    try:
        lib = ctypes.CDLL(str(_build()))
    except OSError as err:
        warnings.warn(f"twomass: fused C kernel unavailable ({err}); using the torch eager path",
                      RuntimeWarning, stacklevel=2)
        return None
    for sfx, real in _R.items():
        adv = getattr(lib, f"advance_{sfx}")
        adv.restype = None
        adv.argtypes = [_I64, _INT, real, real, real, real, _INT] + [_P] * 16
        run = getattr(lib, f"run_test_{sfx}")
        run.restype = _I64
        run.argtypes = ([_I64, _INT, real, real, real, real, _INT] + [_P] * 22
                        + [_D, _D, real, real, real, real, real, _I32, _I32, _I64, _I64, _I64, _I64] + [_P] * 4)
        rep = getattr(lib, f"run_replay_{sfx}")
        rep.restype = None
        rep.argtypes = [_I64, _INT, real, real, real, real, _INT] + [_P] * 16 + [_D, _D, _I32, _I32, _P, _P, _I64, _I64, _P]
    return lib
