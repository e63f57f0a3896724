"""Issue 40 (SPEC 1.1 real axes): ``twomass evaluate --drives N --real-axis [both|load|motor]`` measures
each real-axis part alone and both together; the figures gain ``M_L0`` within 5 %, ``M_FC`` and
``M_FCM`` within 1 % of ``M*``."""

from __future__ import annotations

import json

import pytest
import torch

from training.evaluation import (DRIVES, REAL_AXIS_EFFECTS, drive_figures, drives_markdown, real_axis_effect,
                                 real_axis_figures)


@pytest.mark.parametrize("drive", ["reference", "servo_200w"])
def test_each_effect_draws_only_its_parts_on_the_same_systems(drive):
    case, n, seed = DRIVES[drive], 400, 11
    M = case.signal.M_star
    plain = case.population(n, seed)
    both, load, motor = (case.population(n, seed, REAL_AXIS_EFFECTS[e]) for e in ("both", "load", "motor"))
    assert torch.equal(case.population(n, seed, real_axis=True).M_L0, both.M_L0)  # True: SPEC 1.1's population
    for p in (both, load, motor):  # the seven parameters of the plain population
        assert torch.equal(p.J_sigma, plain.J_sigma) and torch.equal(p.backlash, plain.backlash)
    # load: M_L0 on about half, either sign, |M_L0| <= 0.15 M*; no motor friction at all
    has = load.M_L0 != 0
    assert 0.4 < has.double().mean() < 0.6 and bool((load.M_L0 > 0).any() and (load.M_L0 < 0).any())
    assert float(load.M_L0.abs().max()) <= 0.15 * M + 1e-12
    assert not load.M_FCM.any() and not load.mu_FM.any()
    # motor: M_FCM on about half (<= 0.03 M*), mu_FM on all; no load torque
    assert not motor.M_L0.any() and bool((motor.mu_FM > 0).all())
    assert 0.4 < (motor.M_FCM != 0).double().mean() < 0.6 and float(motor.M_FCM.max()) <= 0.03 * M + 1e-12
    # both: the load's M_L0 and the motor's friction on the same systems
    assert torch.equal(both.M_L0, load.M_L0)
    assert torch.equal(both.M_FCM, motor.M_FCM) and torch.equal(both.mu_FM, motor.mu_FM)


def test_an_unknown_effect_names_the_valid_ones():
    assert real_axis_effect("load") is REAL_AXIS_EFFECTS["load"]
    with pytest.raises(ValueError, match=r"^expected an effect of both, load, motor, received 'gravity'$"):
        real_axis_effect("gravity")
    with pytest.raises(TypeError, match="real_axis"):
        DRIVES["reference"].population(2, 1, real_axis="load")  # type: ignore[arg-type]


def _row(M_L0, M_FC, M_FCM, est_L0, est_FC, est_FCM, M_star=10.0, error=None):
    truth = dict(structure="stiff", f_e=300.0, V_J=1.0, J_sigma=0.1, s_N=0.0, backlash=0.0, r_osc=100.0,
                 w_e_T_Ei=2.0, gap_counts=0.0, M_L0=M_L0, M_FC=M_FC, M_FCM=M_FCM, mu_F=0.0, mu_FM=0.0, M_star=M_star)
    som = dict(structure=None if error else "stiff", J_sigma=0.1, backlash=0.0, n_warnings=0, error=error)
    if error is None:
        som.update(M_L0=est_L0, M_FC=est_FC, M_FCM=est_FCM)
    return {"truth": truth, "som": som}


