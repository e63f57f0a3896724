"""Model-based refinement (training.identification._refine): recovers a known plant from a perturbed start."""

import math

import numpy as np
import pytest

from _refine_problems import DRIVE, refine_problem

from sim import TwoMassParams
from training.identification._refine import RefineConfig, refine, torque_reference


def test_torque_reference_of_the_six_sections():
    bounds = np.array([[3, 10], [10, 20], [20, 25], [25, 40], [40, 55], [55, 60]])
    start, level = torque_reference(bounds, 8.0)
    assert start.tolist() == [0, 3, 10, 20, 25, 40, 55, 60]
    assert np.allclose(level, [0, 8, 0, -5.6, -8, 0, 5.6, 0])
    with pytest.raises(ValueError, match=r"shape \(6, 2\)"):
        torque_reference(bounds[:5], 8.0)


def test_recovers_an_elastic_plant_with_backlash_from_a_perturbed_start():
    true = TwoMassParams(J_sigma=0.03, V_J=2.0, f_e=40.0, d=0.03, backlash=math.radians(0.6), M_FC=0.2, mu_F=0.001)
    s_N = float(true.s_N(DRIVE))
    assert 0.1 < s_N < 1.0  # elastic_backlash
    start = np.array([math.log10(40.0 * 1.2), math.log10(2.0 * 0.8), 0.05, math.log10(2 * s_N)])
    p = refine_problem(true, start)
    out = refine([p], RefineConfig(seed=0))[0]
    assert out.residual < 0.6 * out.start_residual  # the start reproduces none of the oscillation (~1)
    assert abs(out.f_e / 40.0 - 1) < 0.05
    assert abs(out.V_J / 2.0 - 1) < 0.3  # E_30; V_J and s_N trade off along a narrow valley
    assert abs(out.d - 0.03) < 0.02
    assert abs(out.s_N / s_N - 1) < 0.3
    assert abs(out.backlash / float(true.backlash) - 1) < 0.3


def test_a_start_at_the_truth_stays_there():
    true = TwoMassParams(J_sigma=0.03, V_J=1.0, f_e=60.0, d=0.02, backlash=0.0, M_FC=0.1, mu_F=0.0)
    p = refine_problem(true, np.array([math.log10(60.0), 0.0, 0.02, -3.0]))
    out = refine([p], RefineConfig(rounds=1, candidates=8, elites=4))[0]
    assert out.residual <= out.start_residual
    assert abs(out.f_e / 60.0 - 1) < 0.01 and abs(out.V_J - 1.0) < 0.05 and out.s_N < 0.05


def test_bad_config_is_rejected():
    with pytest.raises(ValueError, match="candidates >= elites >= 2"):
        refine([], RefineConfig(candidates=4, elites=8))
