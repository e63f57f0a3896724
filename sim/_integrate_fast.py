"""Fixed-step path: RK4 substeps per sample, with stiction and backlash event logic.

Two implementations of the same arithmetic, with the same numbers (the same operations in the same order;
two selects of the twin are products that give the same values):

* the fused C kernel (:mod:`sim._kernel`), used when it builds;
* the torch eager twin below (fallback, and the reference for the kernel in the tests).

Substep (mode frozen over the substep): shaft torque
``M_S = C_F e + [e != 0] D_F (w_M - w_L)`` with ``e = dphi - clamp(dphi, -s, s)``; the load is
*stuck* when ``w_L == 0`` and ``|M_S - M_ext| <= M_FC`` (then ``dw_L = 0``), else the friction
sign is ``sign(w_L)`` (or ``sign(M_S - M_ext)`` when breaking away from rest); ``M_ext`` is the
constant load torque ``M_L0`` (SPEC 1.1; plus an external load torque of :func:`sim.simulate`).
After the RK4 update a load speed that changed sign against the friction direction is clamped to
0 (it stops and the next substep decides stick or slip). The motor likewise (SPEC 1.1), where it
has Coulomb friction (``M_FCM > 0``; without it the motor never sticks, as in SPEC 1): *stuck*
when ``w_M == 0`` and ``|M_M - M_S| <= M_FCM``, friction ``M_FCM sign(w_M)`` (or
``sign(M_M - M_S)`` from rest) and ``mu_FM w_M``, the same stop rule. A motor torque ``|M_M|``
below :data:`TORQUE_FLOOR` is 0. The motor angle is integrated per sample in float32/float64 and
accumulated in float64, so the encoder count is exact.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
import torch

from som_torch import CLibrary

from sim import _config
from sim._kernel import load_kernel
from sim.params import DriveConfig, TwoMassParams

_DTYPES = (torch.float32, torch.float64)

#: [Nm] A motor torque below this is 0 (its Kahan compensation too; ``TORQUE_FLOOR`` in ``_kernel.c``):
#: at zero reference the current loop's lag decays exponentially, through subnormal numbers (in
#: float32 from 69 ``T_Ei`` on), on which every operation costs the CPU a microcode assist; over a
#: whole test the kernel ran 2.4x slower for them. Physically nothing: 1e-30 Nm.
TORQUE_FLOOR = 1e-30


def rk4_substeps(w_0: float, T_s: float, T_Ei: float, *, w_0_dt: float = 0.25, minimum: int = 4) -> int:
    """RK4 substeps per sample of ``T_s`` for a stiffest mode ``w_0`` [rad/s]: ``w_0 dt <= w_0_dt``, and
    ``dt <= T_Ei/2`` for the current loop (RK4 turns unstable on it above ``dt = 2.79 T_Ei``); at
    least ``minimum``."""
    return int(max(minimum, math.ceil(w_0 * T_s / w_0_dt), math.ceil(2.0 * T_s / T_Ei)))


def default_substeps(params: TwoMassParams, drive: DriveConfig) -> int:
    """Substeps per sample (:func:`rk4_substeps`) for the stiffest system of ``params``: ``w_0 dt <= 0.25``,
    ``dt <= T_Ei/2``, at least 4."""
    return rk4_substeps(float(params.w_0.max()) if params.w_0.numel() else 0.0, drive.T_s, drive.T_Ei)


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
    comp: torch.Tensor  # 4 x n Kahan compensations of w_M, w_L, dphi, M_M (working dtype)

    @classmethod
    def zeros(cls, n: int, dtype: torch.dtype) -> "FastState":
        z = lambda: torch.zeros(n, dtype=dtype)  # noqa: E731
        return cls(z(), z(), z(), z(), z(), torch.zeros(n, dtype=torch.float64),
                   torch.zeros(n, dtype=torch.float64), torch.zeros(4, n, dtype=dtype))

    @classmethod
    def held(cls, params: TwoMassParams, dtype: torch.dtype) -> "FastState":
        """Rest, held by the torque ``M_hold = params.M_hold`` (SPEC 1.1): ``M_M = M_ref = M_hold``
        and the shaft twisted to carry it, ``dphi = M_hold / C_F + s sign(M_hold)`` (in contact on the
        load's side; the motor angle is 0). Where ``M_hold`` is 0: :meth:`zeros`, bit for bit."""
        x = cls.zeros(params.J_sigma.numel(), dtype)
        M = params.M_hold.reshape(-1)
        if bool((M != 0).any()):
            x.M_M = M.to(dtype, copy=True).contiguous()  # a copy: the kernels write the state in place
            x.M_ref = x.M_M.clone()
            x.dphi = (M / params.C_F.reshape(-1) + params.s.reshape(-1) * torch.sign(M)).to(dtype).contiguous()
        return x


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
    M_FCM: torch.Tensor
    mu_FM: torch.Tensor
    S: int
    dt: float
    iTE: float
    dtype: torch.dtype
    _work: "_Work | None" = field(default=None, init=False, repr=False, compare=False)

    @classmethod
    def build(cls, params: TwoMassParams, drive: DriveConfig, S: int, dtype: torch.dtype,
              M_ext: torch.Tensor | None = None) -> "FastParams":
        if dtype not in _DTYPES:
            raise TypeError(f"dtype: expected torch.float32 or torch.float64, received {dtype}")
        if isinstance(S, bool) or not isinstance(S, int) or S < 1:
            raise ValueError(f"substeps: expected an int >= 1, received {S!r}")
        f = lambda t: t.reshape(-1).to(dtype).contiguous()  # noqa: E731
        ext = params.M_L0 if M_ext is None else params.M_L0 + torch.as_tensor(M_ext, dtype=torch.float64)
        return cls(f(1.0 / params.J_M), f(1.0 / params.J_L), f(params.C_F), f(params.D_F), f(params.s),
                   f(params.M_FC), f(params.mu_F), f(ext.expand(params.batch_shape)), f(params.M_FCM), f(params.mu_FM),
                   S, drive.T_s / S, 1.0 / drive.T_Ei, dtype)

    def consts(self) -> tuple[float, float, float, float]:
        """``dt, h = dt/2, k6 = dt/6, 1/T_Ei`` as the kernel receives them."""
        return self.dt, 0.5 * self.dt, self.dt / 6.0, self.iTE


def _c(x: float, dtype: torch.dtype) -> torch.Tensor:
    """A scalar rounded to the working dtype, exactly as the C kernel receives it."""
    return torch.tensor(x, dtype=dtype)


class _Work:
    """The eager twin's constants and buffers for one :class:`FastParams` (made once, reused by every
    call: they hold nothing between calls). Row order of every stack: ``w_M, w_L, dphi, M_M``, the
    order of ``FastState.comp``.

    * ``P``, ``P2``: ``8 x n``, the state (rows 0-3) and its Kahan compensations (rows 4-7); a
      substep reads one and writes the other;
    * ``M``: ``8 x n``, the stage slopes ``dw_M, dw_L, ddphi, dM_M`` (rows 0-3) and the stage's
      state (rows 4-7), so rows 0-4 are the slopes and the stage's ``w_M``, whose sum is the angle
      increment;
    * ``N``: the slopes' numerators ``((M_M - M_S) - fric_M) - mu_FM w_M``, ``(net - fric) - mu_F w_L``,
      ``w_M - w_L``, ``M_ref - M_M``; ``coef`` their factors ``1/J_M``, ``1/J_L`` (each 0 while stuck), 1,
      ``1/T_Ei``: one product gives the four slopes (``x * 1 = x`` exactly);
    * ``Sum``: the RK4 sums of rows 0-4 of ``M``; stage 1 writes its slopes there directly.
    * ``views``: per buffer its state, compensations, state rows and the pairs (value, compensation)
      of ``w_L`` (the stop rule resets it), of ``M_M`` (:data:`TORQUE_FLOOR`) and of ``w_M`` (the
      motor's stop rule).

    Row views are made once (a view costs as much as a small op)."""

    def __init__(self, p: FastParams, n: int):
        self.dt, self.h, self.k6, _ = (_c(v, p.dtype) for v in p.consts())
        self.zero, self.ns = _c(0.0, p.dtype), -p.s
        # M_S - M_ext is M_S, bit for bit, when every M_ext is +0 (x - (+0) = x, also for x = -0)
        self.no_ext = not bool(torch.any((p.M_ext != 0) | p.M_ext.signbit()))
        new = lambda rows: torch.empty(rows, n, dtype=p.dtype)  # noqa: E731
        self.P, self.P2, self.M, self.N, self.Sum, self.kS, self.fK, self.Y = (new(r) for r in (8, 8, 8, 4, 5, 5, 4, 4))
        one = torch.ones(n, dtype=p.dtype)
        self.coef = torch.stack((p.iJM, p.iJL, one, torch.full((n,), p.iTE, dtype=p.dtype)))
        self.e, self.t1, self.t2, self.MS, self.net, self.inc, self.sgn, self.fric = (
            torch.empty(n, dtype=p.dtype) for _ in range(8))
        self.rest, self.stuck, self.stop, self.gone = (torch.empty(n, dtype=torch.bool) for _ in range(4))
        self.floor = _c(TORQUE_FLOOR, p.dtype)
        self.views = tuple((B[:4], B[4:], B[:4].unbind(0), B[1::4], B[3::4], B[0::4]) for B in (self.P, self.P2))
        # the motor's friction (SPEC 1.1), where any system has Coulomb friction on it (M_FCM > 0: it may
        # stick and stop; without, the motor never sticks)
        self.motor_coulomb = bool((p.M_FCM > 0).any())
        # none at all (SPEC 1's motor): its terms are skipped (they would subtract +-0: the same values)
        self.motor_friction = self.motor_coulomb or bool((p.mu_FM != 0).any())
        self.hasM = p.M_FCM > 0
        self.netM, self.sgnM, self.fricM = (torch.empty(n, dtype=p.dtype) for _ in range(3))
        self.restM, self.stuckM, self.stopM = (torch.empty(n, dtype=torch.bool) for _ in range(3))
        self.K4, self.K5, self.Xi, self.Xir = self.M[:4], self.M[:5], self.M[4:], self.M[4:].unbind(0)
        self.Sum4, self.Sum_w, self.kS4, self.kS_w, self.Nr = self.Sum[:4], self.Sum[4], self.kS[:4], self.kS[4], self.N.unbind(0)


def _work(p: FastParams, n: int) -> _Work:
    """``p``'s buffers of the eager twin, made on first use."""
    if p._work is None:
        p._work = _Work(p, n)
    return p._work


def _net_torque(wM, wL, dp, p: FastParams, w: _Work) -> torch.Tensor:
    """``net = M_S - M_ext`` at a stage state (``w.net``, or ``w.MS`` itself when ``M_ext`` is +0;
    ``M_S`` into ``w.MS``, ``w_M - w_L`` into ``w.N``). Shaft torque ``M_S = C_F e + [e != 0] D_F
    dw`` with ``e = dphi - clamp(dphi, -s, s)``, the select as a product with ``|sign e|`` (same
    bits: ``e`` is +0 inside the gap, ``C_F e + (+-0) = +0``)."""
    dw = torch.sub(wM, wL, out=w.Nr[2])
    e, MS = w.e, w.MS
    torch.sub(dp, torch.clamp(dp, w.ns, p.s, out=e), out=e)
    torch.mul(p.D_F, dw, out=w.t1).mul_(torch.abs(e, out=w.t2).sign_())
    torch.mul(p.C_F, e, out=MS).add_(w.t1)
    return MS if w.no_ext else torch.sub(MS, p.M_ext, out=w.net)


def _slopes(wM, wL, MM, Mref, fric, net, p: FastParams, w: _Work, out: torch.Tensor) -> None:
    """The slopes ``dw_M, dw_L, ddphi, dM_M`` into ``out`` (``4 x n``) from ``w.MS``, ``net`` and
    the numerators in ``w.N`` (the motor's friction ``w.fricM``, from the substep's mode)."""
    a, b, _, d = w.Nr
    torch.sub(MM, w.MS, out=a)
    if w.motor_friction:
        a.sub_(w.fricM).sub_(torch.mul(p.mu_FM, wM, out=w.t1))
    torch.sub(net, fric, out=b).sub_(torch.mul(p.mu_F, wL, out=w.t1))
    torch.sub(Mref, MM, out=d)
    torch.mul(w.N, w.coef, out=out)


def advance_eager(x: FastState, p: FastParams) -> None:
    """One sample (``S`` RK4 substeps) in torch eager ops, in place: the kernel's numbers.

    The same operations in the same order as ``_kernel.c``, the four state variables stacked where
    they get the same one (stage states, slopes, RK4 sums, Kahan updates), written into
    preallocated buffers (:class:`_Work`): about 100 tensor ops per substep. Two selects are products
    that give the same values: the shaft torque's (see :func:`_net_torque`) and the stuck load's
    ``dw_L = 0``, a product with ``1/J_L`` or 0 (``+-0``; a stuck load's speed is reset to +0 by the
    stop rule), as in the kernel. ``2 K`` in the RK4 sums is exact, so adding it with ``alpha=2``
    gives the same bits. The ops run in inference mode (the buffers are made outside it, the
    results copied out of it: no inference tensor reaches the caller)."""
    w = _work(p, x.w_M.numel())
    with torch.inference_mode():  # no autograd bookkeeping per op (-15 %); the results below are plain tensors
        X, C = w.views[0][:2]
        torch.stack((x.w_M, x.w_L, x.dphi, x.M_M), out=X)
        C.copy_(x.comp)
        inc, zero, Mref, iJM_free, iJL_free = w.inc.zero_(), w.zero, x.M_ref, w.coef[0], w.coef[1]
        for j in range(p.S):
            (X, C, Xr, _, _, _), (T, Cn, Tr, stop_pair, torque_pair, motor_pair) = w.views[j % 2], w.views[1 - j % 2]
            wM, wL, dp, MM = Xr
            # the mode, frozen over the substep (stuck, friction sign), from stage 1's net torque
            net = _net_torque(wM, wL, dp, p, w)
            rest = torch.eq(wL, zero, out=w.rest)
            stuck = torch.le(torch.abs(net, out=w.t2), p.M_FC, out=w.stuck).logical_and_(rest)
            sgn = torch.where(rest, net, wL, out=w.sgn).sign_()
            fric = torch.mul(p.M_FC, sgn, out=w.fric)
            torch.where(stuck, zero, p.iJL, out=iJL_free)
            if w.motor_friction:  # the motor's mode: net torque M_M - M_S, stuck only where M_FCM > 0
                netM = torch.sub(MM, w.MS, out=w.netM)
                restM = torch.eq(wM, zero, out=w.restM)
                stuckM = torch.le(torch.abs(netM, out=w.t2), p.M_FCM, out=w.stuckM)
                stuckM.logical_and_(restM).logical_and_(w.hasM)
                sgnM = torch.where(restM, netM, wM, out=w.sgnM).sign_()
                torch.mul(p.M_FCM, sgnM, out=w.fricM)
                torch.where(stuckM, zero, p.iJM, out=iJM_free)
            _slopes(wM, wL, MM, Mref, fric, net, p, w, w.Sum4)
            w.Sum_w.copy_(wM)
            # stages 2, 3, 4 from X + h K1, X + h K2, X + dt K3; sums ((K1 + 2 K2) + 2 K3) + K4
            K = w.Sum4
            for f, weight in ((w.h, 2), (w.h, 2), (w.dt, 1)):
                torch.add(X, torch.mul(K, f, out=w.fK), out=w.Xi)
                xwM, xwL, xdp, xMM = w.Xir
                _slopes(xwM, xwL, xMM, Mref, fric, _net_torque(xwM, xwL, xdp, p, w), p, w, w.K4)
                w.Sum.add_(w.K5, alpha=weight)
                K = w.K4
            # Kahan-compensated update (the angle increment from row 4); a load that changed sign against its friction stops
            torch.mul(w.Sum, w.k6, out=w.kS)
            inc.add_(w.kS_w)
            Y = torch.sub(w.kS4, C, out=w.Y)
            torch.add(X, Y, out=T)
            torch.sub(T, X, out=Cn).sub_(Y)
            stop = torch.lt(torch.mul(Tr[1], sgn, out=w.t2), zero, out=w.stop).logical_or_(stuck)
            torch.where(stop, zero, stop_pair, out=stop_pair)
            gone = torch.lt(torch.abs(Tr[3], out=w.t2), w.floor, out=w.gone)
            torch.where(gone, zero, torque_pair, out=torque_pair)
            if w.motor_coulomb:  # a motor that changed sign against its friction stops (only with M_FCM > 0)
                stopM = torch.lt(torch.mul(Tr[0], w.sgnM, out=w.t2), zero, out=w.stopM).logical_or_(w.stuckM)
                torch.where(stopM.logical_and_(w.hasM), zero, motor_pair, out=motor_pair)
    X, C = w.views[p.S % 2][:2]
    x.comp = C.clone()
    x.w_M, x.w_L, x.dphi, x.M_M = X.clone().unbind(0)
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
            p.iJM, p.iJL, p.C_F, p.D_F, p.s, p.M_FC, p.mu_F, p.M_ext, p.M_FCM, p.mu_FM,
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
                   k0: int, nk: int, out: dict[str, torch.Tensor], M_hold: torch.Tensor | None = None) -> int:
    """Up to ``nk`` fused samples (``k0 ..``) of the switching test in C, written into columns
    ``k0 .. k0+nk-1`` of the buffers ``out`` (``n x cap``, cap >= k0+nk); returns systems left.
    ``M_hold``: the holding torques [Nm] (``n``, working dtype) the levels run around (SPEC 1.1:
    ``M_hold + level``, clamped to ``+-M_max``); None: the plain levels."""
    cap = out["speed"].shape[-1]
    if cap < k0 + nk:
        raise ValueError(f"run_test_chunk: expected buffers of >= {k0 + nk} columns, received {cap}")
    hold = torch.zeros_like(x.w_M) if M_hold is None else M_hold
    left = lib.function("run_test", p.dtype)(
        *plant_args(x, p), c.sec, c.cnt, c.nI, c.nIV, c.length, c.tmo, hold, *encoder_args(drive), *levels,
        drive.M_max, n_timeout, n_tail, k0, nk, cap, k0, *(out[k] for k in ("speed", "torque", "torque_ref", "section")))
    return int(left)
