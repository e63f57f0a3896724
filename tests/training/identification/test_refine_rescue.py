"""The refinement's rescue: a maps' answer so far off that the exploration around it explains nothing."""

import math

from _refine_problems import refine_problem

from sim import DriveConfig, TestSignalConfig, TwoMassParams
from training.identification._refine import AngleFitSettings, RefineConfig, RescueSettings, RestartSettings, refine

# a large industrial axis (500 us, 2^16 counts, current loop 1.5 ms: bandwidth 106 Hz)
AXIS = DriveConfig(M_N=200.0, M_max=600.0, K_M=2.0, T_s=5e-4, T_Ei=1.5e-3, encoder_counts=2**16, current_noise_std=0.1)
SIGNAL = TestSignalConfig(M_star=200.0, w_max=150.0)
NO_RESTART = RestartSettings(above=math.inf)  # the restart finds these too ...
NO_ANGLE_FIT = AngleFitSettings(win=0.0)  # ... and the angle fit
NO_RESCUE = RefineConfig(rescue=RescueSettings(above=math.inf), restart=NO_RESTART, angle_fit=NO_ANGLE_FIT)


def test_a_stiff_shaft_with_a_wide_gap_answered_elastic_at_14_hz_gets_its_width():
    # f_e 259 Hz, s_N 1.5 (stiff_backlash); the shipped maps answered elastic, f_e 14 Hz, V_J 0.21
    # (measured in the drive matrix, large axis, seed 11): the exploration around it leaves the
    # windows' energy unexplained and its width came out 11 000 x too wide
    true = TwoMassParams(J_sigma=0.180, V_J=2.76, f_e=258.5, d=0.076, backlash=6.51e-3, M_FC=8.86, mu_F=0.05)
    p = refine_problem(true, [math.log10(14.3), math.log10(0.208), 0.060, -3.0], AXIS, SIGNAL)
    out, without = refine([p])[0], refine([p], NO_RESCUE)[0]
    assert abs(without.backlash / 6.51e-3 - 1) > 1.0
    assert abs(out.backlash / 6.51e-3 - 1) < 0.2 and abs(out.f_e / 258.5 - 1) < 0.1
    assert out.residual < 0.5 < without.residual


def test_no_rescue_where_the_windows_hold_only_quantization_noise():
    # a stiff shaft on a 2^13-count 1 ms drive: its response stays within the speed's quantum, so
    # the windows' energy is noise, which no model explains (with the noise gate off, the rescue runs)
    coarse = DriveConfig(T_s=1e-3, encoder_counts=2**13)
    true = TwoMassParams(J_sigma=0.05, V_J=1.0, f_e=300.0, d=0.05, backlash=0.0, M_FC=0.5, mu_F=0.001)
    p = refine_problem(true, [math.log10(300.0), 0.0, 0.05, -3.0], coarse)
    out = refine([p])[0]
    assert out == refine([p], NO_RESCUE)[0]
    assert refine([p], RefineConfig(rescue=RescueSettings(signal=0.0)))[0].n_sims > out.n_sims


def test_an_answer_that_explains_under_half_of_the_windows_is_rescued():
    # the noisy drive of the matrix (5 % current noise), seed 9 #105: 95 Hz, V_J 0.68, a gap of s_N
    # 0.57. From the maps' answer (56 Hz, V_J 0.17) the exploration ended at 75 Hz and V_J 0.32,
    # leaving 70 % of the windows' energy (the truth leaves 2 %); a rescue from 80 % only did not
    # run, and the answer kept V_J 53 % low and half the width
    noisy = DriveConfig(current_noise_std=0.5)
    true = TwoMassParams(J_sigma=0.046095, V_J=0.67783, f_e=95.434, d=0.016267, backlash=2.8712e-3, M_FC=0.49829,
                         mu_F=3.6057e-3)
    p = refine_problem(true, [math.log10(56.3), math.log10(0.17), 0.044, math.log10(0.071)], noisy, TestSignalConfig())
    out, late = refine([p])[0], refine([p], RefineConfig(rescue=RescueSettings(above=0.8), restart=NO_RESTART,
                                                        angle_fit=NO_ANGLE_FIT))[0]
    assert abs(late.V_J / 0.678 - 1) > 0.3 and abs(late.backlash / 2.87e-3 - 1) > 0.3
    assert abs(out.f_e / 95.43 - 1) < 0.03 and abs(out.V_J / 0.678 - 1) < 0.03
    assert abs(out.backlash / 2.87e-3 - 1) < 0.1
