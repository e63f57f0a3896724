"""The refinement's Levenberg-Marquardt polish (training.identification._refine._polish): from a
model a few % off, back to the plant that made the record."""

import math
from dataclasses import replace

import numpy as np
import pytest

from _refine_problems import refine_problem

from sim import DriveConfig, TestSignalConfig, TwoMassParams
from training.identification._refine import PolishSettings, RefineConfig, Refined, RetrySettings
from training.identification._refine._pipeline import polish as polish_chosen
from training.identification._refine._replay import detrend_basis, detrended_energy
from training.identification._refine._space import NO_GAP


NO_RETRY = RefineConfig(retry=RetrySettings(above=math.inf))


def polish(problems, chosen, config=RefineConfig()):
    """The polish of ``chosen`` on ``problems`` (the measured speeds' detrended energies as refine has them)."""
    measured = [float(detrended_energy(p.speed[:, None], detrend_basis(p.segments))[0]) for p in problems]
    return polish_chosen(problems, chosen, measured, config)


def _refined(f_e: float, V_J: float, d: float, s_N: float = 1e-3, J_sigma: float | None = None) -> Refined:
    return Refined(f_e=f_e, V_J=V_J, d=d, s_N=s_N, backlash=0.0, residual=1.0, start_residual=1.0, dof=1000, n_sims=100,
                   J_sigma=J_sigma)


ELASTIC = TwoMassParams(J_sigma=0.03, V_J=1.5, f_e=25.0, d=0.02, backlash=0.0, M_FC=0.1, mu_F=0.001)


def test_polish_returns_from_a_model_a_few_percent_off_to_the_plant():
    p = refine_problem(ELASTIC, np.zeros(4))
    off = _refined(25.0 * 1.02, 1.5 * 1.12, 0.035)
    out = polish([p], [off])[0]
    assert abs(out.f_e / 25.0 - 1) < 0.003 and abs(out.V_J / 1.5 - 1) < 0.03 and abs(out.d - 0.02) < 0.004
    assert out.residual < 0.5 and out.start_residual == 1.0  # the maps' answer's residual is kept
    assert out.s_N == off.s_N and out.n_sims > off.n_sims


def test_a_lightly_damped_model_30_percent_off_comes_back():
    # a record of many periods of a lightly damped mechanic (the exploration's windows start each
    # quasi-static and miss the ringing from the section before, so its answer can be 30 % off in
    # V_J): a full Gauss-Newton step overshoots in the needle-sharp f_e, and only a more damped
    # one gains (measured on the envelope: two such answers came out untouched with V_J 30 % low)
    true = replace(ELASTIC, V_J=2.0, f_e=56.0, d=0.017)
    p = refine_problem(true, np.zeros(4))
    off = _refined(56.2, 1.39, 0.05)
    out = polish([p], [off])[0]
    assert abs(out.f_e / 56.0 - 1) < 0.003 and abs(out.V_J / 2.0 - 1) < 0.05 and abs(out.d - 0.017) < 0.003
    # (the retry finds it too)
    undamped = RefineConfig(polish=PolishSettings(damping=(1e-2, 1e-1)), retry=RetrySettings(above=math.inf))
    assert polish([p], [off], undamped)[0].V_J == off.V_J


def test_a_fit_left_above_the_noise_is_tried_again_from_a_lighter_damping():
    # the noisy drive of the matrix (5 % current noise), seed 7 #138: d 0.012 at 20 Hz with a small
    # gap (s_N 0.057); the polish stopped in a valley at V_J 4.9 and d 0.028 (relative residual 0.48,
    # the truth's 0.02; unwarned); from the same model with half its damping it reaches the truth
    drive = DriveConfig(current_noise_std=0.5)
    true = TwoMassParams(J_sigma=0.0909, V_J=3.483, f_e=19.948, d=0.01219, backlash=0.004567, M_FC=0.1151,
                         mu_F=0.002457)
    p = refine_problem(true, np.zeros(4), drive, TestSignalConfig())
    off = _refined(19.87, 4.894, 0.0275, s_N=0.034)  # where the polish stopped
    out = polish([p], [off])[0]
    assert abs(out.f_e / 19.948 - 1) < 0.005 and abs(out.V_J / 3.483 - 1) < 0.03 and abs(out.d - 0.0122) < 0.002
    assert abs(out.s_N / 0.0565 - 1) < 0.1 and out.residual < 0.1
    assert polish([p], [off], NO_RETRY)[0].V_J == pytest.approx(off.V_J, rel=0.1)


