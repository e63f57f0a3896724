"""Evaluation (issue 5): aggregation on hand-made rows, the report writer, the cache, a tiny CLI run."""

from __future__ import annotations

import builtins
import json
import math

import numpy as np
import pytest
import torch

from sim import DriveConfig, TestSignalConfig
import training.evaluation as ev
from training.cli import main
from training.errors import UserError
from training.evaluation import _cache, _sets, _summary
from training.evaluation._report import NO_MATPLOTLIB

TRUTH = {"J_sigma": 0.1, "V_J": 1.0, "f_e": 50.0}


#: The methods the hand-made rows below carry.
ROW_METHODS = ("som", "iv4")


def _row(cell: tuple[float, float], som: dict | None, iv4: dict | None, *, structure: str = "elastic",
         s_N: float = 0.0, r_osc: float = 10.0, som_structure: str | None = "elastic") -> dict:
    """A system with TRUTH and the given relative deviations (``None`` entries = missing)."""
    truth = dict(TRUTH, d=0.05, backlash=0.0, M_FC=0.2, mu_F=0.001, C_F=1e4, s_N=s_N, r_osc=r_osc,
                 w_e_T_Ei=0.1, structure=structure)

    def est(dev: dict | None) -> dict:
        dev = dev or {}
        return {k: (None if dev.get(k, 0.0) is None else TRUTH[k] * (1.0 + dev.get(k, 0.0))) for k in TRUTH}

    s = dict(est(som), d=0.05, backlash=0.0, M_FC=0.25, mu_F=0.001, structure=som_structure, osc_quanta=5.0,
             outside_training=False, n_warnings=0, error=None)
    if som_structure is None:  # the analysis failed: no estimates at all
        s.update(dict.fromkeys(_sets.METHOD_PARAMS["som"]), osc_quanta=None, error="ValueError: no test run")
    i = dict(est(iv4), d=0.05, valid=iv4 is not None, reason="" if iv4 is not None else "no resonance",
             converged=True, iterations=3)
    return {"set": "grid", "index": 0, "cell_f_e": cell[0], "cell_backlash_deg": cell[1], "truth": truth,
            "som": s, "iv4": i}


def _hand_rows() -> tuple[list[dict], ev.EvalSet]:
    """Grid 2 x 2 cells, 4 systems each, with known E_30 / E_50 per cell and method."""
    grid = ev.grid_set(4, 0, f_e=(20.0, 80.0), backlash_deg=(0.0, 0.5))
    rows = []
    # (20 Hz, 0 deg): SOM 4 exact -> 100/100; IV4: exact, -0.4 f_e (miss at 30, hit at 50), invalid, +0.6 V_J
    c = (20.0, 0.0)
    rows += [_row(c, {}, {}), _row(c, {}, {"f_e": -0.4}), _row(c, {}, None), _row(c, {}, {"V_J": 0.6})]
    # (20 Hz, 0.5 deg): SOM stiff (no f_e) / -0.35 J_sigma / +0.29 f_e / failed; IV4 all exact
    c = (20.0, 0.5)
    rows += [_row(c, {"f_e": None, "V_J": None}, {}, som_structure="stiff"), _row(c, {"J_sigma": -0.35}, {}),
             _row(c, {"f_e": 0.29}, {}), _row(c, None, {}, som_structure=None)]
    # (80 Hz, 0 deg): all exact for both
    c = (80.0, 0.0)
    rows += [_row(c, {}, {}) for _ in range(4)]
    # (80 Hz, 0.5 deg): s_N > 1 in 3 of 4; SOM 2 exact, 2 at -0.45 V_J; IV4 1 exact, 3 at +0.8 f_e
    c = (80.0, 0.5)
    rows += [_row(c, {}, {}, structure="stiff_backlash", s_N=2.0, som_structure="stiff_backlash"),
             _row(c, {}, {"f_e": 0.8}, structure="stiff_backlash", s_N=2.0, som_structure="elastic"),
             _row(c, {"V_J": -0.45}, {"f_e": 0.8}, structure="stiff_backlash", s_N=3.0, som_structure="stiff_backlash"),
             _row(c, {"V_J": -0.45}, {"f_e": 0.8}, structure="elastic_backlash", s_N=0.5, r_osc=0.5,
                  som_structure="elastic_backlash")]
    for k, r in enumerate(rows):
        r["index"] = k
    return rows, grid


