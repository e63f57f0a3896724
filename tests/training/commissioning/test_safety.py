"""Safety of the commissioning (SPEC 8.2): the limits are the user's, the first record that shows
one passed ends the experiments on that drive (nothing more runs, nothing is delivered, one line
says which limit, by how much, in which experiment); a file drive's recordings must be the
experiment requested; a drive that does not answer, exits, or returns a cut, malformed or
otherwise sampled record is a fault at that experiment."""

from __future__ import annotations

import json
import subprocess
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

sim = pytest.importorskip("sim")

from training.cli import main  # noqa: E402
from training.commissioning import CommissioningConfig, FileDrive, commission  # noqa: E402
from training.errors import AxisNotHeld, CommissioningError, ExperimentPending  # noqa: E402

HERE = Path(__file__).parent
sys.path.insert(0, str(HERE))
from setups import FAST, LIMITS, STIFF, ONE_MASS, shipped_identifier  # noqa: E402
import faulty_drives  # noqa: E402

DRIVES = HERE / "faulty_drives.py"
USER_LIMITS = ["--w-limit", "20", "--travel-limit", "5"]
PLANT = faulty_drives.PLANT


def _one_error_line(capsys, *words):
    err = capsys.readouterr().err
    assert len(err.strip().splitlines()) == 1 and "Traceback" not in err, err
    for w in words:
        assert w in err, err
    return err


# --------------------------------------------------------------------------- 1: a passed limit ends the experiments


def test_a_drive_applying_more_torque_than_asked_ends_the_experiments_at_once(stub):
    """8 x the asked torque against a 5 Nm cap: the rest check (torque 0) passes, the second test
    run (experiment 3) measures 8 Nm; nothing runs after it, nothing is delivered, the report's
    text and JSON say which limit, by how much, where."""
    drive = faulty_drives.torque8()
    rep = commission(drive, sim.DriveLimits(w_max=20.0, travel=5.0, M_max=5.0), identifier=stub("elastic", PLANT), config=FAST)
    b = rep.breach
    assert b is not None and [p.limit for p in b.passed] == ["measured torque"]
    assert drive.experiments == b.experiment == 3 and b.kind == "test run" and b.M_star == pytest.approx(1.0)
    assert b.passed[0].value == pytest.approx(8.0, rel=0.01) and b.passed[0].bound == 5.0
    assert rep.delivered is None and not rep.runs and rep.identification is None
    d = json.loads(json.dumps(rep.to_dict()))
    assert d["delivered"] is None and d["breach"]["experiment"] == 3 and d["breach"]["passed"][0]["limit"] == "measured torque"
    text = rep.to_text()
    assert "limit passed in experiment 3 (test run, M* 1 Nm): measured torque 8 Nm > cap 5 Nm (x1.6)" in text
    assert "8 delivered: none (limit passed in experiment 3)" in text
    assert "measured torque 8" in next(ln for ln in text.splitlines() if "outside the limits" in ln)  # the check names torque


def test_a_drive_ignoring_the_limits_ends_at_its_first_test_record(stub):
    """The rest check (experiment 1) holds the axis; the first test run (experiment 2) runs away."""
    drive = faulty_drives.speed_runaway()
    rep = commission(drive, LIMITS, identifier=stub("elastic", PLANT), config=FAST)
    assert rep.rest is not None and rep.rest.held
    assert drive.experiments == 2 and rep.breach.experiment == 2 and rep.breach.kind == "test run" and rep.delivered is None
    assert {p.limit for p in rep.breach.passed} & {"speed", "travel"}
    assert rep.excitation.code == "limit_passed" and rep.excitation.log[-1]["decision"] == "stop"


