"""Model-based refinement (training.identification._refine): recovers a known plant from a perturbed start."""

import math

import numpy as np
import pytest

from _refine_problems import DRIVE, refine_problem

from sim import STRUCTURE_CLASSES, TwoMassParams
from training.evaluation import DRIVES
from training.identification._refine import (ExploreSettings, FreeSettings, PolishSettings, RefineConfig,
                                             RefineProblem, RescueSettings, RestartSettings, SearchSettings, refine,
                                             torque_reference)
from training.identification._policy import MapsAnswer, second_f_e_start
from training.identification._refine._explore import explore_windows, starts


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
    small = RefineConfig(explore=ExploreSettings(rounds=1), search=SearchSettings(candidates=8, elites=4))
    out = refine([p], small)[0]
    assert out.residual <= out.start_residual
    assert abs(out.f_e / 60.0 - 1) < 0.01 and abs(out.V_J - 1.0) < 0.05 and out.s_N < 0.05


@pytest.mark.parametrize(("T_s", "f_e", "expected"), [(1e-3, 10.0, 400), (1e-3, 50.0, 80), (2.5e-4, 10.0, 400),
                                                      (62.5e-6, 10.0, 1600), (62.5e-6, 500.0, 128)])
def test_exploring_windows_hold_4_periods_up_to_0_1_s_or_400_samples(T_s: float, f_e: float, expected: int):
    # 4 periods at the start's f_e, at most 0.1 s or 400 samples, whichever is longer: 10 Hz at 1 ms
    # gets 400 samples (4 periods; 0.1 s would be one), 50 Hz at 1 ms its 4 periods (80); 10 Hz at
    # 250 us 400 (0.1 s), at 62.5 us 1600 (0.1 s); 500 Hz at 62.5 us 4 periods (128)
    seg = np.array([[0, 2000], [2000, 4000], [4000, 4010]])
    p = RefineProblem(speed=np.zeros(4100), start=np.array([0, 0, 2000, 4000]), level=np.array([0.0, 1.0, 0.0, -1.0]),
                      segments=seg, J_sigma=0.04, M_FC=0.1, mu_F=0.0, T_s=T_s, T_Ei=1e-3, encoder_counts=2**13,
                      M_N=10.0, theta=np.array([math.log10(f_e), 0.0, 0.03, -3.0]))
    w = explore_windows(p, ExploreSettings())
    assert (w.inside.sum(1)).tolist() == [expected, expected, 10]  # the third segment is shorter


def test_a_small_gap_on_a_slowly_sampled_drive_is_found():
    # the low-resolution 1 ms drive of the drive matrix, a 10 Hz shaft with a gap of 7 encoder counts
    # (s_N 0.023: elastic): without its gap no model reproduces the record (the truth without it
    # scores worse than the maps' start), and windows of 0.1 s (one period) never showed it: the
    # answer stayed at the start, V_J 0.6 x the truth
    case = DRIVES["low_res_1ms"]
    drive = case.drive
    true = TwoMassParams(J_sigma=0.04, V_J=0.68, f_e=9.66, d=0.016, backlash=0.0129, M_FC=0.1, mu_F=5.8e-4)
    start = np.array([0.982, -0.392, 0.041, -2.695])  # the maps' answer on such a record
    p = refine_problem(true, start, drive, case.signal)
    out = refine([p], RefineConfig(seed=0))[0]
    assert abs(out.f_e / 9.66 - 1) < 0.05 and abs(out.V_J / 0.68 - 1) < 0.3
    assert 0.5 < out.s_N / float(true.s_N(drive)) < 2.0
    assert out.residual < 0.6 * out.start_residual