def _cell(summary: dict, f_e: float, bl: float) -> dict:
    return next(c for c in summary["cells"] if c["f_e"] == f_e and c["backlash_deg"] == bl)


def test_cell_recognition_rates_are_exact():
    rows, grid = _hand_rows()
    s = _summary.summarize_set(rows, ROW_METHODS, grid)
    want = {  # cell: (SOM E_30, SOM E_50, IV4 E_30, IV4 E_50)
        (20.0, 0.0): (100, 100, 25, 50),
        (20.0, 0.5): (25, 50, 100, 100),
        (80.0, 0.0): (100, 100, 100, 100),
        (80.0, 0.5): (50, 100, 25, 25),
    }
    for (f, b), (s30, s50, i30, i50) in want.items():
        c = _cell(s, f, b)
        assert c["n"] == 4
        assert (c["som"]["E_30"], c["som"]["E_50"], c["iv4"]["E_30"], c["iv4"]["E_50"]) == (s30, s50, i30, i50), (f, b)
    assert _cell(s, 80.0, 0.5)["s_N_above_1"] == 0.75
    assert _cell(s, 80.0, 0.5)["r_osc_below_1"] == 1 and s["r_osc_below_1"] == 1
    means = {b["backlash_deg"]: b for b in s["backlash_means"]}
    assert means[0.0]["som"]["E_30"] == 100 and means[0.0]["iv4"]["E_30"] == 62.5
    assert means[0.5]["som"]["E_50"] == 75
    assert s["overall"]["som"]["E_30"] == 100 * 11 / 16 and s["overall"]["iv4"]["E_50"] == 100 * 11 / 16
    per_class = {c["class"]: c for c in s["per_class"]}
    assert per_class["stiff_backlash"]["n"] == 3 and per_class["stiff_backlash"]["iv4"]["E_30"] == pytest.approx(100 / 3)
    assert math.isnan(_summary.recognition([], "som", 30))
    assert per_class["stiff"]["n"] == 0 and per_class["stiff"]["som"]["E_30"] is None


def test_failures_confusion_and_parameter_stats():
    rows, grid = _hand_rows()
    s = _summary.summarize_set(rows, ROW_METHODS, grid)
    m = np.array(s["confusion"]["matrix"])
    assert m.shape == (4, 5) and m.sum() == 16
    assert m[1, 0] == 1 and m[1, 4] == 1  # true elastic -> stiff, -> failed
    assert m[3, 1] == 1 and m[3, 3] == 2 and m[2, 2] == 1
    assert s["failures"]["som"]["n_error"] == 1 and s["failures"]["som"]["n_stiff_no_f_e"] == 1
    assert s["failures"]["iv4"]["n_invalid"] == 1
    f_e = s["parameters"]["som"]["f_e"]
    assert (f_e["n"], f_e["n_missing"]) == (14, 2)
    assert f_e["mean"] == pytest.approx(0.29 / 14) and f_e["median_abs"] == pytest.approx(0.0)
    assert f_e["within_30"] == pytest.approx(100 * 14 / 16)  # the stiff and the failed system are outside
    assert s["parameters"]["iv4"]["f_e"]["within_30"] == pytest.approx(100 * 11 / 16)
    assert s["parameters"]["iv4"]["f_e"]["within_50"] == pytest.approx(100 * 12 / 16)
    v = s["parameters"]["iv4"]["V_J"]
    assert (v["n"], v["n_missing"]) == (15, 1)
    errs = np.array([0.6] + [0.0] * 14)
    assert v["mean"] == pytest.approx(errs.mean()) and v["std"] == pytest.approx(errs.std())
    assert s["parameters"]["som"]["M_FC"]["kind"] == "absolute"
    assert s["parameters"]["som"]["M_FC"]["mean"] == pytest.approx(0.05)
    assert "backlash" not in s["parameters"]["iv4"]