def test_a_fit_left_above_the_noise_is_tried_again_from_the_maps_answer():
    # the fast spindle of the matrix (62.5 us, 2^22 counts), seed 12 #24: 88 Hz, d 0.011, a gap of
    # s_N 0.009. The windows' search ended at V_J 1.98 and d 0.004 with a gap 4 x too wide, and the
    # polish stayed there (relative residual 0.48, the truth's 0.00; unwarned, V_J 33 % off). The
    # maps' answer was near (V_J 2.75, d 0.035, no gap): polished from there, with the small gaps
    # tried first, it reaches the truth
    drive = DriveConfig(M_max=12.0, M_N=5.0, T_Ei=1e-4, T_s=6.25e-5, encoder_counts=2**22, current_noise_std=0.005)
    true = TwoMassParams(J_sigma=5.5929e-4, V_J=2.9475, f_e=87.899, d=0.011405, backlash=2.8629e-3, M_FC=0.026293,
                         mu_F=2.1565e-4)
    maps = np.array([math.log10(87.9), math.log10(2.75), 0.035, -3.0])
    p = refine_problem(true, maps, drive, TestSignalConfig(M_star=5.0, w_max=600.0))
    off = _refined(87.6, 1.982, 0.0043, s_N=0.039)  # where the polish stopped
    out = polish([p], [off])[0]
    assert abs(out.V_J / 2.9475 - 1) < 0.02 and abs(out.d - 0.0114) < 0.001 and abs(out.s_N / 0.00924 - 1) < 0.1
    assert out.residual < 0.1
    assert polish([p], [off], NO_RETRY)[0].V_J == pytest.approx(off.V_J, rel=0.1)


def test_a_tiny_gap_the_answer_lacks_is_found():
    # 0.1 degree on a lightly damped shaft (s_N 0.016): the whole-record error is needle-sharp in s_N,
    # the searches answered without a gap and bent V_J and d instead (measured on the large axis:
    # V_J 30 % off, once unwarned); from the best of a few small gaps the polish finds it
    true = TwoMassParams(J_sigma=0.02, V_J=1.0, f_e=30.0, d=0.02, backlash=math.radians(0.1), M_FC=0.2, mu_F=0.001)
    p = refine_problem(true, np.zeros(4), DriveConfig(), TestSignalConfig())
    off = _refined(29.75, 0.93, 0.034)  # the answer without the seeds
    out = polish([p], [off])[0]
    assert abs(out.s_N / 0.0155 - 1) < 0.05 and abs(out.V_J - 1.0) < 0.02 and abs(out.d - 0.02) < 0.002
    assert polish([p], [off], RefineConfig(polish=PolishSettings(gap_seeds=())))[0].s_N == off.s_N


def test_a_gap_the_polish_removes_is_not_reported():
    # a chosen model with a gap at the class threshold (s_N 0.1) on a shaft without one: the polish
    # takes s_N down to the search's floor; the answer reported the chosen model's gap all the same
    # (envelope seed 12 #508: elastic answered elastic_backlash, 3.4e-3 rad, unwarned; its own
    # model, without the gap, scored 0.0026 of the measured energy, with it 0.60)
    p = refine_problem(ELASTIC, np.zeros(4))
    off = _refined(25.0 * 1.02, 1.5 * 1.12, 0.035, s_N=0.1)
    out = polish([p], [off])[0]
    assert abs(out.V_J / 1.5 - 1) < 0.02 and out.residual < 0.1
    assert out.s_N <= 10.0 ** NO_GAP


def test_without_iterations_nothing_moves():
    p = refine_problem(ELASTIC, np.zeros(4))
    off = _refined(26.0, 1.7, 0.035)
    assert polish([p], [off], RefineConfig(polish=PolishSettings(iterations=0)))[0] == off


def test_a_free_stage_model_returns_with_its_one_mass_part():
    # the free stage's model (J_sigma, M_FC, mu_F its own) a few % off everywhere: the polish moves
    # all seven coordinates on the plain error, back to the plant
    p = refine_problem(ELASTIC, np.zeros(4))
    off = replace(_refined(25.0 * 1.02, 1.5 * 1.1, 0.03, J_sigma=0.03 * 1.05), M_FC=0.12, mu_F=0.0)
    out = polish([p], [off])[0]
    assert abs(out.f_e / 25.0 - 1) < 0.003 and abs(out.V_J / 1.5 - 1) < 0.03 and abs(out.J_sigma / 0.03 - 1) < 0.01
    friction = lambda r: r.M_FC + r.mu_F * 40.0  # noqa: E731  at w_max (M_FC and mu_F alone are near-collinear)
    assert abs(friction(out) - friction(ELASTIC)) < 0.005 < abs(friction(off) - friction(ELASTIC))
    assert out.n_sims > off.n_sims


def test_a_model_it_cannot_halve_the_error_of_stays():
    p = refine_problem(ELASTIC, np.zeros(4))
    near = _refined(25.0 * 1.0005, 1.5, 0.02)  # as good as the record allows: no clear win to be had
    out = polish([p], [near])[0]
    assert out == replace(near, n_sims=out.n_sims) and out.n_sims > near.n_sims


def test_each_answer_is_the_same_whatever_the_others():
    p1 = refine_problem(ELASTIC, np.zeros(4))
    p2 = refine_problem(replace(ELASTIC, f_e=40.0, V_J=0.8), np.zeros(4))
    r1, r2 = _refined(25.5, 1.6, 0.03), _refined(39.0, 0.9, 0.03)
    together = polish([p1, p2], [r1, r2])
    assert together == [polish([p1], [r1])[0], polish([p2], [r2])[0]]
    assert math.isfinite(together[1].residual)


def test_a_negative_iteration_count_is_refused():
    with pytest.raises(ValueError, match=r"PolishSettings\.iterations: expected an integer >= 0"):
        PolishSettings(iterations=-1)
