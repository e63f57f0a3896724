"""The switching-speed-controller test signal of SPEC section 2, as a sampled control law.

Sections: I ``+M*`` until ``w_m >= w_max``; II ``0`` until it lasted as long as I or
``w_m <= 0.2 w_max``; III ``-0.7 M*`` until ``w_m <= 0``; IV ``-M*`` until ``w_m <= -w_max``;
V ``0`` until it lasted as long as IV or ``w_m >= -0.2 w_max``; VI ``+0.7 M*`` until ``w_m >= 0``;
then ``0`` for the tail. Each section also ends after ``timeout`` (flagged).

Bookkeeping: ``section`` label of a sample is the section whose reference is applied during
that sample interval (1..6, 0 for the tail). A reference decided at sample ``k`` applies from
sample ``k+1``; sample 0 belongs to section I (with ``M_ref = 0``, nothing decided yet).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields

import torch

from sim.params import DriveConfig

SECTION_NAMES: tuple[str, ...] = ("I", "II", "III", "IV", "V", "VI")
#: The torque reference of sections I..VI in units of ``M*`` (SPEC 2); the tail and the time before I are 0.
SECTION_LEVELS: tuple[float, ...] = (1.0, 0.0, -0.7, -1.0, 0.0, 0.7)
#: The speed, in units of ``w_max``, below which II (and above whose negative V) ends.
SPEED_RETURN = 0.2
_LOW = SECTION_LEVELS[5]  # the lower torque level (VI; III is its negative), in units of M*


@dataclass(frozen=True)
class TestSignalConfig:
    """``M_star`` [Nm], ``w_max`` [rad/s], section ``timeout`` [s], ``tail`` [s]."""

    __test__ = False  # not a pytest class

    M_star: float = 10.0
    w_max: float = 100.0
    timeout: float = 10.0
    tail: float = 0.05

    def __post_init__(self) -> None:
        for f in fields(self):
            v = getattr(self, f.name)
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
                raise TypeError(f"TestSignalConfig.{f.name}: expected a finite number, received {v!r}")
            if v <= 0 and f.name != "tail":
                raise ValueError(f"TestSignalConfig.{f.name}: expected > 0, received {v}")
            if v < 0:
                raise ValueError(f"TestSignalConfig.{f.name}: expected >= 0, received {v}")

    def n_timeout(self, drive: DriveConfig) -> int:
        return max(1, int(round(self.timeout / drive.T_s)))

    def n_tail(self, drive: DriveConfig) -> int:
        return max(1, int(round(self.tail / drive.T_s)))

    def max_samples(self, drive: DriveConfig) -> int:
        """Upper bound of a record's length (all six sections time out)."""
        return 6 * self.n_timeout(drive) + self.n_tail(drive) + 1

    def levels(self, drive: DriveConfig) -> tuple[float, float, float, float]:
        """``(M*, 0.7 M*, w_max, 0.2 w_max)`` as used by the controller: ``M*``, the level of VI
        (:data:`SECTION_LEVELS`), ``w_max`` and the return speed (:data:`SPEED_RETURN`)."""
        return (self.M_star, _LOW * self.M_star, self.w_max, SPEED_RETURN * self.w_max)

    def expected_duration(self, J_sigma: torch.Tensor, M_FC: torch.Tensor | float = 0.0) -> torch.Tensor:
        """Rough test duration [s] per system (for batching by duration): one-mass estimate."""
        a = J_sigma * self.w_max
        t1 = a / self.M_star
        t3 = SPEED_RETURN * a / (_LOW * self.M_star)
        return torch.clamp(2 * (2 * t1 + t3), max=6 * self.timeout) + self.tail


class SwitchingController:
    """The SPEC 2 switching controller for a batch (torch; the C kernel fuses the same logic).

    Protocol: ``reset(batch_shape)``, ``step(k, w_meas) -> M_ref``; extras ``label()`` (section
    label of the reference now applied), ``finished()`` (bool ``*batch``), ``length``
    (samples recorded once finished) and ``timed_out`` (bool ``*batch x 6``).
    """

    def __init__(self, signal: TestSignalConfig, drive: DriveConfig, dtype: torch.dtype = torch.float32):
        self.signal, self.drive, self.dtype = signal, drive, dtype
        M_star, _M_low, w_max, w_low = signal.levels(drive)
        # the reference by section state: none before I (0), I..VI, the tail (7), done (8)
        self._table = torch.tensor([0.0, *(v * M_star for v in SECTION_LEVELS), 0.0, 0.0], dtype=dtype)
        self._w = tuple(torch.tensor(v, dtype=dtype) for v in (w_max, w_low))
        self._n_timeout = signal.n_timeout(drive)
        self._n_tail = signal.n_tail(drive)
        self.reset(())

    def reset(self, batch_shape: tuple[int, ...] | torch.Size) -> None:
        shape = tuple(batch_shape)
        self.sec = torch.ones(shape, dtype=torch.int32)
        self.cnt = torch.zeros(shape, dtype=torch.int32)
        self.nI = torch.zeros(shape, dtype=torch.int32)
        self.nIV = torch.zeros(shape, dtype=torch.int32)
        self.length = torch.zeros(shape, dtype=torch.int32)
        self.tmo = torch.zeros(shape, dtype=torch.int32)

    def label(self) -> torch.Tensor:
        """Section label (0 tail, 1..6) of the reference applied now; int8 ``*batch``."""
        return torch.where(self.sec == 7, 0, self.sec).to(torch.int8)

    def finished(self) -> torch.Tensor:
        return self.sec >= 8

    @property
    def timed_out(self) -> torch.Tensor:
        bits = torch.arange(6, dtype=torch.int32)
        return ((self.tmo.unsqueeze(-1) >> bits) & 1).bool()

    def step(self, k: int, w_meas: torch.Tensor) -> torch.Tensor:
        w = w_meas.to(self.dtype)
        w_max, w_low = self._w
        active = self.sec < 8
        q, t = self.sec, self.cnt + 1
        zero = torch.zeros((), dtype=self.dtype)
        end = torch.where(q == 1, w >= w_max,
              torch.where(q == 2, (t >= self.nI) | (w <= w_low),
              torch.where(q == 3, w <= zero,
              torch.where(q == 4, w <= -w_max,
              torch.where(q == 5, (t >= self.nIV) | (w >= -w_low),
              torch.where(q == 6, w >= zero, t >= self._n_tail))))))
        tmo = ~end & (q <= 6) & (t >= self._n_timeout)
        bit = torch.bitwise_left_shift(torch.ones_like(q), (q - 1).clamp(0, 30))
        self.tmo = torch.where(active & tmo, self.tmo | bit, self.tmo)
        end = end | tmo
        upd = active & end
        self.nI = torch.where(upd & (q == 1), t, self.nI)
        self.nIV = torch.where(upd & (q == 4), t, self.nIV)
        q_new = torch.where(upd, q + 1, q)
        t_new = torch.where(upd, torch.zeros_like(t), t)
        self.length = torch.where(upd & (q_new == 8), torch.full_like(t, k + 1), self.length)
        self.sec = torch.where(active, q_new, self.sec)
        self.cnt = torch.where(active, t_new, self.cnt)
        M = self._table[self.sec.long()]
        return torch.clamp(M, -self.drive.M_max, self.drive.M_max)