def test_a_closed_loop_past_the_limits_gets_no_further_run_and_no_fallback(stub):
    """The closed loop ignores the limits: its first run ends everything; the fallback F1 does not
    run on that drive."""
    plant = dict(PLANT, J_sigma=0.01)
    drive = faulty_drives.LoopRunawayDrive(plant)
    rep = commission(drive, LIMITS, identifier=stub("elastic", plant), config=FAST)
    assert drive.calls[0] == "rest" and drive.calls.count("rest") == 1  # the rest check, as asked
    assert drive.calls[-1] == "closed_loop" and drive.calls.count("closed_loop") == 1
    assert rep.breach.kind == "closed loop 0" and rep.breach.experiment == len(drive.calls)
    assert "speed" in {p.limit for p in rep.breach.passed}
    assert rep.delivered is None and rep.fallback is None and not rep.fallback_runs
    assert rep.proposal is not None and rep.identification.ok  # what the chain had reached is reported


class _FallingDrive(sim.SimulatedDrive):
    """In its closed loops a 30 Nm load it does not hold pulls the axis, the limits ignored.
    ``calls``: the law type (``hold``, ``PI``) or ``test`` of every experiment, in order."""

    def __init__(self, *args, **kwargs):
        super().__init__(*args, **kwargs)
        self.calls = []

    def run_test(self, M_star, w_max, limits):
        self.calls.append("test")
        return super().run_test(M_star, w_max, limits)

    def run_closed_loop(self, law, scenario, limits):
        self.calls.append(law.params["type"])
        falling = sim.Scenario(scenario.w_ref, scenario.M_dist + 30.0)
        return super().run_closed_loop(law, falling, sim.DriveLimits(w_max=1e9, travel=1e9, M_max=limits.M_max))


def test_a_limit_passed_in_the_rest_check_ends_the_experiments_at_once(stub):
    """The axis falls past the 10 rad/s limit while it should rest (experiment 1, before any test):
    nothing runs after it, one line names the limit, the experiment and the rest check."""
    drive, ident = _FallingDrive(PLANT), stub("elastic", PLANT)
    with pytest.raises(AxisNotHeld) as err:
        commission(drive, sim.DriveLimits(w_max=10.0, travel=5.0), identifier=ident, config=FAST)
    message = str(err.value)
    assert drive.calls == ["hold"] and drive.experiments == 1 and not ident.records
    assert "limit passed in experiment 1 (rest check): speed" in message and "> limit 10 rad/s" in message
    assert "no further experiment ran" in message and "\n" not in message
    assert err.value.peak_speed > 10.0


class _EagerDrive(sim.SimulatedDrive):
    """Runs its test to 10 x the asked w_max, but stops at the (guarded) limit it is handed."""

    def run_test(self, M_star, w_max, limits):
        return super().run_test(M_star, 10 * w_max, limits)


def test_a_stop_at_the_limit_handed_to_the_drive_is_no_breach(stub):
    """The chain hands the drive guarded limits; a drive that stops there and coasts on inside the
    user's limits has kept them: the chain goes on."""
    rep = commission(_EagerDrive(PLANT), sim.DriveLimits(w_max=20.0, travel=1000.0), identifier=stub("elastic", PLANT),
                     config=FAST)
    assert rep.excitation.log[0]["aborted"] and rep.excitation.log[0]["peak_speed"] < 20.0
    assert rep.breach is None and rep.delivered is not None


def test_command_reports_a_passed_limit_in_one_line(tmp_path, capsys):
    shipped_identifier()
    out = tmp_path / "out.json"
    assert main(["commission", "--drive", f"{DRIVES}:torque8", *USER_LIMITS, "--M-max", "5", "--json", str(out), "--quiet",
                 "--no-progress"]) == 3
    _one_error_line(capsys, "drive 'drive'", "limit passed in experiment 3", "measured torque 8 Nm > cap 5 Nm",
                    "no controller delivered")
    rep = json.loads(out.read_text())["reports"][0]
    assert rep["delivered"] is None and rep["breach"]["passed"][0]["limit"] == "measured torque"


# --------------------------------------------------------------------------- 2: limits are the user's


def test_command_requires_limits_with_a_drive_of_ones_own(capsys):
    """No default limits for a user's drive: refused before the drive's module is even imported
    (its factory would say 'cannot open /dev/ttyUSB0')."""
    assert main(["commission", "--drive", f"{DRIVES}:factory_raises", "--no-progress"]) == 2
    err = _one_error_line(capsys, "--w-limit and --travel-limit required")
    assert "ttyUSB0" not in err
    assert main(["commission", "--drive", f"{DRIVES}:factory_raises", "--w-limit", "20", "--no-progress"]) == 2
    err = _one_error_line(capsys, "--travel-limit required")
    assert "ttyUSB0" not in err


