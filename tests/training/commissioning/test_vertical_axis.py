"""SPEC 1.1 in the chain: a vertical axis (constant load torque ``M_L0``) held by the drive is
commissioned like a horizontal one (the validation simulates the identified ``M_L0`` from the held
state; the delivered law's integrator starts at the hold); a drive that does not hold the axis is
reported by the rest check before anything is excited."""

from __future__ import annotations

import json
import math
import sys
from pathlib import Path

import numpy as np
import pytest

sim = pytest.importorskip("sim")

from training.commissioning import HoldLaw, commission, validate_model  # noqa: E402
from training.errors import AxisNotHeld  # noqa: E402

sys.path.insert(0, str(Path(__file__).parent))
from setups import FAST, LIMITS  # noqa: E402

CONFIG = sim.DriveConfig()
ELASTIC = dict(J_sigma=0.05, V_J=1.0, f_e=30.0, d=0.03, backlash=0.0, M_FC=0.2, mu_F=0.001)


class SaggingDrive:
    """A SPEC 8.1 drive around :class:`sim.SimulatedDrive` whose holding torque is wrong: it holds
    with ``M_hold`` (0: no hold) whatever the axis's load torque; it counts the calls it gets."""

    def __init__(self, params: dict, M_hold: float) -> None:
        self.inner = sim.SimulatedDrive(params, CONFIG)
        self.inner.M_hold = float(M_hold)
        self.config = self.inner.config
        self.tests = 0
        self.laws: list = []

    def run_test(self, M_star, w_max, limits):
        self.tests += 1
        return self.inner.run_test(M_star, w_max, limits)

    def run_closed_loop(self, law, scenario, limits):
        self.laws.append(law)
        return self.inner.run_closed_loop(law, scenario, limits)


def test_a_held_vertical_axis_is_validated_and_its_law_starts_at_the_hold(stub):
    M_L0 = 0.1 * CONFIG.M_N
    identified = M_L0 + 0.02  # the identification's estimate, a little off
    ident = stub("elastic", {**ELASTIC, "M_L0": identified})
    rep = commission(sim.SimulatedDrive({**ELASTIC, "M_L0": M_L0}, CONFIG), LIMITS, identifier=ident, config=FAST)
    count = 2 * math.pi / CONFIG.encoder_counts
    assert rep.rest is not None and rep.rest.held and rep.rest.drift <= 2 * count  # the current noise: a count of jitter
    assert rep.validation.passed, rep.validation.reason
    assert rep.permission.allowed and rep.fallback is None and rep.delivered is not None
    M_star = rep.excitation.log[-1]["M_star"]
    assert rep.delivered.M_hold == identified and abs(rep.delivered.M_hold - M_L0) <= 0.05 * M_star
    assert rep.proposal.M_hold == identified
    out = rep.to_dict()
    assert out["delivered"]["M_hold"] == identified and out["rest_check"]["held"] is True
    json.dumps(out, allow_nan=False)
    text = rep.to_text()
    assert f"holding torque M_hold {identified:.4g} Nm" in text and "0 rest check: the drive holds the axis" in text
    assert rep.checks["runs"][0]["kind"] == "rest check" and rep.checks["within_limits"]


def test_the_validation_simulates_the_held_model():
    """The identified model with its M_L0 reproduces a held axis's record; the same model without it
    (what the chain simulated before) does not: the recorded torque includes the hold."""
    M_L0 = 0.1 * CONFIG.M_N
    rec = sim.SimulatedDrive({**ELASTIC, "M_L0": M_L0}, CONFIG).run_test(2.0, 5.0, LIMITS.for_drive(CONFIG))
    assert rec.meta["M_hold"] == M_L0 and rec.torque_ref[0] == M_L0
    held = validate_model({**ELASTIC, "M_L0": M_L0, "M_FCM": None}, CONFIG, rec)
    unheld = validate_model(ELASTIC, CONFIG, rec)
    assert held.passed and held.nrmse < 0.01
    assert not unheld.passed and unheld.nrmse > 0.5


def test_a_drive_that_does_not_hold_the_axis_is_reported_not_excited(stub):
    M_L0 = 0.15 * CONFIG.M_N
    drive = SaggingDrive({**ELASTIC, "M_L0": M_L0}, M_hold=0.0)
    ident = stub("elastic", {**ELASTIC, "M_L0": M_L0})
    with pytest.raises(AxisNotHeld) as err:
        commission(drive, LIMITS, identifier=ident, config=FAST)
    message = str(err.value)
    assert "does not hold the axis at rest" in message and "set M_hold" in message and "\n" not in message
    assert drive.tests == 0 and len(drive.laws) == 1 and isinstance(drive.laws[0], HoldLaw)
    assert ident.records == [] and err.value.code == "axis_not_held"
    # the sag, by hand: the load falls with (M_L0 - M_FC) / J_sigma once the current loop has let go of the hold
    duration = FAST.rest.duration
    expected = 0.5 * (M_L0 - ELASTIC["M_FC"]) / ELASTIC["J_sigma"] * duration**2
    assert err.value.duration == pytest.approx(duration)
    assert err.value.drift == pytest.approx(expected, rel=0.15)
    assert f"drifted {err.value.drift:.3g} rad" in message


def test_a_drive_holding_the_axis_right_passes_the_rest_check():
    """The same wrapper with the right hold: the rest check passes and the test runs around it."""
    M_L0 = 0.15 * CONFIG.M_N
    from training.commissioning._guard import CheckedDrive
    from training.commissioning._rest import check_rest

    for hold, held in ((M_L0, True), (M_L0 - 0.05 * CONFIG.M_N, False)):
        drive = SaggingDrive({**ELASTIC, "M_L0": M_L0}, M_hold=hold)
        checked = CheckedDrive(drive, CONFIG, LIMITS.for_drive(CONFIG), None)
        if held:
            found = check_rest(checked, CONFIG, LIMITS.for_drive(CONFIG))
            assert found.held and found.drift <= 2 * 2 * math.pi / CONFIG.encoder_counts
            assert found.max_drift == pytest.approx(4 * 2 * math.pi / CONFIG.encoder_counts)
        else:  # 0.5 Nm short: more than the load's friction, it sags slowly
            with pytest.raises(AxisNotHeld):
                check_rest(checked, CONFIG, LIMITS.for_drive(CONFIG))
        assert np.all(checked.experiments[0][1].torque_ref[1:] == pytest.approx(hold))


def test_the_real_identifier_commissions_a_held_vertical_axis():
    """End to end with the shipped maps: the held records are identified around their hold, the
    validation passes on the identified M_L0, and the law starts at it."""
    from training.identification import Identifier

    M_L0 = 0.1 * CONFIG.M_N
    rep = commission(sim.SimulatedDrive({**ELASTIC, "M_L0": M_L0}, CONFIG), LIMITS, identifier=Identifier.load(),
                     config=FAST)
    assert rep.identification is not None and rep.identification.structure == "elastic"
    assert rep.validation.passed, rep.validation.reason
    assert rep.delivered is not None and rep.fallback is None
    M_star = rep.excitation.log[-1]["M_star"]
    assert abs(rep.delivered.M_hold - M_L0) <= 0.05 * M_star
