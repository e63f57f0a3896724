"""The bench's independent plant keeps SPEC 8.1's timing: a torque reference computed at sample k
acts from k+1, as the chain's models (``LinearPlant``) and ``sim.SimulatedDrive`` assume. The same
speed loop run on both drives gives the same measured speed over the first step's rise to a speed
quantum or two (two integrators apart); a plant that applied the torque one sample early leads it
by one sample, about 0.1 rad/s (4 quanta) there."""

from __future__ import annotations

import numpy as np
import pytest

sim = pytest.importorskip("sim")

from training.bench._remote_plant import CONFIG, make_drive  # noqa: E402
from training.commissioning import PISpeedLaw  # noqa: E402

PLANT = dict(J_sigma=0.05, V_J=1.0, f_e=300.0, d=0.05, s_N=0.0, M_FC=0.0, mu_F=0.0)


def _speed(drive, n: int = 800) -> np.ndarray:
    law = PISpeedLaw(40.0, 0.02, T_s=CONFIG["T_s"], M_max=CONFIG["M_max"])
    w_ref = np.where(np.arange(n) < n // 2, 2.0, -2.0)
    rec = drive.run_closed_loop(law, sim.Scenario(w_ref, np.zeros(n)), sim.DriveLimits(w_max=50.0, travel=50.0))
    return np.asarray(rec.speed, dtype=np.float64)


def test_the_remote_plant_applies_a_torque_from_the_next_sample():
    params = {**PLANT, "backlash": 0.0}
    config = sim.DriveConfig(**{k: CONFIG[k] for k in ("T_s", "K_M", "T_Ei", "encoder_counts", "M_N", "M_max")})
    reference = _speed(sim.SimulatedDrive({k: params[k] for k in sim.PARAM_NAMES}, config))
    remote = make_drive(params)
    try:
        measured = _speed(remote)
    finally:
        remote.close()
    q_w = sim.speed_quantum(float(CONFIG["encoder_counts"]), CONFIG["T_s"])
    rise = slice(0, 30)
    assert np.abs(measured[rise] - reference[rise]).max() <= 2.5 * q_w
    assert np.abs(measured[rise][1:] - reference[rise][:-1]).max() > 3 * q_w  # one sample apart is told apart
