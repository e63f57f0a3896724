"""The frequency-response experiment: the multisine planned inside the limits on the model's closed
loop, the indirect estimate in the convention of ``LinearPlant.speed_response`` (hand-computed on
a synthetic record, and against the exact linear plant on a simulated drive), the resonance a
``stiff`` answer lacks, the CSV export."""

from __future__ import annotations

import csv
import math
from dataclasses import replace

import numpy as np
import pytest

sim = pytest.importorskip("sim")

from training.commissioning import PISpeedLaw, linear_plant, margins  # noqa: E402
from training.commissioning._frf import (FRF_SETTINGS, FRFPlan, MeasuredResponse, estimate_response, excited_lines,  # noqa: E402
                                         multisine)
from training.commissioning._measure import measured_response, plan_frf  # noqa: E402

CONFIG = sim.DriveConfig()
LIMITS = sim.DriveLimits(w_max=20.0, travel=5.0)
#: A short period keeps the simulated runs quick (3.9 Hz lines at 4 kHz).
FAST = replace(FRF_SETTINGS, period=1024)
#: A loop of w_c ~ 50 rad/s on J_sigma 0.05 kg m^2 (PI, no low-pass).
GAINS = (2.5, 0.08, 0.0)


def _plant(**kw: float) -> dict[str, float]:
    return {"J_sigma": 0.05, "V_J": 1.0, "f_e": 40.0, "d": 0.1, "backlash": 0.0, "M_FC": 0.0, "mu_F": 0.0, **kw}


def test_estimate_on_a_hand_made_record_is_the_convention_of_speed_response():
    """A record whose speed is half the torque commanded one sample before (``torque_ref[k]`` holds
    the torque commanded at ``k-1``): ``G(z) = 0.5 z^-1`` exactly, coherence 1."""
    period, periods = 64, 4
    lines = excited_lines(period, 100.0)
    d = np.tile(multisine(period, lines), periods)
    u = d + 0.3 * np.roll(d, 3)  # what the loop made of d: any periodic signal
    u = np.concatenate([u, [0.0]])
    torque_ref = np.concatenate([[0.0], u[:-1]])  # applied over [t_k, t_k+1): commanded at k-1
    speed = np.concatenate([[0.0], 0.5 * u[:-1]])
    rec = sim.Record(t=np.arange(len(u)) * 1e-3, speed=speed, current=np.zeros(len(u)), torque_ref=torque_ref, meta={})
    plan = FRFPlan(sim.Scenario(w_ref=np.zeros(len(u)), M_dist=np.concatenate([d, [0.0]])), lines, period, 1.0, {})
    w, G, coh = estimate_response(rec, plan, 1e-3)
    z = np.exp(1j * w * 1e-3)
    np.testing.assert_allclose(G, 0.5 / z, rtol=1e-9)
    np.testing.assert_allclose(w, 2 * np.pi * lines / (period * 1e-3))
    assert coh.min() > 1 - 1e-9


def test_the_experiment_is_planned_inside_its_share_of_the_limits():
    plan = plan_frf(_plant(), CONFIG, GAINS, None, LIMITS, FAST)
    p, share = plan.prediction, FAST.limit_share
    assert p["peak_speed"] <= share * LIMITS.w_max * (1 + 1e-9) and p["travel"] <= share * LIMITS.travel * (1 + 1e-9)
    assert p["peak_torque"] <= FAST.torque_share * LIMITS.torque_cap(CONFIG) * (1 + 1e-9)
    binding = [p["peak_speed"] / (share * LIMITS.w_max), p["travel"] / (share * LIMITS.travel),
               p["peak_torque"] / (FAST.torque_share * LIMITS.torque_cap(CONFIG))]
    assert max(binding) == pytest.approx(1.0)  # the largest amplitude inside all three
    sc = plan.scenario
    assert len(sc) == FAST.periods * FAST.period + 1 and not sc.w_ref.any()
    first = sc.M_dist[:FAST.period]
    np.testing.assert_allclose(sc.M_dist[FAST.period:2 * FAST.period], first)  # periodic
    assert abs(first.mean()) < 1e-9 * np.abs(first).max()  # zero mean: no drift of the travel


def _run(true: dict, identified: dict) -> tuple[MeasuredResponse, sim.Record, FRFPlan]:
    plan = plan_frf(identified, CONFIG, GAINS, None, LIMITS, FAST)
    law = PISpeedLaw(GAINS[0], GAINS[1], T_s=CONFIG.T_s, M_max=CONFIG.M_max, T_f=GAINS[2])
    rec = sim.SimulatedDrive(true, CONFIG, seed=3).run_closed_loop(law, plan.scenario, LIMITS)
    return measured_response(rec, plan, identified, CONFIG, FAST), rec, plan


