"""``twomass bench sim``: every line, the arithmetic count it states and the library it ran."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from sim._kernel import FLOPS_PER_SUBSTEP, load_kernel
from training.bench import run_target


@pytest.mark.skipif(load_kernel() is None, reason="no C compiler: no kernel to bench")
def test_bench_sim_figures_name_the_count_and_every_line(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "sim.json"
    argv = ["--batch", "40", "--samples", "5", "--repeat", "2", "--naive-samples", "0", "--json", str(out)]
    assert run_target("sim", argv) == 0
    text = capsys.readouterr().out
    assert "kernel library: " in text
    assert f"GFLOP/s counts {FLOPS_PER_SUBSTEP} add/sub/mul per system-substep" in text
    figures = json.loads(out.read_text())
    assert figures["flops_per_substep"] == FLOPS_PER_SUBSTEP == 129
    lines = [(r["implementation"], r["threads"]) for r in figures["runs"]]
    assert lines[:3] == [("numpy RK4, vectorized over systems", 1),
                         ("torch eager twin (the fallback without a C compiler)", 1), ("fused C kernel", 1)]
    assert all(r["wall_s"] > 0 for r in figures["runs"])
    assert "load average after the runs" in text and len(figures["load_average_after"]) == 3
