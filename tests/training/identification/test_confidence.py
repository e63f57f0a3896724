"""The confidence of an answer (SPEC 4.1): class probabilities, the calibration file."""

from __future__ import annotations

import json

import pytest

from sim import STRUCTURE_CLASSES
from training.identification._confidence import Calibration, class_margin, share_rest


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


def test_class_margin_is_the_nearest_thresholds_log_distance() -> None:
    assert class_margin({"w_e_T_Ei": 2.0}) == pytest.approx(0.6931, abs=1e-4)  # threshold 1
    assert class_margin({"s_N": 0.12, "w_e_T_Ei": 0.5}) == pytest.approx(abs(__import__("math").log(1.2)))
    assert class_margin({"r_osc": float("nan")}) == 3.0


def test_calibration_of_another_version_is_refused(tmp_path) -> None:
    path = tmp_path / "confidence.json"
    path.write_text(json.dumps({"version": "twomass-confidence-v0", "features": []}))
    with pytest.raises(ValueError, match="rerun `twomass calibrate`"):
        Calibration.load(path)
    path.write_text("{not json")
    with pytest.raises(ValueError, match="unreadable"):
        Calibration.load(path)
