"""The drive matrix of issue 11 (``twomass evaluate --drives``): every drive inside SPEC 3.1's
envelope, and the figures (silent-wrong rate included) on hand-made rows."""

from __future__ import annotations

import json
import math

import pytest

from training.evaluation import DRIVES, drive_figures, drives_markdown
from training.identification import SPEC_ENVELOPE


def test_the_matrix_spans_the_envelope():
    assert len(DRIVES) >= 6 and "reference" in DRIVES
    env = SPEC_ENVELOPE
    for case in DRIVES.values():
        d, s = case.drive, case.signal
        assert env["T_s"][0] <= d.T_s <= env["T_s"][1]
        assert env["encoder_counts"][0] <= d.encoder_counts <= env["encoder_counts"][1]
        assert env["T_Ei"][0] <= d.T_Ei <= env["T_Ei"][1]
        assert env["M_max_over_M_N"][0] <= d.M_max / d.M_N <= env["M_max_over_M_N"][1]
        assert s.M_star <= d.M_max and d.current_noise_std * d.K_M / s.M_star <= env["current_noise"][1]
        J = case.ranges().J_sigma
        assert env["time_scale"][0] <= J[0] * s.w_max / s.M_star and J[1] * s.w_max / s.M_star <= env["time_scale"][1]
    assert {c.drive.T_s for c in DRIVES.values()} >= {125e-6, 1e-3, 5e-4, 62.5e-6, 2.5e-4}


def _row(cls, f_e, V_J, J, s_N=0.0, backlash=0.0, som=None, warnings=0):
    truth = dict(structure=cls, f_e=f_e, V_J=V_J, J_sigma=J, s_N=s_N, backlash=backlash, r_osc=100.0,
                 w_e_T_Ei=0.1)
    est = dict(structure=cls, f_e=f_e, V_J=V_J, J_sigma=J, backlash=backlash, n_warnings=warnings, error=None)
    est.update(som or {})
    return {"truth": truth, "som": est}


def test_figures_and_the_silent_wrong_rate():
    rows = [
        _row("elastic", 30.0, 1.0, 0.1),  # right
        _row("elastic", 30.0, 1.0, 0.1, som=dict(f_e=45.0)),  # outside E_30, unwarned: silent wrong
        _row("elastic", 30.0, 1.0, 0.1, som=dict(f_e=45.0), warnings=2),  # wrong but warned
        _row("elastic_backlash", 30.0, 1.0, 0.1, s_N=0.5, backlash=0.01, som=dict(backlash=0.012)),  # within 30 %
        _row("stiff", math.nan, math.nan, 0.1, som=dict(structure="elastic", J_sigma=0.2)),  # class and J wrong
    ]
    f = drive_figures(rows)
    assert f["n"] == 5 and f["n_elastic"] == 4 and f["n_backlash"] == 1
    assert f["E_30"] == pytest.approx(50.0) and f["backlash_30"] == 100.0
    assert f["structure"] == pytest.approx(80.0) and f["J_sigma_5"] == pytest.approx(80.0)
    assert f["silent_wrong"] == pytest.approx(40.0) and f["warned"] == pytest.approx(20.0)
    assert "| reference" not in drives_markdown({"x": f}, "cmd") and "`cmd`" in drives_markdown({"x": f}, "cmd")


def test_visible_figures_leave_out_only_the_gaps_the_record_cannot_show():
    def row(cls, s_N, gap_counts, answer):
        r = _row(cls, 300.0, 1.0, 0.1, s_N=s_N, backlash=0.001, som=dict(structure=answer))
        r["truth"]["gap_counts"] = gap_counts
        return r

    rows = [row("stiff_backlash", 2.0, 1.5, "stiff"),  # hidden gap, missed: out of the visible figure
            row("stiff_backlash", 2.0, 2.5, "stiff"),  # visible gap, missed: counts
            row("stiff_backlash", 2.0, 3.0, "stiff_backlash"),
            row("stiff", 0.05, 0.5, "stiff_backlash")]  # no backlash in the class rule: counts, wrong
    f = drive_figures(rows)
    assert f["structure"] == pytest.approx(25.0) and f["n_structure"] == 4
    assert f["structure_visible"] == pytest.approx(100.0 / 3) and f["n_structure_visible"] == 3
    assert f["n_backlash"] == 3 and f["n_backlash_visible"] == 2


def test_E_30_visible_leaves_out_only_the_oscillations_below_the_resolution():
    rows = [_row("elastic", 30.0, 1.0, 0.1, som=dict(f_e=45.0), warnings=1),  # visible (r_osc 100), missed
            _row("elastic", 30.0, 1.0, 0.1),
            _row("elastic_backlash", 30.0, 1.0, 0.1, s_N=0.5, som=dict(structure="stiff", f_e=None), warnings=1)]
    rows[2]["truth"]["r_osc"] = 0.2  # below the resolution: out of the visible figure
    f = drive_figures(rows)
    assert f["E_30"] == pytest.approx(100.0 / 3) and f["n_elastic"] == 3
    assert f["E_30_visible"] == pytest.approx(50.0) and f["n_elastic_visible"] == 2
    assert "| 50.0 (2) |" in drives_markdown({"x": f}, "cmd")


def test_drives_drawn_over_the_envelope(tmp_path):
    """``--envelope-drives``: drives of the maps' own training distribution, none of them the reference
    drive, each inside the envelope, identified and scored; the table has a row per drive and one for all."""
    from sim import EnvelopeRanges, sample_envelope
    from training.cli import main

    sample = sample_envelope(6, 3, EnvelopeRanges(cell=3, reference_share=0.0))
    env = SPEC_ENVELOPE
    for drive, signal in sample.cases:
        assert env["T_s"][0] <= drive.T_s <= env["T_s"][1] and drive.T_s != 250e-6
        assert env["encoder_counts"][0] <= drive.encoder_counts <= env["encoder_counts"][1]
        assert signal.M_star <= drive.M_max
    assert main(["evaluate", "--drives", "3", "--envelope-drives", "2", "--seed", "3", "--out", str(tmp_path)]) == 0
    md = (tmp_path / "drives_envelope.md").read_text()
    assert "--envelope-drives 2 --seed 3" in md and "| all: the 2 drives together | 6 |" in md
    for drive, _ in sample.cases:  # the drives of the same seed and cells, in words
        assert f"T_s {drive.T_s * 1e6:.4g} us, 2^{math.log2(drive.encoder_counts):.0f} counts" in md
    assert md.count("| envelope_") == 2 and not (tmp_path / "drives.md").exists()
    conf = (tmp_path / "confidence_envelope.md").read_text()  # the confidence of the same answers
    assert "--envelope-drives 2 --seed 3" in conf and conf.count("| envelope_") >= 2
    data = json.loads((tmp_path / "confidence_envelope.json").read_text())
    assert data["n_calibrated"] + data["n_uncalibrated"] + data["n_failed"] == 6
    assert data["structure_probability"]["reliability"]["n"] == 6 - data["n_failed"]
    assert not (tmp_path / "confidence.md").exists()


@pytest.mark.parametrize(("argv", "message"), [
    (["--envelope-drives", "2"], "--envelope-drives K: give the systems per drive with --drives N"),
    (["--drives", "2", "--envelope-drives", "0"], "--envelope-drives: expected K >= 1 drives, received 0")])
def test_envelope_drives_bad_input(tmp_path, capsys, argv, message):
    from training.cli import main

    assert main(["evaluate", *argv, "--out", str(tmp_path)]) == 2
    assert capsys.readouterr().err.strip() == f"twomass evaluate: error: {message}"
    assert not any(tmp_path.iterdir())
