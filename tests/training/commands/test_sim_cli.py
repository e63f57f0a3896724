"""The simulator's subcommands: simulate, bench (dispatch and errors), demo."""

import json

import pytest

from sim import read_record
from training.cli import main


def test_simulate_from_json_writes_records(tmp_path, capsys):
    params = [{"name": "a", "J_sigma": 0.01, "V_J": 1.0, "f_e": 40.0, "d": 0.05, "backlash": 0.002, "M_FC": 0.1,
               "mu_F": 0.001},
              {"J_M": 0.005, "J_L": 0.006, "C_F": 300.0, "D_F": 0.1}]
    (tmp_path / "p.json").write_text(json.dumps(params))
    out = tmp_path / "rec"
    assert main(["simulate", "--params", str(tmp_path / "p.json"), "--out", str(out), "--no-progress"]) == 0
    rec = read_record(out / "a.csv")
    assert rec.meta["truth"]["f_e"] == 40.0 and set(rec.section.tolist()) == {0, 1, 2, 3, 4, 5, 6}
    assert abs(read_record(out / "sys00001").meta["truth"]["J_M"] - 0.005) < 1e-12
    # refuses to overwrite, one-line error, exit code 2
    assert main(["simulate", "--params", str(tmp_path / "p.json"), "--out", str(out), "--no-progress"]) == 2
    assert "2 of the 2 records exist" in capsys.readouterr().err


def test_simulate_population(tmp_path):
    assert main(["simulate", "--population", "3", "--seed", "4", "--out", str(tmp_path), "--no-progress"]) == 0
    assert len(list(tmp_path.glob("*.csv"))) == 3 and len(list(tmp_path.glob("*.json"))) == 3


def test_simulate_real_axis_from_json_and_population(tmp_path, capsys):
    """SPEC 1.1: M_L0, M_FCM, mu_FM in a params file; --real-axis for a population; --plain-levels."""
    params = [{"name": "held", "J_sigma": 0.01, "V_J": 1.0, "f_e": 40.0, "d": 0.05, "M_L0": -1.5, "M_FCM": 0.2,
               "mu_FM": 0.001}]
    (tmp_path / "p.json").write_text(json.dumps(params))
    for flags, folder in (([], "around"), (["--plain-levels"], "plain")):
        out = tmp_path / folder
        argv = ["simulate", "--params", str(tmp_path / "p.json"), "--out", str(out), "--w-max", "20", "--no-progress"]
        assert main(argv + flags) == 0
        rec = read_record(out / "held")
        assert (rec.meta["truth"]["M_L0"], rec.meta["truth"]["M_FCM"], rec.meta["truth"]["mu_FM"]) == (-1.5, 0.2, 0.001)
        assert rec.torque_ref[0] == -1.5  # held before the test
        if flags:
            assert "M_hold" not in rec.meta and rec.torque_ref[1] == 10.0
        else:
            assert rec.meta["M_hold"] == -1.5 and rec.torque_ref[1] == 8.5
    out = tmp_path / "pop"
    assert main(["simulate", "--population", "6", "--seed", "2", "--real-axis", "--out", str(out), "--w-max", "20",
                 "--no-progress"]) == 0
    truths = [read_record(p).meta["truth"] for p in sorted(out.glob("*.csv"))]
    assert any(t["M_L0"] != 0 for t in truths) and all(0 <= t["mu_FM"] <= 0.002 for t in truths)
    assert main(["simulate", "--params", str(tmp_path / "p.json"), "--real-axis", "--out", str(tmp_path / "x")]) == 2
    assert "--real-axis" in capsys.readouterr().err


def test_simulate_bad_params_file(tmp_path, capsys):
    (tmp_path / "p.json").write_text('{"J_sigma": 0.01}')
    assert main(["simulate", "--params", str(tmp_path / "p.json"), "--out", str(tmp_path)]) == 2
    err = capsys.readouterr().err.strip()
    assert "missing keys" in err and len(err.splitlines()) == 1


def test_bench_without_or_with_unknown_target(capsys):
    assert main(["bench"]) == 2
    assert "valid targets: commission, identify, sim, som" in capsys.readouterr().err
    assert main(["bench", "nope"]) == 2
    err = capsys.readouterr().err.strip()
    assert "unknown bench target 'nope'" in err and "sim" in err and len(err.splitlines()) == 1


def test_bench_sim_small(capsys):
    assert main(["bench", "sim", "--batch", "40", "--samples", "5", "--repeat", "1", "--naive-samples", "2"]) == 0
    out = capsys.readouterr().out
    assert "numpy RK4" in out and "fused C kernel" in out and "solve_ivp" in out




def test_params_column_wise_and_text(tmp_path):
    """Column-wise JSON (``DataFrame.to_json(orient="list")``) and JSON text are read like rows."""
    from training.errors import UserError
    from training.params_file import read_params_file

    cols = {"J_sigma": [0.05, 0.1], "V_J": [1.0, 2.0], "f_e": [30.0, 60.0], "name": ["a", "b"]}
    path = tmp_path / "cols.json"
    path.write_text(json.dumps(cols))
    params, names = read_params_file(path)
    assert names == ["a", "b"] and params.V_J.tolist() == [1.0, 2.0]
    params, names = read_params_file('[{"J_sigma": 0.05, "V_J": 1, "f_e": 30}]', name_prefix="plant")
    assert names == ["plant00000"] and params.f_e.tolist() == [30.0]
    path.write_text(json.dumps({"J_sigma": [0.05, 0.1], "V_J": [1.0], "f_e": [30.0, 60.0]}))
    with pytest.raises(UserError, match="one length"):
        read_params_file(path)
    assert main(["simulate", "--params", str(path), "--out", str(tmp_path / "o")]) == 2


def test_simulate_into_a_folder_with_some_records_writes_nothing(tmp_path, capsys):
    """The batch is written whole or not at all, and the message names the command's flag."""
    params = [{"name": n, "J_sigma": 0.01, "V_J": 1.0, "f_e": 40.0} for n in ("a", "b", "c")]
    (tmp_path / "p.json").write_text(json.dumps(params))
    out = tmp_path / "rec"
    out.mkdir()
    (out / "b.csv").write_text("keep me")
    assert main(["simulate", "--params", str(tmp_path / "p.json"), "--out", str(out), "--no-progress"]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "1 of the 3 records exist (b)" in err
    assert "--overwrite" in err and "overwrite=True" not in err
    assert sorted(p.name for p in out.iterdir()) == ["b.csv"] and (out / "b.csv").read_text() == "keep me"


def test_generate_shards_a_small_run(monkeypatch, tmp_path):
    """``--n 200`` without ``--shard-size`` is 10 shards (an interrupt loses one), 20000 are 40 of 500."""
    import training.learning as learning
    from training.commands.generate import default_shard_size

    seen = []
    monkeypatch.setattr(learning, "generate", lambda out, config, **kw: seen.append(config))
    monkeypatch.setattr(learning, "load_dataset", lambda out: pytest.skip("only the config is checked"))
    with pytest.raises(pytest.skip.Exception):
        main(["generate", "--n", "200", "--out", str(tmp_path), "--no-progress"])
    assert seen[0].n == 200 and seen[0].shard_size == 20
    assert default_shard_size(20000) == 500 and default_shard_size(10000) == 500 and default_shard_size(3) == 1
