"""What the chain does with a drive that breaks its assumptions: a closed loop that oscillates at
the torque cap, a reversed speed sign, limits the encoder cannot resolve or that a smaller test
cannot keep, methods and factories that raise; and the command's checks before any experiment."""

from __future__ import annotations

import json
import math
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

sim = pytest.importorskip("sim")

from training.cli import main  # noqa: E402
from training.commissioning import (CommissioningConfig, ExcitationRules, FileDrive, HoldLaw, adapt_test_signal,  # noqa: E402
                                    commission)
from training.commissioning._tuning import TuningScenario, loop_verdict, response_figures  # noqa: E402
from training.errors import CommissioningError, ExperimentPending  # noqa: E402

HERE = Path(__file__).parent
sys.path.insert(0, str(HERE))
from setups import FAST, LIMITS  # noqa: E402
import faulty_drives  # noqa: E402

USER_LIMITS = ["--w-limit", "20", "--travel-limit", "5"]  # a drive of one's own has no default limits
DRIVES = HERE / "faulty_drives.py"


def _scenario() -> TuningScenario:
    return TuningScenario(T_s=2.5e-4, w_step=1.0, M_dist=1.0, n_segment=400, T_ref=0.01, dip_ref=1.0, q_w=0.024)


def _healthy(sc: TuningScenario) -> np.ndarray:
    t = np.arange(sc.n_segment) * sc.T_s
    step = 1 - np.exp(-t / 0.005)
    return np.concatenate([step, 1 - step, -step, step - 1, np.zeros(2 * sc.n_segment)])


def test_loop_verdict_names_saturation_limit_cycle_and_model_mismatch():
    sc = _scenario()
    w = _healthy(sc)
    assert loop_verdict(w, np.zeros_like(w), sc, 20.0, 5.0, 5.0, False) == (None, "settled")
    assert math.isfinite(response_figures(w, sc)["settling_time"])
    cycle = w + 0.2 * np.sin(2 * np.pi * 80 * np.arange(len(w)) * sc.T_s)  # the tester's limit cycle: 0.22 rad/s RMS
    at_cap = np.where(np.arange(len(w)) % 4 == 0, 0.0, 20.0)  # 75 % of the samples at the cap
    assert loop_verdict(cycle, at_cap, sc, 20.0, 50.0, 5.0, False)[0] == "saturated"
    assert loop_verdict(cycle, None, sc, 20.0, 50.0, 5.0, False)[0] == "limit_cycle"
    assert loop_verdict(w, None, sc, 20.0, 110.0, 5.0, False)[0] == "unlike_model"
    assert loop_verdict(w, None, sc, 20.0, 5.0, 5.0, True)[0] == "stopped"


def test_an_oscillating_loop_is_not_delivered_and_never_called_settled(stub):
    """The drive applies 50 x the law's torque: every loop sits at the torque cap. Nothing is
    delivered, warnings say why, and no run is settled without a settling time."""
    rep = commission(faulty_drives.gain50(), LIMITS, identifier=stub("elastic", faulty_drives.PLANT), config=FAST)
    assert rep.delivered is None
    assert {"loop_rejected", "loop_not_settled"} <= {w.code for w in rep.warnings}
    runs = rep.to_dict()["runs"] + rep.to_dict()["fallback"]["runs"]
    assert runs and all(not r["settled"] and r["verdict"] in ("saturated", "limit_cycle") for r in runs)
    assert "8 delivered: none" in rep.to_text()


@pytest.mark.parametrize("gain", [0.5, 3.0, 14.0])
def test_a_drive_that_scales_the_law_is_named(stub, gain):
    """A drive that applies ``gain`` x the law's torque: the law replayed on its records says so
    (``loop_unlike_model``); the healthy drive's replay fits the law to 1e-6."""
    drive = faulty_drives.GainDrive(faulty_drives.PLANT)
    drive.gain = gain
    rep = commission(drive, LIMITS, identifier=stub("elastic", faulty_drives.PLANT), config=FAST)
    assert "loop_unlike_model" in {w.code for w in rep.warnings}
    assert f"applied {gain:.3g} x the law's torque" in next(w.text for w in rep.warnings if w.code == "loop_unlike_model")
    healthy = commission(sim.SimulatedDrive(faulty_drives.PLANT), LIMITS,
                         identifier=stub("elastic", faulty_drives.PLANT), config=FAST)
    assert "loop_unlike_model" not in {w.code for w in healthy.warnings}


