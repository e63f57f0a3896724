"""The confidence study of SPEC 4.1 on hand-made drive rows: interval coverage, half-widths, the
calibration error and reliability table of the probabilities, the warned shares, the report files."""

from __future__ import annotations

import json

import numpy as np
import pytest

from training.evaluation import (confidence_report, coverage_table, drive_figures, drives_markdown,
                                 expected_calibration_error, median_half_width, reliability, warned_shares,
                                 write_confidence)
from training.evaluation._confidence import MIN_CELL, confidence_markdown


def _row(cls="elastic", answer=None, f_e=(25.0, 35.0), backlash=(0.0, 0.001), p=0.8, answer_p=0.8, warnings=0,
         f_e_true=30.0, backlash_true=0.0, calibrated=True, error=None, J=0.1):
    """A system of class ``cls`` answered ``answer`` (default: right, every value exact) with ``f_e``
    and ``backlash`` intervals (the other parameters' intervals hold their truth)."""
    truth = dict(structure=cls, f_e=f_e_true, V_J=1.0, J_sigma=0.1, backlash=backlash_true)
    som = dict(structure=answer or cls, f_e=f_e_true, V_J=1.0, J_sigma=J, backlash=backlash_true,
               n_warnings=warnings, error=error,
               intervals=dict(f_e=list(f_e), backlash=list(backlash), V_J=[0.9, 1.1], J_sigma=[0.09, 0.11])
               if calibrated else None,
               probabilities={c: (p if c == (answer or cls) else (1 - p) / 3)
                              for c in ("stiff", "elastic", "elastic_backlash", "stiff_backlash")},
               answer_probability=answer_p if calibrated else None, warning_codes=[], note_codes=[])
    if error is not None:
        som = dict(structure=None, n_warnings=0, error=error)
    return {"truth": truth, "som": som}


PARAMS = ("f_e", "backlash", "V_J", "J_sigma")


def test_coverage_counts_the_truth_inside_inclusive_and_a_zero_backlash_at_a_zero_bound():
    rows = [_row() for _ in range(8)]
    rows.append(_row(f_e=(30.0, 40.0)))  # truth on the bound: inside
    rows.append(_row(f_e=(31.0, 40.0), backlash=(1e-4, 1e-3)))  # f_e outside; backlash 0 below a bound > 0: outside
    rows.append(_row(calibrated=False))  # skipped, counted
    rows.append(_row(error="record too short"))  # failed, counted
    table = coverage_table({"d": rows}, PARAMS)
    assert table.overall["f_e"].n == 10 and table.overall["f_e"].covered == 9
    assert table.overall["f_e"].percent == pytest.approx(90.0)
    assert table.overall["backlash"].percent == pytest.approx(90.0) and table.overall["V_J"].percent == 100.0
    assert table.n_uncalibrated == 1 and table.n_failed == 1
    assert table.by_drive["d"]["f_e"] == table.overall["f_e"]


def test_cells_by_reported_class_and_drive_list_only_those_of_30_and_more():
    # drive a: 30 elastic answers, 3 of them outside; 29 stiff ones (too few: left out); drive b: 5 elastic ones
    a = [_row(f_e=(31.0, 40.0) if i < 3 else (25.0, 35.0)) for i in range(MIN_CELL)]
    a += [_row("stiff") for _ in range(MIN_CELL - 1)]
    b = [_row() for _ in range(5)]
    b.append(_row("stiff", answer="elastic", f_e=(31.0, 40.0)))  # true stiff, reported elastic, outside
    table = coverage_table({"a": a, "b": b}, PARAMS)
    assert [(c.structure, c.drive, c.n) for c in table.cells] == [("elastic", "a", MIN_CELL)]
    assert table.cells[0].coverage["f_e"].percent == pytest.approx(90.0)
    assert table.n_small_cells == 2  # stiff x a (29), elastic x b (6)
    assert table.by_reported_class["elastic"]["f_e"].n == MIN_CELL + 6
    assert table.by_reported_class["elastic"]["f_e"].covered == MIN_CELL - 3 + 5
    assert table.by_true_class["stiff"]["f_e"].n == MIN_CELL and table.by_true_class["stiff"]["f_e"].covered == MIN_CELL - 1
    assert table.worst_cell("f_e").drive == "a"


def test_median_relative_half_width():
    rows = [_row(f_e=(27.0, 33.0)), _row(f_e=(24.0, 36.0)), _row(f_e=(29.0, 31.0)), _row(calibrated=False)]
    assert median_half_width(rows, "f_e") == pytest.approx(0.1)  # half-widths 0.1, 0.2, 1/30 of 30 Hz
    assert median_half_width(rows, "backlash") is None  # every true backlash 0: no relative width
    assert median_half_width([_row(calibrated=False)], "f_e") is None


@pytest.mark.parametrize(("p", "right", "ece"), [(0.8, 8, 0.0), (0.9, 5, 0.4), (0.3, 3, 0.0), (1.0, 10, 0.0)])
def test_expected_calibration_error_of_one_probability(p, right, ece):
    hit = np.arange(10) < right
    assert expected_calibration_error(np.full(10, p), hit) == pytest.approx(ece, abs=1e-12)


def test_expected_calibration_error_weights_the_bins_by_their_answers():
    # 4 answers at 0.95 (all right: |0.95 - 1| = 0.05) and 6 at 0.55 (3 right: 0.05): ECE 0.05
    p = np.array([0.95] * 4 + [0.55] * 6)
    hit = np.array([True] * 4 + [True, True, True, False, False, False])
    assert expected_calibration_error(p, hit) == pytest.approx(0.05)
    # two bins off by 0.4 and 0.1, 5 answers each: (0.4 + 0.1) / 2
    p = np.array([0.9] * 5 + [0.15] * 5)
    hit = np.array([True, False, False, False, True] + [True, False, False, False, False])
    assert expected_calibration_error(p, hit) == pytest.approx(0.5 * 0.5 + 0.5 * 0.05)


