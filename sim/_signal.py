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
from typing import TypeVar

import torch

from sim.params import DriveConfig, check_real

_T = TypeVar("_T", float, torch.Tensor)

SECTION_NAMES: tuple[str, ...] = ("I", "II", "III", "IV", "V", "VI")
#: The torque reference of sections I..VI in units of ``M*`` (SPEC 2); the tail and the time before I are 0.
SECTION_LEVELS: tuple[float, ...] = (1.0, 0.0, -0.7, -1.0, 0.0, 0.7)
#: The speed, in units of ``w_max``, below which II (and above whose negative V) ends.
SPEED_RETURN = 0.2
_LOW = SECTION_LEVELS[5]  # the lower torque level (VI; III is its negative), in units of M*


def time_scale(J_sigma: _T, M_star: _T | float, w_max: _T | float) -> _T:
    """The test's time scale ``tau = J_sigma w_max / M*`` [s] (SPEC 3.1): how long the torque ``M*``
    takes to bring the inertia ``J_sigma`` [kg m^2] to ``w_max`` [rad/s]. Floats or tensors
    (broadcast); :func:`inertia_of_time_scale` is its inverse."""
    return J_sigma * w_max / M_star


def inertia_of_time_scale(tau: _T, M_star: _T | float, w_max: _T | float) -> _T:
    """The inertia ``J_sigma = tau M* / w_max`` [kg m^2] whose test time scale is ``tau`` [s]
    (the inverse of :func:`time_scale`)."""
    return tau * M_star / w_max


@dataclass(frozen=True)
class TestSignalConfig:
    """``M_star`` [Nm], ``w_max`` [rad/s], section ``timeout`` [s], ``tail`` [s]: finite real numbers
    (numpy scalars stored as Python numbers; bools and strings raise ``TypeError``)."""

    __test__ = False  # not a pytest class

    M_star: float = 10.0
    w_max: float = 100.0
    timeout: float = 10.0
    tail: float = 0.05

    def __post_init__(self) -> None:
        for f in fields(self):
            v = check_real(f"TestSignalConfig.{f.name}", getattr(self, f.name))
            object.__setattr__(self, f.name, v)
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
    (samples recorded once finished) and ``timed_out`` (bool ``*batch x 6``). State (int32
    ``*batch``): ``sec`` (0 before I, 1..6, 7 the tail, 8 done), ``cnt`` (samples in the section),
    ``limit`` (the count that ends the section by time: II and V as many as I and IV lasted, the
    tail ``n_tail``, else never), ``length``, ``tmo`` (a bit per section that timed out).

    ``M_hold`` (SPEC 1.1): holding torques [Nm] (a tensor that broadcasts to the batch, or a number);
    the references are then ``M_hold + level`` clamped to ``+-M_max`` (before section I and after the
    tail too: the axis stays held). None: the plain levels.
    """

    def __init__(self, signal: TestSignalConfig, drive: DriveConfig, dtype: torch.dtype = torch.float32,
                 M_hold: torch.Tensor | float | None = None):
        self.signal, self.drive, self.dtype = signal, drive, dtype
        self.M_hold = None if M_hold is None else torch.as_tensor(M_hold, dtype=torch.float64).to(dtype)
        M_star, _M_low, w_max, w_low = signal.levels(drive)
        n_timeout, n_tail, never = signal.n_timeout(drive), signal.n_tail(drive), torch.iinfo(torch.int32).max
        # tables by section state: none before I (0), I..VI, the tail (7), done (8)
        self._levels = torch.tensor([0.0, *(v * M_star for v in SECTION_LEVELS), 0.0, 0.0], dtype=dtype)
        self._table = torch.clamp(self._levels, -drive.M_max, drive.M_max)  # the reference (plain)
        # the speed test as one compare, sgn w >= thr (sgn = +-1: exact): I w >= w_max, II w <= w_low,
        # III w <= 0, IV w <= -w_max, V w >= -w_low, VI w >= 0; none outside I..VI (NaN: never true)
        w = tuple(torch.tensor(v, dtype=dtype).item() for v in (w_max, w_low))  # rounded to dtype
        self._sgn = torch.tensor([1, 1, -1, -1, -1, 1, 1, 1, 1], dtype=dtype)
        self._thr = torch.tensor([math.nan, w[0], -w[1], -0.0, w[0], -w[1], 0.0, math.nan, math.nan], dtype=dtype)
        # the sample counts that end a section by time when it starts (II and V: the count at the
        # end of I and IV, by system) or time it out
        self._ends = torch.tensor([never] * 7 + [n_tail, never], dtype=torch.int32)
        self._by_count = torch.tensor([False, False, True, False, False, True, False, False, False])
        self._n_timeout = torch.tensor([never, *[n_timeout] * 6, never, never], dtype=torch.int32)
        self._bit = torch.tensor([0, 1, 2, 4, 8, 16, 32, 0, 0], dtype=torch.int32)  # timed-out flag of I..VI
        self._label = torch.tensor([0, 1, 2, 3, 4, 5, 6, 0, 8], dtype=torch.int8)  # the tail is labelled 0
        self.reset(())

    def reset(self, batch_shape: tuple[int, ...] | torch.Size) -> None:
        shape = tuple(batch_shape)
        self.sec = torch.ones(shape, dtype=torch.int32)
        self.cnt = torch.zeros(shape, dtype=torch.int32)
        self.limit = torch.full(shape, torch.iinfo(torch.int32).max, dtype=torch.int32)
        self.length = torch.zeros(shape, dtype=torch.int32)
        self.tmo = torch.zeros(shape, dtype=torch.int32)

    def label(self) -> torch.Tensor:
        """Section label (0 tail, 1..6) of the reference applied now; int8 ``*batch``."""
        return self._look(self._label, self.sec)

    @staticmethod
    def _look(table: torch.Tensor, q: torch.Tensor) -> torch.Tensor:
        """``table[q]`` by ``index_select`` (advanced indexing costs five times more), shape of ``q``."""
        return table.index_select(0, q.reshape(-1)).view(q.shape)

    def finished(self) -> torch.Tensor:
        return self.sec >= 8

    @property
    def timed_out(self) -> torch.Tensor:
        bits = torch.arange(6, dtype=torch.int32)
        return ((self.tmo.unsqueeze(-1) >> bits) & 1).bool()

    def step(self, k: int, w_meas: torch.Tensor) -> torch.Tensor:
        """Sample ``k``'s decision from the measured speed ``w_meas`` (``*batch``): the reference
        from sample ``k+1`` on. Table lookups by section state, so that every rule is one op for all
        sections."""
        w = w_meas.to(self.dtype)
        q, t, at = self.sec, self.cnt + 1, self._look
        active = q < 8
        end = (w * at(self._sgn, q) >= at(self._thr, q)) | (t >= self.limit)
        tmo = (t >= at(self._n_timeout, q)) & ~end
        self.tmo = self.tmo | at(self._bit, q) * tmo
        end = (end | tmo) & active
        self.cnt = (self.cnt + active) * ~end
        self.sec = q = q + end  # the section from the next sample on
        self.length = torch.where(end & (q == 8), k + 1, self.length)
        self.limit = torch.where(end, torch.where(at(self._by_count, q), t, at(self._ends, q)), self.limit)
        if self.M_hold is None:
            return at(self._table, q)
        return torch.clamp(at(self._levels, q) + self.M_hold, -self.drive.M_max, self.drive.M_max)
