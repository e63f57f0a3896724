"""Settings and plants shared by the chain's end-to-end tests (not a test module)."""

from __future__ import annotations

import pytest

import sim
from training.commissioning import CommissioningConfig

#: A short chain: few tuning evaluations, short closed-loop experiments, no frequency-response experiment.
FAST = CommissioningConfig(tune_evaluations=6, max_samples=1200, measure_response=False)
LIMITS = sim.DriveLimits(w_max=20.0, travel=5.0)
STIFF = dict(J_sigma=0.05, V_J=0.5, f_e=400.0, d=0.05, backlash=0.0, M_FC=0.1, mu_F=0.001)
ONE_MASS = {"J_sigma": 0.05, "M_FC": 0.1, "mu_F": 0.001, "V_J": None, "f_e": None, "d": None, "backlash": 0.0}


def shipped_identifier():
    """The shipped maps; skip (with the reason) while they do not match the toolkit's features."""
    from som_torch import CheckpointError
    from training.identification import Identifier

    try:
        return Identifier.load()
    except CheckpointError as err:
        pytest.skip(f"shipped maps not loadable: {err}")
