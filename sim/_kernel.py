"""The fused C kernel of the fixed-step path (``_kernel.c``): its signature table and its loader.

Compiled per float type when the package is built or installed (``setup.py``, portable flags,
see :mod:`som_torch._prebuilt`); in a checkout without those libraries, on first use with the
system C compiler into a cache folder (``$TWOMASS_CACHE``, see :mod:`sim._config`; about one
second). Loaded with ctypes by :class:`som_torch.CKernel`, which also checks every call's tensors
against :data:`KERNEL`'s table. When the kernel cannot be loaded, :func:`load_kernel` returns
``None`` (after one warning) and the simulator uses its torch eager twin (same arithmetic, slower).
"""

from __future__ import annotations

from functools import lru_cache
from pathlib import Path

from som_torch import CFunction, CKernel, CLibrary

from sim import _config

#: The step constants, the plant coefficients and the state, ``n`` systems (the first 25 arguments of each function).
_PLANT = ("n: int64", "S: int", "dt: REAL", "h: REAL", "k6: REAL", "iTE: REAL", "nthreads: int",
          *(f"{c}: REAL[n]" for c in ("iJM", "iJL", "CF", "DF", "s", "MFC", "muF", "Mext", "MFCM", "muFM", "wM", "wL",
                                      "dp", "MM", "Mref")),
          "phi: double[n]", "cntp: double[n]", "comp: REAL[4, n]")
#: The measurement constants: speed quantum and counts per radian.
_ENCODER = ("qw: double", "scale: double")

#: add/sub/mul per system-substep in ``_kernel.c`` as written, for a block of plants without motor
#: friction (SPEC 1's model, the default population; as compiled: the vectorized loops hold 129
#: add/sub/mul instructions per vector of lanes): 23 for the mode and stage 1 (shaft torque, net
#: torque, friction, slopes, stage-2 state), 32 each for stages 2 and 3 (shaft torque, slopes, RK4
#: sums, next stage's state), 42 for stage 4 and the update (shaft torque, slopes, angle increment,
#: four Kahan updates, the stop test's product). Compares, min/max, selects and negations are not
#: counted, nor the per-sample encoder and controller.
FLOPS_PER_SUBSTEP = 129
#: The same for a block with SPEC 1.1's motor friction (the kernel's second compiled variant of the
#: substep): 15 more (the motor's net torque and Coulomb term in stage 1, ``- fric_M - mu_FM w_M`` in
#: each stage's slope, its stop test's product).
FLOPS_PER_SUBSTEP_MOTOR = 144

#: Build facts as plain literals (``setup.py`` reads them without importing torch). ``-ffp-contract=off``
#: keeps the arithmetic of the torch twin (no fused multiply-add), on every CPU and variant.
NAME, SOURCE = "twomass_kernel", "_kernel.c"
FLAGS = ("-O3", "-march=native", "-fopenmp", "-ffp-contract=off", "-fno-trapping-math", "-std=c99")
LINK_FLAGS = ("-fopenmp", "-lm")

KERNEL = CKernel(
    name=NAME,
    source=Path(__file__).with_name(SOURCE),
    functions={
        "advance": CFunction(_PLANT),
        "run_test": CFunction((
            *_PLANT, *(f"{c}: int32[n]" for c in ("sec", "cnt", "nI", "nIV", "len", "tmo")), "Mhold: REAL[n]",
            *_ENCODER,
            "Mstar: REAL", "Mlow: REAL", "wmax: REAL", "wlow: REAL", "Mmax: REAL", "n_timeout: int32",
            "n_tail: int32", "k0: int64", "nk: int64", "ostride: int64", "ocol0: int64",
            "o_speed: REAL[n, ostride]", "o_torque: REAL[n, ostride]", "o_tref: REAL[n, ostride]",
            "o_sec: int8[n, ostride]"), returns="int64"),
        "run_replay": CFunction((
            *_PLANT, *_ENCODER, "quantize: int32", "K: int32", "start: int32[n, K]", "lev: REAL[n, K]",
            "k0: int64", "nk: int64", "ostride: int64", "o_speed: REAL[nk, ostride]")),
    },
    flags=FLAGS,
    link_flags=LINK_FLAGS,
)


@lru_cache(maxsize=1)
def load_kernel() -> CLibrary | None:
    """The compiled kernel, or ``None`` when disabled or (with one warning) when it cannot be built."""
    return _config.load_c_kernel(KERNEL)
