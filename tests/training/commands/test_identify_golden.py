"""Behaviour pinned across refactorings: ``twomass identify`` on a fixed set of simulated records
gives the JSON Lines stored in ``tests/training/commands/data/identify_golden.jsonl`` (written by the code before
the layout change of issue 10; regenerate only for an intended change of the identification:
``python tests/training/commands/test_identify_golden.py``)."""

from __future__ import annotations

import json
import math
import sys
from pathlib import Path
from typing import Any

from training.cli import main

GOLDEN = Path(__file__).parent / "data" / "identify_golden.jsonl"
N_RECORDS, SEED = 8, 11


def _identify(folder: Path, capsys: Any = None) -> list[dict[str, Any]]:
    records = folder / "records"
    assert main(["simulate", "--population", str(N_RECORDS), "--seed", str(SEED), "--out", str(records),
                 "--no-progress"]) == 0
    out = folder / "out.jsonl"
    names = sorted(p.with_suffix("").name for p in records.glob("*.csv"))
    code = main(["identify", *[str(records / n) for n in names], "--out", str(out), "--no-progress", "--jobs", "1"])
    assert code in (0, 1)
    lines = [json.loads(line) for line in out.read_text().splitlines()]
    for line in lines:
        line["record"] = Path(line["record"]).name
    return lines


def _close(a: Any, b: Any, where: str) -> None:
    if isinstance(a, dict):
        assert isinstance(b, dict) and set(a) == set(b), f"{where}: keys {sorted(a)} != {sorted(b)}"
        for k in a:
            _close(a[k], b[k], f"{where}.{k}")
    elif isinstance(a, list):
        assert isinstance(b, list) and len(a) == len(b), f"{where}: {a} != {b}"
        for i, (x, y) in enumerate(zip(a, b)):
            _close(x, y, f"{where}[{i}]")
    elif isinstance(a, float) and not isinstance(b, bool) and isinstance(b, (int, float)):
        assert math.isclose(a, b, rel_tol=1e-6, abs_tol=1e-12), f"{where}: {a} != {b}"
    else:
        assert a == b, f"{where}: {a!r} != {b!r}"


def test_identify_output_unchanged(tmp_path: Path) -> None:
    got = _identify(tmp_path)
    expected = [json.loads(line) for line in GOLDEN.read_text().splitlines()]
    assert len(got) == len(expected)
    for g, e in zip(got, expected):
        _close(g, e, e["record"])


if __name__ == "__main__":  # regenerate the golden file
    import tempfile

    with tempfile.TemporaryDirectory() as d:
        lines = _identify(Path(d))
    GOLDEN.write_text("".join(json.dumps(line) + "\n" for line in lines))
    print(f"wrote {len(lines)} lines to {GOLDEN}", file=sys.stderr)