def test_settled_runs_have_a_settling_time(stub):
    rep = commission(sim.SimulatedDrive(faulty_drives.PLANT), LIMITS, identifier=stub("elastic", faulty_drives.PLANT),
                     config=FAST)
    assert rep.delivered is not None
    for r in rep.to_dict()["runs"]:
        assert not r["settled"] or r["figures"]["settling_time"] is not None


def test_a_reversed_speed_sign_is_named_and_stops_at_once(stub):
    res = adapt_test_signal(faulty_drives.reversed_sign(), LIMITS)
    assert res.code == "speed_against_torque" and len(res.log) == 1 and "against the torque" in res.reason
    ident = stub("elastic", faulty_drives.PLANT)
    rep = commission(faulty_drives.reversed_sign(), LIMITS, identifier=ident, config=replace(FAST, fallback=False))
    assert not ident.records  # nothing identified from a run that went the wrong way
    assert rep.permission.rule == "V1" and "against the torque" in rep.permission.reason
    assert "speed_against_torque" in {w.code for w in rep.warnings}


def test_a_stopped_run_is_never_repeated_unchanged():
    """A 10 mrad travel limit: the stopped runs used to repeat (only w_max halved, M* kept) up to the
    10-run cap; then M* came down too and no stopped run repeated the one before; now (E6d: the travel
    predicted from the peak as well, below the drive's stop travel) the drive stops none."""
    res = adapt_test_signal(sim.SimulatedDrive(faulty_drives.PLANT), sim.DriveLimits(w_max=100.0, travel=0.01),
                            ExcitationRules(refuse_uninformative_limits=False))  # E0 would refuse it before any run
    assert len(res.log) < 10
    stopped = [(e["M_star"], e["w_max"], e["peak_speed"], e["travel"]) for e in res.log if e["aborted"]]
    assert all(a != b for a, b in zip(stopped, stopped[1:]))
    assert max(e["travel"] for e in res.log) <= 0.01
    # E8: after a stop less torque, down to E1's start
    assert all(b["M_star"] < a["M_star"] or a["M_star"] <= res.log[0]["M_star"] for a, b in zip(res.log, res.log[1:]) if a["aborted"])


def test_a_speed_limit_below_the_encoder_resolution_is_refused_up_front(stub):
    ident = stub("elastic", faulty_drives.PLANT)
    with pytest.raises(CommissioningError, match="speed quanta"):
        commission(sim.SimulatedDrive(faulty_drives.PLANT), sim.DriveLimits(w_max=0.01, travel=5.0), identifier=ident)
    assert not ident.records


def test_a_recording_of_another_experiment_is_refused(tmp_path, stub):
    conf = sim.DriveConfig()
    (tmp_path / "drive.json").write_text(json.dumps({"config": {k: getattr(conf, k) for k in
                                                                ("T_s", "K_M", "T_Ei", "encoder_counts", "M_N", "M_max")},
                                                     "limits": {"w_max": 20.0, "travel": 5.0}}))
    ident = stub("elastic", faulty_drives.PLANT)
    with pytest.raises(ExperimentPending) as pending:
        commission(FileDrive(tmp_path), LIMITS, identifier=ident, config=FAST)
    rest = json.loads(Path(pending.value.request).read_text())  # the rest check, answered as asked
    answer = sim.SimulatedDrive(faulty_drives.PLANT)
    rec = answer.run_closed_loop(HoldLaw(), sim.Scenario(np.array(rest["scenario"]["w_ref"]), np.array(rest["scenario"]["M_dist"])),
                                 sim.DriveLimits(**rest["limits"]))
    rec.meta.pop("aborted", None)
    sim.write_record(tmp_path / "001", rec)
    with pytest.raises(ExperimentPending) as pending:
        commission(FileDrive(tmp_path), LIMITS, identifier=ident, config=FAST)
    req = json.loads(Path(pending.value.request).read_text())
    rec = answer.run_test(2 * req["M_star"], req["w_max"], sim.DriveLimits(**req["limits"]))
    rec.meta.pop("aborted", None)
    sim.write_record(tmp_path / "002", rec)
    with pytest.raises(CommissioningError, match="another experiment"):
        commission(FileDrive(tmp_path), LIMITS, identifier=ident, config=FAST)


