import inspect

import numpy as np
import pytest

from sim import class_index
from training.evaluation._metrics import (CLASS_THRESHOLDS, confusion_matrix, finite_or_none, recognition_rate,
                                         recognized, relative_error, threshold_margin)


def test_relative_error_hand_values():
    np.testing.assert_allclose(relative_error(np.array([1.1, 0.5, 2.0]), np.array([1.0, 1.0, -2.0])),
                               [0.1, 0.5, 2.0])


def test_recognition_rate_requires_all_three_params():
    errors = {"f_e": np.array([0.1, 0.1, 0.4, np.nan]),
              "V_J": np.array([0.2, 0.35, 0.1, 0.0]),
              "J_sigma": np.array([0.0, 0.0, 0.0, 0.0])}
    assert recognized(errors, 30).tolist() == [True, False, False, False]
    assert recognition_rate(errors, 30) == 25.0
    assert recognition_rate(errors, 50) == 75.0  # NaN is a miss


def test_recognition_rate_names_missing_params():
    with pytest.raises(ValueError, match="V_J"):
        recognition_rate({"f_e": np.zeros(2), "J_sigma": np.zeros(2)}, 30)


def test_confusion_matrix_counts():
    cm = confusion_matrix(np.array([0, 1, 1, 3]), np.array([0, 1, 2, 3]), 4)
    assert cm.tolist() == [[1, 0, 0, 0], [0, 1, 1, 0], [0, 0, 0, 0], [0, 0, 0, 1]]
    with pytest.raises(ValueError, match="outside"):
        confusion_matrix(np.array([4]), np.array([0]), 4)


def test_threshold_margin_takes_the_nearest_threshold():
    q = {"w_e_T_Ei": np.array([0.5, 0.5]), "s_N": np.array([0.09, 0.5]), "r_osc": np.array([10.0, 3.0])}
    np.testing.assert_allclose(threshold_margin(q), [0.1, 0.5])


@pytest.mark.parametrize("quantity, threshold, context", [
    ("s_N", 0.1, {"w_e_T_Ei": 0.5, "r_osc": 2.0}),   # elastic -> elastic_backlash
    ("s_N", 1.0, {"w_e_T_Ei": 0.5, "r_osc": 2.0}),   # elastic_backlash -> stiff_backlash
    ("w_e_T_Ei", 1.0, {"s_N": 0.5, "r_osc": 2.0}),   # elastic_backlash -> stiff_backlash
    ("r_osc", 1.0, {"s_N": 0.05, "w_e_T_Ei": 0.5}),  # stiff -> elastic
])
def test_class_thresholds_are_those_of_the_class_rule(quantity, threshold, context):
    """Each threshold of CLASS_THRESHOLDS is where sim.class_index changes its answer."""
    assert threshold in CLASS_THRESHOLDS[quantity]

    def cls(value: float) -> int:
        return int(class_index(**{**context, quantity: value}))

    assert cls(threshold * 0.999) != cls(threshold * 1.001)
    assert cls(threshold * 0.9) == cls(threshold * 0.999) and cls(threshold * 1.001) == cls(threshold * 1.1)


def test_class_thresholds_cover_every_quantity_of_the_class_rule():
    assert sorted(CLASS_THRESHOLDS) == sorted(inspect.signature(class_index).parameters)
    assert sum(len(t) for t in CLASS_THRESHOLDS.values()) == 4


def test_finite_or_none():
    assert finite_or_none(np.float32(2.5)) == 2.5 and finite_or_none(None) is None
    assert finite_or_none(float("nan")) is None and finite_or_none(np.inf) is None
