"""Fixed-step path: RK4 substeps per sample, with stiction and backlash event logic.

Two implementations of the same arithmetic (operation for operation):

* the fused C kernel (:mod:`sim._kernel`), used when it builds;
* the torch eager twin below (fallback, and the reference for the kernel in the tests).

Substep (mode frozen over the substep): shaft torque
``M_S = C_F e + [e != 0] D_F (w_M - w_L)`` with ``e = dphi - clamp(dphi, -s, s)``; the load is
*stuck* when ``w_L == 0`` and ``|M_S - M_ext| <= M_FC`` (then ``dw_L = 0``), else the friction
sign is ``sign(w_L)`` (or ``sign(M_S - M_ext)`` when breaking away from rest). After the RK4
update a load speed that changed sign against the friction direction is clamped to 0 (it stops
and the next substep decides stick or slip). The motor angle is integrated per sample in float32
/float64 and accumulated in float64, so the encoder count is exact.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from som_torch import CLibrary

from sim import _config
from sim._kernel import load_kernel
from sim.params import DriveConfig, TwoMassParams

_DTYPES = (torch.float32, torch.float64)


def default_substeps(params: TwoMassParams, drive: DriveConfig) -> int:
    """Substeps per sample: ``w_0 dt <= 0.25`` and ``dt <= T_Ei/2`` for the stiffest system, >= 4."""
    w0 = float(params.w_0.max()) if params.w_0.numel() else 0.0
    n = max(4, math.ceil(w0 * drive.T_s / 0.25), math.ceil(2.0 * drive.T_s / drive.T_Ei))
    return int(n)


@dataclass
class FastState:
    """Flat (``n``) contiguous arrays: plant state, applied reference, encoder accumulators."""

    w_M: torch.Tensor
    w_L: torch.Tensor
    dphi: torch.Tensor
    M_M: torch.Tensor
    M_ref: torch.Tensor
    phi: torch.Tensor  # float64 motor angle [rad]
    cnt_prev: torch.Tensor  # float64 encoder count at the previous sample
    comp: torch.Tensor  # n x 4 Kahan compensations of w_M, w_L, dphi, M_M (working dtype)

    @classmethod
    def zeros(cls, n: int, dtype: torch.dtype) -> "FastState":
        z = lambda: torch.zeros(n, dtype=dtype)  # noqa: E731
        return cls(z(), z(), z(), z(), z(), torch.zeros(n, dtype=torch.float64),
                   torch.zeros(n, dtype=torch.float64), torch.zeros(n, 4, dtype=dtype))


@dataclass
class FastParams:
    """Per-system coefficients in the working dtype (flat ``n``) and the step constants."""

    iJM: torch.Tensor
    iJL: torch.Tensor
    C_F: torch.Tensor
    D_F: torch.Tensor
    s: torch.Tensor
    M_FC: torch.Tensor
    mu_F: torch.Tensor
    M_ext: torch.Tensor
    S: int
    dt: float
    iTE: float
    dtype: torch.dtype

    @classmethod
    def build(cls, params: TwoMassParams, drive: DriveConfig, S: int, dtype: torch.dtype,
              M_ext: torch.Tensor | None = None) -> "FastParams":
        if dtype not in _DTYPES:
            raise TypeError(f"dtype: expected torch.float32 or torch.float64, received {dtype}")
        if isinstance(S, bool) or not isinstance(S, int) or S < 1:
            raise ValueError(f"substeps: expected an int >= 1, received {S!r}")
        f = lambda t: t.reshape(-1).to(dtype).contiguous()  # noqa: E731
        n = params.J_sigma.numel()
        ext = torch.zeros(n, dtype=dtype) if M_ext is None else f(torch.as_tensor(M_ext, dtype=torch.float64).expand(params.batch_shape))
        return cls(f(1.0 / params.J_M), f(1.0 / params.J_L), f(params.C_F), f(params.D_F), f(params.s),
                   f(params.M_FC), f(params.mu_F), ext, S, drive.T_s / S, 1.0 / drive.T_Ei, dtype)

    def consts(self) -> tuple[float, float, float, float]:
        """``dt, h = dt/2, k6 = dt/6, 1/T_Ei`` as the kernel receives them."""
        return self.dt, 0.5 * self.dt, self.dt / 6.0, self.iTE


def _c(x: float, dtype: torch.dtype) -> torch.Tensor:
    """A scalar rounded to the working dtype, exactly as the C kernel receives it."""
    return torch.tensor(x, dtype=dtype)


def _shaft_torque(wM, wL, dp, p: FastParams) -> tuple[torch.Tensor, torch.Tensor]:
    """Shaft torque ``M_S`` and the twist beyond the backlash gap ``e``."""
    cl = torch.minimum(torch.maximum(dp, -p.s), p.s)
    e = dp - cl
    return p.C_F * e + torch.where(e != 0, p.D_F * (wM - wL), torch.zeros_like(e)), e


def _rhs(wM, wL, dp, MM, Mref, Mext, stuck, fric, p: FastParams, iTE):
    MS, e = _shaft_torque(wM, wL, dp, p)
    a = (MM - MS) * p.iJM
    b = torch.where(stuck, torch.zeros_like(e), (MS - Mext - fric - p.mu_F * wL) * p.iJL)
    c = wM - wL
    d = (Mref - MM) * iTE
    return a, b, c, d


def _compensated(x: torch.Tensor, step: torch.Tensor, comp: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """``x + step`` with Kahan compensation ``comp``: the sum and the new compensation (as the C kernel)."""
    y = step - comp
    t = x + y
    return t, (t - x) - y


def advance_eager(x: FastState, p: FastParams) -> None:
    """One sample (``S`` RK4 substeps) in torch eager ops, in place."""
    dt, h, k6, iTE = (_c(v, p.dtype) for v in p.consts())
    two = _c(2.0, p.dtype)
    wM, wL, dp, MM, Mref, Mext = x.w_M, x.w_L, x.dphi, x.M_M, x.M_ref, p.M_ext
    inc = torch.zeros_like(wM)
    cwM, cwL, cdp, cMM = x.comp.unbind(-1)
    for _ in range(p.S):
        MS, _e = _shaft_torque(wM, wL, dp, p)
        net = MS - Mext
        rest = wL == 0
        stuck = rest & (net.abs() <= p.M_FC)
        sgn = torch.where(rest, torch.sign(net), torch.sign(wL))
        fric = p.M_FC * sgn
        a1, b1, c1, d1 = _rhs(wM, wL, dp, MM, Mref, Mext, stuck, fric, p, iTE)
        wM2, wL2, dp2, MM2 = wM + h * a1, wL + h * b1, dp + h * c1, MM + h * d1
        a2, b2, c2, d2 = _rhs(wM2, wL2, dp2, MM2, Mref, Mext, stuck, fric, p, iTE)
        wM3, wL3, dp3, MM3 = wM + h * a2, wL + h * b2, dp + h * c2, MM + h * d2
        a3, b3, c3, d3 = _rhs(wM3, wL3, dp3, MM3, Mref, Mext, stuck, fric, p, iTE)
        wM4, wL4, dp4, MM4 = wM + dt * a3, wL + dt * b3, dp + dt * c3, MM + dt * d3
        a4, b4, c4, d4 = _rhs(wM4, wL4, dp4, MM4, Mref, Mext, stuck, fric, p, iTE)
        inc = inc + k6 * (wM + two * wM2 + two * wM3 + wM4)
        wM, cwM = _compensated(wM, k6 * (a1 + two * a2 + two * a3 + a4), cwM)
        t, c = _compensated(wL, k6 * (b1 + two * b2 + two * b3 + b4), cwL)
        clamp = stuck | (t * sgn < 0)
        cwL = torch.where(clamp, torch.zeros_like(t), c)
        wL = torch.where(clamp, torch.zeros_like(t), t)
        dp, cdp = _compensated(dp, k6 * (c1 + two * c2 + two * c3 + c4), cdp)
        MM, cMM = _compensated(MM, k6 * (d1 + two * d2 + two * d3 + d4), cMM)
    x.comp = torch.stack([cwM, cwL, cdp, cMM], -1).contiguous()
    x.w_M, x.w_L, x.dphi, x.M_M = wM, wL, dp, MM
    x.phi = x.phi + inc.to(torch.float64)


#: Systems per block of the C kernel (``BLK`` in ``_kernel.c``): a block is one thread's unit of work.
KERNEL_BLOCK = 32


def kernel_threads(n: int) -> int:
    """Threads for ``n`` systems: the kernel's thread setting (:func:`sim._config.kernel_threads`:
    every usable CPU unless limited), but no more than there are blocks (waking idle threads for
    one system costs ~10x on a busy machine)."""
    return max(1, min(_config.kernel_threads(), -(-n // KERNEL_BLOCK)))


def plant_args(x: FastState, p: FastParams) -> tuple:
    """The kernel functions' first arguments: ``n``, the step constants, the coefficients, the state."""
    n = x.w_M.numel()
    return (n, p.S, *p.consts(), kernel_threads(n),
            p.iJM, p.iJL, p.C_F, p.D_F, p.s, p.M_FC, p.mu_F, p.M_ext,
            x.w_M, x.w_L, x.dphi, x.M_M, x.M_ref, x.phi, x.cnt_prev, x.comp)


