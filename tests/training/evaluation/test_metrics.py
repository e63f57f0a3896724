import numpy as np
import pytest

from training.evaluation._metrics import (confusion_matrix, recognition_rate, recognized, relative_error,
                              threshold_margin)


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
