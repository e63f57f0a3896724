"""The confidence of an answer (SPEC 4.1): class probabilities, the calibration file."""

from __future__ import annotations

import json
import math

import pytest

from sim import STRUCTURE_CLASSES
from training.identification._confidence import Calibration, class_margins, share_rest


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


def test_calibration_of_another_version_is_refused(tmp_path) -> None:
    path = tmp_path / "confidence.json"
    path.write_text(json.dumps({"version": "twomass-confidence-v0", "features": []}))
    with pytest.raises(ValueError, match="rerun `twomass calibrate`"):
        Calibration.load(path)
    path.write_text("{not json")
    with pytest.raises(ValueError, match="unreadable"):
        Calibration.load(path)