def encoder_args(drive: DriveConfig) -> tuple[float, float]:
    """The kernel's measurement constants: speed quantum ``q_w`` [rad/s] and counts per radian."""
    return drive.q_w, drive.counts_per_rad


def advance(x: FastState, p: FastParams, use_kernel: bool = True) -> None:
    """One sample for all systems, in place: the C kernel when available, else eager."""
    lib = load_kernel() if use_kernel else None
    if lib is None:
        advance_eager(x, p)
        return
    lib.function("advance", p.dtype)(*plant_args(x, p))


@dataclass
class SignalState:
    """Switching-controller state per system (flat int32 arrays), as the C kernel keeps it."""

    sec: torch.Tensor
    cnt: torch.Tensor
    nI: torch.Tensor
    nIV: torch.Tensor
    length: torch.Tensor
    tmo: torch.Tensor

    @classmethod
    def start(cls, n: int) -> "SignalState":
        z = lambda: torch.zeros(n, dtype=torch.int32)  # noqa: E731
        return cls(torch.ones(n, dtype=torch.int32), z(), z(), z(), z(), z())


def new_test_buffers(n: int, cap: int, dtype: torch.dtype) -> dict[str, torch.Tensor]:
    """Uninitialised output buffers ``n x cap`` for :func:`run_test_chunk`."""
    return {"speed": torch.empty(n, cap, dtype=dtype), "torque": torch.empty(n, cap, dtype=dtype),
            "torque_ref": torch.empty(n, cap, dtype=dtype), "section": torch.empty(n, cap, dtype=torch.int8)}


def run_test_chunk(lib: CLibrary, x: FastState, p: FastParams, c: SignalState, drive: DriveConfig,
                   levels: tuple[float, float, float, float], n_timeout: int, n_tail: int,
                   k0: int, nk: int, out: dict[str, torch.Tensor]) -> int:
    """Up to ``nk`` fused samples (``k0 ..``) of the switching test in C, written into columns
    ``k0 .. k0+nk-1`` of the buffers ``out`` (``n x cap``, cap >= k0+nk); returns systems left."""
    cap = out["speed"].shape[-1]
    if cap < k0 + nk:
        raise ValueError(f"run_test_chunk: expected buffers of >= {k0 + nk} columns, received {cap}")
    left = lib.function("run_test", p.dtype)(
        *plant_args(x, p), c.sec, c.cnt, c.nI, c.nIV, c.length, c.tmo, *encoder_args(drive), *levels,
        drive.M_max, n_timeout, n_tail, k0, nk, cap, k0, *(out[k] for k in ("speed", "torque", "torque_ref", "section")))
    return int(left)
