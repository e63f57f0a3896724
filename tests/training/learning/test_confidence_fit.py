"""The calibration's fit: hand-computed conformal quantiles and thresholds, the logistic model's
optimality, and a calibration that recovers a known noise scale."""

from __future__ import annotations

import math

import numpy as np
import pytest

from training.identification._confidence import ASINH, FEATURE_NAMES, ConfidenceInputs
from training.identification._result import INTERVAL_NAMES
from training.learning._confidence import (CalibrationSample, _logistic, conformal_quantile, fit_calibration,
                                           warn_threshold)


def test_conformal_quantile_is_the_ceil_n_plus_one_rank() -> None:
    scores = np.arange(1.0, 20.0)  # n = 19: ceil(20 * 0.9) = 18th smallest
    assert conformal_quantile(scores, 0.9) == 18.0
    assert conformal_quantile(np.arange(1.0, 9.0), 0.9) == math.inf  # n = 8: ceil(8.1) = 9 > n


def test_warn_threshold_leaves_the_allowed_share_unwarned() -> None:
    p = np.array([0.99, 0.95, 0.9, 0.5])
    # 200 wrong answers, 0.5 %: one may stay silent -> the threshold lies just above the second largest
    t = warn_threshold(p, 200, 0.005)
    assert 0.95 < t < 0.96 and (p >= t).sum() == 1
    assert warn_threshold(p, 100, 0.005) > 0.99  # none may stay silent
    assert warn_threshold(np.array([]), 100, 0.005) == 0.0


def test_logistic_fit_zeroes_the_penalized_gradient() -> None:
    rng = np.random.default_rng(1)
    Z = rng.normal(size=(400, 3))
    y = rng.random(400) < 1.0 / (1.0 + np.exp(-(Z @ [2.0, -1.0, 0.0] + 0.5)))
    coef, b = _logistic(Z, y, lam=1.0)
    p = 1.0 / (1.0 + np.exp(-(Z @ coef + b)))
    assert np.allclose(Z.T @ (p - y) + 1.0 * coef, 0.0, atol=1e-6)
    assert abs(np.sum(p - y)) < 1e-6  # the unpenalized intercept
    assert coef[0] > 1.0 and coef[1] < -0.5


def _samples(n: int, seed: int) -> list[CalibrationSample]:
    """Synthetic answers: ``f_e``'s log error is normal with std 0.01 where feature 5 is 0 and 0.1
    where it is 1; every other parameter's error 0.02."""
    rng = np.random.default_rng(seed)
    out = []
    for i in range(n):
        x = np.zeros(len(FEATURE_NAMES))
        x[0] = 1.0  # class stiff
        x[5] = float((i // 10) % 2)  # independent of which answers are wrong (i % 10 == 0)
        sigma = 0.1 if x[5] else 0.01
        truth = {k: 1.0 for k in INTERVAL_NAMES}
        points = {k: math.exp(rng.normal(0.0, sigma if k == "f_e" else 0.02)) for k in INTERVAL_NAMES}
        rule = {"backlash_low": 100.0, "backlash_high": 1000.0, "ln_w_e_T_Ei": 2.0, "ln_r_osc": -2.0}  # stiff, no gap
        inputs = ConfidenceInputs(x, points, {k: 1.0 for k in ASINH}, "stiff", rule)
        errors = {"f_e": 0.0, "V_J": 0.0, "J_sigma": 0.0}
        out.append(CalibrationSample(inputs, truth, "stiff" if i % 10 else "elastic", errors, (), "synthetic"))
    return out


def test_calibration_learns_the_record_dependent_scale() -> None:
    calibration = fit_calibration(_samples(2000, 0), {"maps_sha256": {}})
    test = _samples(2000, 1)
    widths = {0.0: [], 1.0: []}
    covered = 0
    for s in test:
        low, high = calibration.intervals(s.inputs)["f_e"]
        covered += low <= s.truth["f_e"] <= high
        widths[s.inputs.features[5]].append(math.log(high / low) / 2)
    assert 0.87 <= covered / len(test) <= 0.93
    assert np.median(widths[0.0]) == pytest.approx(1.645 * 0.01, rel=0.2)  # the normal's 90 % half-width
    assert np.median(widths[1.0]) == pytest.approx(1.645 * 0.1, rel=0.2)
    p = calibration.probabilities(test[0].inputs, {"stiff": 0.6, "elastic": 0.3})
    assert sum(p.values()) == pytest.approx(1.0) and max(p, key=p.get) == "stiff"
    assert p["stiff"] == pytest.approx(0.9, abs=0.03)  # 9 of 10 answers name the right class
