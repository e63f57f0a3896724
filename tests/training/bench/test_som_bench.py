"""``twomass bench som``: the equal-quality verdict by hand, and a tiny run with both baselines."""

from __future__ import annotations

import pytest

from training.bench import run_target
from training.bench._som import Run, Schedule, _verdict


def _run(wall: float, maps: int, qe: list[float], te: list[float]) -> Run:
    return Run("x", "s", "float32", maps, 1, wall, wall, qe, te)


def test_verdict_compares_speed_per_map_and_quality_on_the_common_maps():
    ours = _run(1.0, 4, [0.10, 0.30, 9.0, 9.0], [0.01, 0.03, 9.0, 9.0])  # maps 2, 3: not trained by theirs
    theirs = _run(2.0, 2, [0.20, 0.20], [0.02, 0.02])
    assert _verdict(ours, theirs) == ("4.0x per map; QE 0.2000 vs 0.2000, TE 0.0200 vs 0.0200 "
                                      "(mean over 2 map(s)): equal or better: yes")
    worse_te = _run(1.0, 1, [0.1], [0.05])
    assert _verdict(worse_te, theirs).endswith("(mean over 1 map(s)): equal or better: NO")


def test_schedule_label():
    assert Schedule("asymptotic", (8.0, 8 / 3), (0.5, 0.5 / 3)).label() == "asymptotic sigma 8->2.67, lr 0.5->0.167"


def test_bench_som_tiny_with_both_baselines(capsys: pytest.CaptureFixture[str]) -> None:
    pytest.importorskip("minisom")
    pytest.importorskip("xpysom")
    argv = ["--maps", "2", "--rows", "4", "--cols", "4", "--samples", "30", "--epochs", "2", "--active", "3",
            "--inactive", "1", "--sigma", "2"]
    assert run_target("som", argv) == 0
    out = capsys.readouterr().out
    assert "| XPySom 1.0.7 batch | float32 | 2 |" in out and "| CPU/wall |" in out and "kernel " in out
    assert out.count("vs XPySom (float32)") == 4 and out.count("vs MiniSom (float64)") == 2
    assert out.count("equal or better: ") == 6
