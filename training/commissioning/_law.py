"""The speed-controller law: a batched discrete PI speed controller with an optional speed
low-pass and an optional notch on the torque reference.

:class:`PISpeedController` implements the sim controller contract (``reset(batch_shape)``,
``step(k, w_meas) -> M_ref``) and is batched: gains are tensors with a leading batch shape,
broadcast to the plant's batch. Units SI: torque [Nm], speed [rad/s], ``Kp`` [Nm s/rad],
``Ti``, ``T_f``, ``T_s`` [s].
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch

__all__ = ["NotchSpec", "PISpeedController"]


@dataclass(frozen=True)
class NotchSpec:
    """Notch ``(s^2 + 2 D_z w_n s + w_n^2)/(s^2 + 2 D_p w_n s + w_n^2)`` on the torque reference.

    ``f_n`` [Hz] centre, ``D_z`` (depth: gain at ``f_n`` = ``D_z/D_p``) and ``D_p`` (width).
    Discretized by Tustin with pre-warping at ``f_n``.
    """

    f_n: float
    D_z: float = 0.05
    D_p: float = 0.5

    def coefficients(self, T_s: float) -> tuple[np.ndarray, np.ndarray]:
        """Biquad ``(b0, b1, b2), (1, a1, a2)`` in powers of ``z^-1``."""
        w_n = 2.0 * math.pi * self.f_n
        if not 0 < w_n * T_s < math.pi:
            raise ValueError(f"notch f_n={self.f_n} Hz: expected below the Nyquist frequency {0.5 / T_s} Hz")
        c = w_n / math.tan(w_n * T_s / 2.0)  # pre-warped Tustin constant
        def poly(D: float) -> np.ndarray:
            return np.array([c * c + 2 * D * w_n * c + w_n**2, 2 * (w_n**2 - c * c), c * c - 2 * D * w_n * c + w_n**2])
        b, a = poly(self.D_z), poly(self.D_p)
        return b / a[0], a / a[0]


def _as_tensor(value: Any, name: str) -> torch.Tensor:
    t = torch.as_tensor(value, dtype=torch.float64)
    if not torch.isfinite(t).all():
        raise ValueError(f"{name}: expected finite values, received {value}")
    return t


class PISpeedController:
    """Batched discrete PI speed controller (contract: ``reset(batch_shape)``, ``step(k, w_meas)``).

    Law per sample ``k`` (``e = w_ref[k] - w_f[k]``)::

        w_f[k] = a w_f[k-1] + (1-a) w_meas[k],  a = exp(-T_s/T_f)   (T_f = 0: w_f = w_meas)
        I[k]   = I[k-1] + Kp T_s/Ti e[k]        (not while the output saturates in the sign of e)
        u[k]   = Kp e[k] + I[k];  v = notch(u);  M_ref[k] = clamp(v, -M_max, M_max)

    Args:
        Kp: proportional gain [Nm s/rad], float or tensor ``*gbatch``.
        Ti: integral time [s], same broadcastable shape.
        T_s: sample time [s]. M_max: torque limit [Nm].
        T_f: speed low-pass time constant [s] (0: none), float or tensor ``*gbatch``.
        notch: optional :class:`NotchSpec` (one for the whole batch).
        w_ref: speed reference [rad/s]: a float, a tensor ``N`` (sample ``k`` uses
            ``w_ref[min(k, N-1)]``) or ``*batch x N``.

    ``reset(batch_shape)`` broadcasts the gains to ``batch_shape`` (the plant's batch) and clears
    the states; ``step`` takes ``w_meas`` ``*batch`` [rad/s] and returns ``M_ref`` ``*batch`` [Nm].
    """

    def __init__(
        self,
        Kp: float | torch.Tensor,
        Ti: float | torch.Tensor,
        *,
        T_s: float,
        M_max: float,
        T_f: float | torch.Tensor = 0.0,
        notch: NotchSpec | None = None,
        w_ref: float | torch.Tensor = 0.0,
    ) -> None:
        self.Kp = _as_tensor(Kp, "Kp")
        self.Ti = _as_tensor(Ti, "Ti")
        self.T_f = _as_tensor(T_f, "T_f")
        if (self.Kp <= 0).any() or (self.Ti <= 0).any() or (self.T_f < 0).any():
            raise ValueError("Kp, Ti: expected > 0 and T_f >= 0")
        if not (T_s > 0 and M_max > 0):
            raise ValueError(f"T_s, M_max: expected > 0, received {T_s}, {M_max}")
        self.T_s, self.M_max = float(T_s), float(M_max)
        if notch is not None and not isinstance(notch, NotchSpec):
            raise TypeError(f"notch: expected NotchSpec or None, received {type(notch).__name__}")
        self.notch = notch
        self._nb, self._na = notch.coefficients(self.T_s) if notch is not None else (None, None)
        self.w_ref = _as_tensor(w_ref, "w_ref")
        self.batch_shape: torch.Size | None = None

    @property
    def gain_shape(self) -> torch.Size:
        return torch.broadcast_shapes(self.Kp.shape, self.Ti.shape, self.T_f.shape)

    def reset(self, batch_shape: tuple[int, ...] | torch.Size) -> None:
        shape = torch.Size(batch_shape)
        try:
            torch.broadcast_shapes(self.gain_shape, shape)
        except RuntimeError as err:
            raise ValueError(f"controller gains of shape {tuple(self.gain_shape)} do not broadcast to plant batch {tuple(shape)}") from err
        if torch.broadcast_shapes(self.gain_shape, shape) != shape:
            raise ValueError(f"controller gains of shape {tuple(self.gain_shape)} are larger than plant batch {tuple(shape)}")
        self.batch_shape = shape
        self._kp = self.Kp.expand(shape)
        self._ki = (self.Kp * self.T_s / self.Ti).expand(shape)
        self._a = torch.where(self.T_f > 0, torch.exp(-self.T_s / self.T_f.clamp_min(1e-300)), torch.zeros(())).expand(shape)
        self._1a = 1.0 - self._a
        zero = torch.zeros(shape, dtype=torch.float64)
        self._I, self._wf = zero.clone(), zero.clone()
        self._nx = [zero.clone(), zero.clone()]  # notch input history u[k-1], u[k-2]
        self._ny = [zero.clone(), zero.clone()]  # notch output history
        self._started = False

    def reference(self, k: int) -> torch.Tensor:
        """Speed reference at sample ``k`` [rad/s], broadcastable to the batch."""
        r = self.w_ref
        if r.dim() == 0:
            return r
        return r[..., min(k, r.shape[-1] - 1)]

    def step(self, k: int, w_meas: torch.Tensor) -> torch.Tensor:
        if self.batch_shape is None:
            raise ValueError("call reset(batch_shape) before step()")
        w = torch.as_tensor(w_meas, dtype=torch.float64)
        if w.shape != self.batch_shape:
            raise ValueError(f"w_meas: expected shape {tuple(self.batch_shape)}, received {tuple(w.shape)}")
        if not self._started:
            self._wf = w.clone()
            self._started = True
        self._wf = self._a * self._wf + self._1a * w
        e = self.reference(k) - self._wf
        pe = self._kp * e
        I_try = (self._I + self._ki * e).clamp(-self.M_max, self.M_max)
        u_try = pe + I_try
        windup = (u_try.abs() > self.M_max) & (u_try * e > 0)
        self._I = torch.where(windup, self._I, I_try)
        u = pe + self._I
        if self.notch is not None:
            b, a = self._nb, self._na
            v = b[0] * u + b[1] * self._nx[0] + b[2] * self._nx[1] - a[1] * self._ny[0] - a[2] * self._ny[1]
            self._nx = [u, self._nx[0]]
            self._ny = [v, self._ny[0]]
            u = v
        return u.clamp(-self.M_max, self.M_max)
