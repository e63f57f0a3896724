"""A refinement problem from a simulated switching test of a known plant (shared by the refinement
and polish tests)."""

import numpy as np

from sim import DriveConfig, TestSignalConfig, TwoMassParams, responses_to_records, simulate_test
from training.identification._analysis import analyze
from training.identification._refine import RefineProblem, torque_reference

DRIVE = DriveConfig()
SIGNAL = TestSignalConfig(w_max=40.0)


def refine_problem(true: TwoMassParams, theta: np.ndarray, drive: DriveConfig = DRIVE,
                   signal: TestSignalConfig = SIGNAL) -> RefineProblem:
    """The record of ``true`` on ``drive`` under ``signal`` as STEP 2 sees it, started at ``theta``."""
    rec = responses_to_records(simulate_test(true, drive, signal, seed=1), true.reshape(1), drive, signal)[0]
    a = analyze(rec)
    b = a.sections.bounds
    start, level = torque_reference(b, a.M_star)
    return RefineProblem(speed=a.fit.speed, start=start, level=level,
                         segments=np.concatenate([b, [[b[5, 1], len(rec.speed)]]]), J_sigma=a.fit.J_sigma,
                         M_FC=a.fit.M_FC, mu_F=a.fit.mu_F, T_s=drive.T_s, T_Ei=drive.T_Ei,
                         encoder_counts=drive.encoder_counts, M_N=drive.M_N, theta=np.asarray(theta, dtype=np.float64))
