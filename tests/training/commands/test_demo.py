"""``twomass demo``: runs without arguments and prints true and identified values side by side."""

from __future__ import annotations

import json
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


_TRUTH = {"structure": "elastic", "s_N": 0.04, "r_osc": 44.0, "J_sigma": 0.05, "V_J": 1.0, "J_M": 0.025,
          "J_L": 0.025, "f_e": 30.0, "C_F": 444.0, "d": 0.02, "backlash": 0.0017, "M_FC": 0.2, "mu_F": 0.001,
          "M_L0": 0.1, "M_FCM": 0.05, "mu_FM": 0.0001}


def _result(intervals, answer_probability):
    """A result whose parameters are the truth, with ``intervals`` and one warning and two notes."""
    from training.identification import IdentificationResult, IdentWarning, Parameters, Quality

    quality = Quality(structure_probabilities={"stiff": 0.01, "elastic": 0.83, "elastic_backlash": 0.15,
                                               "stiff_backlash": 0.01},
                      map_distance_ratio={"f_e": 0.3}, osc_quanta=13.8, oscillation_fit_r2=0.6,
                      one_mass_rel_residual=0.003, outside_training=False, section_flags=(), maps_estimate={},
                      outside_envelope={}, answer_probability=answer_probability)
    return IdentificationResult(
        "elastic", Parameters(**{k: _TRUTH[k] for k in PARAMETER_NAMES}), quality,
        warnings=(IdentWarning("likely_wrong", "the answer is right with probability 0.42 only"),),
        intervals=intervals,
        notes=(IdentWarning("refine_partial_fit", "long text one"), IdentWarning("class_undecided", "long text two")))


def _print(res) -> str:
    import io

    from training.commands import demo

    out = io.StringIO()
    demo.print_result("p", _TRUTH, res, 100, 2.5e-4, out)
    return out.getvalue()


def test_demo_prints_each_values_90_percent_interval_and_the_calibrated_probabilities():
    from training.identification import Intervals

    bounds = dict(J_sigma=(0.0499, 0.0501), V_J=(0.8, 1.3), J_M=(0.024, 0.026), J_L=(0.02, 0.024),
                  f_e=(29.7, 30.3), C_F=(400.0, 500.0), d=(0.004, 0.13), backlash=(0.0, 0.00349066),
                  M_FC=(0.15, 0.25), mu_F=(0.0, 0.002), M_L0=(-0.01, 0.01), M_FCM=(0.0, 0.01), mu_FM=(0.0, 1e-4))
    text = _print(_result(Intervals(**bounds), 0.42))
    rows = _table_rows(text)
    assert "90 % interval" in text and "no calibration" not in text
    cell = {name: " ".join(rows[name][6:]) for name in PARAMETER_NAMES}
    assert cell["J_sigma"] == "+-0.2 %"  # 0.0001 / 0.05 either side
    assert cell["f_e"] == "+-1 %"
    assert cell["V_J"] == "-20/+30 %"  # sides differ by more than a factor 1.25
    assert cell["J_M"] == "+-4 %"
    assert cell["J_L"] == "[0.02 .. 0.024] (true value outside)"  # the value outside: not relative to it
    assert cell["C_F"] == "-9.9/+13 %"  # (444 - 400) / 444, (500 - 444) / 444
    assert cell["d"] == "[0.004 .. 0.13]"  # the upper side lies 550 % above the value
    assert cell["backlash"] == "[0 .. 0.2]"  # in degrees, as the row's unit; may be 0: never relative
    assert cell["M_FC"] == "[0.15 .. 0.25]" and cell["mu_F"] == "[0 .. 0.002]"
    assert "quality: P(elastic) 0.83 (next: elastic_backlash 0.15); P(right) 0.42;" in text
    assert "  warnings: the answer is right with probability 0.42 only\n" in text
    assert "  notes: refine_partial_fit, class_undecided\n" in text and "long text" not in text


def test_demo_says_where_the_maps_carry_no_calibration():
    text = _print(_result(None, None))
    assert "   90 % interval\n" not in text  # no column
    assert text.count("  90 % intervals: none (the maps carry no calibration") == 1
    rows = _table_rows(text)
    assert all(len(rows[name]) == 6 for name in PARAMETER_NAMES)  # name, unit, true, identified, error "+0.0 %"
    assert "quality: P(elastic) 0.83 uncalibrated (next: elastic_backlash 0.15); map distance" in text
    assert "P(right)" not in text


def test_demo_explains_its_figures():
    import io

    from training.commands import demo

    out = io.StringIO()
    demo._explain(out)
    explained = out.getvalue()
    for figure in ("s_N", "r_osc", "90 % interval", "P(class)", "P(right)", "warnings", "notes", "map distance",
                   "oscillation", "one-mass residual"):
        assert f"\n  {figure} " in explained, figure
