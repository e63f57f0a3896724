"""A gap answer refitted on the motor's angle (``training.identification._refine._angle_fit``)."""

import math
from dataclasses import replace

import numpy as np
import pytest

from sim import DriveConfig, TestSignalConfig, TwoMassParams, normalized_backlash, two_mass_derived
from training.identification._refine import AngleFitSettings, RefineConfig, Refined, SplitSettings
from training.identification._refine._angle_fit import angle_fit
from training.identification._refine._replay import detrend_basis, detrended_energy, replay_drive, simulate

from _refine_problems import refine_problem

#: The large axis of the drive matrix (2^16 counts at 500 us, 200 Nm steps) and one of its real axes
#: (SPEC 1.1's population, seed 5): a 176 Hz shaft with a 0.31 degree gap, 4.4 Nm of the 14 Nm
#: Coulomb friction on the motor. The speed refinement answered its gap 0.39 x as wide with all
#: friction on the load, at about the speed error of the truth, but 45 x the truth's angle error.
LARGE = DriveConfig(M_max=600.0, M_N=200.0, K_M=2.0, T_Ei=1.5e-3, T_s=5e-4, encoder_counts=2**16, current_noise_std=0.1)
SIGNAL = TestSignalConfig(M_star=200.0, w_max=150.0)
SHAFT = dict(J_sigma=2.2407, V_J=4.389, f_e=176.41, d=0.0351, backlash=0.0053794, mu_F=0.00909)


def _answer(true: TwoMassParams, gap_share: float, M_FCM: float | None = None, mu_FM: float | None = None):
    """The problem of ``true`` on the large axis (STEP 2's friction, all on the load) and an answer with
    its shaft, ``gap_share`` x its gap and the given motor friction, with its measured energy."""
    p = refine_problem(true, np.zeros(4), LARGE, SIGNAL)
    C_F = two_mass_derived(true.J_sigma, true.V_J, true.f_e, true.d).C_F
    s_N = float(normalized_backlash(true.backlash, LARGE.M_N, C_F)) * gap_share
    theta = np.array([math.log10(float(true.f_e)), math.log10(float(true.V_J)), float(true.d), math.log10(s_N)])
    q = p.with_motor_share((M_FCM or 0.0) / p.coulomb, (mu_FM or 0.0) / p.viscous)
    basis = detrend_basis(p.segments)
    measured = float(detrended_energy(p.speed[:, None], basis)[0])
    cost = float(detrended_energy(simulate(q, theta[None], replay_drive(q)), basis)[0])
    r = Refined(**p.answer(theta, s_N), residual=math.sqrt(cost / measured), start_residual=1.0, dof=len(p.speed),
                n_sims=0, M_FC=q.M_FC if M_FCM else None, M_FCM=M_FCM, mu_FM=mu_FM)
    return p, r, measured


def _fit(p, r, measured, settings=AngleFitSettings()):
    config = RefineConfig()
    return angle_fit([p], [r], [measured], settings, config.split, config.angle, config.search, config.seed)[0]


def test_a_gap_too_narrow_with_the_motors_friction_on_the_load_is_refitted_on_the_angle():
    true = TwoMassParams(**SHAFT, M_FC=9.7598, M_FCM=4.4205, mu_FM=0.000722)
    p, r, measured = _answer(true, 0.39)
    assert r.backlash / float(true.backlash) == pytest.approx(0.39, rel=0.01)
    fitted = _fit(p, r, measured)
    gap_error = abs(math.log(fitted.backlash / float(true.backlash)))
    assert gap_error < 0.5 * abs(math.log(0.39))  # 0.65 x the truth (the shaft's V_J trades against the gap)
    assert fitted.M_FCM == pytest.approx(4.4205, abs=0.01 * SIGNAL.M_star)  # the motor's share, within 1 % of M*
    assert fitted.M_FC + fitted.M_FCM == pytest.approx(p.coulomb)  # STEP 2's sum stays
    assert fitted.n_sims > r.n_sims and fitted.residual <= AngleFitSettings().speed_slack ** 0.5 * r.residual


def test_a_right_answer_without_motor_friction_keeps_its_gap_and_gets_none():
    true = TwoMassParams(**SHAFT, M_FC=14.18)
    p, r, measured = _answer(true, 1.0)
    fitted = _fit(p, r, measured)
    assert fitted.backlash == pytest.approx(float(true.backlash), rel=0.3)
    assert not fitted.M_FCM and not fitted.mu_FM


def test_answers_without_a_gap_or_worth_splitting_friction_are_left_as_they_are():
    true = TwoMassParams(**SHAFT, M_FC=9.7598, M_FCM=4.4205)
    p, r, measured = _answer(true, 0.39)
    no_gap = replace(r, s_N=0.01)
    assert _fit(p, no_gap, measured) is no_gap
    config = RefineConfig()
    unsplit = angle_fit([p], [r], [measured], AngleFitSettings(), SplitSettings(min_friction=1.0), config.angle,
                        config.search, 0)[0]
    assert unsplit is r  # STEP 2's friction below the split's floor (here the whole test torque)
    assert _fit(p, r, measured, AngleFitSettings(win=0.0)) is r  # nothing beats 0 x the answer's angle error