def test_estimate_matches_the_known_linear_plant_where_coherent():
    """A linear plant (no friction, no backlash) on the simulated drive, identified exactly: where
    the coherence is high the estimate is the exact sampled plant's response within 5 % (the
    simulator's own integration places a resonance a little off the exact sampled model's: a
    well-damped one keeps that below the bound)."""
    true = _plant()
    measured, rec, _ = _run(true, true)
    exact = linear_plant(true, CONFIG).speed_response(np.exp(1j * measured.w * CONFIG.T_s))
    error = np.abs(measured.G / exact - 1)
    good = measured.coherence >= 0.995
    assert good.mean() > 0.3 and measured.w[good].max() > 2 * np.pi * 150  # well beyond the resonance
    assert error[good].max() < 0.05 and np.median(error[good]) < 0.01
    assert measured.resonances == ()  # the model has the resonance
    assert not rec.meta["aborted"]


def test_a_stiff_answer_hides_a_400_Hz_mode_the_experiment_finds():
    """The true plant has a 400 Hz mode at d 0.01 that the test run read as stiff: the measured
    response peaks where the one-mass model has none (within 5 % of the true mode)."""
    true = _plant(f_e=400.0, d=0.01)
    stiff = {"J_sigma": 0.05, "V_J": None, "f_e": None, "d": 0.0, "backlash": 0.0, "M_FC": 0.0, "mu_F": 0.0}
    assert margins(linear_plant(true, CONFIG), *GAINS).stable  # the loop the experiment runs on is safe
    measured, rec, plan = _run(true, stiff)
    found = [r / (2 * np.pi) for r in measured.resonances]
    assert len(found) == 1 and found[0] == pytest.approx(400.0, rel=0.05)
    assert not rec.meta["aborted"] and np.abs(rec.speed).max() < 2 * FAST.limit_share * LIMITS.w_max
    assert np.abs(np.cumsum(rec.speed) * CONFIG.T_s).max() < 2 * FAST.limit_share * LIMITS.travel


def test_csv_has_the_measured_and_the_model_columns(tmp_path):
    w = np.array([10.0, 100.0, 1000.0])
    G, model = np.array([1.0, 0.1j, -0.01]), np.array([1.0, 0.1, 0.01])
    path = MeasuredResponse(w=w, G=G, coherence=np.array([1.0, 0.9, 0.5]), T_s=1e-4, model=model).to_csv(tmp_path / "f.csv")
    rows = list(csv.reader(path.open()))
    assert rows[0] == ["f_Hz", "magnitude_dB", "phase_deg", "coherence", "model_magnitude_dB", "model_phase_deg"]
    vals = np.array(rows[1:], dtype=float)
    np.testing.assert_allclose(vals[:, 0], w / (2 * math.pi))
    np.testing.assert_allclose(vals[:, 1], [0.0, -20.0, -40.0], atol=1e-9)
    np.testing.assert_allclose(vals[:, 2], [0.0, 90.0, 180.0], atol=1e-9)
    np.testing.assert_allclose(vals[:, 4], [0.0, -20.0, -40.0], atol=1e-9)
    bare = MeasuredResponse(w=w, G=G, coherence=np.ones(3), T_s=1e-4).to_csv(tmp_path / "g.csv")
    assert next(csv.reader(bare.open())) == ["f_Hz", "magnitude_dB", "phase_deg", "coherence"]


def test_resonances_are_peaks_of_the_response_not_plateaus_or_a_models_anti_resonance():
    """Exact responses, coherence 1: a 300 Hz mode a one-mass model lacks is found (within 1 %); a
    decoupled motor (a backlash gap open: ``J_M`` alone, +``20 log10(1 + V_J)`` dB over the model)
    measured against a two-mass model is a plateau and the model's misplaced anti-resonance: none."""
    from training.commissioning._frf import find_resonances

    w = 2 * np.pi * np.geomspace(2.0, 1900.0, 400)
    z = np.exp(1j * w * CONFIG.T_s)
    two_mass = _plant(f_e=300.0, d=0.02)
    one_mass = {"J_sigma": 0.05}
    G_two = linear_plant(two_mass, CONFIG).speed_response(z)
    G_one = linear_plant(one_mass, CONFIG).speed_response(z)
    coherence = np.ones(len(w))
    found = find_resonances(w, G_two, coherence, G_one)
    assert len(found) == 1 and found[0] / (2 * np.pi) == pytest.approx(300.0, rel=0.01)
    decoupled = linear_plant({"J_sigma": 0.025}, CONFIG).speed_response(z)  # J_M of V_J 1
    assert find_resonances(w, decoupled, coherence, G_two) == ()
    assert find_resonances(w, G_two, np.zeros(len(w)), G_one) == ()  # nothing coherent: nothing found
