"""Shared test fixtures: where ``../shared`` lies (skip with a message when it is absent)."""

from __future__ import annotations

import math
import os
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
SHARED = Path(os.environ.get("TWOMASS_SHARED", REPO.parent / "shared"))


@pytest.fixture(scope="session")
def shared_dir() -> Path:
    if not SHARED.is_dir():
        pytest.skip(f"../shared not found at {SHARED} (set TWOMASS_SHARED to its path)")
    return SHARED


@pytest.fixture(scope="session")
def good():
    """One simulated test run of a plain elastic plant (reference drive), as a ``sim.Record``."""
    from sim import DriveConfig, TestSignalConfig, TwoMassParams, responses_to_records, simulate_test

    drive, signal = DriveConfig(), TestSignalConfig()
    params = TwoMassParams(J_sigma=0.02, V_J=1.0, f_e=30.0, d=0.02, backlash=math.radians(0.1), M_FC=0.2, mu_F=0.001)
    resp = simulate_test(params, drive, signal, seed=0)
    return responses_to_records(resp, params.reshape(1), drive, signal, names=["good"])[0]
