"""ZOH responses of paper eq. 1's resonance ``s / (s^2 + 2 d w0 s + w0^2)`` to a sampled torque,
for many ``(f_0, d)`` at once: the inner loop of the oscillation fit.

The C kernel ``_resonance.c`` runs the recursion for every pair in one call (built and loaded like
the simulator's kernel, :mod:`sim._kernel`); without it, ``scipy.signal.lfilter`` runs each pair
(the same numbers to rounding: the tests compare them).
"""

from __future__ import annotations

import math
from functools import lru_cache
from pathlib import Path

import numpy as np
import torch
from scipy import signal as _signal

from sim import load_c_kernel
from som_torch import CFunction, CKernel, CLibrary

#: Build facts as plain literals (``setup.py`` reads them without importing torch).
NAME, SOURCE = "twomass_resonance", "_resonance.c"
FLAGS = ("-O2", "-std=c99", "-ffp-contract=off")
LINK_FLAGS = ("-lm",)

KERNEL = CKernel(
    name=NAME,
    source=Path(__file__).with_name(SOURCE),
    functions={"zoh_responses": CFunction(("n: int64", "M: double[n]", "K: int64", "c: double[K]", "a1: double[K]",
                                           "a2: double[K]", "out: double[K, n]"))},
    flags=FLAGS,
    link_flags=LINK_FLAGS,
)


@lru_cache(maxsize=1)
def _kernel() -> CLibrary | None:
    return load_c_kernel(KERNEL)  # the toolkit's kernel settings (switch, cache folder, compiler)


def _coefficients(f_0: np.ndarray, d: np.ndarray, T_s: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``c, a1, a2`` of ``H(z) = c (z^-1 - z^-2) / (1 - a1 z^-1 + a2 z^-2)``: the ZOH of the step
    response ``exp(-sigma t) sin(w_d t) / w_d`` (``r = exp(-sigma T_s)``, ``c = r sin(w_d T_s) / w_d``)."""
    w0 = 2 * math.pi * f_0
    sigma, w_d = d * w0, w0 * np.sqrt(1.0 - d * d)
    r = np.exp(-sigma * T_s)
    return r * np.sin(w_d * T_s) / w_d, 2 * r * np.cos(w_d * T_s), r * r


def zoh_responses(M: np.ndarray, f_0: np.ndarray, d: np.ndarray, T_s: float) -> np.ndarray:
    """Responses ``K x N`` to the torque ``M`` (``N``) of the resonances ``f_0`` [Hz], ``d`` (``K`` each)."""
    M = np.ascontiguousarray(M, dtype=np.float64)
    c, a1, a2 = (np.ascontiguousarray(v, dtype=np.float64).reshape(-1) for v in _coefficients(
        np.asarray(f_0, dtype=np.float64), np.asarray(d, dtype=np.float64), T_s))
    out = np.empty((c.size, M.size))
    lib = _kernel()
    if lib is None:
        for k in range(c.size):
            out[k] = _signal.lfilter([0.0, c[k], -c[k]], [1.0, -a1[k], a2[k]], M)
        out[np.abs(out) < 1e-150] = 0.0
        return out
    t = torch.from_numpy
    lib.function("zoh_responses", torch.float64)(M.size, t(M), c.size, t(c), t(a1), t(a2), t(out))
    return out
