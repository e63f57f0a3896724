"""training.identification._plausibility: units and metadata checked against the signals (one-line messages)."""

from __future__ import annotations

import copy
import math
import re

import numpy as np
import pytest

import torch

from sim import (DriveConfig, Record, TestSignalConfig, TwoMassParams, iter_records, responses_to_records,
                 sample_population, simulate_test)
from test_sections import envelope_record

from training.identification import analyze
from training.identification._plausibility import check_record

RPM = 60.0 / (2.0 * math.pi)




def variant(rec: Record, *, drop_meta: tuple[str, ...] = (), **changes) -> Record:
    new = copy.deepcopy(rec)
    for k in drop_meta:
        new.meta.pop(k, None)
    for k, v in changes.items():
        if k in new.meta:
            new.meta[k] = v
        else:
            setattr(new, k, v)
    return new


def test_good_record_passes(good):
    check_record(good)


def test_minimal_metadata_passes(good):
    check_record(variant(good, drop_meta=("M_star", "w_max", "M_max", "M_N", "encoder_counts", "timed_out", "truth")))


def test_simulated_population_passes():
    records = list(iter_records(sample_population(12, seed=3), seed=3))
    for r in records:
        check_record(r)


def test_torque_column_passes(good):
    check_record(variant(good, current=None, torque=good.current * good.meta["K_M"]))


def test_current_in_mA(good):
    with pytest.raises(ValueError, match=r"^current looks like wrong units \(.*1e\+03 x metadata M_star.*mA") as e:
        check_record(variant(good, current=good.current * 1000.0))
    assert "\n" not in str(e.value)


def test_current_in_mA_without_M_star_uses_M_max(good):
    with pytest.raises(ValueError, match=r"current looks like wrong units .*M_max"):
        check_record(variant(good, drop_meta=("M_star",), current=good.current * 1000.0))


def test_current_far_too_small(good):
    with pytest.raises(ValueError, match=r"current looks like wrong units .*0\.001 x metadata M_star"):
        check_record(variant(good, current=good.current / 1000.0))


def test_torque_in_wrong_units(good):
    with pytest.raises(ValueError, match=r"^torque looks like wrong units"):
        check_record(variant(good, current=None, torque=good.current * 100.0))


def test_speed_in_rpm_against_w_max(good):
    with pytest.raises(ValueError, match=r"^speed looks like wrong units \(peak \|speed\| .* x metadata w_max .*rpm"):
        check_record(variant(good, speed=good.speed * RPM))


def test_a_current_that_is_zero_throughout_is_named(good):
    with pytest.raises(ValueError, match=r"^current: expected the test's torque steps, received zeros throughout"):
        check_record(variant(good, current=np.zeros_like(good.current)))


def test_a_speed_glitch_is_named_as_such_not_as_units(good):
    speed = good.speed.copy()
    speed[500] = 3.5 * good.meta["w_max"]  # one sample
    at = f"t = {float(good.t[500]):.9g} s"  # the glitch's time: one place in a file and in memory alike
    with pytest.raises(ValueError, match=r"^speed has 1 sample\(s\) far above the rest .*" + re.escape(at) + ".*glitches"):
        check_record(variant(good, speed=speed))


@pytest.mark.parametrize("J_sigma, w_max, T_Ei", [(1e-4, 2.0, 1e-3), (1e-4, 1.0, 2e-3), (2e-4, 0.5, 1e-3)])
def test_small_drive_overshoot_is_not_wrong_units(J_sigma, w_max, T_Ei):
    # issue 13: a tiny inertia keeps accelerating while the current loop takes the torque away, so
    # the motor overshoots w_max 5-8x; that is physics the record itself shows, not rpm
    p = TwoMassParams(J_sigma=torch.tensor([J_sigma]), V_J=torch.tensor([1.0]), f_e=torch.tensor([200.0]),
                      d=torch.tensor([0.05]), backlash=torch.tensor([0.0]), M_FC=torch.tensor([1e-3]),
                      mu_F=torch.tensor([0.0]))
    drive, signal = DriveConfig(T_Ei=T_Ei, M_max=1.0), TestSignalConfig(M_star=0.5, w_max=w_max)
    rec = responses_to_records(simulate_test(p, drive, signal, seed=0), p, drive, signal)[0]
    assert np.abs(rec.speed).max() > 3.0 * w_max  # beyond the fixed ratio bound
    check_record(rec)
    with pytest.raises(ValueError, match=r"speed looks like wrong units"):  # rpm still refused
        check_record(variant(rec, speed=rec.speed * RPM))


def test_speed_in_rpm_from_the_encoder_quantum(good):
    # no w_max: the speed is still exactly quantized, in steps of the speed quantum in rpm
    with pytest.raises(ValueError, match=r"speed looks like wrong units \(its values are multiples of .* in rpm"):
        check_record(variant(good, drop_meta=("w_max",), speed=good.speed * RPM))


