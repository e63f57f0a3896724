"""Fixed-step path: RK4 substeps per sample, with stiction and backlash event logic.

Two implementations of the same arithmetic, with the same numbers (the same operations in the same order;
two selects of the twin are products that give the same values):

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

import numpy as np
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


class _Work:
    """The eager twin's constants and buffers for one call: ``4 x n`` stacks (rows ``w_M, w_L,
    dphi, M_M``) for the state ``X``, its next value ``T``, the Kahan compensations ``C``, the stage
    state ``Xi``; ``5 x n`` for the stage slopes ``K`` (rows ``dw_M, dw_L, ddphi, dM_M`` and the
    stage's ``w_M``, whose sum gives the angle increment) and their RK4 sums ``Sum``. Row views
    are made once (a view costs as much as a small op)."""

    def __init__(self, p: FastParams, n: int):
        self.dt, self.h, self.k6, self.iTE = (_c(v, p.dtype) for v in p.consts())
        self.two = _c(2.0, p.dtype)
        self.zero, self.ns = torch.zeros(n, dtype=p.dtype), -p.s
        new = lambda rows: torch.empty(rows, n, dtype=p.dtype)  # noqa: E731
        self.X, self.T, self.C, self.Xi, self.fK, self.Y = (new(4) for _ in range(6))
        self.K, self.Sum = new(5), new(5)
        self.K4, self.Sum4, self.Sum_w = self.K[:4], self.Sum[:4], self.Sum[4]
        self.Xr, self.Tr, self.Cr, self.Xir, self.Kr = (t.unbind(0) for t in (self.X, self.T, self.C, self.Xi, self.K))


def _shaft_torque(dp: torch.Tensor, dw: torch.Tensor, p: FastParams, w: _Work) -> torch.Tensor:
    """Shaft torque ``M_S = C_F e + [e != 0] D_F dw`` with ``e = dphi - clamp(dphi, -s, s)``; the
    select as a product with ``|sign e|`` (same bits: ``e`` is +0 inside the gap, ``C_F e + (+-0) = +0``)."""
    e = dp - torch.clamp(dp, w.ns, p.s)
    return p.C_F * e + p.D_F * dw * e.abs().sign()


def _slopes(wM, wL, MM, MS, net, fric, iJL_free, Mref, p: FastParams, w: _Work) -> None:
    """Rows ``dw_M, dw_L, dM_M`` and the stage's ``w_M`` of ``w.K`` (``ddphi`` is written by the caller);
    ``net = M_S - M_ext``."""
    a, b, _c_row, d, wM_row = w.Kr
    torch.mul(MM - MS, p.iJM, out=a)
    torch.mul(net - fric - p.mu_F * wL, iJL_free, out=b)
    torch.mul(Mref - MM, w.iTE, out=d)
    wM_row.copy_(wM)


def advance_eager(x: FastState, p: FastParams) -> None:
    """One sample (``S`` RK4 substeps) in torch eager ops, in place: the kernel's numbers.

    The same operations in the same order as ``_kernel.c``, the four state variables stacked where
    they get the same one (stage states, RK4 sums, Kahan updates), written into preallocated
    buffers: about 115 tensor ops per substep. Two selects are products that give the same values:
    the shaft torque's (see :func:`_shaft_torque`) and the stuck load's ``dw_L = 0``, a product with
    ``1/J_L`` or 0 (``+-0``; a stuck load's speed is reset to +0 by the stop rule)."""
    w = _Work(p, x.w_M.numel())
    X, T, C, Xr, Tr = w.X, w.T, w.C, w.Xr, w.Tr
    for row, v in zip(Xr, (x.w_M, x.w_L, x.dphi, x.M_M)):
        row.copy_(v)
    C.copy_(x.comp.t())
    wMi, wLi, dpi, MMi = w.Xir
    dw_row = w.Kr[2]
    inc = torch.zeros_like(x.w_M)
    Mref, Mext, zero = x.M_ref, p.M_ext, w.zero
    for _ in range(p.S):
        wM, wL, dp, MM = Xr
        # the mode, frozen over the substep: stuck, friction sign; stage 1 shares its shaft torque
        dw = torch.sub(wM, wL, out=dw_row)
        MS = _shaft_torque(dp, dw, p, w)
        net = MS - Mext
        rest = wL == zero
        stuck = rest & (net.abs() <= p.M_FC)
        sgn = torch.where(rest, net.sign(), wL.sign())
        fric = p.M_FC * sgn
        iJL_free = torch.where(stuck, zero, p.iJL)
        _slopes(wM, wL, MM, MS, net, fric, iJL_free, Mref, p, w)
        w.Sum.copy_(w.K)
        # stages 2, 3, 4 from X + h K1, X + h K2, X + dt K3; sums ((K1 + 2 K2) + 2 K3) + K4
        for f, weight in ((w.h, w.two), (w.h, w.two), (w.dt, None)):
            torch.add(X, torch.mul(w.K4, f, out=w.fK), out=w.Xi)
            dw = torch.sub(wMi, wLi, out=dw_row)
            MS = _shaft_torque(dpi, dw, p, w)
            _slopes(wMi, wLi, MMi, MS, MS - Mext, fric, iJL_free, Mref, p, w)
            w.Sum.add_(w.K * weight if weight is not None else w.K)
        inc = inc + w.k6 * w.Sum_w
        # Kahan-compensated update; a load that changed sign against its friction stops
        Y = torch.sub(w.k6 * w.Sum4, C, out=w.Y)
        torch.add(X, Y, out=T)
        torch.sub(T - X, Y, out=C)
        stop = stuck | (Tr[1] * sgn < 0)
        torch.where(stop, zero, Tr[1], out=Tr[1])
        torch.where(stop, zero, w.Cr[1], out=w.Cr[1])
        X, T, Xr, Tr = T, X, Tr, Xr
    x.comp = C.t().contiguous()
    x.w_M, x.w_L, x.dphi, x.M_M = (v.clone() for v in Xr)
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
    """Uninitialised output buffers ``n x cap`` for :func:`run_test_chunk`, from numpy's allocator:
    it asks for transparent huge pages for large arrays, so the kernel's first touch costs a page
    fault per 2 MiB, not per 4 KiB as with ``torch.empty`` (4096 x 400 float32: about 5000 faults,
    several ms, against a 30 ms test)."""
    real = np.float32 if dtype == torch.float32 else np.float64
    out = {k: torch.from_numpy(np.empty((n, cap), real)) for k in ("speed", "torque", "torque_ref")}
    out["section"] = torch.from_numpy(np.empty((n, cap), np.int8))
    return out


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
