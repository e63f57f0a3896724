"""The backlash the speed hides, found in the motor's angle (``training.identification._angle``)."""

import math

import numpy as np
import pytest

from sim import DriveConfig, TestSignalConfig, TwoMassParams, responses_to_records, simulate_test
from training.identification import Identifier
from training.identification._refine import RefineConfig, find_hidden_gap
from training.identification._refine._angle import angle_energy, angle_basis
from training.identification._refine._replay import trend_basis

from _refine_problems import refine_problem

COARSE = DriveConfig(T_s=1e-3, T_Ei=1e-3, encoder_counts=2**13)  # 0.77 mrad per count, 0.77 rad/s per quantum
SHAFT = dict(J_sigma=0.15, V_J=1.0, f_e=300.0, d=0.05)  # stiff: w_e T_Ei = 1.9


def test_the_angle_basis_holds_the_integrated_trends_but_not_an_offset_held_for_a_section():
    segments = np.array([[0, 50], [50, 120], [120, 200]])
    Q = angle_basis(segments, 200)
    assert Q.shape == (200, 10) and np.allclose(Q.T @ Q, np.eye(10), atol=1e-12)
    # a constant plus the running sum of a quadratic speed trend on the second section, held after it
    tau = np.linspace(-1.0, 1.0, 70)
    trend = np.zeros(200)
    trend[50:120] = np.cumsum(2.0 - tau + 3.0 * tau * tau)
    trend[120:] = trend[119]
    x = 0.3 + trend
    assert np.allclose(Q @ (Q.T @ x), x, atol=1e-9)
    assert np.allclose(trend_basis(70).T @ trend_basis(70), np.eye(3))
    # what a gap leaves: the motor ahead of the one-mass motion for one section
    step = np.zeros(200)
    step[50:120] = 1.0
    r = step - Q @ (Q.T @ step)
    assert (r * r).sum() > 0.02 * (step * step).sum()


def test_the_angle_at_every_stride_th_sample_is_the_angle_there():
    rng = np.random.default_rng(0)
    segments, N, stride, T_s = np.array([[0, 90], [90, 230], [230, 301]]), 301, 7, 1e-3
    E = rng.standard_normal((N, 5))  # N x C speed errors
    Q = angle_basis(segments, N, stride)
    at = np.arange(stride - 1, N // stride * stride, stride)
    assert Q.shape == (N // stride, 10) and np.allclose(Q.T @ Q, np.eye(10), atol=1e-12)
    phi = np.cumsum(E, axis=0)[at] * T_s  # the angle error at those samples, summed in full
    r = phi - Q @ (Q.T @ phi)
    assert np.allclose(angle_energy(E, T_s, Q, stride), (r * r).sum(axis=0), rtol=1e-12)


@pytest.mark.parametrize(("backlash_deg", "found"), [(0.3, True), (0.0, False)])
def test_a_gap_the_speed_hides_shows_in_the_angle(backlash_deg, found):
    """2^13 counts at 1 ms: a 0.3 degree gap leads the motor by 3.4 counts, a pulse of a sample or
    two in a speed of 0.77 rad/s quanta, but an offset of whole sections in the angle."""
    true = TwoMassParams(**SHAFT, backlash=math.radians(backlash_deg), M_FC=0.1, mu_F=0.001)
    p = refine_problem(true, np.array([math.log10(300.0), 0.0, 0.05, -3.0]), COARSE, TestSignalConfig())
    gap = find_hidden_gap(p, RefineConfig())
    if not found:
        assert gap is None
        return
    assert gap is not None and gap.s_N >= 0.15 and gap.angle_ratio < 0.85
    assert gap.backlash == pytest.approx(math.radians(backlash_deg), rel=0.3)


def test_the_identifier_answers_a_gap_from_the_angle_with_a_remark():
    """The maps and the speed's refinement answered this shaft ``stiff``, unwarned but for the
    resolution's bound; the angle shows its gap: ``stiff_backlash`` with its width and the warning
    that it rests on a few encoder counts."""
    ident = Identifier.load()
    signal = TestSignalConfig()

    def identify(backlash_deg: float):
        params = TwoMassParams(**SHAFT, backlash=math.radians(backlash_deg), M_FC=0.1, mu_F=0.001)
        rec = responses_to_records(simulate_test(params, COARSE, signal, seed=0), params.reshape(1), COARSE, signal)[0]
        return ident.identify(rec)

    res = identify(0.3)
    assert res.structure == "stiff_backlash" and res.has_note("backlash_from_angle")
    assert res.parameters.backlash == pytest.approx(math.radians(0.3), rel=0.3)
    assert 0.0 < res.quality.angle_ratio < 0.85 and res.quality.maps_structure is not None
    plain = identify(0.0)
    assert plain.structure == "stiff" and not plain.has_note("backlash_from_angle")
    assert plain.quality.angle_ratio is None
