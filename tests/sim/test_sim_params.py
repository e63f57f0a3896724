import math

import numpy as np
import pytest
import torch

from sim import (STRUCTURE_CLASSES, DriveConfig, EnvelopeRanges, PopulationRanges, TwoMassParams, gap_width,
                 inertia_of_time_scale, normalized_backlash, sample_envelope, sample_population, structure_class,
                 time_scale)


def test_derived_values_round_trip():
    p = sample_population(64, 3)
    q = TwoMassParams.from_physical(J_M=p.J_M, J_L=p.J_L, C_F=p.C_F, D_F=p.D_F, backlash=p.backlash, M_FC=p.M_FC, mu_F=p.mu_F)
    for name in ("J_sigma", "V_J", "f_e", "d"):
        torch.testing.assert_close(getattr(q, name), getattr(p, name), rtol=1e-12, atol=0)
    # definitions of SPEC 1
    torch.testing.assert_close(p.w_0, torch.sqrt(p.C_F * p.J_sigma / (p.J_M * p.J_L)), rtol=1e-12, atol=0)
    torch.testing.assert_close(p.d, p.w_0 * p.D_F / (2 * p.C_F), rtol=1e-12, atol=0)
    torch.testing.assert_close(2 * math.pi * p.f_e, p.w_0 * torch.sqrt(1 - p.d**2), rtol=1e-12, atol=0)
    torch.testing.assert_close(p.J_L / p.J_M, p.V_J, rtol=1e-12, atol=0)


def test_dicts_round_trip_and_indexing():
    p = sample_population(5, 1)
    q = TwoMassParams.from_dicts(p.to_dicts())
    for name in ("J_sigma", "V_J", "f_e", "d", "backlash", "M_FC", "mu_F"):
        assert torch.equal(getattr(q, name), getattr(p, name))
    assert p[2].batch_shape == torch.Size([])
    assert p[1:3].batch_shape == torch.Size([2])
    assert p.reshape(5, 1).batch_shape == torch.Size([5, 1])


def test_gap_width_and_normalized_backlash_are_inverse():
    # hand-computed: s_N 0.5 at M_N 10 Nm, C_F 1000 Nm/rad -> 2s = 2 * 0.5 * 10 / 1000 = 0.01 rad
    assert gap_width(0.5, 10.0, 1000.0) == pytest.approx(0.01, rel=1e-15)
    assert normalized_backlash(0.01, 10.0, 1000.0) == pytest.approx(0.5, rel=1e-15)
    s_N = np.array([0.1, 1.0, 30.0])
    np.testing.assert_allclose(normalized_backlash(gap_width(s_N, 0.64, 250.0), 0.64, 250.0), s_N, rtol=1e-15)


def test_s_N_and_r_osc():
    drive = DriveConfig()
    p = TwoMassParams(J_sigma=0.05, V_J=1.0, f_e=30.0, d=0.02, backlash=math.radians(0.1), M_FC=0.2, mu_F=0.001)
    assert float(p.s_N(drive)) == pytest.approx(float(p.s * p.C_F / 10.0), rel=1e-12)
    q_w = 2 * math.pi / (2**20 * 2.5e-4)
    assert drive.q_w == pytest.approx(q_w)
    assert float(p.r_osc(drive, 10.0)) == pytest.approx(1.0 * 10.0 / (0.05 * float(p.w_0) * q_w), rel=1e-12)


def test_structure_classes():
    drive = DriveConfig()
    t = torch.tensor
    # elastic: soft, visible, no backlash; stiff: w_e T_Ei >= 1; backlash cases by s_N
    p = TwoMassParams(J_sigma=t([0.05, 0.05, 0.05, 0.05, 0.05]), V_J=t([1.0, 1.0, 1.0, 1.0, 1.0]),
                      f_e=t([30.0, 400.0, 30.0, 30.0, 400.0]), d=t([0.02] * 5),
                      backlash=t([0.0, 0.0, 0.0, 0.0, 0.0]), M_FC=t([0.0] * 5), mu_F=t([0.0] * 5))
    C_F = p.C_F
    s_target = t([0.0, 0.0, 0.5, 2.0, 0.5]) * 10.0 / C_F  # s_N = 0, 0, 0.5, 2, 0.5
    p = TwoMassParams(J_sigma=p.J_sigma, V_J=p.V_J, f_e=p.f_e, d=p.d, backlash=2 * s_target, M_FC=p.M_FC, mu_F=p.mu_F)
    names = [STRUCTURE_CLASSES[i] for i in structure_class(p, drive, 10.0).tolist()]
    assert names == ["elastic", "stiff", "elastic_backlash", "stiff_backlash", "stiff_backlash"]


def test_population_is_seeded_and_in_range():
    a, b = sample_population(500, 11), sample_population(500, 11)
    assert torch.equal(a.f_e, b.f_e) and not torch.equal(a.f_e, sample_population(500, 12).f_e)
    assert float(a.J_sigma.min()) >= 0.01 and float(a.J_sigma.max()) <= 0.2
    assert float(a.f_e.min()) >= 5 and float(a.f_e.max()) <= 500
    zero = float((a.backlash == 0).double().mean())
    assert 0.2 < zero < 0.4
    nz = a.backlash[a.backlash > 0]
    assert float(nz.min()) >= math.radians(0.02) - 1e-15 and float(nz.max()) <= math.radians(1.0) + 1e-15
    c = sample_population(100, 1, PopulationRanges(f_e=(10.0, 20.0), backlash_zero_share=1.0))
    assert float(c.f_e.max()) <= 20 and float(c.backlash.max()) == 0


def test_bad_inputs_raise_clear_errors():
    with pytest.raises(ValueError, match="J_sigma"):
        TwoMassParams(J_sigma=-1.0, V_J=1.0, f_e=10.0, d=0.0, backlash=0.0, M_FC=0.0, mu_F=0.0)
    with pytest.raises(ValueError, match="T_s"):
        DriveConfig(T_s=0)
    with pytest.raises(ValueError, match="unknown keys"):
        TwoMassParams.from_dicts({"J_sigma": 1.0, "V_J": 1.0, "f_e": 10.0, "foo": 1})
    with pytest.raises(ValueError, match="n >= 1"):
        sample_population(0, 1)


def test_current_noise_as_a_share_of_M_star():
    # 0.05 A on a 2 Nm/A motor is 0.1 Nm: 1 % of a test's M* of 10 Nm
    assert DriveConfig(K_M=2.0, current_noise_std=0.05).current_noise(10.0) == pytest.approx(0.01)


def test_time_scale_by_hand_and_its_inverse():
    # SPEC 1's reference test: J_sigma 0.02 kg m^2, w_max 100 rad/s, M* 10 Nm -> 0.2 s to reach w_max
    assert time_scale(0.02, 10.0, 100.0) == pytest.approx(0.2, rel=1e-15)
    assert inertia_of_time_scale(0.2, 10.0, 100.0) == pytest.approx(0.02, rel=1e-15)
    # an envelope draw's inertias come from its time scales: every one inside the drawn range
    sample = sample_envelope(60, 3, EnvelopeRanges(cell=20))
    M_star = torch.tensor([s.M_star for _, s in sample.cases], dtype=torch.float64)[sample.cell]
    w_max = torch.tensor([s.w_max for _, s in sample.cases], dtype=torch.float64)[sample.cell]
    tau = time_scale(sample.params.J_sigma, M_star, w_max)
    lo, hi = EnvelopeRanges().time_scale
    assert bool(((tau >= lo * (1 - 1e-12)) & (tau <= hi * (1 + 1e-12))).all())
