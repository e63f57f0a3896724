"""Optional native kernel for the online rule: one C loop per epoch over steps and maps.

The online rule is sequential (one sample per step), so with torch every step pays ~10 kernel
launches on small tensors. This kernel runs a whole epoch in one call on the transposed weights
``B x C x U`` (the unit axis is contiguous and vectorizes). It is compiled on first use with the
system C compiler (``$CC``, ``cc`` or ``gcc``; flags in ``_FLAGS``) into a private per-user cache
(see :func:`_cache_dir`) keyed by source, flags, host and compiler, and loaded with ctypes; nothing is downloaded. Without a compiler, :func:`kernel`
returns ``None`` and training falls back to the torch path. Set ``SOM_TORCH_NATIVE=0`` to disable.
"""

from __future__ import annotations

import ctypes
import hashlib
import os
import platform
import shutil
import subprocess
from functools import lru_cache
from pathlib import Path

import torch

_TEMPLATE = r"""
#include <math.h>
#include <stddef.h>

/* w: B x C x U (transposed weights); x, valid: N x B x C; act: B x C; d2: U x U; lr, sg: N x B;
   kind: 0 gaussian, 1 bubble, 2 cut_gaussian, 3 epanechnikov; dist, h: U scratch; bmus: N x B.
   One pass over the weights per step: the update of step i also accumulates the distances of
   sample i+1 (known in advance) to the updated weights. */
void som_epoch_TYPE(int B, int U, int C, int N, TYPE *restrict w, const TYPE *restrict x,
                    const TYPE *restrict valid, const TYPE *restrict act, const TYPE *restrict d2,
                    const TYPE *restrict lr, const TYPE *restrict sg, int kind,
                    TYPE *restrict dist, TYPE *restrict h, long long *restrict bmus)
{
    for (int b = 0; b < B; ++b) {          /* maps are independent: one map's weights stay in cache */
        TYPE *restrict wb = w + (size_t)b * C * U;
        const TYPE *restrict ab = act + (size_t)b * C;
        for (int u = 0; u < U; ++u) dist[u] = 0;
        {
            const TYPE *restrict xv = x + (size_t)b * C;
            const TYPE *restrict vv = valid ? valid + (size_t)b * C : NULL;
            for (int c = 0; c < C; ++c) {
                if (ab[c] == 0 || (vv && vv[c] == 0)) continue;
                const TYPE xc = xv[c];
                const TYPE *restrict wc = wb + (size_t)c * U;
                for (int u = 0; u < U; ++u) { TYPE d = xc - wc[u]; dist[u] += d * d; }
            }
        }
        for (int i = 0; i < N; ++i) {
            const TYPE *restrict xv = x + ((size_t)i * B + b) * C;
            const TYPE *restrict vv = valid ? valid + ((size_t)i * B + b) * C : NULL;
            const TYPE *restrict xn = i + 1 < N ? x + ((size_t)(i + 1) * B + b) * C : NULL;
            const TYPE *restrict vn = (valid && xn) ? valid + ((size_t)(i + 1) * B + b) * C : NULL;
            TYPE bd = dist[0];                 /* min (vectorizes), then its first index */
            for (int u = 1; u < U; ++u) bd = dist[u] < bd ? dist[u] : bd;
            int best = 0;
            while (dist[best] != bd) ++best;
            bmus[(size_t)i * B + b] = best;
            const TYPE rate = lr[(size_t)i * B + b], s = sg[(size_t)i * B + b];
            const TYPE *restrict row = d2 + (size_t)best * U;
            const TYPE q = (TYPE)(-0.5) / (s * s), s2 = s * s;
            if (kind == 0) {
                for (int u = 0; u < U; ++u) h[u] = rate * EXP(row[u] * q);
            } else {
                for (int u = 0; u < U; ++u) {
                    TYPE r = row[u], v;
                    if (kind == 1) v = r <= s2 ? 1 : 0;
                    else if (kind == 2) v = r <= s2 ? EXP(r * q) : 0;
                    else { v = 1 - r / s2; v = v > 0 ? v : 0; }
                    h[u] = rate * v;
                }
            }
            for (int u = 0; u < U; ++u) dist[u] = 0;
            for (int c = 0; c < C; ++c) {
                TYPE *restrict wc = wb + (size_t)c * U;
                const int move = !(vv && vv[c] == 0);
                const int next = xn && ab[c] != 0 && !(vn && vn[c] == 0);
                const TYPE xc = xv[c], xnc = xn ? xn[c] : 0;
                if (move && next) {
                    for (int u = 0; u < U; ++u) {
                        TYPE nw = wc[u] + h[u] * (xc - wc[u]);
                        wc[u] = nw;
                        TYPE d = xnc - nw;
                        dist[u] += d * d;
                    }
                } else if (move) {
                    for (int u = 0; u < U; ++u) wc[u] += h[u] * (xc - wc[u]);
                } else if (next) {
                    for (int u = 0; u < U; ++u) { TYPE d = xnc - wc[u]; dist[u] += d * d; }
                }
            }
        }
    }
}
"""

