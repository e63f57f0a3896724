"""Test-signal adaptation through the drive: too small a response gets more torque; limits hold in
every run; a run the drive stops at a limit is never accepted."""

from __future__ import annotations


import numpy as np
import pytest

sim = pytest.importorskip("sim")

from training.commissioning import ExcitationRules, adapt_test_signal, measure_response  # noqa: E402
from training.commissioning._excitation import guarded_limits, stop_headroom  # noqa: E402

DRIVE = sim.DriveConfig()


class Recording(sim.SimulatedDrive):
    """The simulated drive, keeping every test record."""

    def __init__(self, params, **kw):
        super().__init__(params, **kw)
        self.records = []

    def run_test(self, M_star, w_max, limits):
        rec = super().run_test(M_star, w_max, limits)
        self.records.append(rec)
        return rec


def test_small_response_gets_larger_M_star():
    """Large inertia, start at 10 % torque: the elastic mode is below resolution -> M_star is raised."""
    drive = Recording(dict(J_sigma=0.2, V_J=1.0, f_e=30.0, d=0.02, backlash=0.0, M_FC=0.3, mu_F=0.001))
    res = adapt_test_signal(drive, sim.DriveLimits(w_max=100.0, travel=200.0))
    first = res.log[0]
    assert first["M_star"] == pytest.approx(0.1 * DRIVE.M_max)
    assert first["osc_quanta"] < ExcitationRules().min_osc_quanta and first["decision"].startswith("M_star")
    assert res.informative and res.log[-1]["M_star"] > first["M_star"] and res.log[-1]["decision"] == "accept"
    assert len(res.log) == len(drive.records) and res.record is drive.records[-1]
    assert res.log[-1]["f_osc"] == pytest.approx(30.0, rel=0.15)  # the measured oscillation's frequency


def test_timed_out_section_raises_torque():
    """Friction above the first M_star: section I never reaches w_max, times out -> more torque."""
    drive = sim.SimulatedDrive(dict(J_sigma=0.05, V_J=1.0, f_e=100.0, d=0.05, backlash=0.0, M_FC=0.6, mu_F=0.0), timeout=0.2)
    res = adapt_test_signal(drive, sim.DriveLimits(w_max=50.0, travel=50.0, M_max=4.0))
    assert res.log[0]["timed_out"] and res.log[0]["M_star"] == pytest.approx(0.4)
    assert res.log[1]["M_star"] > res.log[0]["M_star"] and not res.log[-1]["timed_out"]


@pytest.mark.parametrize(
    "params, limits",
    [
        (dict(J_sigma=1.0, V_J=2.0, f_e=10.0, d=0.02, backlash=0.0, M_FC=0.5, mu_F=0.0), sim.DriveLimits(w_max=30.0, travel=5.0)),
        (dict(J_sigma=0.01, V_J=0.3, f_e=300.0, d=0.05, backlash=0.002, M_FC=0.1, mu_F=0.0),
         sim.DriveLimits(w_max=6.0, travel=20.0, M_max=8.0)),
    ],
)
def test_limits_never_exceeded_in_any_run(params, limits):
    drive = Recording(params)
    adapt_test_signal(drive, limits)
    assert len(drive.records) >= 2
    for rec in drive.records:
        assert not rec.meta["aborted"]
        assert np.abs(rec.torque_ref).max() <= limits.torque_cap(DRIVE) + 1e-6
        assert np.abs(rec.speed).max() <= limits.w_max
        assert np.abs(np.cumsum(rec.speed) * DRIVE.T_s).max() <= limits.travel


def test_a_run_stopped_by_the_drive_is_never_accepted():
    """A drive whose travel limit is far tighter than the chain's (it stops every run that moves
    more than 2 mrad): every run is flagged, none accepted, w_max halves (E8); the second stopped run
    repeats the first's peak and travel (M* is already at E1's start), so the adaptation stops (E8b)."""
    drive = sim.SimulatedDrive(dict(J_sigma=0.05, V_J=1.0, f_e=50.0, d=0.05, backlash=0.0, M_FC=0.1, mu_F=0.0))
    tight = sim.DriveLimits(w_max=100.0, travel=0.002)

    class Tight:
        config = drive.config

        def run_test(self, M_star, w_max, limits):
            return drive.run_test(M_star, w_max, tight)

    res = adapt_test_signal(Tight(), sim.DriveLimits(w_max=100.0, travel=100.0), ExcitationRules(max_iterations=3))
    assert not res.informative and all(e["aborted"] for e in res.log)
    assert [e["w_max"] for e in res.log] == pytest.approx([res.log[0]["w_max"] / 2**i for i in range(2)])
    assert res.code == "run_repeated" and res.log[-1]["decision"] == "stop"
    rec = res.record
    stop = int(np.argmax(np.abs(np.cumsum(rec.speed) * DRIVE.T_s) > tight.travel))
    assert np.all(rec.torque_ref[stop + 2:] == 0.0)  # torque reference 0 from the stop on
    assert measure_response(rec, DRIVE)["aborted"]


