"""Drives that break what the chain assumes, for ``twomass commission --drive`` and the tests:
a closed loop with 50 times the law's torque (a limit cycle at the torque cap), a reversed speed
sign, and methods that raise."""

from __future__ import annotations

from typing import Any

import numpy as np

import sim

PLANT = dict(J_sigma=0.05, V_J=1.0, f_e=30.0, d=0.03, backlash=0.0, M_FC=0.2, mu_F=0.001)


class _Gained:
    """The law with its torque reference multiplied by ``gain`` and clamped at ``cap``."""

    def __init__(self, law: Any, gain: float, cap: float) -> None:
        self.law, self.gain, self.cap, self.params = law, gain, cap, law.params

    def reset(self) -> None:
        self.law.reset()

    def step(self, w_meas: Any, w_ref: Any) -> Any:
        return np.clip(self.gain * np.asarray(self.law.step(w_meas, w_ref)), -self.cap, self.cap)


class GainDrive(sim.SimulatedDrive):
    """A simulated drive whose own speed loop applies ``gain`` times the law's torque."""

    gain = 50.0

    def run_closed_loop(self, law: Any, scenario: sim.Scenario, limits: sim.DriveLimits) -> sim.Record:
        return super().run_closed_loop(_Gained(law, self.gain, limits.torque_cap(self.config)), scenario, limits)


class ReversedDrive(sim.SimulatedDrive):
    """A simulated drive whose encoder counts the other way: the speed moves against the torque."""

    def run_test(self, M_star: float, w_max: float, limits: sim.DriveLimits) -> sim.Record:
        rec = super().run_test(M_star, w_max, limits)
        rec.speed = -rec.speed
        return rec


class RaisingDrive(sim.SimulatedDrive):
    def run_test(self, M_star: float, w_max: float, limits: sim.DriveLimits) -> sim.Record:
        raise RuntimeError("hardware fault E42")


def gain50(params: dict | None = None) -> GainDrive:
    return GainDrive(params or PLANT)


def reversed_sign(params: dict | None = None) -> ReversedDrive:
    return ReversedDrive(params or PLANT)


def raising(params: dict | None = None) -> RaisingDrive:
    return RaisingDrive(params or PLANT)


def factory_raises(params: dict | None = None) -> Any:
    raise OSError("cannot open /dev/ttyUSB0")
