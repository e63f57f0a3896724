"""Validation by re-simulation (wrong models are flagged) and the knowledge-base refusal rules."""

from __future__ import annotations

import math

import pytest

from training.commissioning._validation import may_propose_controller

GOOD = {
    "structure": "elastic",
    "parameters": {"J_sigma": 0.05, "V_J": 1.0, "f_e": 30.0, "d": 0.03},
    "quality": {"validation_error": 0.03, "outside_training": False},
    "warnings": ["d poorly identified"],
}


def test_good_result_may_get_a_controller():
    perm = may_propose_controller(GOOD)
    assert perm and perm.allowed and perm.notes == ("d poorly identified",)


@pytest.mark.parametrize(
    "change, rule",
    [
        ({"structure": "wobbly"}, "V1"),
        ({"error": "no sections found"}, "V1"),
        ({"parameters": {"J_sigma": 0.05, "V_J": 1.0, "f_e": None}}, "V2"),
        ({"parameters": {"J_sigma": -0.05}}, "V2"),
        ({"quality": {"validation_error": 0.4, "outside_training": False}}, "V3"),
        ({"quality": {"outside_training": False}}, "V3"),
        ({"quality": {"validation_error": float("nan")}}, "V3"),
        ({"quality": {"validation_error": 0.02, "outside_training": True}}, "V4"),
        ({"warnings": ["section IV timed out"]}, "V6"),
    ],
)
def test_refusals_name_the_rule(change, rule):
    perm = may_propose_controller({**GOOD, **change})
    assert not perm and perm.reason.startswith(rule)


def test_stiff_needs_only_J_sigma_and_type_check():
    assert may_propose_controller({**GOOD, "structure": "stiff", "parameters": {"J_sigma": 0.05, "f_e": None}}).allowed
    with pytest.raises(TypeError):
        may_propose_controller(["not", "a", "dict"])


# --------------------------------------------------------------------------- re-simulation

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
    from training.commissioning._validation import validate_model

    drive, signal, rec = record
    res = validate_model(model, drive, rec, mode="switching", signal=signal)
    assert res.passed is ok, res.reason
    if ok:
        assert res.nrmse <= 0.02 and (res.osc_nrmse is None or res.osc_nrmse <= 0.1)


@needs_sim
def test_replay_of_recorded_torque_flags_wrong_inertia():
    from training.commissioning._validation import validate_model

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
    from training.commissioning._validation import validate_model

    drive, signal, resp = record
    rec = sim.responses_to_records(resp, sim.TwoMassParams.from_dicts(TRUE).reshape(1), drive, signal)[0]
    assert validate_model(TRUE, drive, rec, mode="switching").passed
    assert not validate_model({**TRUE, "f_e": 60.0}, drive, rec, mode="switching").passed
