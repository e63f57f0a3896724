"""``twomass bench`` targets on tiny inputs: they run, print their table and the command that reproduces it."""

from __future__ import annotations

import sys

import pytest

from sim._kernel import load_kernel
from training.bench import TARGETS, run_target
from training.bench._report import Table
from training.errors import UserError


def test_table_renders_markdown() -> None:
    t = Table(["a", "b"])
    t.add(1, "x")
    assert t.render() == "| a | b |\n| --- | --- |\n| 1 | x |"


def test_targets() -> None:
    assert sorted(TARGETS) == ["commission", "identify", "sim", "som", "train"]
    with pytest.raises(UserError, match="valid targets: commission, identify, sim, som, train"):
        run_target("nope", [])


@pytest.mark.skipif(load_kernel() is None, reason="no C compiler: no kernel to bench")
def test_bench_sim_tiny(capsys: pytest.CaptureFixture[str]) -> None:
    argv = ["--batch", "40", "--samples", "5", "--repeat", "1", "--naive-samples", "2"]
    assert run_target("sim", argv) == 0
    out = capsys.readouterr().out
    assert "machine: " in out and "GFLOP/s on 1 thread(s)" in out
    assert "| numpy RK4, vectorized over systems | 1 |" in out
    assert "| fused C kernel | 1 |" in out and "naive script: solve_ivp" in out
    assert out.rstrip().endswith("reproduce: twomass bench sim " + " ".join(argv))


def test_bench_som_tiny(capsys: pytest.CaptureFixture[str]) -> None:
    pytest.importorskip("minisom")
    argv = ["--maps", "2", "--rows", "3", "--cols", "4", "--samples", "30", "--epochs", "1", "--active", "3",
            "--inactive", "1", "--sigma", "1"]
    assert run_target("som", argv) == 0
    out = capsys.readouterr().out
    for row in ("float64 | 1 |", "float64 | 2 |", "float32 | 2 |", "MiniSom 2.3.6 online | float64 | 1 |"):
        assert row in out
    assert "vs MiniSom (float64)" in out
    assert out.rstrip().endswith("reproduce: twomass bench som " + " ".join(argv))


@pytest.mark.parametrize("target", ["identify", "train"])
def test_process_targets_reject_too_few_records(target: str) -> None:
    with pytest.raises(UserError, match="--n: expected"):
        run_target(target, ["--n", "0"])


def test_bench_som_without_minisom(capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setitem(sys.modules, "minisom", None)  # as if not installed: its lines are skipped, the rest runs
    monkeypatch.setitem(sys.modules, "xpysom", None)
    argv = ["--maps", "2", "--rows", "3", "--cols", "3", "--samples", "20", "--epochs", "1", "--active", "2",
            "--inactive", "1", "--sigma", "1"]
    assert run_target("som", argv) == 0
    out = capsys.readouterr().out
    assert "MiniSom not installed (pip install 'minisom==2.3.6'" in out and "float64 | 2 |" in out
    assert out.rstrip().endswith("reproduce: twomass bench som " + " ".join(argv))


@pytest.mark.parametrize("target, argv, message", [
    ("som", ["--learning-rate", "nan"], "--learning-rate: expected a finite number > 0"),
    ("som", ["--sigma", "0"], "--sigma: expected a finite number > 0"),
    ("som", ["--inactive", "-1"], "--inactive: expected an integer >= 0"),
    ("sim", ["--naive-samples", "-1"], "--naive-samples: expected an integer >= 0"),
    ("train", ["--ensemble", "0"], "ensemble >= 1"),  # before its long generate
])
def test_bad_bench_options_are_refused_before_any_work(target: str, argv: list[str], message: str) -> None:
    with pytest.raises(ValueError, match=message):
        run_target(target, argv)


def test_bench_identify_reuses_records_of_its_own_seed_only(tmp_path) -> None:
    from training.bench._identify import MARKER

    (tmp_path / "sys00000.csv").write_text("t,speed,current\n")  # records of an earlier run
    with pytest.raises(UserError, match="holds records this bench did not write"):
        run_target("identify", ["--n", "2", "--records-dir", str(tmp_path)])
    (tmp_path / MARKER).write_text('{"seed": 7}')
    with pytest.raises(UserError, match="holds records of --seed 7"):
        run_target("identify", ["--n", "2", "--seed", "8", "--records-dir", str(tmp_path)])
