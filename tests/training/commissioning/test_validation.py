"""Validation by re-simulation: wrong models are flagged."""

from __future__ import annotations

import math

import pytest

sim = pytest.importorskip("sim")
HAVE_SIM = all(hasattr(sim, n) for n in ("simulate", "simulate_test", "TwoMassParams", "TestSignalConfig", "DriveConfig"))
needs_sim = pytest.mark.skipif(not HAVE_SIM, reason="sim.simulate / simulate_test not available yet")

TRUE = dict(J_sigma=0.05, V_J=1.0, f_e=30.0, d=0.03, backlash=0.0, M_FC=0.2, mu_F=0.001)


@pytest.fixture(scope="module")
def record():
    drive = sim.DriveConfig()
    signal = sim.TestSignalConfig(M_star=10.0, w_max=20.0)
    return drive, signal, sim.simulate_test(sim.TwoMassParams.from_dicts(TRUE), drive, signal, seed=1)


@needs_sim
@pytest.mark.parametrize(
    "model, ok",
    [(TRUE, True), ({**TRUE, "f_e": 60.0}, False), ({**TRUE, "f_e": 15.0}, False),
     ({**TRUE, "J_sigma": 0.075}, False), ({"J_sigma": 0.05, "M_FC": 0.2, "mu_F": 0.001}, False)],
    ids=["true", "f_e_x2", "f_e_half", "J_plus_50pct", "stiff_for_elastic"],
)
def test_switching_resimulation_flags_wrong_models(record, model, ok):
    from training.commissioning import validate_model

    drive, signal, rec = record
    res = validate_model(model, drive, rec, mode="switching", signal=signal)
    assert res.passed is ok, res.reason
    if ok:
        assert res.nrmse <= 0.02 and (res.osc_nrmse is None or res.osc_nrmse <= 0.1)


@needs_sim
def test_replay_of_recorded_torque_flags_wrong_inertia():
    from training.commissioning import validate_model

    drive = sim.DriveConfig()
    signal = sim.TestSignalConfig(M_star=10.0, w_max=4.0)
    rec = sim.simulate_test(sim.TwoMassParams.from_dicts(TRUE), drive, signal, seed=2)
    good = validate_model(sim.TwoMassParams.from_dicts(TRUE), drive, rec, mode="replay")
    bad = validate_model({**TRUE, "J_sigma": 0.075}, drive, rec, mode="replay")
    assert good.passed and good.nrmse < 0.02
    assert not bad.passed and bad.nrmse > 0.1 and math.isfinite(bad.nrmse)
    with pytest.raises(ValueError):
        validate_model(TRUE, drive, rec, mode="guess")


@needs_sim
def test_validation_from_a_record_uses_its_meta(record):
    from training.commissioning import validate_model

    drive, signal, resp = record
    rec = sim.responses_to_records(resp, sim.TwoMassParams.from_dicts(TRUE).reshape(1), drive, signal)[0]
    assert validate_model(TRUE, drive, rec, mode="switching").passed
    assert not validate_model({**TRUE, "f_e": 60.0}, drive, rec, mode="switching").passed