def test_real_axis_figures_on_hand_made_rows():
    rows = [  # M* 10 Nm: M_L0 within 0.5 Nm, M_FC and M_FCM within 0.1 Nm
        _row(1.0, 0.3, 0.2, 1.4, 0.35, 0.25),  # all three within
        _row(-1.0, 0.3, 0.0, -0.4, 0.45, None),  # M_L0 off by 0.6, M_FC off by 0.15; M_FCM None = 0: within
        _row(0.0, 0.05, 0.08, None, None, None),  # None = 0: M_L0 within, M_FC within (0.05), M_FCM within (0.08)
        _row(0.0, 0.0, 0.2, 0.0, 0.0, None),  # M_FCM None = 0, off by 0.2
        _row(0.0, 0.0, 0.0, None, None, None, error="failed"),  # a failed analysis: off in all three
        _row(2.0, 0.1, 0.1, 2.04, 0.1, 0.14, M_star=0.64),  # M* 0.64: within 0.032, 0.0064: M_L0 off, M_FC in, M_FCM off
    ]
    assert real_axis_figures(rows) == pytest.approx({"M_L0_5": 300 / 6, "M_FC_1": 400 / 6, "M_FCM_1": 300 / 6})
    f = drive_figures(rows, real_axis=True)
    assert f["M_L0_5"] == pytest.approx(50.0) and f["failed"] == 1
    assert not {"M_L0_5", "M_FC_1", "M_FCM_1"} & set(drive_figures(rows))  # the default: none of them
    md = drives_markdown({"x": f}, "cmd")
    assert "| M_L0 5 % of M* | M_FC 1 % of M* | M_FCM 1 % of M* |" in md and "| 50.0 | 66.7 | 50.0 |" in md
    assert "M_L0 5 %" not in drives_markdown({"x": drive_figures(rows)}, "cmd")
    assert real_axis_figures([]) == {"M_L0_5": None, "M_FC_1": None, "M_FCM_1": None}
    del rows[2]["truth"]["M_star"]
    with pytest.raises(ValueError, match="M_star"):
        real_axis_figures(rows)


def _refused(argv, tmp_path, capsys, monkeypatch):
    from training.cli import main
    from training.identification import Identifier

    monkeypatch.setattr(Identifier, "load", lambda *a, **k: pytest.fail("maps loaded"))
    assert main(["evaluate", *argv, "--out", str(tmp_path)]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1, err
    return err


@pytest.mark.parametrize(("argv", "message"), [
    (["--drives", "1", "--real-axis", "gravity"],
     "--real-axis: expected an effect of both, load, motor, received 'gravity'"),
    (["--drives", "1", "--real-axis", "--envelope-drives", "2"],
     "--real-axis: the matrix's study only, not with --envelope-drives"),
    (["--drives", "1", "--drive-names", "reference,mars"],
     "--drive-names: expected drives of reference, servo_200w, low_res_1ms, noisy, large_axis, fast_spindle, "
     "received 'mars'"),
    (["--drives", "1", "--drive-names", "reference=0"],
     "--drive-names: expected NAME=K with K >= 1 systems, received 'reference=0'"),
    (["--drives", "1", "--drive-names", "noisy,noisy=3"], "--drive-names: drive 'noisy' given twice")])
def test_the_cli_refuses_bad_effects_and_drives(tmp_path, capsys, monkeypatch, argv, message):
    assert _refused(argv, tmp_path, capsys, monkeypatch) == f"twomass evaluate: error: {message}"
    assert not any(tmp_path.iterdir())


@pytest.mark.parametrize(("effect", "name"), [([], "drives_real_axis.md"), (["load"], "drives_real_axis_load.md"),
                                               (["motor"], "confidence_real_axis_motor.json")])
def test_the_effect_names_the_files(tmp_path, capsys, monkeypatch, effect, name):
    (tmp_path / name).write_text("mine")
    err = _refused(["--drives", "1", "--real-axis", *effect], tmp_path, capsys, monkeypatch)
    assert name in err and "--overwrite" in err and (tmp_path / name).read_text() == "mine"


def test_a_load_study_on_one_drive(tmp_path, monkeypatch):
    """End to end on two systems of the reference drive (the maps without a calibration)."""
    from training.cli import main
    from training.identification import Identifier

    load = Identifier.load
    monkeypatch.setattr(Identifier, "load", lambda path=None: load(path, calibrated=False))
    assert main(["evaluate", "--drives", "5", "--real-axis", "load", "--drive-names", "reference=2", "--seed", "3",
                 "--no-plots", "--out", str(tmp_path)]) == 0
    md = (tmp_path / "drives_real_axis_load.md").read_text()
    assert "--real-axis load --drive-names reference=2 --seed 3" in md and "the load part alone" in md
    assert md.count("| reference: the reference drive | 2 |") == 1 and "| M_L0 5 % of M* |" in md
    figures = json.loads((tmp_path / "drives_real_axis_load.json").read_text())["drives"]
    assert list(figures) == ["reference"] and {"M_L0_5", "M_FC_1", "M_FCM_1"} <= set(figures["reference"])
    assert (tmp_path / "confidence_real_axis_load.md").exists() and not (tmp_path / "drives_real_axis.md").exists()
