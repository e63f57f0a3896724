"""Informative within the limits, or say what to change (E0, E11) and the inertia F1 may trust.

The soft plants are plants 13, 22 and 44 of the 50-plant study (``sim.sample_population(50, 0)``) on
the independent plant of :mod:`remote_plant`, limits 20 rad/s and 5 rad: the rules alone end 22 and 44
"not informative" (refusal V6), with sections of a few ms against a 6.6 Hz (7.4 Hz) mode.
"""

from __future__ import annotations

import json
import math
import sys
from pathlib import Path

import pytest

sim = pytest.importorskip("sim")

from training.cli import main  # noqa: E402
from training.commissioning import ExcitationRules, adapt_test_signal, commission  # noqa: E402
from training.commissioning._excitation import (ExcitationResult, check_limits, measure_run, rigid_travel,  # noqa: E402
                                                trusted_inertia, trusted_J)
from training.errors import LimitsTooTight  # noqa: E402

HERE = Path(__file__).parent
sys.path.insert(0, str(HERE))
from setups import shipped_identifier  # noqa: E402
import remote_plant  # noqa: E402

DRIVE = sim.DriveConfig()
LIMITS = sim.DriveLimits(w_max=20.0, travel=5.0)
STUDY = sim.sample_population(50, 0).to_dicts()
SOFT, SOFT_LIGHT, STIFF = STUDY[13], STUDY[22], STUDY[33]  # 10 Hz V_J 5; 6.6 Hz V_J 0.74; 291 Hz V_J 0.36
REFUSED = STUDY[44]  # 7.4 Hz V_J 1.9: the rules alone end at the limits (V6)


class Counting(sim.SimulatedDrive):
    def __init__(self, params):
        super().__init__(params)
        self.runs = 0

    def run_test(self, M_star, w_max, limits):
        self.runs += 1
        return super().run_test(M_star, w_max, limits)


def _adapt(params, limits=LIMITS, rules=None):
    """The adaptation on the remote plant, and the largest true motor speed and travel of its runs."""
    drive = remote_plant.make_drive(params)
    try:
        res = adapt_test_signal(drive, limits, rules)
    finally:
        drive.close()
    return res, max(e["w_M"] for e in drive.experiments), max(e["phi_M"] for e in drive.experiments)


def test_limits_no_informative_test_fits_are_refused_before_any_run():
    """E0 by hand: 400 speed quanta of q_w = 2 pi / (2^20 * 250 us) need a peak of 200 q_w = 4.794
    rad/s; a rigid run at it with sections of 40 samples travels 0.7 * 4.794 * 0.01 = 0.03356 rad,
    plus the stop's run-on 4.794 * 2 (T_Ei + 3 T_s) = 0.01198 rad."""
    drive = Counting(SOFT)
    with pytest.raises(LimitsTooTight) as err:
        adapt_test_signal(drive, sim.DriveLimits(w_max=0.5, travel=0.01))
    w = 200 * 2 * math.pi / (2**20 * 250e-6)
    assert err.value.needed == pytest.approx({"w_max": w, "travel": 0.7 * w * 0.01 + w * 0.0025})
    text = str(err.value)
    assert "\n" not in text and "speed limit to >= 4.79 rad/s" in text and "travel limit to >= 0.0455 rad" in text
    assert drive.runs == 0
    for fits in (LIMITS, sim.DriveLimits(w_max=100.0, travel=50.0), sim.DriveLimits(w_max=6.0, travel=1.5, M_max=5.0)):
        check_limits(fits, DRIVE, ExcitationRules())  # the study's and the tests' limits: no refusal


