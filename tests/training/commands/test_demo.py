"""``twomass demo``: runs without arguments and prints true and identified values side by side."""

from __future__ import annotations

import json

from training.cli import main
from training.identification import PARAMETER_NAMES


def _table_rows(out: str) -> dict[str, list[str]]:
    return {line.split()[0]: line.split() for line in out.splitlines() if line.startswith("  ") and line.split()}


def test_demo_runs_without_arguments(capsys):
    assert main(["demo"]) == 0
    out = capsys.readouterr().out
    assert "elastic plant:" in out and "plant with backlash:" in out
    assert out.count("true") >= 2 and out.count("identified") >= 2  # both tables have both columns
    rows = _table_rows(out)
    for name in ("structure", *PARAMETER_NAMES):
        assert name in rows, name
        assert len(rows[name]) >= 4  # name, unit, true, identified (, error)
    assert "true class elastic," in out and "true class elastic_backlash," in out
    assert out.count("quality: P(") == 2 and out.count("warnings: ") == 2
    backlash = [line.split() for line in out.splitlines() if line.strip().startswith("backlash")]
    assert [b[2] for b in backlash] == ["0.1", "0.5"]  # true backlash [deg] of the two plants


def test_demo_params_and_seed(capsys):
    plant = {"name": "stiff one", "J_sigma": 0.03, "V_J": 0.5, "f_e": 300.0, "d": 0.05, "backlash": 0.0,
             "M_FC": 0.1, "mu_F": 0.0}
    assert main(["demo", "--params", json.dumps(plant), "--seed", "3"]) == 0
    out = capsys.readouterr().out
    assert "stiff one:" in out and "elastic plant" not in out
    assert _table_rows(out)["J_sigma"][2] == "0.03"


def test_demo_rejects_bad_params(capsys, tmp_path):
    assert main(["demo", "--params", "{not json"]) == 2
    assert "invalid JSON" in capsys.readouterr().err
    assert main(["demo", "--params", str(tmp_path / "missing.json")]) == 2
    assert "--params" in capsys.readouterr().err
    assert main(["demo", "--params", '{"J_sigma": -1, "V_J": 1, "f_e": 30}']) == 2
    err = capsys.readouterr().err
    assert err.startswith("twomass demo: error: --params") and len(err.strip().splitlines()) == 1