def test_reliability_bins():
    rel = reliability(np.array([0.0, 0.05, 0.1, 0.3, 0.99, 1.0]), np.array([False, False, True, True, True, False]))
    assert rel.count == (2, 1, 0, 1, 0, 0, 0, 0, 0, 2)
    assert rel.mean_p[0] == pytest.approx(0.025) and rel.observed[0] == 0.0
    assert rel.observed[1] == 1.0 and rel.mean_p[2] is None and rel.observed[2] is None
    assert rel.mean_p[9] == pytest.approx(0.995) and rel.observed[9] == 0.5
    assert rel.edges[0] == 0.0 and rel.edges[-1] == 1.0 and len(rel.edges) == 11
    with pytest.raises(ValueError, match="0..1"):
        reliability(np.array([1.2]), np.array([True]))
    with pytest.raises(TypeError, match="booleans"):
        reliability(np.array([0.5]), np.array([1]))
    with pytest.raises(ValueError, match="at least one"):
        expected_calibration_error(np.array([]), np.array([], dtype=bool))


def test_warned_shares_and_the_drive_table_columns():
    rows = [_row(), _row(warnings=1), _row(), _row(),  # right, one warned: 25 %
            _row(answer="stiff"), _row(answer="stiff", warnings=2),  # class wrong, one unwarned: 50 %
            _row(J=0.2, warnings=1),  # J_sigma off by 100 %: wrong, warned
            _row(error="no sections")]  # failed: in neither
    w = warned_shares(rows)
    assert (w.n_right, w.n_right_warned, w.n_wrong, w.n_wrong_unwarned, w.n_failed) == (4, 1, 3, 1, 1)
    assert w.right_warned == pytest.approx(25.0) and w.wrong_unwarned == pytest.approx(100.0 / 3)
    for r in rows:
        r["truth"].update(s_N=0.0, r_osc=100.0, w_e_T_Ei=0.1)
    f = drive_figures(rows)
    assert f["right_warned"] == pytest.approx(25.0) and f["n_right"] == 4
    assert f["wrong_unwarned"] == pytest.approx(100.0 / 3) and f["n_wrong"] == 3
    assert "| 25.0 (4) | 33.3 (3) |" in drives_markdown({"x": f}, "cmd")


def test_class_and_answer_calibration_in_the_report():
    rows = [_row(p=0.9, answer_p=0.9, answer=None if i < 5 else "stiff") for i in range(10)]
    rows.append(_row(calibrated=False))  # no answer_probability: uncalibrated; its class probability counts
    report = confidence_report({"d": rows}, PARAMS)
    assert report.structure.reliability.n == 11 and report.answer.reliability.n == 10
    assert report.answer.reliability.ece == pytest.approx(0.4) and report.answer.n_uncalibrated == 1
    assert report.structure.reliability.count[9] == 10 and report.structure.reliability.count[8] == 1
    assert report.structure.n_not_summing == 0 and report.structure.n_not_argmax == 0
    rows[0]["som"]["probabilities"].update(stiff=0.95)  # the reported elastic no longer the most probable, sum 1.85
    rows[1]["som"]["probabilities"].update(stiff=0.1)  # sums to 1.0333
    again = confidence_report({"d": rows}, PARAMS).structure
    assert again.n_not_summing == 2 and again.n_not_argmax == 1
    checks = {c.name: c.passed for c in report.checks}
    assert checks["answer_probability: ECE <= 0.05"] is False
    assert checks["f_e: every class x drive cell >= 80 %"] is None  # no cell of 30


def test_the_report_refuses_all_as_a_drive_name():
    with pytest.raises(ValueError, match="reserved"):
        confidence_report({"all": [_row()]}, PARAMS)


def test_the_report_files(tmp_path):
    rows = [_row() for _ in range(9)] + [_row(f_e=(31.0, 40.0))]
    report = confidence_report({"a": rows}, PARAMS)
    written = write_confidence(report, tmp_path, "confidence", "twomass evaluate --drives 10", {"a": "drive a"},
                               plots=False)
    assert [p.name for p in written] == ["confidence.md", "confidence.json"]
    data = json.loads((tmp_path / "confidence.json").read_text())
    assert data["coverage"]["overall"]["f_e"] == {"n": 10, "covered": 9, "percent": 90.0}
    assert data["coverage"]["by_drive"]["a"]["f_e"]["percent"] == 90.0
    assert data["median_relative_half_width"]["all"]["f_e"] == pytest.approx(1 / 6)
    assert data["structure_probability"]["ece"] == pytest.approx(0.2)  # all 0.8, all right
    md = (tmp_path / "confidence.md").read_text()
    assert "`twomass evaluate --drives 10`" in md and "| a: drive a | 90.0 (10) |" in md
    assert "| f_e: coverage 85..95 % | PASS | 90.0 % of 10 |" in md
    assert md == confidence_markdown(report, "twomass evaluate --drives 10", {"a": "drive a"})


def test_the_reliability_figure(tmp_path):
    pytest.importorskip("matplotlib")
    rows = [_row(p=0.2 + 0.07 * i, answer_p=0.5) for i in range(10)]
    written = write_confidence(confidence_report({"a": rows}, PARAMS), tmp_path, "confidence_envelope", "cmd")
    assert [p.name for p in written] == ["confidence_envelope.md", "confidence_envelope.json",
                                         "fig_reliability_envelope.png"]
    assert (tmp_path / "fig_reliability_envelope.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert "![reliability](fig_reliability_envelope.png)" in (tmp_path / "confidence_envelope.md").read_text()
