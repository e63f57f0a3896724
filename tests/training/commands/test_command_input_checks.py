"""Bad input to simulate, generate, train, evaluate, inspect and demo: a one-line reason naming the
option, exit code 2, nothing written (issues found by the tester: tracebacks, overwrites, escapes)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from training import _checks
from training.cli import main

PLANT = {"J_sigma": 0.05, "V_J": 1.0, "d": 0.02, "backlash": 0.0, "M_FC": 0.0, "mu_F": 0.0, "f_e": 30.0}


def _refused(argv: list[str], capsys: pytest.CaptureFixture[str], *words: str) -> str:
    """Run ``twomass argv``: exit code 2 and one stderr line holding ``words``; that line."""
    assert main(argv) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1, err
    assert all(w in err for w in words), err
    return err


@pytest.mark.parametrize("option, value", [("--w-max", "nan"), ("--M-star", "inf"), ("--timeout", "nan"),
                                           ("--w-max", "-1")])
def test_simulate_refuses_values_that_are_not_finite(tmp_path, capsys, option, value):
    _refused(["simulate", "--population", "2", "--out", str(tmp_path / "o"), option, value], capsys, option)
    assert not (tmp_path / "o").exists()


def test_simulate_refuses_m_star_above_the_drives_m_max(tmp_path, capsys):
    _refused(["simulate", "--population", "1", "--out", str(tmp_path / "o"), "--M-star", "1e6"], capsys,
             "--M-star", "M_max 20")
    assert not (tmp_path / "o").exists()


@pytest.mark.parametrize("argv", [["--timeout", "1e9", "--w-max", "1e9"], ["--population", "1000000000"]])
def test_simulate_refuses_sizes_beyond_the_machines_memory(tmp_path, capsys, monkeypatch, argv):
    monkeypatch.setattr(_checks, "available_memory", lambda: 64 * 2**30)
    base = ["simulate", "--population", "2", "--out", str(tmp_path / "o"), "--no-progress"]
    _refused(base + argv, capsys, "memory")
    assert not (tmp_path / "o").exists()


@pytest.mark.parametrize("name", ["../escape", "/tmp/abs_escape", "a/b", ".."])
def test_simulate_refuses_record_names_that_leave_out(tmp_path, capsys, name):
    params = tmp_path / "p.json"
    params.write_text(json.dumps({**PLANT, "name": name}))
    _refused(["simulate", "--params", str(params), "--out", str(tmp_path / "o")], capsys, "record name", repr(name))
    assert not (tmp_path / "o").exists() and not (tmp_path / "escape.csv").exists()


def test_simulate_names_a_system_whose_simulation_diverges(tmp_path, capsys):
    params = tmp_path / "p.json"
    params.write_text(json.dumps({**PLANT, "J_sigma": 1e300, "name": "huge"}))
    _refused(["simulate", "--params", str(params), "--out", str(tmp_path / "o")], capsys,
             "huge: the simulation diverged", "J_sigma 1e+300")
    assert not (tmp_path / "o").exists()


@pytest.mark.parametrize("command", [["simulate", "--population", "1"], ["generate", "--n", "4"],
                                     ["train", "--data", "d"], ["demo"], ["evaluate"]])
def test_a_negative_seed_is_refused_naming_the_option(tmp_path, capsys, command):
    _refused([*command, "--out", str(tmp_path / "o"), "--seed", "-1"] if command[0] != "demo"
             else [*command, "--seed", "-1"], capsys, "--seed: expected an integer >= 0")
    assert not (tmp_path / "o").exists()


def test_simulation_cost_is_bounded(capsys):
    """f_e 1e9 Hz would take millions of RK4 substeps per sample: hours. Refused before any work."""
    err = _refused(["demo", "--params", json.dumps({**PLANT, "f_e": 1e9})], capsys, "f_e", "substeps",
                   str(_checks.MAX_SUBSTEPS))
    assert "--params" in err


# --- generate / datasets ---------------------------------------------------------------------------------


def test_generate_refuses_shards_no_dataset_json_vouches_for(tmp_path, capsys):
    (tmp_path / "shard_00000.npz").write_bytes(b"from another run")
    _refused(["generate", "--n", "4", "--out", str(tmp_path), "--no-progress"], capsys, "shard_00000.npz",
             "no dataset.json")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["shard_00000.npz"]


def test_an_unreadable_shard_is_named(tmp_path, capsys):
    from training.learning import GenerateConfig
    from training.learning._dataset import _prepare

    _prepare(tmp_path, GenerateConfig(n=4, seed=1, shard_size=4))  # a dataset.json vouching for one shard
    with open(tmp_path / "shard_00000.npz", "wb") as f:  # pickled objects, as the tester's stray file
        np.save(f, np.array([{"not": "a shard"}], dtype=object), allow_pickle=True)
    _refused(["train", "--data", str(tmp_path), "--out", str(tmp_path / "ck"), "--no-progress"], capsys,
             str(tmp_path / "shard_00000.npz"))


@pytest.mark.parametrize("stray", ["npy", "empty"])
def test_a_stray_shard_that_is_no_archive_is_named(tmp_path, capsys, stray):
    from training.learning import GenerateConfig
    from training.learning._dataset import _prepare

    _prepare(tmp_path, GenerateConfig(n=4, seed=1, shard_size=4))  # a dataset.json vouching for one shard
    with open(tmp_path / "shard_00000.npz", "wb") as f:  # a plain .npy array, or nothing at all
        if stray == "npy":
            np.save(f, np.zeros(3))
    _refused(["train", "--data", str(tmp_path), "--out", str(tmp_path / "ck"), "--no-progress"], capsys,
             str(tmp_path / "shard_00000.npz"), "not a readable dataset shard")


def test_a_failed_generate_leaves_no_dataset_json(tmp_path, capsys, monkeypatch):
    import training.learning._dataset as dataset

    def fails(*args, **kwargs):
        raise ValueError("the simulation failed")

    monkeypatch.setattr(dataset, "_shard", fails)
    _refused(["generate", "--n", "4", "--out", str(tmp_path / "g"), "--no-progress", "--workers", "1"], capsys,
             "the simulation failed")
    assert not (tmp_path / "g" / "dataset.json").exists()


def test_generate_refuses_a_size_beyond_memory_and_zero_workers(tmp_path, capsys, monkeypatch):
    monkeypatch.setattr(_checks, "available_memory", lambda: 64 * 2**30)
    _refused(["generate", "--n", "1000000000", "--out", str(tmp_path / "g")], capsys, "--n 1000000000", "memory")
    _refused(["generate", "--n", "4", "--workers", "0", "--out", str(tmp_path / "g")], capsys, "--workers")
    assert not (tmp_path / "g").exists()


# --- evaluate --------------------------------------------------------------------------------------------


def _no_study(monkeypatch):
    import training.evaluation as evaluation

    def study(*args, **kwargs):
        raise AssertionError("the study ran")

    monkeypatch.setattr(evaluation, "run_study", study)


def test_evaluate_refuses_an_existing_report_before_any_work(tmp_path, capsys, monkeypatch):
    _no_study(monkeypatch)
    (tmp_path / "report.md").write_text("mine")
    _refused(["evaluate", "--out", str(tmp_path), "--per-cell", "1", "--population", "0", "--f-e", "20",
              "--backlash", "0", "--no-cache"], capsys, "report.md", "--overwrite")
    assert [p.name for p in tmp_path.iterdir()] == ["report.md"] and (tmp_path / "report.md").read_text() == "mine"


def test_evaluate_drives_refuses_an_existing_report(tmp_path, capsys, monkeypatch):
    from training.identification import Identifier

    monkeypatch.setattr(Identifier, "load", lambda *a, **k: pytest.fail("maps loaded"))
    (tmp_path / "drives.json").write_text("mine")
    _refused(["evaluate", "--drives", "1", "--out", str(tmp_path)], capsys, "drives.json", "--overwrite")
    assert (tmp_path / "drives.json").read_text() == "mine"


@pytest.mark.parametrize("name, argv", [("confidence.md", []), ("fig_reliability.png", []),
                                        ("fig_reliability_envelope.png", ["--envelope-drives", "1"])])
def test_evaluate_drives_refuses_an_existing_confidence_report(tmp_path, capsys, monkeypatch, name, argv):
    from training.identification import Identifier

    monkeypatch.setattr(Identifier, "load", lambda *a, **k: pytest.fail("maps loaded"))
    (tmp_path / name).write_text("mine")
    _refused(["evaluate", "--drives", "1", *argv, "--out", str(tmp_path)], capsys, name, "--overwrite")
    assert (tmp_path / name).read_text() == "mine"


def test_report_files_name_what_write_report_writes(tmp_path):
    from training.evaluation import report_files
    from training.evaluation._report import write_report

    summary = {"methods": ["som"], "sets": {}, "checks": []}
    written = write_report(summary, {}, tmp_path, plots=False)
    assert [Path(f) for f in written["files"]] == report_files(tmp_path, [], plots=False)


@pytest.mark.parametrize("option, value", [("--backlash", "1000"), ("--backlash", "-1"), ("--backlash", "nan"),
                                           ("--f-e", "nan"), ("--f-e", "1e9")])
def test_evaluate_bounds_the_grid(tmp_path, capsys, monkeypatch, option, value):
    _no_study(monkeypatch)
    _refused(["evaluate", "--out", str(tmp_path / "o"), option, value], capsys, option)
    assert not (tmp_path / "o").exists()


def test_evaluate_shows_no_progress_bar_when_stderr_is_no_terminal(tmp_path, capsys, monkeypatch):
    import training.evaluation as evaluation

    def study(*args, progress, **kwargs):
        progress(1)
        raise ValueError("stop here")

    monkeypatch.setattr(evaluation, "run_study", study)
    assert main(["evaluate", "--out", str(tmp_path / "o"), "--per-cell", "1", "--population", "0", "--f-e", "20",
                 "--backlash", "0", "--no-cache"]) == 2  # no --no-progress: stderr is captured, no terminal
    err = capsys.readouterr().err
    assert err.strip() == "twomass evaluate: error: stop here"  # a bar would write "evaluate: 100%|...| 1/2 sys"


# --- inspect ---------------------------------------------------------------------------------------------


def test_inspect_names_its_own_argument(tmp_path, capsys):
    err = _refused(["inspect", str(tmp_path / "none"), "--out", str(tmp_path / "x")], capsys, "CHECKPOINT_DIR")
    assert "--checkpoints" not in err


def test_inspect_refuses_an_existing_out_before_printing(tmp_path, capsys):
    pytest.importorskip("matplotlib")
    from training.config import checkpoints_folder
    from training.identification import MAP_SPECS

    name = next(iter(MAP_SPECS))
    (tmp_path / name).mkdir()
    (tmp_path / name / "u_matrix.png").write_bytes(b"mine")
    assert main(["inspect", str(checkpoints_folder()), "--out", str(tmp_path)]) == 2
    captured = capsys.readouterr()
    assert captured.out == "" and "u_matrix.png" in captured.err
