"""The confidence of an answer (SPEC 4.1): class probabilities, the calibration file."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from sim import STRUCTURE_CLASSES
from training.identification._confidence import (FEATURE_NAMES, Calibration, ConfidenceInputs, class_margins,
                                                 rule_probabilities, share_rest)


def test_share_rest_hand_computed() -> None:
    p = share_rest("elastic", 0.7, {"stiff": 0.2, "elastic": 0.9, "elastic_backlash": 0.1, "stiff_backlash": 0.0})
    assert p == pytest.approx({"stiff": 0.2, "elastic": 0.7, "elastic_backlash": 0.1, "stiff_backlash": 0.0})
    assert list(p) == list(STRUCTURE_CLASSES)


def test_share_rest_caps_the_others_at_the_answers_probability() -> None:
    # 0.7 of the rest would go to stiff (0.49 > 0.3): stiff gets 0.3, its excess goes to the others
    p = share_rest("elastic", 0.3, {"stiff": 7.0, "elastic": 0.0, "elastic_backlash": 2.0, "stiff_backlash": 1.0})
    assert sum(p.values()) == pytest.approx(1.0)
    assert p["stiff"] == pytest.approx(0.3) and p["elastic_backlash"] == pytest.approx(0.4 * 2 / 3)
    assert max(p.values()) == pytest.approx(0.3)
    flat = share_rest("stiff", 0.25, {})
    assert flat == pytest.approx(dict.fromkeys(STRUCTURE_CLASSES, 0.25))


def test_class_margins_are_the_nearest_thresholds_log_distances() -> None:
    m = class_margins({"w_e_T_Ei": 2.0, "s_N": 0.12})
    assert m["w_e_T_Ei"] == pytest.approx(math.log(2.0))  # threshold 1
    assert m["s_N"] == pytest.approx(math.log(1.2))  # thresholds 0.1 and 1: the nearer
    assert m["r_osc"] == 3.0  # missing
    assert class_margins({"r_osc": float("nan")})["r_osc"] == 3.0


def _inputs(structure: str, backlash: float, ln_w_e_T_Ei: float, ln_r_osc: float) -> ConfidenceInputs:
    """An answer with the backlash thresholds at 1 and 10 mrad (asinh scale 1 mrad)."""
    rule = {"backlash_low": 1e-3, "backlash_high": 1e-2, "ln_w_e_T_Ei": ln_w_e_T_Ei, "ln_r_osc": ln_r_osc}
    return ConfidenceInputs(np.zeros(len(FEATURE_NAMES)), {"backlash": backlash}, {"backlash": 1e-3}, structure, rule)


def test_the_class_rules_probabilities_hand_computed() -> None:
    half = {"backlash": 0.0, "f_e": 1.6448536269514722 * 0.5, "V_J": 0.0, "J_sigma": 0.0}  # f_e: sd 0.5 in ln
    # no gap for sure, w_e T_Ei one sd below 1 (soft with P = Phi(1) = 0.8413), r_osc far above 1 (visible)
    p = rule_probabilities(_inputs("elastic", 0.0, -0.5, 5.0), half.get)
    assert p["elastic"] == pytest.approx(0.841345, abs=1e-6) and p["stiff"] == pytest.approx(0.158655, abs=1e-6)
    assert p["elastic_backlash"] == p["stiff_backlash"] == 0.0
    # a gap between the thresholds (5 mrad): elastic_backlash where soft, stiff_backlash where not
    p = rule_probabilities(_inputs("elastic_backlash", 5e-3, -0.5, 5.0), half.get)
    assert p["elastic_backlash"] == pytest.approx(0.841345, abs=1e-6)
    assert p["stiff_backlash"] == pytest.approx(0.158655, abs=1e-6)
    # a soft shaft's backlash on its upper threshold with a scatter: half above, nearly all the rest
    # between the thresholds (asinh(1) lies 3.48 sd below asinh(10): Phi(-3.48) = 0.00025 below)
    p = rule_probabilities(_inputs("stiff_backlash", 1e-2, -5.0, 5.0), {**half, "backlash": 1.0}.get)
    assert p["stiff_backlash"] == pytest.approx(0.5, abs=1e-9) and p["elastic"] == pytest.approx(2.5e-4, abs=1e-5)
    assert sum(p.values()) == pytest.approx(1.0)


def test_calibration_of_another_version_is_refused(tmp_path) -> None:
    path = tmp_path / "confidence.json"
    path.write_text(json.dumps({"version": "twomass-confidence-v0", "features": []}))
    with pytest.raises(ValueError, match="rerun `twomass calibrate`"):
        Calibration.load(path)
    path.write_text("{not json")
    with pytest.raises(ValueError, match="unreadable"):
        Calibration.load(path)


def _record(**params):
    from sim import DriveConfig, TestSignalConfig, TwoMassParams, responses_to_records, simulate_test

    drive, signal = DriveConfig(), TestSignalConfig()
    p = TwoMassParams(**{k: float(v) for k, v in params.items()})
    return responses_to_records(simulate_test(p, drive, signal, seed=3), p.reshape(1), drive, signal)[0]


@pytest.fixture(scope="module")
def shipped():
    from training.identification import Identifier

    ident = Identifier.load()
    if ident.calibration is None:
        pytest.fail("the shipped maps carry no confidence calibration (checkpoints/confidence.json)")
    return ident


def test_intervals_cover_the_truth_narrow_where_the_record_shows_it(shipped) -> None:
    # a 30 Hz shaft whose oscillation spans hundreds of speed quanta: V_J is well determined
    informative = shipped.identify(_record(J_sigma=0.05, V_J=1.5, f_e=30.0, d=0.02, backlash=0.0, M_FC=0.1,
                                           mu_F=0.001))
    # a 250 Hz shaft with a light load: its oscillation is below one speed quantum (r_osc ~0.4), the
    # answer stiff, and the record says nothing about V_J
    blind = shipped.identify(_record(J_sigma=0.2, V_J=0.3, f_e=250.0, d=0.02, backlash=0.0, M_FC=0.1, mu_F=0.001))
    assert informative.structure == "elastic" and blind.structure == "stiff"
    low, high = informative.intervals["V_J"]
    assert low <= 1.5 <= high and high / low < 1.3
    low, high = blind.intervals["V_J"]
    assert low <= 0.3 <= high and high / low > 2.5  # the shipped calibration: 2.9
    for res in (informative, blind):
        assert all(res.intervals[n][0] <= res.intervals[n][1] for n in ("J_sigma", "f_e", "d", "backlash"))
        assert res.intervals["J_sigma"][0] <= (0.05 if res is informative else 0.2) <= res.intervals["J_sigma"][1]
        # no load torque detected: the interval spans the detection's threshold (0.5 % of M* = 10 Nm)
        assert res.parameters.M_L0 == 0.0
        assert res.intervals["M_L0"][0] <= -0.05 and res.intervals["M_L0"][1] >= 0.05


def test_probabilities_sum_to_one_and_the_class_is_their_argmax(shipped, good) -> None:
    res = shipped.identify(good)
    p = res.quality.structure_probabilities
    assert list(p) == list(STRUCTURE_CLASSES) and sum(p.values()) == pytest.approx(1.0, abs=1e-12)
    assert max(p, key=p.get) == res.structure
    assert 0.0 < res.quality.answer_probability <= 1.0
    d = res.to_dict()
    assert set(d["intervals"]) == set(d["parameters"]) and d["notes"] == [w.text for w in res.notes]
