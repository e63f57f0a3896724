"""Real axes (SPEC 1.1): a held vertical axis and motor friction are identified, not absorbed."""

from __future__ import annotations

import math

import numpy as np
import pytest

from sim import DriveConfig, TestSignalConfig, TwoMassParams, iter_records
from training.identification import Identifier, analyze
from training.identification._analysis import around_hold

ELASTIC = dict(J_sigma=0.05, V_J=1.0, f_e=30.0, d=0.02, backlash=0.0, mu_F=0.001)
M_STAR = TestSignalConfig().M_star


def _answer(plant: dict[str, float], around_hold: bool = True, signal: TestSignalConfig | None = None):
    record = next(iter(iter_records(TwoMassParams.from_dicts([plant]), signal=signal, seed=3,
                                    around_hold=around_hold)))
    return record, Identifier.load().identify(record)


@pytest.mark.parametrize("held", [True, False], ids=["levels around the hold", "plain levels"])
def test_a_held_vertical_axis_is_answered_with_its_class_and_load_torque(held):
    record, answer = _answer({**ELASTIC, "M_FC": 0.2, "M_L0": 0.1 * M_STAR}, around_hold=held)
    assert ("M_hold" in record.meta) == held
    assert answer.structure == "elastic"
    assert answer.parameters.f_e == pytest.approx(30.0, rel=0.05)
    assert answer.parameters.J_sigma == pytest.approx(0.05, rel=0.02)
    assert answer.parameters.M_L0 == pytest.approx(0.1 * M_STAR, abs=0.01 * M_STAR)
    low, high = answer.intervals["M_L0"]
    assert low <= 0.1 * M_STAR <= high


def test_motor_friction_is_reported_as_the_motors_not_the_loads():
    _, answer = _answer({**ELASTIC, "M_FC": 0.1, "M_FCM": 0.2})
    assert answer.structure == "elastic"
    assert answer.parameters.M_FCM == pytest.approx(0.2, abs=0.01 * M_STAR)
    assert answer.parameters.M_FC == pytest.approx(0.1, abs=0.01 * M_STAR)


#: Stiff shafts with a gap, with the motor's viscous friction (and on the first its Coulomb friction):
#: refined with all friction on the load, both were answered without their gap (0.4 and 7.5 % of it).
GAP_AXES = {"both frictions": dict(J_sigma=0.0466, V_J=1.29, f_e=302.6, d=0.073, backlash=0.00078, M_FC=0.142,
                                   mu_F=0.0003, M_FCM=0.141, mu_FM=0.0012),
            "viscous only": dict(J_sigma=0.0467, V_J=3.70, f_e=199.1, d=0.057, backlash=0.00331, M_FC=0.199,
                                 mu_F=0.00015, M_FCM=0.0, mu_FM=0.00085)}


@pytest.mark.parametrize("plant", GAP_AXES.values(), ids=GAP_AXES)
def test_a_gap_is_found_where_the_motor_has_friction_of_its_own(plant):
    _, answer = _answer(plant)
    assert answer.structure == "stiff_backlash"
    assert answer.parameters.backlash == pytest.approx(plant["backlash"], rel=0.3)
    assert answer.parameters.M_FCM == pytest.approx(plant["M_FCM"], abs=0.01 * M_STAR)
    assert answer.parameters.mu_FM > 0.0  # the motor's viscous share, reported


def test_an_axis_without_real_axis_parts_reports_none_of_them():
    _, answer = _answer({**ELASTIC, "M_FC": 0.2})
    assert answer.parameters.M_L0 == pytest.approx(0.0, abs=0.002 * M_STAR)
    assert answer.parameters.M_FCM == 0.0
    assert answer.parameters.mu_FM is None
    assert set(answer.to_dict()["parameters"]) >= {"M_L0", "M_FCM", "mu_FM"}


def test_a_hold_larger_than_the_test_torque_still_shows_the_sections():
    """A small test (M* 2 Nm) around a hold of 3 Nm: the levels run from 1 to 5 Nm, never through 0."""
    signal = TestSignalConfig(M_star=2.0, w_max=30.0)
    record, answer = _answer({**ELASTIC, "J_sigma": 0.01, "M_FC": 0.05, "M_L0": 3.0}, signal=signal)
    assert record.meta["M_hold"] == pytest.approx(3.0)
    assert answer.ok and answer.parameters.M_L0 == pytest.approx(3.0, abs=0.02)
    assert analyze(record).sections.M_star == pytest.approx(2.0, rel=0.01)


def test_the_analysis_reads_a_held_record_around_its_hold():
    record = next(iter(iter_records(TwoMassParams.from_dicts([{**ELASTIC, "M_FC": 0.2, "M_L0": 1.5}]), seed=0)))
    view = around_hold(record)
    K_M = record.meta["K_M"]
    np.testing.assert_allclose(view.current, record.current - 1.5 / K_M)
    assert view.meta is record.meta  # M_hold stays: the analysis adds it back to STEP 2's offset
    plain = next(iter(iter_records(TwoMassParams.from_dicts([{**ELASTIC, "M_FC": 0.2}]), seed=0)))
    assert around_hold(plain) is plain
    assert math.isclose(analyze(record).M_L0, 1.5, abs_tol=0.02)


def test_drive_config_is_untouched_by_a_hold():
    """The hold is the record's, not the drive's: the same drive runs held and plain axes."""
    assert not hasattr(DriveConfig(), "M_hold")
