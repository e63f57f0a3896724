"""The identify page and the record on the maps, on one known record (``good``: elastic, f_e 30 Hz)
with the shipped maps: axes with units, the replay close to the measured speed, f_e and the
anti-resonance where the parameters put them, the best match where the recall finds it."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
import torch

import som_torch as st
from training.figures import failure_figure, identify_figure, maps_figure, page_names, unit_xy
from training.identification import FEATURE_NAMES, PARAMETER_NAMES, PARAMETER_UNITS, Identifier, Intervals, analyze

pytest.importorskip("matplotlib")


@pytest.fixture(scope="module")
def identified(good):
    ident = Identifier.load()
    result = ident.identify(good)
    assert result.ok and result.structure == "elastic"
    return ident, result, analyze(good)


def _line(ax, label: str):
    (line,) = [ln for ln in ax.get_lines() if ln.get_label() == label]
    return line


def test_identify_page_shows_the_replay_on_the_measured_speed(good, identified) -> None:
    _, result, analysis = identified
    fig = identify_figure(good, result, analysis)
    ax_w, ax_o, ax_i, ax_f, ax_t, _ = fig.axes
    assert ax_w.get_ylabel() == "motor speed w_M [rad/s]"
    assert ax_o.get_ylabel().endswith("[rad/s]") and ax_o.get_ylabel().startswith("w_osc")
    assert ax_i.get_ylabel() == "motor current i [A]" and ax_i.get_xlabel() == "time t [s]"
    assert ax_f.get_xlabel() == "frequency f [Hz]" and ax_f.get_ylabel().endswith("[rad/s]")
    # the six sections are labelled over the speed
    assert [t.get_text() for t in ax_w.texts] == ["I", "II", "III", "IV", "V", "VI", "tail"]
    # the identified model replayed through the record's test signal follows the measured speed
    model = _line(ax_w, "identified model, replayed").get_ydata()
    measured = _line(ax_w, "measured").get_ydata()
    np.testing.assert_array_equal(measured, good.speed)
    rms = lambda x: float(np.sqrt(np.mean(np.square(x))))  # noqa: E731
    assert rms(model - good.speed) < 0.02 * rms(good.speed)
    # ... and its oscillation matches the measured one (eq. 1 part)
    osc_model = _line(ax_o, "model's w_osc").get_ydata()
    osc = _line(ax_o, "measured w_osc").get_ydata()
    assert rms(osc_model - osc) < 0.6 * rms(osc)
    # the spectrum marks f_e and the anti-resonance f_e / sqrt(1 - d^2) / sqrt(1 + V_J)
    p = result.parameters
    f_e = _line(ax_f, f"f_e = {p.f_e:.4g} Hz").get_xdata()
    assert f_e[0] == pytest.approx(p.f_e)
    f_a = p.f_e / math.sqrt(1.0 - p.d ** 2) / math.sqrt(1.0 + p.V_J)
    (anti,) = [ln for ln in ax_f.get_lines() if ln.get_label().startswith("anti-resonance")]
    assert anti.get_xdata()[0] == pytest.approx(f_a, rel=1e-9)
    assert 20.0 < f_a < p.f_e
    # the measured spectrum peaks at the true f_e, and the marked f_e lies there too (each within
    # one FFT bin, 2 % here)
    f, X = _line(ax_f, "measured w_osc").get_data()
    df = 1.0 / (len(good) * good.T_s)
    assert abs(f[np.argmax(X)] - good.meta["truth"]["f_e"]) <= df
    assert abs(p.f_e - good.meta["truth"]["f_e"]) <= df
    # the text box: structure, every parameter with its unit, quality, warnings
    text = ax_t.texts[0].get_text()
    assert "structure: elastic" in text and "quality" in text and "warnings: none" in text
    for name in PARAMETER_NAMES:
        (row,) = [ln for ln in text.splitlines() if ln.split()[:1] == [name]]
        assert PARAMETER_UNITS[name] in row  # the value, its unit, then its 90 % interval
    assert "refine residual" in text and "map distance / training 99 % quantile" in text


def test_identify_page_draws_each_interval_as_a_bar_over_the_value(good, identified) -> None:
    """A calibrated result: the text gives each interval (as ``interval_text`` writes it), the
    calibrated class probabilities and P(answer right); the bars span interval / value, clipped."""
    _, result, analysis = identified
    p = result.parameters
    bounds = {n: (0.9 * getattr(p, n), 1.2 * getattr(p, n)) for n in PARAMETER_NAMES[:10]}
    bounds |= {"d": (0.0, 10.0 * p.d), "backlash": (0.0, 2.0 * p.backlash), "M_L0": (-0.01, 0.01), "M_FCM": (0.0, 0.01),
               "mu_FM": (0.0, 1e-4)}
    calibrated = dataclasses.replace(result, intervals=Intervals(**bounds),
                                     quality=dataclasses.replace(result.quality, answer_probability=0.87))
    fig = identify_figure(good, calibrated, analysis)
    ax_t, ax_c = fig.axes[4:]
    text = ax_t.texts[0].get_text()
    assert "parameters (reported), 90 % interval" in text and "no calibration" not in text
    assert "P(class), calibrated:" in text and "P(answer right) 0.87" in text
    rows = {ln.split()[0]: ln for ln in text.splitlines() if ln.split()[:1] and ln.split()[0] in PARAMETER_NAMES}
    assert rows["f_e"].endswith("Hz       -10/+20 %")  # sides 10 % and 20 %: not +-
    assert rows["backlash"].endswith(f"rad      [0 .. {2.0 * p.backlash:.4g}]")
    assert ax_c.get_xlabel() == "90 % interval / reported value"
    assert [t.get_text() for t in ax_c.get_yticklabels()] == list(PARAMETER_NAMES)[::-1]
    for name in ("J_sigma", "f_e", "mu_F"):
        np.testing.assert_allclose(_line(ax_c, f"{name} interval").get_xdata(), [0.9, 1.2], rtol=1e-12)
    np.testing.assert_allclose(_line(ax_c, "d interval").get_xdata(), [1 / 3, 3.0])  # 0 .. 10: clipped both sides
    np.testing.assert_allclose(_line(ax_c, "backlash interval").get_xdata(), [1 / 3, 2.0])
    assert _line(ax_c, "d interval").get_ydata()[0] == PARAMETER_NAMES[::-1].index("d")


def test_identify_page_without_calibration_says_so_and_draws_no_bars(good, identified) -> None:
    _, result, analysis = identified
    uncalibrated = dataclasses.replace(result, intervals=None,  # as from maps without a calibration
                                       quality=dataclasses.replace(result.quality, answer_probability=None))
    fig = identify_figure(good, uncalibrated, analysis)
    ax_t, ax_c = fig.axes[4:]
    text = ax_t.texts[0].get_text()
    assert text.count("90 % intervals: none (the maps carry no calibration)") == 1
    assert "P(class), the structure map's (uncalibrated):" in text and "P(answer right)" not in text
    assert not ax_c.axison and not ax_c.get_lines() and not ax_c.texts


def test_maps_page_marks_the_best_match_the_recall_returns(identified) -> None:
    ident, result, analysis = identified
    fig = maps_figure(analysis, ident.maps, result)
    panels = [ax for ax in fig.axes if ax.get_label() != "<colorbar>"]
    assert len(panels) == 4
    for ax, name in zip(panels, ("structure", "f_e", "V_J", "backlash")):
        trained = ident.maps[name]
        cols = [FEATURE_NAMES.index(f) for f in trained.spec.features]
        r = st.recall(trained.som, torch.as_tensor(analysis.features[cols])[None])  # independent recall, member 0
        unit = int(r.units[0, 0])
        (star,) = [ln for ln in ax.get_lines() if ln.get_label() == "record's best match"]
        np.testing.assert_allclose(np.r_[star.get_xdata(), star.get_ydata()], unit_xy(trained.som.grid)[unit])
        row, col = divmod(unit, trained.som.grid.cols)
        assert ax.get_title().startswith(f"{name} map") and f"best match row {row}, column {col}" in ax.get_title()
        cells = ax.collections[0]
        values = np.asarray(cells.get_array())
        assert cells.norm.vmin == pytest.approx(values.min()) and cells.norm.vmax == pytest.approx(values.max())
        assert cells.colorbar.ax.get_ylabel().endswith("]")
    assert "[Hz]" in panels[1].collections[0].colorbar.ax.get_ylabel()


def test_failure_page_says_why(good) -> None:
    fig = failure_figure("no recognisable test-signal sections", good, "runs/x.csv")
    assert fig.texts[0].get_text() == "runs/x.csv: not identified"  # the suptitle
    ax_w, ax_i = fig.axes
    assert "no recognisable test-signal sections" in ax_w.get_title(loc="left")
    assert ax_w.get_ylabel() == "motor speed w_M [rad/s]" and ax_i.get_xlabel() == "time t [s]"
    only_text = failure_figure("file not found", None, "gone.csv")
    assert not any(ax.get_visible() and ax.axison for ax in only_text.axes)


def test_page_names_are_distinct() -> None:
    assert page_names(["a/run.csv", "b/run", "c/run.json", "other.csv"]) == {
        "a/run.csv": "run", "b/run": "run_2", "c/run.json": "run_3", "other.csv": "other"}
    # x's maps page is x_maps.png: a record named x_maps gets another stem, in either order
    assert page_names(["x", "x_maps"]) == {"x": "x", "x_maps": "x_maps_2"}
    assert page_names(["x_maps", "x"]) == {"x_maps": "x_maps", "x": "x_2"}
    assert page_names(["RUN.CSV"]) == {"RUN.CSV": "RUN"}
