"""The rest check before the first test run (SPEC 1.1): does the drive hold the axis?

A vertical or unbalanced axis carries a constant load torque ``M_L0``; the drive holds it at rest
with its holding torque ``M_hold`` (ideally ``M_L0``) and runs every experiment around it. The
switching test starts moving at its first sample, so its record shows no time at rest; the chain
therefore asks the drive for one short closed-loop experiment first: the speed loop off
(:class:`training.commissioning._law.HoldLaw`, torque reference 0, so the drive's holding torque
acts alone), reference and disturbance 0, :attr:`RestSettings.duration` long. An axis that drifts
there (its encoder travel beyond :attr:`RestSettings.drift_counts` counts, or a measured speed
beyond :attr:`RestSettings.speed_quanta` speed quanta) is not held: the chain raises
:class:`training.errors.AxisNotHeld` (one line naming the drift) and runs no test. A horizontal
axis (no load torque, no hold) rests too and passes.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

import sim
from training._settings import POSITIVE, check_settings
from training.errors import AxisNotHeld, LimitPassed

from ._law import HoldLaw

__all__ = ["RestSettings", "REST_SETTINGS", "RestCheck", "rest_figures", "check_rest"]


@dataclass(frozen=True)
class RestSettings:
    """The rest check's length and its drift bounds."""

    duration: float = 0.05
    """How long the drive holds the axis with the speed loop off [s]."""
    drift_counts: float = 4.0
    """The largest travel of a held axis [encoder counts] (an encoder's jitter is a count or two)."""
    speed_quanta: float = 3.0
    """The largest measured speed of a held axis [speed quanta ``q_w``]."""

    def __post_init__(self) -> None:
        check_settings(self, {"duration": POSITIVE, "drift_counts": POSITIVE, "speed_quanta": POSITIVE})


REST_SETTINGS = RestSettings()


@dataclass(frozen=True)
class RestCheck:
    """What the rest check measured: ``duration`` [s], ``drift`` [rad] (the largest ``|phi|`` of the
    integrated measured speed), ``peak_speed`` [rad/s], the bounds they were held against
    (``max_drift`` [rad], ``max_speed`` [rad/s]) and whether the axis was held (``held``)."""

    duration: float
    drift: float
    peak_speed: float
    max_drift: float
    max_speed: float

    @property
    def held(self) -> bool:
        return self.drift <= self.max_drift and self.peak_speed <= self.max_speed

    def text(self) -> str:
        """One line: held, or the drift and what to do."""
        if self.held:
            return (f"the drive holds the axis at rest: {self.drift:.3g} rad, peak {self.peak_speed:.3g} rad/s in "
                    f"{self.duration:.3g} s with the speed loop off")
        return (f"the drive does not hold the axis at rest: it drifted {self.drift:.3g} rad (peak speed {self.peak_speed:.3g} "
                f"rad/s) in {self.duration:.3g} s before the test; release the brake only with the holding torque on / set "
                f"M_hold (the axis's constant load torque, SPEC 1.1)")

    def to_dict(self) -> dict[str, Any]:
        return {"duration": self.duration, "drift": self.drift, "peak_speed": self.peak_speed, "max_drift": self.max_drift,
                "max_speed": self.max_speed, "held": self.held}


def rest_figures(speed: np.ndarray, config: Any, duration: float, settings: RestSettings = REST_SETTINGS) -> RestCheck:
    """The :class:`RestCheck` of the measured speed ``N`` [rad/s] of a rest check on the drive
    ``config`` (``T_s``, ``encoder_counts``)."""
    w = np.asarray(speed, dtype=np.float64).reshape(-1)
    T_s, counts = float(config.T_s), float(config.encoder_counts)
    phi = np.cumsum(w) * T_s
    drift = float(np.abs(phi).max()) if w.size else 0.0
    peak = float(np.abs(w).max()) if w.size else 0.0
    return RestCheck(duration=duration, drift=drift if math.isfinite(drift) else math.inf,
                     peak_speed=peak if math.isfinite(peak) else math.inf,
                     max_drift=settings.drift_counts * 2 * math.pi / counts,
                     max_speed=settings.speed_quanta * sim.speed_quantum(counts, T_s))


def check_rest(drive: Any, config: Any, limits: sim.DriveLimits, settings: RestSettings = REST_SETTINGS) -> RestCheck:
    """The rest check on ``drive`` (a :class:`training.commissioning._guard.CheckedDrive`: its
    ``run_closed_loop(law, scenario, limits, kind)``); raises :class:`AxisNotHeld` where the axis
    drifted, or passed one of ``limits`` while it should have rested."""
    n = max(2, round(settings.duration / float(config.T_s)))
    zeros = np.zeros(n)
    duration = n * float(config.T_s)
    try:
        rec = drive.run_closed_loop(HoldLaw(), sim.Scenario(zeros, zeros), limits, "rest check")
    except LimitPassed as passed:
        if getattr(drive, "breach", None) is None:  # not the guard's: the drive raised it
            raise
        rec = drive.experiments[-1][1]
        found = rest_figures(rec.speed, config, duration, settings)
        raise AxisNotHeld(f"{found.text()}; it passed a limit: {passed}", found.drift, duration, found.peak_speed) from None
    found = rest_figures(rec.speed, config, duration, settings)
    if not found.held:
        raise AxisNotHeld(found.text(), found.drift, duration, found.peak_speed)
    return found
