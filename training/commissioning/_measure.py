"""The frequency-response experiment on the drive's running loop (:mod:`._frf`): planned on the
identified model's closed loop inside the limits handed to the drive, and its record turned into a
:class:`MeasuredResponse` beside the model's response."""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import scipy.signal

import sim

from ._frf import FRF_SETTINGS, FRFPlan, FRFSettings, MeasuredResponse, estimate_response, excited_lines, find_resonances, multisine
from ._law import NotchSpec
from ._loop import LinearPlant, closed_loop_matrices, linear_plant

__all__ = ["plan_frf", "measured_response"]


def _closed_loop_peaks(plant: LinearPlant, gains: tuple[float, float, float], notch: NotchSpec | None,
                       d: np.ndarray) -> dict[str, float]:
    """The identified model's closed loop (zero reference) under the disturbance ``d``: peaks of the
    motor and load speed, their travel, and the commanded torque."""
    A, _, b_d, c, c_L = closed_loop_matrices(plant, *gains, notch)
    n = plant.Ad.shape[0]
    u_row = np.zeros(A.shape[0])
    u_row[n] = 1.0  # the torque applied over the sample: the commanded one of the sample before, incl. d
    C = np.stack([c, c_L, u_row])
    _, y, _ = scipy.signal.dlsim((A, b_d[:, None], C, np.zeros((3, 1)), plant.T_s), d)
    travel = np.abs(np.cumsum(y[:, :2], axis=0) * plant.T_s).max(axis=0)
    return {"peak_speed": float(np.abs(y[:, :2]).max()), "travel": float(travel.max()), "peak_torque": float(np.abs(y[:, 2]).max())}


def plan_frf(mech: Any, config: Any, gains: tuple[float, float, float], notch: NotchSpec | None, limits: sim.DriveLimits,
             settings: FRFSettings = FRF_SETTINGS) -> FRFPlan:
    """The experiment for the law ``gains`` (+ ``notch``) on the identified mechanics ``mech``: the
    largest multisine amplitude for which the model's closed loop keeps the motor and load speed and
    travel within ``settings.limit_share`` of ``limits`` (those handed to the drive) and the
    commanded torque within ``settings.torque_share`` of the torque cap. One sample more than the
    periods: the torque commanded at the last sample is recorded at the next one."""
    plant = linear_plant(mech, config)
    lines = excited_lines(settings.period, settings.lines_per_decade)
    unit = np.tile(multisine(settings.period, lines), settings.periods)
    unit = np.concatenate([unit, [0.0]])
    peaks = _closed_loop_peaks(plant, gains, notch, unit)
    share = settings.limit_share
    amplitude = min(share * limits.w_max / peaks["peak_speed"], share * limits.travel / peaks["travel"],
                    settings.torque_share * limits.torque_cap(config) / peaks["peak_torque"])
    if not (math.isfinite(amplitude) and amplitude > 0):
        raise ValueError(f"frequency-response experiment: the model predicts no bounded response (amplitude {amplitude})")
    scenario = sim.Scenario(w_ref=np.zeros(len(unit)), M_dist=amplitude * unit)
    return FRFPlan(scenario, lines, settings.period, float(amplitude), {k: amplitude * v for k, v in peaks.items()})


def measured_response(record: sim.Record, plan: FRFPlan, mech: Any, config: Any,
                      settings: FRFSettings = FRF_SETTINGS) -> MeasuredResponse:
    """The :class:`MeasuredResponse` of a complete record of ``plan``, beside the identified model ``mech``."""
    T_s = float(config.T_s)
    w, G, coherence = estimate_response(record, plan, T_s, sim.speed_quantum(float(config.encoder_counts), T_s))
    model = linear_plant(mech, config).speed_response(np.exp(1j * w * T_s))
    return MeasuredResponse(w=w, G=G, coherence=coherence, T_s=T_s, model=model,
                            resonances=find_resonances(w, G, coherence, model, settings), amplitude=plan.amplitude)
