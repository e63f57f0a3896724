"""Drives that break what the chain assumes, for ``twomass commission --drive`` and the tests:
a closed loop with 50 times the law's torque (a limit cycle at the torque cap), a reversed speed
sign, methods that raise, exit or hang, drives that pass the user's limits, and records that are
cut, malformed or sampled otherwise than the drive's config says."""

from __future__ import annotations

import dataclasses
import sys
import threading
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


# --------------------------------------------------------------------------- drives that pass the user's limits


class TorqueScaleDrive(sim.SimulatedDrive):
    """Applies ``scale`` times the torque asked for (up to its own M_max) and records the torque
    reference it was asked for: the measured current shows what it did."""

    scale = 8.0

    def run_test(self, M_star: float, w_max: float, limits: sim.DriveLimits) -> sim.Record:
        own = sim.DriveLimits(w_max=limits.w_max, travel=limits.travel)
        rec = super().run_test(min(self.scale * M_star, self.config.M_max), w_max, own)
        rec.torque_ref = rec.torque_ref / self.scale
        rec.meta["M_star"] = M_star
        return rec


class SpeedRunawayDrive(sim.SimulatedDrive):
    """Ignores the limits and runs its test to ``over`` times the asked ``w_max``."""

    over = 15.0

    def run_test(self, M_star: float, w_max: float, limits: sim.DriveLimits) -> sim.Record:
        rec = super().run_test(M_star, self.over * w_max, sim.DriveLimits(w_max=1e9, travel=1e9, M_max=limits.M_max))
        rec.meta["w_max"] = w_max
        return rec


class LoopRunawayDrive(sim.SimulatedDrive):
    """Test runs and the rest check (the law ``{"type": "hold"}``) as asked; its speed-loop closed
    loops ignore the limits and follow 100 times the speed reference. ``calls``: every experiment
    it ran, in order (``rest``, ``test``, ``closed_loop``)."""

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self.calls: list[str] = []

    def run_test(self, M_star: float, w_max: float, limits: sim.DriveLimits) -> sim.Record:
        self.calls.append("test")
        return super().run_test(M_star, w_max, limits)

    def run_closed_loop(self, law: Any, scenario: sim.Scenario, limits: sim.DriveLimits) -> sim.Record:
        if law.params.get("type") == "hold":
            self.calls.append("rest")
            return super().run_closed_loop(law, scenario, limits)
        self.calls.append("closed_loop")
        fast = sim.Scenario(100.0 * scenario.w_ref, scenario.M_dist)
        return super().run_closed_loop(law, fast, sim.DriveLimits(w_max=1e9, travel=1e9, M_max=limits.M_max))


class Spec81Drive(sim.SimulatedDrive):
    """Written from SPEC 8.1: reads ``limits.M_max`` [Nm] as a number; keeps the limits it was handed."""

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self.handed: list[sim.DriveLimits] = []

    def run_test(self, M_star: float, w_max: float, limits: sim.DriveLimits) -> sim.Record:
        self.handed.append(limits)
        if not M_star <= float(limits.M_max):
            raise ValueError(f"M_star {M_star} above the torque limit {limits.M_max}")
        return super().run_test(M_star, w_max, limits)

    def run_closed_loop(self, law: Any, scenario: sim.Scenario, limits: sim.DriveLimits) -> sim.Record:
        self.handed.append(limits)
        float(limits.M_max)
        return super().run_closed_loop(law, scenario, limits)


# --------------------------------------------------------------------------- drives that break the interface

#: Released at the end of a test: :class:`HangingDrive`'s calls wait on it.
RELEASE = threading.Event()


class HangingDrive(sim.SimulatedDrive):
    """``run_test`` does not answer (it waits up to an hour, or until :data:`RELEASE` is set)."""

    def run_test(self, M_star: float, w_max: float, limits: sim.DriveLimits) -> sim.Record:
        RELEASE.wait(3600.0)
        return super().run_test(M_star, w_max, limits)


class ExitingDrive(sim.SimulatedDrive):
    """``run_test`` calls ``sys.exit(7)`` (a bug in a drive's own error handling)."""

    def run_test(self, M_star: float, w_max: float, limits: sim.DriveLimits) -> sim.Record:
        sys.exit(7)


class CutLoopDrive(sim.SimulatedDrive):
    """Its closed-loop record is cut to 300 samples, without a stop flagged."""

    def run_closed_loop(self, law: Any, scenario: sim.Scenario, limits: sim.DriveLimits) -> sim.Record:
        rec = super().run_closed_loop(law, scenario, limits)
        for c in ("t", "speed", "current", "torque_ref"):
            setattr(rec, c, getattr(rec, c)[:300])
        return rec


class LongLoopDrive(sim.SimulatedDrive):
    """Its closed-loop record is the scenario's and 300 samples more, flagged as stopped."""

    def run_closed_loop(self, law: Any, scenario: sim.Scenario, limits: sim.DriveLimits) -> sim.Record:
        rec = super().run_closed_loop(law, scenario, limits)
        T_s = rec.T_s
        for c in ("speed", "current", "torque_ref"):
            setattr(rec, c, np.concatenate([getattr(rec, c), np.zeros(300)]))
        rec.t = rec.t[0] + T_s * np.arange(len(rec.speed))
        rec.meta["aborted"] = True
        return rec


class WrongTsDrive(sim.SimulatedDrive):
    """Samples at 250 us (the simulator's config) while the ``config`` it shows says 125 us."""

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self.sampled, self.config = self.config, dataclasses.replace(self.config, T_s=1.25e-4)

    def run_test(self, M_star: float, w_max: float, limits: sim.DriveLimits) -> sim.Record:
        shown, self.config = self.config, self.sampled
        try:
            return super().run_test(M_star, w_max, limits)
        finally:
            self.config = shown


class MetaDrive(sim.SimulatedDrive):
    """Its test records carry ``meta`` (set on the instance) over the simulator's; counts its test runs."""

    meta: dict = {}

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self.tests = 0

    def run_test(self, M_star: float, w_max: float, limits: sim.DriveLimits) -> sim.Record:
        self.tests += 1
        rec = super().run_test(M_star, w_max, limits)
        rec.meta.update({k: (v(rec.meta) if callable(v) else v) for k, v in self.meta.items()})
        return rec


def torque8(params: dict | None = None) -> TorqueScaleDrive:
    return TorqueScaleDrive(params or PLANT)


def speed_runaway(params: dict | None = None) -> SpeedRunawayDrive:
    return SpeedRunawayDrive(params or PLANT)


def hanging(params: dict | None = None) -> HangingDrive:
    return HangingDrive(params or PLANT)


def exiting(params: dict | None = None) -> ExitingDrive:
    return ExitingDrive(params or PLANT)
