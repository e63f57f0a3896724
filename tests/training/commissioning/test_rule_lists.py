"""The commissioning rules as lists of named functions: the order they apply in, their settings
(frozen, each bad value named), and single rules by hand on a typed run or design (no drive, no
margins: cheap)."""

from __future__ import annotations

import dataclasses
import math
import re

import pytest

sim = pytest.importorskip("sim")

from training.commissioning._bands import BandSettings, HiddenResonances, hidden_bands  # noqa: E402
from training.commissioning._excitation import (EXCITATION_RULES, RUN_AGAIN, ExcitationRules, ExcitationRun,  # noqa: E402
                                                Headroom, RuleDecision, RunFigures, RunPlan, e7_limits_reached,
                                                e8_stopped_by_drive, e10_speed_against_torque, judge_run, measure_response,
                                                measure_run)
from training.commissioning._loop import Mechanics  # noqa: E402
from training.commissioning._design import DesignSearch  # noqa: E402
from training.commissioning._rules import (CONTROLLER_RULES, ControllerSpec, Design, DesignInputs,  # noqa: E402
                                           r4_notch_frequencies, r6_backlash, uncertainty_set)
from training.errors import CommissioningError  # noqa: E402

DRIVE = sim.DriveConfig()
LIMITS = sim.DriveLimits(w_max=20.0, travel=5.0)


def test_rules_apply_in_the_documented_order():
    assert [r.__name__.split("_")[0] for r in EXCITATION_RULES] == [
        "e10", "e8b", "e8", "e3", "e4", "e5", "e3b", "e6b", "e4b", "e6d", "e6", "e6c", "e6", "e7", "e7", "e7", "run"]
    assert [r.__name__.split("_")[0] for r in CONTROLLER_RULES] == ["r6", "r7", "r4", "r5"]
    for rule in EXCITATION_RULES + CONTROLLER_RULES:  # each says when it runs: "E3, runs when ..."
        assert re.match(r"[\w ]+, runs (when|for|always)", rule.__doc__), rule.__name__


@pytest.mark.parametrize("settings, field", [
    (lambda: ExcitationRules(factor=1.0), "factor"),
    (lambda: ExcitationRules(max_iterations=0), "max_iterations"),
    (lambda: ExcitationRules(min_section_samples=40.5), "min_section_samples"),
    (lambda: ExcitationRules(speed_margin=math.nan), "speed_margin"),
    (lambda: ControllerSpec(f_e_spread=1.0), "f_e_spread"),
    (lambda: ControllerSpec(class_f_e=(500.0, 5.0)), "class_f_e"),
    (lambda: ControllerSpec(d_scale=(2.0, 0.5)), "d_scale"),
    (lambda: DesignSearch(ti_ratios=(2.0, -3.0)), "ti_ratios"),
    (lambda: DesignSearch(level_ratio=1.0), "level_ratio"),
    (lambda: BandSettings(nyquist_share=0.6), "nyquist_share"),
])
def test_settings_name_the_failing_field(settings, field):
    with pytest.raises(CommissioningError, match=rf"\.{field}: expected"):
        settings()


def test_settings_are_frozen():
    for settings in (ExcitationRules(), ControllerSpec(), BandSettings(), DesignSearch()):
        assert dataclasses.is_dataclass(settings)
        with pytest.raises(dataclasses.FrozenInstanceError):
            settings.factor = 3.0  # type: ignore[misc]


def _figures(**changes) -> RunFigures:
    """An informative run's figures, with ``changes``."""
    base = dict(along_torque_quanta=5000.0, samples_per_section=(400,) * 6, samples_min=400, timed_out=False, aborted=False,
                range_quanta=5000.0, osc_quanta=10.0, f_osc=30.0, longest_section=0.1, accel=100.0, peak_speed=2.0,
                travel=0.5, peak_torque_ref=2.0, peak_torque=2.0, duration=0.6)
    return RunFigures(**{**base, **changes})


def _run(figures: RunFigures, plan: RunPlan = RunPlan(2.0, 1.0), rules: ExcitationRules = ExcitationRules()) -> ExcitationRun:
    M_cap = LIMITS.torque_cap(DRIVE)
    return ExcitationRun.of(plan, figures, LIMITS, LIMITS, M_cap, Headroom().learned(plan, figures), None, DRIVE, rules)


def test_an_informative_run_is_accepted():
    decision = judge_run(_run(_figures()))
    assert (decision.verdict, decision.decision, decision.reason) == ("informative", "accept", "informative")
    assert decision.prediction is not None


