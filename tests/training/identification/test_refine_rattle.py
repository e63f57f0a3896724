"""The refinement's rattle: after a zero-torque section the masses rattle in the gap, and the
windows after it simulated from that section's start read the gap's width where a quasi-static
start reads it narrow."""

import math

import numpy as np
from _refine_problems import refine_problem

from sim import DriveConfig, TestSignalConfig, TwoMassParams
from training.identification._refine import (AngleFitSettings, BatchSettings, ExploreSettings, RattleSettings,
                                             RefineConfig, RestartSettings, refine)
from training.identification._refine._explore import explore_windows
from training.identification._refine._windows import window_speeds
from training.identification._refine._replay import problem_substeps, replay_drive, simulate

# a large industrial axis (500 us, 2^16 counts, current loop 1.5 ms)
AXIS = DriveConfig(M_N=200.0, M_max=600.0, K_M=2.0, T_s=5e-4, T_Ei=1.5e-3, encoder_counts=2**16, current_noise_std=0.1)
SIGNAL = TestSignalConfig(M_star=200.0, w_max=150.0)
# f_e 119 Hz (w_e T_Ei 1.1: stiff), s_N 0.63: stiff_backlash (a system of the drive matrix's large axis)
TRUE = TwoMassParams(J_sigma=0.1424, V_J=1.973, f_e=118.8, d=0.0612, backlash=0.01417, M_FC=2.37, mu_F=0.0186)
THETA = [math.log10(118.8), math.log10(1.973), 0.0612, math.log10(0.63)]  # the truth's coordinates
# the restart finds it too
NO_RATTLE = RefineConfig(rattle=RattleSettings(min_s_N=math.inf), restart=RestartSettings(above=math.inf),
                         angle_fit=AngleFitSettings(win=0.0))  # the restart and the angle fit find it too


def test_a_window_after_a_zero_torque_section_started_at_that_section_replays_the_whole_record():
    p = refine_problem(TRUE, THETA, AXIS, SIGNAL)
    w = explore_windows(p, ExploreSettings())
    after = np.flatnonzero(w.lead)
    assert len(after) == 2  # the windows after sections II and V
    theta = np.array([THETA])
    whole = simulate(p, theta, replay_drive(p))[:, 0] + p.speed  # N
    S = problem_substeps(p, theta)
    led, plain = (window_speeds([(p, theta, w, tag)], replay_drive(p), S, BatchSettings())[0][0]
                  for tag in (True, False))  # J x L
    for j in after:  # up to the quadratic trend the score removes (the one-mass part's drift)
        n, Q = int(w.inside[j].sum()), w.Q[j]
        ref = whole[w.at[j]:w.at[j] + n]
        off = lambda x: np.abs((e := x[:n] - ref) - Q[:n] @ (Q[:n].T @ e)).max()  # noqa: E731
        swing = np.ptp(ref)
        assert off(led[j]) < 0.05 * swing  # measured: 2.7 % and 0.2 %
        assert off(plain[j]) > max(0.1 * swing, 5.0 * off(led[j]))  # the quasi-static contact: not where it rattled
    for j in np.flatnonzero(w.lead == 0):  # the other windows start as before
        np.testing.assert_array_equal(led[j], plain[j])


def test_a_stiff_shaft_with_a_gap_gets_its_width_where_the_quasi_static_start_reads_it_narrow():
    # started from the shipped maps' answer for this system (f_e 148 Hz, s_N 0.015)
    p = refine_problem(TRUE, [2.171, 0.285, 0.035, -1.823], AXIS, SIGNAL)
    out, without = refine([p])[0], refine([p], NO_RATTLE)[0]
    assert abs(without.backlash / 0.01417 - 1) > 0.3
    assert abs(out.backlash / 0.01417 - 1) < 0.15
    assert out.residual < without.residual and out.n_sims > without.n_sims


def test_no_rattle_without_a_gap():
    true = TwoMassParams(J_sigma=0.5, V_J=2.0, f_e=40.0, d=0.03, backlash=0.0, M_FC=2.0, mu_F=0.0)
    p = refine_problem(true, [math.log10(44.0), math.log10(1.8), 0.04, -3.0], AXIS, SIGNAL)
    assert refine([p])[0] == refine([p], NO_RATTLE)[0]


def test_led_windows_replayed_in_chunks_give_the_same_speeds():
    p = refine_problem(TRUE, THETA, AXIS, SIGNAL)
    w = explore_windows(p, ExploreSettings())
    rng = np.random.default_rng(0)
    theta = np.clip(np.array(THETA) + rng.normal(0.0, 0.05, (100, 4)), [-9, -9, 0.01, -9], 9)  # C x 4
    drive = replay_drive(p)
    S = problem_substeps(p, theta)
    whole = window_speeds([(p, theta, w, True)], drive, S, BatchSettings())[0]
    chunked = BatchSettings(led_samples=1000)  # 64 lanes per replay: 4 replays
    np.testing.assert_array_equal(window_speeds([(p, theta, w, True)], drive, S, chunked)[0], whole)