def test_acceptance_checks():
    rows, grid = _hand_rows()
    s = _summary.summarize_set(rows, ROW_METHODS, grid)
    checks = {c["name"][:12]: c for c in _summary.acceptance_checks(s, ROW_METHODS)}
    first, second = checks["SOM E_30 >= "], checks["SOM E_30 > I"]
    assert first["passed"] is True and "2 of 2" in first["detail"]  # (20, 0) and (80, 0)
    assert second["passed"] is True and "1 of 1" in second["detail"]  # (80, 0.5): SOM 50 > IV4 25
    assert _summary.acceptance_checks(s, ("som",))[0]["passed"] is True and len(_summary.acceptance_checks(s, ("som",))) == 1


def test_grid_set_fixes_f_e_and_backlash_per_cell():
    g = ev.grid_set(3, 4, f_e=(10.0, 120.0), backlash_deg=(0.0, 0.2))
    p = g.params()
    assert g.size == 12 and p.batch_shape == (12,)
    assert p.f_e[:6].tolist() == [10.0] * 6 and p.f_e[6:].tolist() == [120.0] * 6
    assert torch.allclose(p.backlash[3:6], torch.deg2rad(torch.tensor(0.2, dtype=torch.float64)).expand(3))
    assert g.cell_of(7) == (120.0, 0.0) and len(set(p.J_sigma.tolist())) == 12
    assert torch.equal(g.params().V_J, p.V_J)  # seeded
    with pytest.raises(ValueError, match="per_cell"):
        ev.grid_set(0, 1)
    with pytest.raises(ValueError, match="kind"):
        ev.EvalSet(name="x", kind="cube", seed=0)


def test_cache_roundtrip_and_refusal(tmp_path):
    s = ev.population_set(3, 1)
    drive, signal = DriveConfig(), TestSignalConfig()
    cfg = ev.method_config("iv4", s, drive, signal)
    assert ev.load_cached(tmp_path, cfg, 3) is None
    path = ev.save_cached(tmp_path, cfg, [{"f_e": 1.0}, {"f_e": None}, {"f_e": 3.0}], {"compute_s": 2.0})
    assert ev.load_cached(tmp_path, cfg, 3) == ([{"f_e": 1.0}, {"f_e": None}, {"f_e": 3.0}], {"compute_s": 2.0})
    with pytest.raises(UserError, match="expected 4 results"):
        ev.load_cached(tmp_path, cfg, 4)
    data = json.loads(path.read_text())
    data["config"]["seed_was_changed"] = True
    path.write_text(json.dumps(data))
    with pytest.raises(UserError, match="another config"):
        ev.load_cached(tmp_path, cfg, 3)
    other = ev.method_config("iv4", ev.population_set(3, 2), drive, signal)
    assert _cache._cache_path(tmp_path, other) != path
    with pytest.raises(ValueError, match="method"):
        ev.method_config("ls", s, drive, signal)


def test_markdown_and_json_writer(tmp_path, monkeypatch):
    rows, grid = _hand_rows()
    summary = ev.summarize({"grid": rows}, {"grid": grid}, ROW_METHODS)
    md = ev.render_markdown(summary, command="twomass evaluate --per-cell 4")
    assert "| 20 | 100 / 25 | 25 / 100 |" in md  # E_30 row, SOM / IV4
    assert "| 80 | 100 / 100 | 50 / 25 |" in md
    assert "| **mean** | 100 / 62 | 38 / 62 |" in md
    assert "twomass evaluate --per-cell 4" in md and "**PASS**" in md

    real_import = builtins.__import__

    def no_matplotlib(name, *args, **kwargs):
        if name.startswith("matplotlib"):
            raise ImportError(name)
        return real_import(name, *args, **kwargs)

    monkeypatch.setattr(builtins, "__import__", no_matplotlib)
    out = ev.write_report(summary, {"grid": rows}, tmp_path, command="cmd")
    assert out["note"] == NO_MATPLOTLIB
    assert NO_MATPLOTLIB in (tmp_path / "report.md").read_text()
    data = json.loads((tmp_path / "report.json").read_text())
    assert data["command"] == "cmd" and data["figures"] == []
    assert _cell(data["sets"]["grid"], 80.0, 0.5)["iv4"]["E_30"] == 25
    lines = (tmp_path / "systems.csv").read_text().splitlines()
    assert len(lines) == 17 and lines[0].startswith("set,index,cell_f_e")


def _shipped_maps_fit() -> bool:
    from som_torch import CheckpointError
    from training.identification import Identifier

    try:
        Identifier.load()
    except CheckpointError:
        return False
    return True