def test_input_checks():
    with pytest.raises(ValueError):
        sim.DriveLimits(w_max=-1.0, travel=1.0)
    with pytest.raises(TypeError):
        adapt_test_signal("not a drive", sim.DriveLimits(w_max=10.0, travel=1.0))


def test_headroom_after_a_stop_by_hand():
    """E9: the drive is handed the user's limits less what a run gains after the stop."""
    rules = ExcitationRules()
    assert stop_headroom(800.0, DRIVE, rules) == pytest.approx(2.0 * 800.0 * (5e-4 + 3 * 2.5e-4))
    lim = guarded_limits(sim.DriveLimits(w_max=20.0, travel=5.0, M_max=8.0), 2.0, DRIVE, rules)
    assert (lim.w_max, lim.M_max) == (18.0, 8.0) and lim.travel == pytest.approx(5.0 - 20.0 * 2.0 * 1.25e-3)
    assert guarded_limits(sim.DriveLimits(w_max=20.0, travel=5.0), 50.0, DRIVE, rules).w_max == 10.0  # at most half


def test_soft_mode_swinging_on_after_section_one_stays_inside():
    """A 14 Hz mode (the issue's plant009): once section I lasts longer than half its period the load
    swings the motor far beyond w_max with zero torque (the drive's stop cannot help). With the swing
    allowance (E6) and the headroom (E9) every run stays inside the user's limit (a run may pass the
    lower limit handed to the drive: stopped, never accepted); without the allowance one does not."""
    p = dict(J_sigma=0.0237, V_J=1.31, f_e=14.4, d=0.067, backlash=0.0016, M_FC=0.2, mu_F=0.0036)
    limits = sim.DriveLimits(w_max=20.0, travel=5.0)
    drive = Recording(p)
    res = adapt_test_signal(drive, limits)
    assert res.log[0]["stop_at"] == pytest.approx(20.0 * (1 - ExcitationRules().first_headroom))
    assert all(e["stop_at"] < 20.0 for e in res.log) and not res.log[-1]["aborted"]
    assert max(np.abs(r.speed).max() for r in drive.records) < 20.0
    bold = Recording(p)
    adapt_test_signal(bold, limits, ExcitationRules(swing_allowance=0.0, first_headroom=0.0))
    assert max(np.abs(r.speed).max() for r in bold.records) > 20.0


@pytest.mark.parametrize("params", [
    # light plants (population seed 3, systems 6 and 8): with a 10 mrad travel limit, w_max lies below
    # the encoder's speed quantum, the speed runs on to the quanta it shows (a peak of 16-35 x w_max
    # that grows with M_star), and the travel follows the peak: a larger M_star alone ran 2.3 x past
    # the limit when the travel was predicted from w_max alone
    dict(J_sigma=0.01814, V_J=4.243, f_e=237.8, d=0.04247, backlash=0.0, M_FC=0.005657, mu_F=0.002512),
    dict(J_sigma=0.03363, V_J=1.670, f_e=5.099, d=0.03747, backlash=0.001331, M_FC=0.3969, mu_F=0.003137),
])
def test_a_travel_limit_below_the_quantized_run_on_holds(params):
    """E6d, with E0's refusal of such a limit switched off (run inside it anyway)."""
    limits = sim.DriveLimits(w_max=100.0, travel=0.01)
    drive = Recording(params)
    res = adapt_test_signal(drive, limits, ExcitationRules(refuse_uninformative_limits=False))
    for rec in drive.records:
        assert not rec.meta["aborted"]
        assert np.abs(np.cumsum(rec.speed) * DRIVE.T_s).max() <= limits.travel
    assert not res.informative and res.code == "limits_reached"  # said so, not run past