def test_the_drive_is_handed_a_concrete_torque_limit(stub):
    """A drive written from SPEC 8.1 reads ``limits.M_max`` as a number: without a user torque
    limit it is the drive's own M_max, never None."""
    drive = faulty_drives.Spec81Drive(STIFF)
    rep = commission(drive, LIMITS, identifier=stub("stiff", ONE_MASS), config=replace(FAST, tune=False))
    assert rep.breach is None and rep.delivered is not None
    assert drive.handed and all(isinstance(lim.M_max, float) and lim.M_max == 20.0 for lim in drive.handed)
    assert rep.to_dict()["limits"]["M_max"] == 20.0


# --------------------------------------------------------------------------- 3: --resume recordings


def _folder(tmp_path: Path) -> Path:
    conf = sim.DriveConfig()
    (tmp_path / "drive.json").write_text(json.dumps({"config": {k: getattr(conf, k) for k in
                                                                ("T_s", "K_M", "T_Ei", "encoder_counts", "M_N", "M_max")},
                                                     "limits": {"w_max": 20.0, "travel": 5.0}}))
    return tmp_path


def _pending(folder: Path, ident, cfg=FAST) -> dict:
    with pytest.raises(ExperimentPending) as pending:
        commission(FileDrive(folder), LIMITS, identifier=ident, config=cfg)
    return json.loads(Path(pending.value.request).read_text())


def _answer(rec, folder: Path, n: int, drop=()) -> None:
    """The recording as NNN.csv + NNN.json, its JSON without the keys ``drop``."""
    rec.meta.pop("aborted", None)
    _, meta = sim.write_record(folder / f"{n:03d}", rec)
    meta.write_text(json.dumps({k: v for k, v in json.loads(meta.read_text()).items() if k not in drop}))


def _rest_answered(folder: Path, ident, answer: sim.SimulatedDrive, cfg=FAST) -> dict:
    """Request 001 (the rest check: the speed loop off) answered by ``answer`` as asked; the next request."""
    from training.commissioning import HoldLaw

    rest = _pending(folder, ident, cfg)
    assert rest["experiment"] == 1 and rest["kind"] == "closed_loop" and rest["law"] == {"type": "hold"}
    scenario = sim.Scenario(np.array(rest["scenario"]["w_ref"]), np.array(rest["scenario"]["M_dist"]))
    _answer(answer.run_closed_loop(HoldLaw(), scenario, sim.DriveLimits(**rest["limits"])), folder, 1)
    return _pending(folder, ident, cfg)


def test_resume_a_recording_past_the_limits_is_a_breach(tmp_path, stub):
    """The drive ran the requested test (experiment 2, after the rest check) away to 50 rad/s
    against the 20 rad/s limit."""
    folder, ident = _folder(tmp_path), stub("elastic", PLANT)
    req = _rest_answered(folder, ident, sim.SimulatedDrive(PLANT))
    assert req["experiment"] == 2 and req["kind"] == "test"
    rec = sim.SimulatedDrive(PLANT).run_test(req["M_star"], 50.0, sim.DriveLimits(w_max=1e3, travel=1e3))
    rec.meta["w_max"] = req["w_max"]
    _answer(rec, folder, 2)
    rep = commission(FileDrive(folder), LIMITS, identifier=ident, config=FAST)
    assert rep.breach.experiment == 2 and rep.breach.kind == "test run" and rep.delivered is None
    assert "speed" in {p.limit for p in rep.breach.passed}
    assert not (folder / "003_request.json").exists()  # nothing more is asked for