def test_command_says_which_limit_to_raise(tmp_path, capsys):
    plant = tmp_path / "p.json"
    plant.write_text(json.dumps({**SOFT, "name": "p"}))
    assert main(["commission", "--params", str(plant), "--w-limit", "0.5", "--travel-limit", "0.01", "--no-progress"]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "raise the speed limit to >= 4.79 rad/s" in err


def test_rigid_travel_by_hand():
    """w = J = M* = 1: no friction 0.5 + 1 + 1/1.4; M_F = 1/4: sections I 4/3 s (2/3 rad), II 4/3 s
    (4/3 - 0.25 (4/3)^2 / 2 = 10/9 rad, to 2/3 rad/s), III (2/3)^2 / (2 * 0.95) rad."""
    assert rigid_travel(1.0, 1.0, 1.0) == pytest.approx(0.5 + 1 + 1 / 1.4)
    assert rigid_travel(1.0, 1.0, 1.0, 0.25) == pytest.approx(2 / 3 + 10 / 9 + (2 / 3) ** 2 / 1.9)
    assert rigid_travel(2.0, 3.0, 0.5) == pytest.approx(4 * 0.5 / 3 * (0.5 + 1 + 1 / 1.4))  # ~ w^2 J / M*
    assert rigid_travel(1.0, 1.0, 1.0, 1.0) == math.inf


def _trusted(params, M_star, w_max):
    drive = remote_plant.make_drive(params)
    try:
        record = drive.run_test(M_star, w_max, LIMITS)
    finally:
        drive.close()
    figures = measure_run(record, DRIVE)
    by_log = trusted_inertia(ExcitationResult(record, [record], [figures.as_dict()]))
    assert by_log == trusted_J(figures, ExcitationRules())
    return by_log, figures


def test_trusted_inertia_only_where_the_run_moved_the_load():
    """A short run on the soft plant (5 ms sections, its 10 Hz mode not completed) moves the motor
    alone: M* / accel is about J_M, 6 x too small; not trusted. A long run (sections of 0.2 s) and a
    stiff plant's run: the rigid-body fit's inertia within a few % of J_sigma."""
    short, figures = _trusted(SOFT, 8.0, 7.2)
    assert short is None and 8.0 / figures.accel < 0.25 * SOFT["J_sigma"]
    long, _ = _trusted(SOFT, 1.68, 6.0)
    assert long == pytest.approx(SOFT["J_sigma"], rel=0.05)
    stiff, _ = _trusted(STUDY[7], 20.0, 7.0)
    assert stiff == pytest.approx(STUDY[7]["J_sigma"], rel=0.03)


def test_long_section_probe_makes_the_soft_plant_informative_inside_the_limits():
    before, _, _ = _adapt(REFUSED, rules=ExcitationRules(max_probes=0))
    assert before.code == "limits_reached"  # the rules alone: refused V6
    res, w_M, phi_M = _adapt(REFUSED)
    assert res.informative and res.log[-1]["reason"].startswith("E11") and res.record is res.records[-1]
    assert res.log[-1]["M_star"] < 0.5 * before.log[-1]["M_star"] and res.log[-1]["samples_min"] >= 40
    assert w_M <= LIMITS.w_max and phi_M <= 0.8 * LIMITS.travel  # true motor states


@pytest.mark.parametrize("params, limit", [(SOFT_LIGHT, "travel"), (STIFF, "w_max")])
def test_where_no_test_fits_the_reason_names_the_limit_and_raising_it_is_enough(params, limit):
    """The light soft plant: longer sections need travel (planned on the envelope's inertia bound,
    6 x the motor's); the stiff one shows a rigid body: a hidden oscillation is accepted only at the
    torque cap, whose sections of 40 samples need speed. With the limit raised as said: informative."""
    res, _, _ = _adapt(params)
    assert not res.informative and set(res.needed) == {limit} and res.needed[limit] > getattr(LIMITS, limit)
    assert f"raise the {'travel' if limit == 'travel' else 'speed'} limit to >= {res.needed[limit]:.3g}" in res.reason
    assert res.record is not res.records[-1] or not res.probes  # an unused probe's record is not the answer
    raised = sim.DriveLimits(**{**{"w_max": LIMITS.w_max, "travel": LIMITS.travel}, limit: res.needed[limit]})
    again, w_M, phi_M = _adapt(params, raised)
    assert again.informative and w_M <= raised.w_max and phi_M <= raised.travel


def test_the_refused_soft_plant_gets_a_model_based_loop():
    """Plant 44 was refused V6 at 20 rad/s and 5 rad (F1): now a validated
    identification and a model-based loop, every experiment inside the limits."""
    drive = remote_plant.make_drive(REFUSED)
    try:
        rep = commission(drive, LIMITS, identifier=shipped_identifier(), name="plant044")
    finally:
        drive.close()
    assert rep.permission.allowed and rep.fallback is None and rep.delivered is not None
    assert rep.checks["within_limits"]
    assert max(e["w_M"] for e in drive.experiments) <= LIMITS.w_max and max(e["phi_M"] for e in drive.experiments) <= LIMITS.travel


def test_the_time_scale_probe_keeps_the_torque_and_raises_the_speed_where_the_speed_cap_allows():
    """Plant 23 (304 Hz): its informative run at 16 Nm and 6.53 rad/s has the time scale 0.0197 s,
    just below the envelope's 0.02 s (the identification then warned ``outside_envelope`` and R7c
    widened the design's set to +-50 %); E12 runs it again at the same 16 Nm and more speed, to
    1.15 x 0.02 s on the run's trusted inertia (a probe at less torque did not show the oscillation)."""
    res, w_M, phi_M = _adapt(STUDY[23])
    last, before = res.log[-1], res.log[-2]
    assert res.informative and last["reason"].startswith("E12") and res.record is res.records[-1]
    assert last["M_star"] == before["M_star"] and last["w_max"] > before["w_max"]
    assert before["rigid_J"] * before["w_max"] / before["M_star"] < 0.02
    assert last["w_max"] == pytest.approx(1.15 * 0.02 * last["M_star"] / before["rigid_J"], rel=1e-9)
    assert w_M <= LIMITS.w_max and phi_M <= LIMITS.travel


def test_an_informative_run_below_the_envelopes_time_scale_gets_one_probe_inside_it():
    """Plant 41 (171 Hz, backlash): its informative run at 4 Nm has the time scale J w_max / M* of
    0.017 s, below the envelope's 0.02 s (its answer failed validation, V3); E12 runs it again inside
    the envelope: the run's speed cap leaves no room for more speed, so at less torque (the study:
    then validated, a model-based loop)."""
    plant = STUDY[41]
    before, _, _ = _adapt(plant, rules=ExcitationRules(min_time_scale=0.0))
    res, w_M, phi_M = _adapt(plant)
    first, last = before.log[-1], res.log[-1]
    assert first["rigid_J"] * first["w_max"] / first["M_star"] < 0.02 and before.informative
    assert res.informative and last["reason"].startswith("E12") and res.record is res.records[-1]
    assert last["rigid_J"] * last["w_max"] / last["M_star"] >= 0.02 and last["rigid_J"] == pytest.approx(plant["J_sigma"], rel=0.05)
    assert w_M <= LIMITS.w_max and phi_M <= LIMITS.travel


def test_an_informative_run_whose_friction_lies_outside_the_envelope_gets_one_probe_at_more_torque():
    """Plant 38 (52 Hz, backlash, M_FC 0.20 Nm): the rules accept a run at a torque where the
    rigid-body friction is more than the envelope's 5 % of M* (its answer came out likely wrong and
    R7c widened the design's set to +-50 %: 0.21 of the oracle); E13 runs it again at the torque
    that puts the friction at 0.8 x 5 % of M* (the study: inside the envelope, 0.81 of the oracle)."""
    plant = STUDY[38]
    before, _, _ = _adapt(plant, rules=ExcitationRules(max_friction_share=1.0))
    res, w_M, phi_M = _adapt(plant)
    first, last = before.log[-1], res.log[-1]
    assert before.informative and first["rigid_M_F"] > 0.05 * first["M_star"]
    assert res.informative and last["reason"].startswith("E13") and res.record is res.records[-1]
    assert last["M_star"] == pytest.approx(first["rigid_M_F"] / (0.8 * 0.05), rel=1e-9)
    assert last["w_max"] == first["w_max"] and last["rigid_M_F"] <= 0.05 * last["M_star"]
    assert last["rigid_J"] * last["w_max"] / last["M_star"] >= 0.02
    assert w_M <= LIMITS.w_max and phi_M <= LIMITS.travel
