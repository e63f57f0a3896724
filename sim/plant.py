"""Closed-loop simulation of the batched plant (SPEC 1) under a sampled controller (SPEC 2).

Timing per sample ``k`` (``t_k = k T_s``): measure the encoder speed ``w_m[k]``, record
``speed, torque (= M_M), torque_ref`` (the reference applied over ``[t_k, t_{k+1})``) and the
section label; the controller decides ``M_ref = step(k, w_m[k])`` (clamped to ``+-M_max``), which
applies from sample ``k+1``; the plant advances over the interval with the previous reference.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Protocol, runtime_checkable

import torch

from som_torch import CLibrary

from sim._integrate_fast import (FastParams, FastState, SignalState, advance, default_substeps, new_test_buffers,
                                  run_test_chunk)
from sim._kernel import load_kernel
from sim.measurement import measure_speed, noisy_current
from sim.params import DriveConfig, TwoMassParams, check_int
from sim._signal import SwitchingController, TestSignalConfig


@runtime_checkable
class Controller(Protocol):
    """A sampled control law: ``reset(batch_shape)``; ``step(k, w_meas *batch) -> M_ref *batch``.

    Optional: ``label() -> int8 *batch`` (recorded as ``section``), ``finished() -> bool *batch``
    (the run stops when all are finished; ``length`` then gives each record's length)."""

    def reset(self, batch_shape: torch.Size) -> None: ...

    def step(self, k: int, w_meas: torch.Tensor) -> torch.Tensor: ...


@runtime_checkable
class Plant(Protocol):
    """What stands where the simulator stands (a real drive can implement it too)."""

    T_s: float

    def reset(self) -> None: ...

    def measure(self) -> torch.Tensor:
        """Measured motor speed now [rad/s], ``*batch``."""
        ...

    def apply(self, M_ref: torch.Tensor) -> None:
        """Apply the torque reference for the next sample interval and wait for it to pass."""
        ...


@dataclass
class Response:
    """Padded responses ``*batch x N`` (``N`` = longest record), ``t`` is ``N`` [s].

    ``speed`` measured [rad/s], ``current`` measured [A], ``torque`` air-gap torque ``M_M`` [Nm]
    at the samples, ``torque_ref`` applied reference [Nm], ``section`` int8 (1..6, 0 tail, -1
    padding), ``length`` int64 ``*batch``, ``timed_out`` bool ``*batch x 6``; optional ``states``
    (``w_M, w_L, dphi, M_M, phi_M`` at the samples, same padding); ``M_hold`` [Nm] ``*batch``: the
    holding torques the test's levels ran around (SPEC 1.1), None where they ran plain."""

    t: torch.Tensor
    speed: torch.Tensor
    current: torch.Tensor
    torque: torch.Tensor
    torque_ref: torch.Tensor
    section: torch.Tensor
    length: torch.Tensor
    timed_out: torch.Tensor
    substeps: int
    states: dict[str, torch.Tensor] = field(default_factory=dict)
    M_hold: torch.Tensor | None = None

    @property
    def batch_shape(self) -> torch.Size:
        return self.length.shape


def _check(params: TwoMassParams, drive: DriveConfig, method: str, dtype: torch.dtype, seed: int) -> int:
    """The arguments both simulators share; one-line ``TypeError``/``ValueError`` naming the argument.
    Returns ``seed`` as a Python ``int``."""
    if not isinstance(params, TwoMassParams):
        raise TypeError(f"params: expected TwoMassParams, received {type(params).__name__}")
    if params.J_sigma.numel() == 0:
        raise ValueError(f"params: expected at least one system, received batch shape {tuple(params.batch_shape)}")
    seed_int = check_int("seed", seed)
    if not -2**63 <= seed_int <= 2**64 - 1:  # what torch.Generator takes
        raise ValueError(f"seed: expected an int in -2**63 .. 2**64-1, received {seed!r}")
    if not isinstance(drive, DriveConfig):
        raise TypeError(f"drive: expected DriveConfig, received {type(drive).__name__}")
    if method not in ("fast", "reference"):
        raise ValueError(f"method: expected 'fast' or 'reference', received {method!r}")
    if dtype not in (torch.float32, torch.float64):
        raise TypeError(f"dtype: expected torch.float32 or torch.float64, received {dtype}")
    return seed_int


def simulate(params: TwoMassParams, drive: DriveConfig, controller: Controller, n_samples: int, *,
             method: str = "fast", dtype: torch.dtype = torch.float32, substeps: int | None = None,
             load_torque: torch.Tensor | float | None = None, seed: int = 0, return_states: bool = False,
             use_kernel: bool = True, progress: Callable[[int], None] | None = None) -> Response:
    """Run ``controller`` in closed loop around the plant for up to ``n_samples`` samples, from rest,
    held by ``params.M_hold`` where it is not 0 (SPEC 1.1, :meth:`FastState.held`: the first
    samples' torque is the holding torque until the controller's reference applies).

    ``load_torque``: external load torque on the load side [Nm], ``*batch`` or scalar (constant),
    on top of ``params.M_L0`` (not held). ``method="reference"`` integrates with torchdiffeq in
    float64 (slow). ``seed`` (an int) seeds the current noise (see :func:`simulate_test`).
    ``use_kernel=False`` forces the torch eager twin of the fused kernel."""
    if method == "reference":
        dtype = torch.float64
    seed = _check(params, drive, method, dtype, seed)
    n_samples = check_int("n_samples", n_samples, 1)
    shape = params.batch_shape
    n = params.J_sigma.numel()
    S = default_substeps(params, drive) if substeps is None else substeps
    fp = FastParams.build(params, drive, S, dtype, load_torque)
    ref = None
    if method == "reference":
        from sim._integrate_reference import ReferenceIntegrator  # torchdiffeq: loaded only when used

        ref = ReferenceIntegrator(params, drive, load_torque)
    x = FastState.held(params, dtype)
    controller.reset(shape)
    rec: dict[str, list[torch.Tensor]] = {k: [] for k in ("speed", "torque", "torque_ref", "section")}
    st: dict[str, list[torch.Tensor]] = {k: [] for k in ("w_M", "w_L", "dphi", "M_M", "phi_M")}
    has_label, has_fin = hasattr(controller, "label"), hasattr(controller, "finished")
    for k in range(n_samples):
        w = measure_speed(x, drive, dtype)
        rec["speed"].append(w)
        rec["torque"].append(x.M_M.clone())
        rec["torque_ref"].append(x.M_ref.clone())
        rec["section"].append(controller.label().reshape(-1) if has_label else torch.zeros(n, dtype=torch.int8))
        if return_states:
            for name, v in (("w_M", x.w_M), ("w_L", x.w_L), ("dphi", x.dphi), ("M_M", x.M_M), ("phi_M", x.phi)):
                st[name].append(v.clone())
        M_new = torch.as_tensor(controller.step(k, w.reshape(shape)))
        M_new = torch.clamp(M_new.to(dtype).expand(shape).reshape(-1), -drive.M_max, drive.M_max).contiguous()
        if ref is not None:
            ref.advance(x, x.M_ref)
        else:
            advance(x, fp, use_kernel)
        x.M_ref = M_new
        if progress is not None:
            progress(1)
        if has_fin and bool(controller.finished().all()):
            break
    N = len(rec["speed"])
    out = {k: torch.stack(v, -1) for k, v in rec.items()}
    if has_fin:
        fin = controller.finished().reshape(-1)
        length = torch.where(fin, controller.length.reshape(-1).to(torch.int64), torch.full((n,), N))
    else:
        length = torch.full((n,), N, dtype=torch.int64)
    timed_out = getattr(controller, "timed_out", torch.zeros(shape + (6,), dtype=torch.bool))
    states = {k: torch.stack(v, -1) for k, v in st.items()} if return_states else {}
    return _finish(out, states, length, timed_out, shape, N, drive, S, seed)


def _finish(out: dict[str, torch.Tensor], states: dict[str, torch.Tensor], length: torch.Tensor,
            timed_out: torch.Tensor, shape: torch.Size, N: int, drive: DriveConfig, S: int, seed: int) -> Response:
    """Pad beyond each length, add current noise, reshape to ``*batch x N``. The noise: one draw of
    ``n x N`` standard normals (flat batch, row-major) from a generator seeded with ``seed``."""
    pad = torch.arange(N) >= length.unsqueeze(-1)
    for k in ("speed", "torque", "torque_ref"):
        out[k] = out[k].masked_fill(pad, 0.0)
    out["section"] = out["section"].masked_fill(pad, -1)
    g = torch.Generator().manual_seed(seed)
    current = noisy_current(out["torque"], drive, g).masked_fill(pad, 0.0)
    r = lambda v: v.reshape(*shape, N)  # noqa: E731
    return Response(t=torch.arange(N, dtype=torch.float64) * drive.T_s, speed=r(out["speed"]), current=r(current),
                    torque=r(out["torque"]), torque_ref=r(out["torque_ref"]), section=r(out["section"]),
                    length=length.reshape(shape), timed_out=timed_out.reshape(*shape, 6), substeps=S,
                    states={k: r(v.masked_fill(pad, 0.0)) for k, v in states.items()})


def hold_levels(params: TwoMassParams, around_hold: bool) -> torch.Tensor | None:
    """The holding torques [Nm] (``*batch``) a test's levels run around (SPEC 1.1): ``params.M_hold``
    where ``around_hold`` and some system has one (``M_L0 != 0``), else None (the plain levels)."""
    if not isinstance(around_hold, bool):
        raise TypeError(f"around_hold: expected a bool, received {type(around_hold).__name__}")
    M = params.M_hold
    return M if around_hold and bool((M != 0).any()) else None


def simulate_test(params: TwoMassParams, drive: DriveConfig | None = None, signal: TestSignalConfig | None = None, *,
                  method: str = "fast", seed: int = 0, dtype: torch.dtype = torch.float32,
                  substeps: int | None = None, chunk_systems: int = 1024, chunk_samples: int = 2048,
                  use_kernel: bool = True, return_states: bool = False, around_hold: bool = True,
                  progress: Callable[[int], None] | None = None) -> Response:
    """The SPEC 2 test for every system; stops when all finished (tail done) -> :class:`Response`.

    Real axes (SPEC 1.1): each system starts at rest held by ``params.M_hold`` (``M_L0``); with
    ``around_hold`` (default) the levels run around it (``M_hold + level``, clamped to ``+-M_max``,
    ``Response.M_hold`` set where some system has ``M_L0 != 0``), else plain (held only before the
    test). Without ``M_L0`` both are the plain test.

    Fast path: the fused C kernel runs the controller, the encoder and the RK4 substeps in one
    loop; systems are sorted by expected duration and run in groups of ``chunk_systems``.
    ``progress(n)`` is called with the number of systems finished. Without the kernel (or with
    ``method="reference"`` / ``return_states``) the generic :func:`simulate` loop runs instead.
    ``chunk_systems``, ``chunk_samples``: ints >= 1 (memory and scheduling only: the numbers do
    not depend on them).

    The response is in input order (flattened batch), whatever order the groups ran in. Current
    noise (as in :func:`simulate`): one ``torch.Generator`` seeded with ``seed`` draws standard
    normals of ``dtype`` for the whole padded ``n x N`` batch at once (row-major; ``n`` systems,
    ``N`` the longest record), so a system's noise depends on its flat index and on ``n`` and ``N``:
    the same system alone or in another batch gets other noise, although its speed and torque are
    the same when ``substeps`` is (the default substeps are chosen for the stiffest system of the
    batch). :func:`sim.iter_records` draws its noise per record instead (see docs/simulator.md)."""
    drive = DriveConfig() if drive is None else drive
    signal = TestSignalConfig() if signal is None else signal
    if method == "reference":
        dtype = torch.float64
    seed = _check(params, drive, method, dtype, seed)
    if not isinstance(signal, TestSignalConfig):
        raise TypeError(f"signal: expected TestSignalConfig or None, received {type(signal).__name__}")
    chunk_systems, chunk_samples = check_int("chunk_systems", chunk_systems, 1), check_int("chunk_samples", chunk_samples, 1)
    shape = params.batch_shape
    N_max = signal.max_samples(drive)
    hold = hold_levels(params, around_hold)
    lib = load_kernel() if use_kernel else None
    if method == "reference" or lib is None or return_states:
        ctl = SwitchingController(signal, drive, dtype, M_hold=hold)
        resp = simulate(params, drive, ctl, N_max, method=method, dtype=dtype, substeps=substeps, seed=seed,
                        return_states=return_states, use_kernel=use_kernel)
        resp.M_hold = hold
        if progress is not None:
            progress(int(params.J_sigma.numel()))
        return resp
    flat = params.reshape(-1)
    n = flat.J_sigma.numel()
    S = default_substeps(params, drive) if substeps is None else substeps
    order = torch.argsort(signal.expected_duration(flat.J_sigma))
    parts = []
    for g0 in range(0, n, chunk_systems):
        idx = order[g0:g0 + chunk_systems]
        parts.append((idx, *run_test_group(lib, flat[idx], drive, signal, S, dtype, chunk_samples, progress,
                                           around_hold=around_hold)))
    N = max(int(p[2].max()) for p in parts)
    out = {k: torch.zeros(n, N, dtype=dtype) for k in ("speed", "torque", "torque_ref")}
    out["section"] = torch.full((n, N), -1, dtype=torch.int8)
    length = torch.zeros(n, dtype=torch.int64)
    tmo = torch.zeros(n, dtype=torch.int32)
    for idx, buf, ln, tm in parts:
        m = min(N, buf["speed"].shape[-1])
        for k in out:
            out[k][idx, :m] = buf[k][:, :m]
        length[idx] = ln
        tmo[idx] = tm
    timed_out = ((tmo.unsqueeze(-1) >> torch.arange(6, dtype=torch.int32)) & 1).bool()
    resp = _finish(out, {}, length, timed_out, shape, N, drive, S, seed)
    resp.M_hold = hold
    return resp


def run_test_group(lib: CLibrary, flat: TwoMassParams, drive: DriveConfig, signal: TestSignalConfig, S: int,
                   dtype: torch.dtype, chunk_samples: int = 2048,
                   progress: Callable[[int], None] | None = None, *,
                   around_hold: bool = True) -> tuple[dict[str, torch.Tensor], torch.Tensor, torch.Tensor]:
    """The fused test for one flat group: buffers ``n x N`` (valid up to each length, rest
    undefined), lengths (int64 ``n``) and the timeout bit masks (int32 ``n``). From rest held by
    ``flat.M_hold``; the levels around it with ``around_hold`` (see :func:`simulate_test`)."""
    n = flat.J_sigma.numel()
    N_max = signal.max_samples(drive)
    fp = FastParams.build(flat, drive, S, dtype)
    x = FastState.held(flat, dtype)
    hold = hold_levels(flat, around_hold)
    hold = None if hold is None else hold.reshape(-1).to(dtype).contiguous()
    c = SignalState.start(n)
    est = float(signal.expected_duration(flat.J_sigma).max()) / drive.T_s
    cap = min(N_max, int(1.25 * est) + chunk_samples)
    buf = new_test_buffers(n, cap, dtype)
    k0, left = 0, n
    while left > 0 and k0 < N_max:
        nk = min(chunk_samples, N_max - k0)
        if k0 + nk > buf["speed"].shape[1]:
            bigger = new_test_buffers(n, min(N_max, 2 * buf["speed"].shape[1] + nk), dtype)
            for k in buf:
                bigger[k][:, :k0] = buf[k][:, :k0]
            buf = bigger
        before = left
        left = run_test_chunk(lib, x, fp, c, drive, signal.levels(drive), signal.n_timeout(drive),
                              signal.n_tail(drive), k0, nk, buf, M_hold=hold)
        k0 += nk
        if progress is not None and before > left:
            progress(before - left)
    length = torch.where(c.sec >= 8, c.length.to(torch.int64), torch.full((n,), k0, dtype=torch.int64))
    N = int(length.max())
    return {k: v[:, :N] for k, v in buf.items()}, length, c.tmo


class SimulatedPlant:
    """The simulator behind the :class:`Plant` interface (fast path, one sample per ``apply``)."""

    def __init__(self, params: TwoMassParams, drive: DriveConfig | None = None, *, dtype: torch.dtype = torch.float32,
                 substeps: int | None = None, load_torque: torch.Tensor | float | None = None):
        self.params, self.drive, self.dtype = params, drive or DriveConfig(), dtype
        self.T_s = self.drive.T_s
        S = default_substeps(params, self.drive) if substeps is None else substeps
        self._fp = FastParams.build(params, self.drive, S, dtype, load_torque)
        self.reset()

    def reset(self) -> None:
        self._x = FastState.held(self.params, self.dtype)
        self._w = torch.zeros(self.params.batch_shape, dtype=self.dtype)

    def measure(self) -> torch.Tensor:
        self._w = measure_speed(self._x, self.drive, self.dtype).reshape(self.params.batch_shape)
        return self._w

    def apply(self, M_ref: torch.Tensor) -> None:
        M = torch.as_tensor(M_ref, dtype=self.dtype).expand(self.params.batch_shape).reshape(-1)
        self._x.M_ref = torch.clamp(M, -self.drive.M_max, self.drive.M_max).contiguous()
        advance(self._x, self._fp)

    @property
    def motor_angle(self) -> torch.Tensor:
        return self._x.phi.reshape(self.params.batch_shape)