@pytest.mark.parametrize("column", ["torque_ref", "current"])
def test_resume_refuses_a_recording_of_another_torque(tmp_path, stub, column):
    """5 x the requested M_star (its JSON without M_star): another experiment, by its torque
    reference, or by its measured torque where it has none."""
    folder, ident = _folder(tmp_path), stub("elastic", PLANT)
    req = _rest_answered(folder, ident, sim.SimulatedDrive(PLANT))
    rec = sim.SimulatedDrive(PLANT).run_test(5 * req["M_star"], req["w_max"], sim.DriveLimits(**req["limits"]))
    if column == "current":
        rec.torque_ref = None
    _answer(rec, folder, 2, drop=("M_star", "w_max"))
    with pytest.raises(CommissioningError, match=r"002\.csv: its (torque_ref|measured torque) reaches .* another experiment"):
        commission(FileDrive(folder), LIMITS, identifier=ident, config=FAST)


def test_resume_recordings_need_not_repeat_the_drive_config(tmp_path, stub):
    """drive.json's config holds K_M, T_Ei, encoder_counts, M_N, M_max, T_s: a recording may leave
    them out; one that states another value is refused naming its file."""
    folder, ident = _folder(tmp_path), stub("elastic", PLANT)
    req = _rest_answered(folder, ident, sim.SimulatedDrive(PLANT))
    rec = sim.SimulatedDrive(PLANT).run_test(req["M_star"], req["w_max"], sim.DriveLimits(**req["limits"]))
    _answer(rec, folder, 2, drop=("K_M", "T_Ei", "T_s", "encoder_counts", "M_N", "M_max", "current_noise_std"))
    assert _pending(folder, ident)["experiment"] == 3
    meta = json.loads((folder / "002.json").read_text())
    (folder / "002.json").write_text(json.dumps({**meta, "K_M": 2.0}))
    with pytest.raises(CommissioningError, match=r"002\.json: K_M 2 disagrees with the drive's config in drive\.json"):
        commission(FileDrive(folder), LIMITS, identifier=ident, config=FAST)


def _sim_law(params):
    """A speed-loop law loaded from the request's ``law`` (the PI law; the rest check is answered
    by :func:`_rest_answered`)."""
    from training.commissioning import NotchSpec, PISpeedLaw

    if params["type"] != "PI":
        raise ValueError(f"law type {params['type']!r}: expected the PI law")
    return PISpeedLaw(params["Kp"], params["Ti"], T_s=params["T_s"], M_max=params["M_max"], T_f=params["T_f"],
                      notch=tuple(NotchSpec(**n) for n in params["notches"]))


def test_resume_refuses_a_closed_loop_recording_of_another_length(tmp_path, stub):
    folder, ident, cfg = _folder(tmp_path), stub("stiff", ONE_MASS), replace(FAST, tune=False)
    answer = sim.SimulatedDrive(STIFF)
    req, n = _rest_answered(folder, ident, answer, cfg), 2  # request 001: the rest check, answered as asked
    while req["kind"] != "closed_loop":
        if n >= 20:
            pytest.fail("no closed-loop experiment was asked for after the rest check")
        _answer(answer.run_test(req["M_star"], req["w_max"], sim.DriveLimits(**req["limits"])), folder, n)
        req, n = _pending(folder, ident, cfg), n + 1
    assert req["experiment"] == n and req["law"]["type"] == "PI"
    scenario = sim.Scenario(np.array(req["scenario"]["w_ref"])[:500], np.array(req["scenario"]["M_dist"])[:500])
    _answer(answer.run_closed_loop(_sim_law(req["law"]), scenario, sim.DriveLimits(**req["limits"])), folder, n)
    with pytest.raises(CommissioningError, match=rf"{n:03d}\.csv: 500 samples, the requested scenario has"):
        commission(FileDrive(folder), LIMITS, identifier=ident, config=cfg)


# --------------------------------------------------------------------------- 4: a drive that does not answer


def test_a_drive_that_does_not_answer_is_a_fault(stub):
    try:
        with pytest.raises(CommissioningError, match=r"drive\.run_test did not answer within 0\.5 s"):
            commission(faulty_drives.hanging(), LIMITS, identifier=stub("elastic", PLANT), config=replace(FAST, drive_timeout=0.5))
    finally:
        faulty_drives.RELEASE.set()
    with pytest.raises(ValueError, match="drive_timeout"):
        CommissioningConfig(drive_timeout=0.0)