# -ffast-math lets gcc call glibc's vectorized expf/exp; the kernel sees no NaN/inf (NaN samples
# arrive zero-filled with a validity mask).
_FLAGS = ("-O3", "-march=native", "-ffast-math")

KINDS = {"gaussian": 0, "bubble": 1, "cut_gaussian": 2, "epanechnikov": 3}


def _source() -> str:
    f32 = _TEMPLATE.replace("TYPE", "float").replace("EXP", "expf")
    f64 = _TEMPLATE.replace("TYPE", "double").replace("EXP", "exp")
    return f32 + f64.replace("#include <math.h>\n#include <stddef.h>\n", "")


def _cache_dir() -> Path | None:
    """``$SOM_TORCH_CACHE`` or ``$XDG_CACHE_HOME/som_torch`` or ``~/.cache/som_torch``, created
    with mode 0700; ``None`` unless it is owned by this user and not writable by others (a
    library loaded from it runs in this process)."""
    base = os.environ.get("SOM_TORCH_CACHE")
    if base:
        folder = Path(base)
    else:
        xdg = os.environ.get("XDG_CACHE_HOME")
        folder = (Path(xdg) if xdg else Path.home() / ".cache") / "som_torch"
    try:
        folder.mkdir(mode=0o700, parents=True, exist_ok=True)
        st = folder.stat()
    except OSError:
        return None
    if hasattr(os, "getuid") and (st.st_uid != os.getuid() or st.st_mode & 0o022):
        return None
    return folder


@lru_cache(maxsize=1)
def _library() -> ctypes.CDLL | None:
    if os.environ.get("SOM_TORCH_NATIVE", "1") == "0":
        return None
    compiler = shutil.which(os.environ.get("CC", "cc")) or shutil.which("gcc")
    if compiler is None:
        return None
    src = _source()
    key = hashlib.sha256(" ".join([src, *_FLAGS, "link-v2", platform.machine(), platform.node(), compiler]).encode()).hexdigest()[:16]
    folder = _cache_dir()
    if folder is None:
        return None
    lib = folder / f"som_{key}.so"
    try:
        if not lib.is_file():
            c_file = folder / f"som_{key}.c"
            c_file.write_text(src)
            obj = folder / f".som_{key}.{os.getpid()}.o"
            tmp = folder / f".som_{key}.{os.getpid()}.so"
            # compile with the fast-math flags, but link without them: a -ffast-math link adds
            # crtfastmath.o, which flushes subnormals to zero for the whole process on load
            subprocess.run([compiler, *_FLAGS, "-fPIC", "-c", str(c_file), "-o", str(obj)],
                           check=True, capture_output=True, timeout=120)
            subprocess.run([compiler, "-shared", str(obj), "-o", str(tmp), "-lm", "-lmvec"],
                           check=True, capture_output=True, timeout=120)
            obj.unlink()
            os.replace(tmp, lib)
        cdll = ctypes.CDLL(str(lib))
    except (OSError, subprocess.SubprocessError):
        return None
    for name in ("som_epoch_float", "som_epoch_double"):
        fn = getattr(cdll, name)
        fn.restype = None
        fn.argtypes = [ctypes.c_int] * 4 + [ctypes.c_void_p] * 7 + [ctypes.c_int] + [ctypes.c_void_p] * 3
    return cdll


def available() -> bool:
    """Whether the native kernel could be built and loaded here."""
    return _library() is not None


def kernel(dtype: torch.dtype):
    """The ctypes epoch function for ``float32``/``float64``, or ``None`` when unavailable."""
    lib = _library()
    if lib is None or dtype not in (torch.float32, torch.float64):
        return None
    return lib.som_epoch_float if dtype == torch.float32 else lib.som_epoch_double
