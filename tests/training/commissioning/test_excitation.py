"""Test-signal adaptation: too small a response gets more torque; limits hold in every run."""

from __future__ import annotations

import math

import numpy as np
import pytest

sim = pytest.importorskip("sim")
if not hasattr(sim, "simulate_test") or not hasattr(sim, "TwoMassParams"):
    pytest.skip("sim.simulate_test / sim.TwoMassParams not available yet", allow_module_level=True)

from training.commissioning._excitation import ExcitationLimits, ExcitationRules, adapt_test_signal, measure_response, sim_test_runner  # noqa: E402

DRIVE = sim.DriveConfig()


def recording_runner(params):
    runs = []
    inner = sim_test_runner(sim.TwoMassParams.from_dicts(params), DRIVE)

    def run(signal):
        resp = inner(signal)
        runs.append((signal, resp))
        return resp

    return run, runs


def test_small_response_gets_larger_M_star():
    """Large inertia, start at 10 % torque: the elastic mode is below resolution -> M_star is raised."""
    params = dict(J_sigma=0.2, V_J=1.0, f_e=30.0, d=0.02, backlash=0.0, M_FC=0.3, mu_F=0.001)
    run, runs = recording_runner(params)
    res = adapt_test_signal(run, DRIVE, ExcitationLimits(w_limit=100.0, travel_limit=200.0))
    first = res.log[0]
    assert first["M_star"] == pytest.approx(0.1 * DRIVE.M_max)
    assert first["osc_quanta"] < ExcitationRules().min_osc_quanta and first["decision"].startswith("M_star")
    assert res.informative and res.signal.M_star > first["M_star"]
    assert res.log[-1]["decision"] == "accept" and res.log[-1]["osc_quanta"] >= 2.0
    assert len(res.log) == len(runs) and res.response is runs[-1][1]
    for entry in res.log:
        for key in ("M_star", "w_max", "samples_min", "range_quanta", "osc_quanta", "travel", "decision"):
            assert key in entry


def test_timed_out_section_raises_torque():
    """Friction above the first M_star: section I never reaches w_max, times out -> more torque."""
    params = dict(J_sigma=0.05, V_J=1.0, f_e=100.0, d=0.05, backlash=0.0, M_FC=0.6, mu_F=0.0)
    run, _ = recording_runner(params)
    res = adapt_test_signal(run, DRIVE, ExcitationLimits(w_limit=50.0, travel_limit=50.0, M_star_max=4.0), timeout=0.2)
    assert res.log[0]["timed_out"] and res.log[0]["M_star"] == pytest.approx(0.4)
    assert res.log[1]["M_star"] > res.log[0]["M_star"]
    assert not res.log[-1]["timed_out"]


@pytest.mark.parametrize(
    "params, limits",
    [
        (dict(J_sigma=1.0, V_J=2.0, f_e=10.0, d=0.02, backlash=0.0, M_FC=0.5, mu_F=0.0),
         ExcitationLimits(w_limit=30.0, travel_limit=5.0)),  # travel-bound
        (dict(J_sigma=0.01, V_J=0.3, f_e=300.0, d=0.05, backlash=0.002, M_FC=0.1, mu_F=0.0),
         ExcitationLimits(w_limit=6.0, travel_limit=20.0, M_star_max=8.0)),  # speed- and torque-bound
    ],
)
def test_limits_never_exceeded_in_any_run(params, limits):
    run, runs = recording_runner(params)
    res = adapt_test_signal(run, DRIVE, limits)
    M_cap = min(DRIVE.M_max, limits.M_star_max or math.inf)
    assert len(runs) >= 2
    for signal, resp in runs:
        n = int(resp.length.reshape(-1)[0])
        w = resp.speed.reshape(-1)[:n].double().numpy()
        tr = resp.torque_ref.reshape(-1)[:n].double().numpy()
        phi = np.cumsum(w) * DRIVE.T_s
        assert signal.M_star <= M_cap + 1e-12
        assert np.abs(tr).max() <= M_cap + 1e-6
        assert np.abs(w).max() <= limits.w_limit
        assert np.abs(phi).max() <= limits.travel_limit
    figs = measure_response(res.response, DRIVE)
    assert figs["peak_speed"] <= limits.w_limit and figs["travel"] <= limits.travel_limit


def test_input_checks():
    with pytest.raises(ValueError):
        ExcitationLimits(w_limit=-1.0, travel_limit=1.0)
    with pytest.raises(TypeError):
        adapt_test_signal("not a plant", DRIVE, ExcitationLimits(w_limit=10.0, travel_limit=1.0))