def test_command_ends_a_drive_that_does_not_answer_with_one_line():
    """In its own process: the hanging call is left in a daemon thread, the command exits."""
    shipped_identifier()
    proc = subprocess.run([sys.executable, "-m", "training.cli", "commission", "--drive", f"{DRIVES}:hanging", *USER_LIMITS,
                           "--drive-timeout", "1", "--no-progress"], capture_output=True, text=True, timeout=300)
    assert proc.returncode == 2, proc.stderr
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and "drive.run_test did not answer within 1 s" in lines[0], proc.stderr


# --------------------------------------------------------------------------- 5: records checked at once


def test_a_boolean_timed_out_still_gets_an_answer():
    """``timed_out: true`` (one flag for the run) is as good as six flags: the identification
    answers and a controller is delivered."""
    ident = shipped_identifier()
    drive = faulty_drives.MetaDrive(STIFF)
    drive.meta = {"timed_out": lambda m: bool(np.any(m.get("timed_out", False)))}
    rep = commission(drive, LIMITS, identifier=ident, config=replace(FAST, tune=False))
    assert rep.identification.ok, rep.identification.error
    assert rep.delivered is not None


@pytest.mark.parametrize("meta", [{"timed_out": "yes"}, {"T_Ei": "fast"}, {"serial": "X1"}])
def test_a_malformed_record_is_a_fault_of_the_first_test_run(stub, meta):
    """The rest check (experiment 1) is answered as asked; the first test record (experiment 2)
    is malformed: nothing runs after it."""
    drive = faulty_drives.MetaDrive(PLANT)
    drive.meta = meta
    ident = stub("elastic", PLANT)
    with pytest.raises(CommissioningError, match=rf"drive\.run_test: the record of experiment 2: .*{next(iter(meta))}"):
        commission(drive, LIMITS, identifier=ident, config=FAST)
    assert drive.tests == 1 and drive.experiments == 2 and not ident.records


# --------------------------------------------------------------------------- drive faults


def test_a_drive_that_exits_is_a_one_line_fault(capsys):
    shipped_identifier()
    assert main(["commission", "--drive", f"{DRIVES}:exiting", *USER_LIMITS, "--no-progress"]) == 2
    _one_error_line(capsys, "drive 'drive'", "drive.run_test raised SystemExit: 7")


def test_a_cut_closed_loop_record_is_a_fault_not_a_stop(stub):
    with pytest.raises(CommissioningError, match=r"drive\.run_closed_loop returned 300 of the scenario's 1200 samples"):
        commission(faulty_drives.CutLoopDrive(PLANT), LIMITS, identifier=stub("elastic", PLANT), config=FAST)


def test_a_closed_loop_record_longer_than_the_scenario_is_a_fault_even_when_stopped(stub):
    """Every closed loop of this drive is 300 samples too long: the rest check's (200 samples, the
    first experiment) is the fault; no test runs."""
    drive, ident = faulty_drives.LongLoopDrive(PLANT), stub("elastic", PLANT)
    with pytest.raises(CommissioningError, match=r"drive\.run_closed_loop returned 500 samples for a scenario of 200"):
        commission(drive, LIMITS, identifier=ident, config=FAST)
    assert drive.experiments == 1 and not ident.records


def test_a_drive_json_nested_too_deeply_is_one_line(tmp_path):
    (tmp_path / "drive.json").write_text("[" * 200_000 + "]" * 200_000)
    with pytest.raises(ValueError, match=r"drive\.json: invalid JSON: objects and lists nested too deeply$"):
        FileDrive(tmp_path)


def test_a_record_sampled_otherwise_than_the_config_is_a_fault(stub):
    ident = stub("elastic", PLANT)
    with pytest.raises(CommissioningError, match=r"experiment 2: its T_s 0\.00025 s .* config T_s 0\.000125 s"):
        commission(faulty_drives.WrongTsDrive(PLANT), LIMITS, identifier=ident, config=FAST)
    assert not ident.records
