"""Section detection (training.identification._sections) on a small numpy two-mass plant under the SPEC 2 test signal.

``simulate_switching`` is a stand-alone reference of the test run (plant SPEC 1, signal SPEC 2),
used here and by test_one_mass.py and test_features.py so that those tests do not depend on
``sim``'s plant and signal (only its ``Record`` container).
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from sim import DriveConfig, Record, TestSignalConfig, TwoMassParams, responses_to_records, simulate_test
from training.identification._sections import SectionSplit, detect_sections

LEVELS = (1.0, 0.0, -0.7, -1.0, 0.0, 0.7)  # SPEC 2, typed here: the reference stands alone


def _record(t, speed, current, torque_ref, section, meta) -> Record:
    return Record(t=t, speed=speed, meta=meta, current=current, torque_ref=torque_ref, section=section)


def _friction_step(w: float, M: float, J: float, M_FC: float, mu_F: float, h: float) -> float:
    """Speed after a step ``h`` of a mass ``J`` driven by ``M`` against Coulomb friction with stiction."""
    if w == 0.0 and abs(M) <= M_FC:
        return 0.0
    new = w + h * (M - M_FC * math.copysign(1.0, w if w != 0 else M) - mu_F * w) / J
    return 0.0 if w != 0.0 and w * new < 0 else new


def simulate_switching(J_sigma=0.05, V_J=1.0, f_e=30.0, d=0.02, backlash_deg=0.0, M_FC=0.2, mu_F=0.002,
                       M_star=10.0, w_max=100.0, T_s=2.5e-4, T_Ei=5e-4, counts=2**20, noise=0.01,
                       substeps=8, seed=0, tail=0.05, timeout=10.0, elastic=True):
    """Simulate the switching-speed-controller test run; returns a ``sim.Record``.

    Semi-implicit Euler with ``substeps`` per sample; shaft with dead zone; Coulomb friction with
    stiction at the load. ``elastic=False`` gives a rigid one-mass plant (J_sigma only).
    """
    rng = np.random.default_rng(seed)
    J_M = J_sigma / (1.0 + V_J)
    J_L = J_sigma - J_M
    w0 = 2 * math.pi * f_e / math.sqrt(max(1 - d * d, 1e-12))
    C_F = w0 ** 2 * J_M * J_L / J_sigma
    D_F = 2 * d * C_F / w0
    s = math.radians(backlash_deg) / 2
    h = T_s / substeps
    wM = wL = dphi = MM = phiM = 0.0
    sec, k_sec, dur = 1, 0, {}
    M_ref = M_star
    out_w, out_i, out_ref, out_sec = [], [], [], []
    q = 2 * math.pi / counts
    last_count = 0
    k = 0
    tail_left = None
    while True:
        # measure at t_k (speed: encoder difference over the last sample; current: M_M(t_k));
        # the sample is labelled with the section of the M_ref applied from t_k on
        count = math.floor(phiM / q)
        w_m = (count - last_count) * q / T_s
        last_count = count
        out_w.append(w_m)
        out_i.append(MM + noise * rng.standard_normal())
        out_ref.append(M_ref)
        out_sec.append(sec if tail_left is None else 0)
        k += 1
        # plant over one sample with M_ref held
        for _ in range(substeps):
            MM += h * (M_ref - MM) / T_Ei
            if elastic:
                if abs(dphi) <= s:
                    MS = 0.0
                else:
                    MS = C_F * (dphi - s * math.copysign(1.0, dphi)) + D_F * (wM - wL)
                wM += h * (MM - MS) / J_M
                wL = _friction_step(wL, MS, J_L, M_FC, mu_F, h)
                dphi += h * (wM - wL)
            else:
                wM = _friction_step(wM, MM, J_sigma, M_FC, mu_F, h)
            phiM += h * wM
        # controller (applies from the next sample)
        if tail_left is not None:
            tail_left -= 1
            if tail_left <= 0:
                break
            continue
        k_sec += 1
        t_sec = k_sec * T_s
        end = t_sec >= timeout
        if sec == 1:
            end |= w_m >= w_max
        elif sec == 2:
            end |= k_sec >= dur[1] or w_m <= 0.2 * w_max
        elif sec == 3:
            end |= w_m <= 0
        elif sec == 4:
            end |= w_m <= -w_max
        elif sec == 5:
            end |= k_sec >= dur[4] or w_m >= -0.2 * w_max
        elif sec == 6:
            end |= w_m >= 0
        if end:
            dur[sec] = k_sec
            if sec == 6:
                tail_left = int(round(tail / T_s))
                M_ref = 0.0
            else:
                sec += 1
                M_ref = LEVELS[sec - 1] * M_star
            k_sec = 0
    n = len(out_w)
    t = np.arange(1, n + 1) * T_s
    meta = {"K_M": 1.0, "T_Ei": T_Ei, "T_s": T_s, "encoder_counts": counts, "M_star": M_star, "w_max": w_max,
            "truth": {"J_sigma": J_sigma, "V_J": V_J, "f_e": f_e, "d": d, "M_FC": M_FC, "mu_F": mu_F,
                      "backlash": 2 * s}}
    return _record(t, np.array(out_w), np.array(out_i), np.array(out_ref), np.array(out_sec, dtype=int), meta)


def true_bounds(section: np.ndarray) -> np.ndarray:
    """(6, 2) start/stop indices from a section column."""
    return np.array([[np.flatnonzero(section == k)[0], np.flatnonzero(section == k)[-1] + 1] for k in range(1, 7)])


@pytest.fixture(scope="module")
def elastic_record():
    return simulate_switching(J_sigma=0.03, V_J=2.0, f_e=40.0, d=0.02, M_FC=0.2, seed=1)


def _no_column(rec: Record) -> Record:
    meta = {k: v for k, v in rec.meta.items() if k != "M_star"}
    return _record(rec.t, rec.speed, rec.current, None, None, meta)


def test_detects_sections_from_current_within_two_samples(elastic_record):
    split = detect_sections(_no_column(elastic_record))
    assert isinstance(split, SectionSplit)
    err = np.abs(split.bounds - true_bounds(elastic_record.section))
    assert err.max() <= 2, (split.bounds, true_bounds(elastic_record.section))
    assert split.M_star == pytest.approx(10.0, rel=0.02)
    assert split.M_star_estimated


def test_uses_torque_ref_exactly_when_given(elastic_record):
    rec = _record(elastic_record.t, elastic_record.speed, elastic_record.current, elastic_record.torque_ref,
                  None, dict(elastic_record.meta))
    split = detect_sections(rec)
    assert np.array_equal(split.bounds, true_bounds(elastic_record.section))
    assert split.source == "torque_ref"


def test_arrays_interface_and_known_M_star(elastic_record):
    split = detect_sections(speed=elastic_record.speed, torque=elastic_record.current, T_s=2.5e-4, M_star=10.0)
    assert not split.M_star_estimated
    assert np.abs(split.bounds - true_bounds(elastic_record.section)).max() <= 2
    lab = split.labels()
    assert lab.shape == elastic_record.speed.shape
    assert set(np.unique(lab)) <= set(range(8))


def test_scaled_torque_and_backlash_ringing():
    rec = simulate_switching(J_sigma=0.02, V_J=4.0, f_e=15.0, d=0.01, backlash_deg=0.5, M_FC=0.4, M_star=3.0,
                             w_max=40.0, seed=3)
    split = detect_sections(_no_column(rec))
    assert np.abs(split.bounds - true_bounds(rec.section)).max() <= 3
    assert split.M_star == pytest.approx(3.0, rel=0.03)


def test_rejects_constant_speed():
    n = 4000
    with pytest.raises(ValueError, match="constant"):
        detect_sections(speed=np.full(n, 3.0), torque=np.zeros(n), T_s=2.5e-4)


def test_rejects_saturated_speed(elastic_record):
    w = np.clip(elastic_record.speed, -30, 30)
    with pytest.raises(ValueError, match="saturat"):
        detect_sections(speed=w, torque=elastic_record.current, T_s=2.5e-4)


def test_rejects_unrelated_signals():
    rng = np.random.default_rng(0)
    n = 4000
    with pytest.raises(ValueError, match="section"):
        detect_sections(speed=np.cumsum(rng.standard_normal(n)), torque=rng.standard_normal(n), T_s=2.5e-4)
    with pytest.raises(ValueError):
        detect_sections(speed=np.sin(np.arange(n) / 100) * 50, torque=np.full(n, 5.0), T_s=2.5e-4)


def test_rejects_bad_input():
    with pytest.raises(ValueError, match="same length"):
        detect_sections(speed=np.zeros(10), torque=np.zeros(11), T_s=1e-3)
    with pytest.raises(ValueError, match="T_s"):
        detect_sections(speed=np.arange(100.0), torque=np.ones(100), T_s=-1.0)
    with pytest.raises(ValueError):
        detect_sections(speed=np.arange(100.0), torque=np.full(100, np.nan), T_s=1e-3)


def test_torque_ringing_and_noise():
    """A damped 80 Hz ringing of 10 % M* after every step and 5x the current noise."""
    rec = simulate_switching(J_sigma=0.03, V_J=2.0, f_e=40.0, d=0.02, M_FC=0.2, seed=4, noise=0.05)
    true = true_bounds(rec.section)
    ring = np.zeros_like(rec.current)
    t = np.arange(ring.size) * rec.meta["T_s"]
    for a in true[:, 0]:
        tt = t[a:] - t[a]
        ring[a:] += 0.1 * 10.0 * np.exp(-tt / 0.02) * np.sin(2 * np.pi * 80.0 * tt)
    split = detect_sections(speed=rec.speed, torque=rec.current + ring, T_s=rec.meta["T_s"], T_Ei=rec.meta["T_Ei"])
    assert np.abs(split.bounds - true).max() <= 2, (split.bounds, true)
    assert split.M_star == pytest.approx(10.0, rel=0.03)


def envelope_record(drive: DriveConfig, M_star: float, w_max: float, **mechanics: float) -> Record:
    """One simulated test run (with ``torque_ref`` and the ``section`` column) on ``drive``."""
    params = TwoMassParams(**mechanics)
    signal = TestSignalConfig(M_star=M_star, w_max=w_max)
    return responses_to_records(simulate_test(params, drive, signal, seed=3), params.reshape(1), drive, signal)[0]


def test_a_section_shorter_than_the_noise_filter_is_found_in_the_torque_reference():
    # a drive of SPEC 3.1's envelope (seed 11) whose section III lasts 4 samples (1 ms): the
    # reference is exact, so no run of it is a transition (2 ms runs were dropped: no sections)
    drive = DriveConfig(M_max=10.9, M_N=3.64, T_Ei=4.77e-4, T_s=2.51e-4, encoder_counts=2**19, current_noise_std=0.129)
    rec = envelope_record(drive, 4.84, 104.8, J_sigma=1.14e-3, V_J=2.87, f_e=28.6, d=0.02, backlash=5e-4,
                          M_FC=0.0715, mu_F=2.5e-4)
    column = np.asarray(rec.section)
    lengths = [int((column == k).sum()) for k in range(1, 7)]
    assert min(lengths) < 2e-3 / drive.T_s
    split = detect_sections(rec)
    assert split.source == "torque_ref"
    found = split.bounds[:, 1] - split.bounds[:, 0]
    np.testing.assert_array_equal(found[1:], lengths[1:])  # I: the column counts sample 0 (reference 0) too
    assert abs(found[0] - lengths[0]) <= 1
