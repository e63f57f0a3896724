"""Measurement model (SPEC 1): incremental encoder speed and noisy current.

The motor angle is kept in float64 (an exact count at hundreds of radians needs ~1e-7 relative;
float32 holds only ~6e-8 * 300 rad = 2e-5 rad = 3 counts), quantized with ``floor`` to encoder
counts; the measured speed is the count difference per sample times ``q_w``.
"""

from __future__ import annotations

from typing import Protocol

import torch

from sim.params import DriveConfig


class _EncoderState(Protocol):
    phi: torch.Tensor
    cnt_prev: torch.Tensor


def encoder_count(phi_M: torch.Tensor, drive: DriveConfig) -> torch.Tensor:
    """Encoder count (float64 integer values) of the motor angle ``phi_M`` [rad] (float64)."""
    if phi_M.dtype != torch.float64:
        raise TypeError(f"encoder_count: expected a float64 angle, received {phi_M.dtype}")
    return torch.floor(phi_M * drive.counts_per_rad)


def measure_speed(x: _EncoderState, drive: DriveConfig, dtype: torch.dtype) -> torch.Tensor:
    """Measured speed at the present sample from ``x.phi``; updates ``x.cnt_prev``. Shape of ``phi``."""
    cnt = encoder_count(x.phi, drive)
    w = ((cnt - x.cnt_prev) * drive.q_w).to(dtype)
    x.cnt_prev = cnt
    return w


def speed_from_angle(phi_M: torch.Tensor, drive: DriveConfig) -> torch.Tensor:
    """Measured speed for a sampled angle trajectory ``*batch x N`` (float64); first sample 0."""
    cnt = encoder_count(phi_M, drive)
    w = torch.diff(cnt, dim=-1, prepend=cnt[..., :1]) * drive.q_w
    return w


def noisy_current(torque: torch.Tensor, drive: DriveConfig, generator: torch.Generator) -> torch.Tensor:
    """Measured current ``M_M / K_M + N(0, current_noise_std^2)``, same shape and dtype."""
    noise = torch.randn(torque.shape, generator=generator, dtype=torque.dtype)
    return torque / drive.K_M + drive.current_noise_std * noise