def test_the_maps_other_f_e_is_a_second_start_only_where_it_lies_apart():
    p = RefineProblem(speed=np.zeros(10), start=np.array([0]), level=np.array([0.0]), segments=np.array([[0, 10]]),
                      J_sigma=0.04, M_FC=0.1, mu_F=0.0, T_s=1e-3, T_Ei=1e-3, encoder_counts=2**13, M_N=10.0,
                      theta=np.array([2.0, 0.0, 0.03, -3.0]))
    assert starts(p, ExploreSettings()).tolist() == [[2.0, 0.0, 0.03, -3.0]]  # no other read-out
    near = starts(RefineProblem(**{**p.__dict__, "f_e_other": 10 ** 1.95}), ExploreSettings())
    assert near.shape == (1, 4)  # 0.05 decades: inside the grid around the start
    apart = starts(RefineProblem(**{**p.__dict__, "f_e_other": 10 ** 1.7}), ExploreSettings())
    np.testing.assert_allclose(apart, [[2.0, 0.0, 0.03, -3.0], [1.7, 0.0, 0.03, -3.0]])
    assert starts(RefineProblem(**{**p.__dict__, "f_e_other": 10 ** 1.7}),
                  ExploreSettings(other_apart=math.inf)).shape == (1, 4)

    def answer(structure: str) -> MapsAnswer:
        return MapsAnswer(structure, {}, f_e=100.0, V_J=1.0, d=0.03, s_N=0.0, s_N_backlash=0.0, distance_ratio={},
                          f_e_flat=50.0)

    assert [second_f_e_start(answer(c)) for c in STRUCTURE_CLASSES] == [50.0, 50.0, 50.0, None]  # the gap hides f_e


def test_a_start_beyond_the_grid_is_rescued_by_the_maps_other_read_out():
    # the 1 ms, 2^13-count drive: the f_e map's local read-out 2.2x too high (0.34 decades: beyond
    # the exploring grid's 0.25), its units' own weights 10 % low
    case = DRIVES["low_res_1ms"]
    true = TwoMassParams(J_sigma=0.04, V_J=1.5, f_e=12.0, d=0.03, backlash=0.0, M_FC=0.1, mu_F=5.8e-4)
    start = np.array([math.log10(12.0 * 2.2), math.log10(1.5), 0.03, -3.0])
    p = refine_problem(true, start, case.drive, case.signal)
    once = RefineConfig(seed=0, restart=RestartSettings(above=math.inf))  # the restart finds it too
    alone = refine([p], once)[0]
    both = refine([RefineProblem(**{**p.__dict__, "f_e_other": 12.0 * 0.9})], once)[0]
    assert abs(both.f_e / 12.0 - 1) < 0.05 and abs(both.V_J / 1.5 - 1) < 0.3
    assert both.residual < 0.5 * alone.residual  # alone: f_e 12.3 Hz, V_J 1.14, residual 0.74 against 0.17


def test_bad_config_is_rejected():
    with pytest.raises(ValueError, match=r"SearchSettings\.candidates: expected an integer >= elites, received 4"):
        SearchSettings(candidates=4, elites=8)
    with pytest.raises(ValueError, match=r"ExploreSettings\.window_samples: expected an integer >= 0"):
        ExploreSettings(window_samples=-1)
    with pytest.raises(ValueError, match=r"RescueSettings\.grid_f_e: expected an integer >= 1"):
        RescueSettings(grid_f_e=0)
    with pytest.raises(ValueError, match=r"RescueSettings\.rounds"):
        RescueSettings(rounds=-1)
    with pytest.raises(ValueError, match=r"FreeSettings\.spread: expected a tuple of 3 values"):
        FreeSettings(spread=(0.1, 0.1))  # the two-coordinate free stage's
    with pytest.raises(ValueError, match=r"PolishSettings\.gap_seeds: expected a tuple, each a finite number > 0.002"):
        PolishSettings(gap_seeds=(0.001, 0.01))  # no gap at all by the search's floor
    with pytest.raises(TypeError, match=r"RefineConfig\.polish: expected PolishSettings"):
        RefineConfig(polish=FreeSettings())