def test_cli_tiny_end_to_end(tmp_path, capsys):
    """All methods through the CLI; IV4 only while the shipped maps do not fit the features."""
    methods = {"som", "maps", "iv4"} if _shipped_maps_fit() else {"iv4"}
    out, cache = tmp_path / "out", tmp_path / "cache"
    argv = ["evaluate", "--out", str(out), "--cache", str(cache), "--per-cell", "1", "--f-e", "20",
            "--backlash", "0,0.5", "--population", "1", "--workers", "1", "--no-progress", "--no-plots"]
    argv += [] if "som" in methods else ["--no-som"]
    assert main(argv) == 0
    text = capsys.readouterr().out
    assert "grid: 2 systems" in text and "population: 1 systems" in text
    data = json.loads((out / "report.json").read_text())
    assert [c["n"] for c in data["sets"]["grid"]["cells"]] == [1, 1]
    assert set(data["sets"]["grid"]["overall"]) == methods
    assert len(list(cache.glob("*.json"))) == 2 * len(methods)
    # rerun: everything from the cache, same numbers (the report replaced only with --overwrite)
    assert main(argv) == 2
    assert "report.md" in capsys.readouterr().err
    assert main(argv + ["--overwrite"]) == 0
    again = json.loads((out / "report.json").read_text())
    assert all(info["cached"] for t in again["timing"]["sets"].values() for info in t["methods"].values())
    assert all(not info["cached"] for t in data["timing"]["sets"].values() for info in t["methods"].values())
    assert "Simulation + identification time: grid (" + "+".join(m for m in ev.METHODS if m in methods) \
        + ", 2 systems)" in (out / "report.md").read_text()
    assert again["sets"] == data["sets"]
    assert (out / "report.md").read_text().count("| 20 |") == 3
    # bad input: one line, exit code 2
    assert main(["evaluate", "--per-cell", "0", "--population", "0", "--out", str(out)]) == 2
    assert "expected at least one > 0" in capsys.readouterr().err
    assert main(["evaluate", "--out", str(out), "--per-cell", "1", "--population", "0", "--no-cache",
                 "--checkpoints", str(tmp_path / "none"), "--no-progress", "--overwrite"]) == 2
    assert "expected a checkpoint folder" in capsys.readouterr().err


def test_source_digest_follows_the_import_closure(monkeypatch):
    seen: list[str] = []
    real = _cache._module_file

    def spy(name: str):
        path = real(name)
        if path is not None:
            seen.append(name)
        return path

    monkeypatch.setattr(_cache, "_module_file", spy)
    som = ev.source_digest(_cache.METHOD_ROOTS["som"])
    assert {"training.identification._analysis", "training.identification._features", "training.identification._identifier", "sim.plant"} <= set(seen)
    assert "training.evaluation._iv4" not in seen and "training.evaluation._study" not in seen
    iv4 = ev.source_digest(_cache.METHOD_ROOTS["iv4"])
    assert som != iv4 == ev.source_digest(_cache.METHOD_ROOTS["iv4"])  # (iv4: files nobody edits during the test)


def test_identification_checks_hand_counts():
    """Issue 4's targets on hand-made rows: 4 elastic systems, one misclassified, one V_J miss."""
    rows = [_row((20.0, 0.0), {}, {}), _row((20.0, 0.0), {}, {}),
            _row((20.0, 0.0), {"V_J": 0.4}, {}), _row((20.0, 0.0), {}, {}, som_structure="elastic_backlash")]
    checks = {c["name"].split(" (")[0]: c for c in _summary.identification_checks(rows)}
    assert checks["structure accuracy >= 95 %"]["detail"] == "measured 75.0 %"
    assert checks["E_30 >= 95 % over elastic + elastic_backlash"]["detail"] == "measured 75.0 %"
    assert checks["E_50 >= 99 % over elastic + elastic_backlash"]["detail"] == "measured 100.0 %"
    assert checks["E_50 >= 99 % over elastic + elastic_backlash"]["passed"] is True
    assert checks["J_sigma within 5 % for >= 95 %"]["passed"] is True
    assert checks["M_FC within 0.05 Nm for >= 90 %"]["detail"] == "measured 100.0 %"  # 0.25 vs 0.2 Nm
