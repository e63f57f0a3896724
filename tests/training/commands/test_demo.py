"""``twomass demo``: runs without arguments and prints true and identified values side by side."""

from __future__ import annotations

import json
import types
from pathlib import Path

import pytest

from training.cli import main
from training.identification import PARAMETER_NAMES

REPO = Path(__file__).resolve().parents[3]


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


def _close(readme, actual, path="") -> None:
    """``readme`` is ``actual`` rounded (4 significant digits): same keys, strings, and numbers within 0.1 %."""
    if isinstance(actual, dict):
        assert isinstance(readme, dict) and list(readme) == list(actual), path
        for k in actual:
            _close(readme[k], actual[k], f"{path}.{k}")
    elif isinstance(actual, list):
        assert isinstance(readme, list) and len(readme) == len(actual), path
        for i, (r, a) in enumerate(zip(readme, actual)):
            _close(r, a, f"{path}[{i}]")
    elif isinstance(actual, float) and not isinstance(readme, bool):
        assert readme == pytest.approx(actual, rel=1e-3, abs=1e-12), path
    else:
        assert readme == actual, path


def test_readme_json_example_is_what_demo_json_prints(capsys):
    """The README's JSON example is the first line of `twomass demo --json` (rounded): kept in step here."""
    readme = (REPO / "README.md").read_text()
    section = readme[readme.index("## Identify your own record"):]
    assert "`twomass demo --json`" in section
    example = json.loads(next(x for x in section.splitlines() if x.startswith('{"record"')))
    assert main(["demo", "--json"]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert len(lines) == 2
    _close(example, json.loads(lines[0]))


def test_demo_flags_a_poorly_determined_parameter_and_explains_its_figures():
    import io

    from training.commands import demo

    truth = {"structure": "elastic", "s_N": 0.04, "r_osc": 44.0, "J_sigma": 0.05, "V_J": 1.0, "J_M": 0.025,
             "J_L": 0.025, "f_e": 30.0, "C_F": 444.0, "d": 0.02, "backlash": 0.0017, "M_FC": 0.2, "mu_F": 0.001}

    class Res:  # the attributes print_result reads
        ok, structure, warnings = True, "elastic", ()
        parameters = types.SimpleNamespace(**{k: truth[k] for k in PARAMETER_NAMES})
        quality = types.SimpleNamespace(structure_probabilities={"elastic": 0.9}, map_distance_ratio={"f_e": 0.3},
                                        osc_quanta=13.8, one_mass_rel_residual=0.003, stiff_mode_note=None)

    other = types.SimpleNamespace(ok=True, parameters=types.SimpleNamespace(**{**vars(Res.parameters), "d": 0.03}))
    spread = demo.spreads([Res(), other])
    assert spread["d"] == pytest.approx(0.5) and spread["f_e"] == 0.0
    out = io.StringIO()
    demo.print_result("p", truth, Res(), 100, 2.5e-4, out, spread)
    text = out.getvalue()
    assert "50 %  poorly determined" in text and "warnings: poorly determined by this test run: d (" in text
    demo._explain(out)
    explained = out.getvalue()
    for figure in ("s_N", "r_osc", "spread", "map distance", "oscillation", "one-mass residual"):
        assert f"\n  {figure} " in explained, figure