def test_speed_in_counts_per_second(good):
    counts_per_s = good.meta["encoder_counts"] / (2.0 * math.pi)
    with pytest.raises(ValueError, match=r"speed looks like wrong units .*counts/s"):
        check_record(variant(good, speed=good.speed * counts_per_s))
    with pytest.raises(ValueError, match=r"speed looks like wrong units .*in counts/s"):
        check_record(variant(good, drop_meta=("w_max",), speed=good.speed * counts_per_s))


def test_speed_too_small_unless_timed_out(good):
    slow = good.speed / (2.0 * math.pi)  # rev/s
    with pytest.raises(ValueError, match=r"speed looks like wrong units .*0\.1\d* x metadata w_max.*rev/s"):
        check_record(variant(good, speed=slow, drop_meta=("encoder_counts",)))
    check_record(variant(good, speed=slow, drop_meta=("encoder_counts",), timed_out=[True] + [False] * 5))


def test_time_in_ms_without_T_s(good):
    rec = variant(good, t=good.t * 1000.0)
    rec.meta["T_s"] = good.meta["T_s"] * 1000.0  # what validate() infers from t when the metadata has no T_s
    with pytest.raises(ValueError, match=r"^time looks like wrong units \(sample time T_s = 0\.25 s.*ms instead of s"):
        check_record(rec)


def test_T_Ei_in_ms(good):
    with pytest.raises(ValueError, match=r"^metadata T_Ei looks like wrong units \(T_Ei = 0\.5 s"):
        check_record(variant(good, T_Ei=0.5))


def test_T_s_far_above_T_Ei(good):
    with pytest.raises(ValueError, match=r"time looks like wrong units \(T_s = .* x T_Ei"):
        check_record(variant(good, T_Ei=1e-6))


def test_speed_sign_flipped(good):
    with pytest.raises(ValueError, match=r"^speed does not follow the current .*check the sign"):
        check_record(variant(good, speed=-good.speed, drop_meta=("w_max",)))


def test_absurd_inertia(good):
    pattern = r"^speed/current look like wrong units \(one-mass inertia estimate .* kg m\^2"
    with pytest.raises(ValueError, match=pattern):
        check_record(variant(good, speed=good.speed * 1e6, drop_meta=("w_max", "encoder_counts")))


def test_degenerate_signals_are_left_to_the_section_detection(good):
    check_record(variant(good, speed=np.zeros_like(good.speed)))
    check_record(variant(good, speed=np.zeros_like(good.speed), current=np.zeros_like(good.current)))


def test_sections_an_encoder_cannot_resolve_are_refused_with_its_quantum():
    # a drive SPEC 3.1's envelope allows (2^12 counts at 65 us: 24 rad/s per count and sample)
    # tested at w_max 16 rad/s: the speed reads one count now and then, no section shows
    drive = DriveConfig(M_max=609.0, M_N=205.0, T_Ei=1.18e-4, T_s=6.454e-5, encoder_counts=2**12, current_noise_std=0.095)
    rec = envelope_record(drive, 180.1, 15.54, J_sigma=0.2835, V_J=1.58, f_e=120.9, d=0.056, backlash=0.0, M_FC=8.21,
                          mu_F=0.23)
    check_record(rec)  # plausible as a record: the one-mass fit reads J_sigma from coarser speeds than this
    with pytest.raises(ValueError, match=r"^speed does not follow the torque: .*; the encoder hardly resolves this "
                                         r"test: its speed quantum .* = 23\.77 rad/s is 1\.5 x w_max"):
        analyze(rec)


def test_a_speed_one_count_above_three_times_w_max_is_the_encoder_not_wrong_units():
    # an envelope drive (2^12 counts at 89 us: 17.2 rad/s per count and sample) tested at w_max
    # 5.7 rad/s: the speed reads 0, 17.2 or 34.3 rad/s, 3.03 x w_max at its peak; it was called
    # "wrong units"
    drive = DriveConfig(M_max=671.0, M_N=353.0, T_Ei=1.69e-3, T_s=8.944e-5, encoder_counts=2**12, current_noise_std=4.38)
    rec = envelope_record(drive, 593.6, 5.655, J_sigma=315.0, V_J=0.888, f_e=117.4, d=0.0607, backlash=0.026,
                          M_FC=1.63, mu_F=2.11)
    assert np.abs(rec.speed).max() > 3.0 * 5.655
    check_record(rec)
    with pytest.raises(ValueError, match=r"the encoder hardly resolves this test: its speed quantum .* = 17\.15 rad/s"):
        analyze(rec)