def _one_error_line(capsys, *words):
    err = capsys.readouterr().err
    assert len(err.strip().splitlines()) == 1 and "Traceback" not in err, err
    for w in words:
        assert w in err, err


def test_command_checks_before_any_experiment(tmp_path, capsys):
    folder = tmp_path / "rig"
    folder.mkdir()
    (folder / "drive.json").write_text(json.dumps({"config": {"T_s": 2.5e-4, "K_M": 1.0, "T_Ei": 5e-4, "encoder_counts": 2**20,
                                                              "M_N": 10.0, "M_max": 20.0}, "limits": {"w_max": 20, "travel": 5}}))
    assert main(["commission", "--resume", str(folder), "--w-limit", "1", "--no-progress"]) == 2
    _one_error_line(capsys, "--w-limit", "drive.json")
    assert main(["commission", "--resume", str(folder), "--drive", f"{DRIVES}:gain50", "--no-progress"]) == 2
    _one_error_line(capsys, "--drive")
    assert not list(folder.glob("*_request.json"))  # no experiment was asked for
    assert main(["commission", "--resume", str(folder), "--w-limit", "20", "--travel-limit", "5", "--no-progress"]) == 0
    assert (folder / "001_request.json").exists()  # the stored values themselves are fine
    plots = tmp_path / "plots"
    plots.mkdir()
    (plots / "drive.png").write_bytes(b"mine")
    assert main(["commission", "--drive", f"{DRIVES}:factory_raises", "--plots", str(plots), *USER_LIMITS, "--no-progress"]) == 2
    _one_error_line(capsys, "--plots", "drive.png")  # before the drive is even built
    plant = tmp_path / "p.json"
    plant.write_text(json.dumps({**faulty_drives.PLANT, "name": "p"}))
    assert main(["commission", "--params", str(plant), "--w-limit", "0.01", "--no-progress"]) == 2
    _one_error_line(capsys, "speed quanta")


def test_command_turns_drive_faults_into_one_line(tmp_path, capsys):
    assert main(["commission", "--drive", f"{DRIVES}:factory_raises", *USER_LIMITS, "--no-progress"]) == 2
    _one_error_line(capsys, "factory_raises", "OSError", "/dev/ttyUSB0")
    bad = tmp_path / "bad_drive.py"
    bad.write_text("import numpy\nraise RuntimeError('no bus')\n")
    assert main(["commission", "--drive", f"{bad}:make", *USER_LIMITS, "--no-progress"]) == 2
    _one_error_line(capsys, "bad_drive.py", "RuntimeError", "no bus")
    (tmp_path / "helper_xyz.py").write_text("def make():\n    raise OSError('rig offline')\n")
    sibling = tmp_path / "sibling_drive.py"
    sibling.write_text("from helper_xyz import make\n")
    assert main(["commission", "--drive", f"{sibling}:make", *USER_LIMITS, "--no-progress"]) == 2
    _one_error_line(capsys, "rig offline")  # the sibling module was imported: the factory ran
    assert str(tmp_path) not in sys.path


def test_command_turns_a_raising_drive_method_into_one_line(capsys):
    from som_torch import CheckpointError
    from training.identification import Identifier

    try:
        Identifier.load()
    except CheckpointError as err:
        pytest.skip(f"shipped maps not loadable: {err}")
    assert main(["commission", "--drive", f"{DRIVES}:raising", *USER_LIMITS, "--no-progress"]) == 2
    _one_error_line(capsys, "run_test", "RuntimeError", "hardware fault E42")


def test_command_exit_code_when_nothing_is_delivered(tmp_path, capsys):
    """A refusal without the fallback delivers nothing: exit 3, not 0; --quiet prints the summary only."""
    plant = tmp_path / "p.json"
    plant.write_text(json.dumps({**faulty_drives.PLANT, "name": "p"}))
    assert main(["commission", "--drive", f"{DRIVES}:reversed_sign", "--params", str(plant), "--w-limit", "20",
                 "--travel-limit", "5", "--no-fallback", "--quiet", "--no-progress"]) == 3
    cap = capsys.readouterr()
    assert "== summary over 1 drives ==" in cap.out and "== commissioning" not in cap.out
    assert "exit 3" in cap.err
