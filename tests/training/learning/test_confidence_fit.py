"""The calibration's fit: hand-computed conformal quantiles and thresholds, the logistic model's
optimality, and a calibration that recovers a known noise scale."""

from __future__ import annotations

import math

import numpy as np
import pytest

from training.identification._confidence import ASINH, FEATURE_NAMES, ConfidenceInputs
from training.identification._result import INTERVAL_NAMES
from training.learning._confidence import (CalibrationSample, _logistic, cell_quantiles, conformal_quantile,
                                           fit_calibration, warn_threshold)


def test_conformal_quantile_is_the_ceil_n_plus_one_rank() -> None:
    scores = np.arange(1.0, 20.0)  # n = 19: ceil(20 * 0.9) = 18th smallest
    assert conformal_quantile(scores, 0.9) == 18.0
    assert conformal_quantile(np.arange(1.0, 9.0), 0.9) == math.inf  # n = 8: ceil(8.1) = 9 > n


def test_cell_quantiles_per_real_axis_cell_and_class() -> None:
    scores = np.r_[np.arange(1.0, 100.0), 0.1 * np.arange(1.0, 100.0)]  # n = 99 per cell: the 90th smallest
    like = np.arange(198) < 99
    classes = np.array(["stiff"] * 198)
    assert cell_quantiles(scores, classes, like) == pytest.approx(
        {"*": 9.0, "stiff": 9.0, "real_axis:*": 90.0, "real_axis:stiff": 90.0})
    # a class below MIN_CLASS_SAMPLES (80) in a cell gets no quantile of its own there; a cell below it
    # takes its "*" over every record
    scores = np.r_[np.arange(100.0, 110.0), 0.1 * np.arange(1.0, 100.0)]
    classes = np.array(["elastic"] * 10 + ["stiff"] * 99)
    q = cell_quantiles(scores, classes, np.arange(109) < 10)
    assert q["*"] == q["stiff"] == pytest.approx(9.0)
    assert q["real_axis:*"] == pytest.approx(9.9) and "real_axis:elastic" not in q  # 99th of 109


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
    assert not any(calibration.is_real_axis(s.inputs) for s in test[:50])  # no real axes calibrated: none


def test_answers_like_real_axes_get_their_own_cell() -> None:
    """Real-axis records (feature 6 set; the scale model may not see that their errors have
    heavier tails) get the quantile of their own cell and their 90 % there."""
    samples = _samples(4000, 2)
    rng = np.random.default_rng(3)
    for k, s in enumerate(samples):
        if k % 2:
            s.inputs.features[6] = 1.0
            heavy = math.exp(rng.normal(0.0, 0.02) * (10.0 if rng.random() < 0.3 else 1.0))
            samples[k] = CalibrationSample(s.inputs, s.truth, s.true_class, s.errors, (), "real_axis:test")
            s.inputs.points["M_FC"] = heavy
    calibration = fit_calibration(samples[:3000], {"maps_sha256": {}})
    test = samples[3000:]
    real = np.array([s.group.startswith("real_axis") for s in test])
    assert [calibration.is_real_axis(s.inputs) for s in test] == real.tolist()
    q = calibration.quantile["M_FC"]
    assert q["real_axis:stiff"] > 2.0 * q["stiff"]
    covered = np.array([(lambda iv: iv[0] <= 1.0 <= iv[1])(calibration.intervals(s.inputs)["M_FC"]) for s in test])
    assert covered[real].mean() >= 0.85 and covered[~real].mean() >= 0.85