def test_speed_against_torque_stops_first():
    run = _run(_figures(along_torque_quanta=-50.0, aborted=True))
    assert e10_speed_against_torque(run, RuleDecision(run.plan)).verdict == "speed_against_torque"
    assert judge_run(run).verdict == "speed_against_torque"


def test_a_stopped_run_halves_speed_and_torque_by_hand():
    rules = ExcitationRules()
    M_start = rules.M_star_start * LIMITS.torque_cap(DRIVE)
    run = _run(_figures(aborted=True), RunPlan(4.0 * M_start, 8.0))
    decision = e8_stopped_by_drive(run, RuleDecision(run.plan))
    assert decision.verdict == RUN_AGAIN and decision.reason == "stopped by the drive at a limit"
    assert (decision.plan.M_star, decision.plan.w_max) == (2.0 * M_start, 4.0)
    assert decision.plan.w_ceiling == pytest.approx(8.0 / math.sqrt(2)) and decision.plan.M_ceiling == pytest.approx(4.0 * M_start / math.sqrt(2))


def test_no_change_is_the_limit():
    run = _run(_figures(osc_quanta=0.5))
    decision = e7_limits_reached(run, RuleDecision(run.plan))
    assert decision.verdict == "limits_reached" and decision.decision == "stop" and "oscillation not visible" in decision.reason


def test_measured_figures_as_the_log_keys():
    rec = sim.SimulatedDrive(dict(J_sigma=0.05, V_J=1.0, f_e=50.0, d=0.05, backlash=0.0, M_FC=0.1, mu_F=0.0)).run_test(
        2.0, 2.0, LIMITS)
    figures = measure_run(rec, DRIVE)
    as_log = measure_response(rec, DRIVE)
    assert list(as_log) == [f.name for f in dataclasses.fields(RunFigures)]
    assert as_log["samples_per_section"] == list(figures.samples_per_section) and as_log["peak_speed"] == figures.peak_speed


def _inputs(structure: str, mech: Mechanics, spec: ControllerSpec, **kw) -> DesignInputs:
    return DesignInputs(structure, mech, DRIVE, DRIVE.T_s, DRIVE.T_Ei, spec,
                        uncertainty_set(mech, spec, structure=structure, **kw), kw.get("notch_at"))


def test_notch_frequencies_and_the_decoupled_motor_by_hand():
    """R4 offers the identified resonance f_0 as a notch frequency (none for a stiff answer); R6 puts
    a backlash plant's motor alone, J_sigma / (1 + V_J), into the set (the gap open)."""
    spec = ControllerSpec()
    soft = Mechanics(0.05, V_J=1.0, f_e=20.0, d=0.01)
    found = r4_notch_frequencies(_inputs("elastic", soft, spec), Design())
    assert found.notch_at == (pytest.approx(soft.derived.w_0 / (2 * math.pi)),) and found.rules[-1].startswith("R4")
    stiff = _inputs("stiff", Mechanics(0.05), spec)
    assert r4_notch_frequencies(stiff, Design()) == Design() and r6_backlash(stiff, Design()) == Design()
    backlash = _inputs("elastic_backlash", soft, spec)
    noted = r6_backlash(backlash, Design())
    members = [m for m in backlash.uncertainty.members() if m.label.startswith("decoupled motor")]
    motor = [m.mechanics for m in members]
    assert noted.rules[-1].startswith("R6") and len(motor) == 1 and not motor[0].two_mass
    assert motor[0].J_sigma == pytest.approx(0.05 / 2.0)
    assert members[0].transient and not any(m.transient for m in backlash.uncertainty.members() if m not in members)
    assert "PM >= 30 deg, GM >= 3 dB" in noted.rules[-1]
    assert not any(m.label.startswith("decoupled") for m in _inputs("elastic", soft, spec).uncertainty.members())


def test_hidden_resonances_unpack_as_before():
    entry = {"M_star": 20.0, "osc_quanta": 3.0, "f_osc": 440.0}
    found = hidden_bands(entry, 0.05, DRIVE, (0.2, 1.0, 5.0), f_lo=5.0, min_osc_quanta=2.0)
    bands, notch_at = found
    assert isinstance(found, HiddenResonances) and found.bands is bands and notch_at == 440.0
    narrower = hidden_bands(entry, 0.05, DRIVE, (0.2, 1.0, 5.0), f_lo=5.0, min_osc_quanta=2.0,
                            settings=BandSettings(nyquist_share=0.3))
    assert all(narrower.bands[v][1] == pytest.approx(0.3 / DRIVE.T_s) for v in (0.2, 1.0, 5.0))
