"""Open-loop replay of piecewise-constant torque references: fast re-simulation for model fits.

A switching test run (SPEC 2) applies a torque reference that is constant between a handful of
switching samples. Replaying that reference open loop through candidate plants reproduces the
record's excitation exactly, whatever the candidates' speeds do, which is what an output-error
fit needs. The fused C kernel runs the whole replay in one call per chunk of samples; without a
compiler its torch eager twin runs the same arithmetic sample by sample.
"""

from __future__ import annotations

import math

import torch

from sim._integrate_fast import (KERNEL_BLOCK, FastParams, FastState, advance, default_substeps, encoder_args,
                                 plant_args)
from sim._kernel import load_kernel
from sim.params import DriveConfig, TwoMassParams
from sim.measurement import measure_speed


def replay_speed(params: TwoMassParams, drive: DriveConfig, start: torch.Tensor, level: torch.Tensor,
                 n_samples: int, *, quantize: bool = True, state: dict[str, torch.Tensor] | None = None,
                 dtype: torch.dtype = torch.float32, substeps: int | None = None,
                 use_kernel: bool = True) -> torch.Tensor:
    """Measured motor speed ``n x n_samples`` [rad/s] of ``n`` systems (``params`` flat ``n``), each
    driven open loop by its torque reference: ``level[i, j]`` [Nm] over samples
    ``start[i, j] <= k < start[i, j+1]`` (``start`` int ``n x K``, ascending, ``start[:, 0] = 0``).

    Same timing and measurement as :func:`sim.simulate` (no current noise: only speed returns):
    ``speed[:, k]`` is measured at ``t_k``, then the level of sample ``k`` acts over ``[t_k, t_k+1)``.
    ``quantize=False`` returns the mean motor speed over the past sample interval instead of the
    encoder's (its expected value: an output-error fit then compares the measurement with the
    model's noise-free speed). The plant starts at rest held by ``params.M_hold`` (SPEC 1.1; the
    levels are the whole references: a held axis's include the holding torque). ``state``: the
    plant state at sample 0 instead of rest, ``n`` tensors ``w_M``, ``w_L``, ``dphi`` [rad/s, rad/s,
    rad] and ``M_M`` [Nm] (the motor angle starts at 0; with ``quantize=False`` sample 0 reads
    ``w_M``). Levels are clamped to ``+-drive.M_max``. ``substeps`` defaults to :func:`default_substeps`."""
    flat = params if params.J_sigma.dim() == 1 else params.reshape(-1)
    n = flat.J_sigma.numel()
    if start.ndim != 2 or level.shape != start.shape or start.shape[0] != n:
        raise ValueError(f"start, level: expected {n} x K each, received {tuple(start.shape)}, {tuple(level.shape)}")
    if isinstance(n_samples, bool) or not isinstance(n_samples, int) or n_samples < 1:
        raise ValueError(f"n_samples: expected an int >= 1, received {n_samples!r}")
    start = start.to(torch.int32).contiguous()
    level = level.to(dtype).clamp(-drive.M_max, drive.M_max).contiguous()
    S = default_substeps(flat, drive) if substeps is None else substeps
    lib = load_kernel() if use_kernel else None
    fp = FastParams.build(flat, drive, S, dtype)
    x = FastState.held(flat, dtype)  # rest, held by M_hold where the plant has M_L0 (SPEC 1.1)
    if state is not None:
        if sorted(state) != ["M_M", "dphi", "w_L", "w_M"]:
            raise ValueError(f"state: expected keys ['M_M', 'dphi', 'w_L', 'w_M'], received {sorted(state)}")
        for k, v in state.items():
            v = torch.as_tensor(v).reshape(-1)
            if v.numel() != n:
                raise ValueError(f"state[{k!r}]: expected {n} values, received {v.numel()}")
            setattr(x, k, v.to(dtype).contiguous())
        # the mean speed over the interval before sample 0 reads w_M (unquantized output)
        x.cnt_prev = (-x.w_M.to(torch.float64) * drive.T_s * drive.encoder_counts / (2.0 * math.pi)).contiguous()
    if lib is None:  # the torch eager twin, sample by sample
        out = torch.empty(n_samples, n, dtype=dtype)
        starts = start.to(torch.int64)
        scale = drive.counts_per_rad
        for k in range(n_samples):
            if quantize:
                out[k] = measure_speed(x, drive, dtype)
            else:  # as the kernel: counts without the floor
                c = x.phi * scale
                out[k] = ((c - x.cnt_prev) * drive.q_w).to(dtype)
                x.cnt_prev = c
            seg = (starts <= k).sum(-1) - 1  # n: the segment of sample k
            x.M_ref = level.gather(-1, seg.unsqueeze(-1)).reshape(n).contiguous()
            advance(x, fp, use_kernel=False)
        return out.T  # n x N (a view)
    # time-major; rows of more than one block padded to whole blocks, so that each block writes
    # whole cache lines (docs/simulator.md, "Open-loop replay")
    stride = n if n <= KERNEL_BLOCK else -(-n // KERNEL_BLOCK) * KERNEL_BLOCK
    out = torch.empty(n_samples, stride, dtype=dtype)
    lib.function("run_replay", dtype)(*plant_args(x, fp), *encoder_args(drive), int(quantize), start.shape[1],
                                      start, level, 0, n_samples, stride, out)
    return out[:, :n].T  # n x N (a view)

