"""The commissioning page (training.figures.commission_figure), drawn headless from a real report."""

from __future__ import annotations

import numpy as np
import pytest

pytest.importorskip("matplotlib")

import sim  # noqa: E402
from training.commissioning import CommissioningConfig, commission  # noqa: E402
from training.figures import COMMISSION_PANELS, commission_figure, figure_image  # noqa: E402
from training.identification import IdentificationResult, Parameters, Quality  # noqa: E402

ELASTIC = dict(J_sigma=0.05, V_J=1.0, f_e=30.0, d=0.03, backlash=0.0, M_FC=0.2, mu_F=0.001)


class _Known:
    """An identifier that answers the plant's own parameters (the page is under test, not the maps)."""

    def identify(self, record):
        quality = Quality(structure_probabilities={}, map_distance_ratio={}, osc_quanta=5.0, oscillation_fit_r2=0.9,
                          one_mass_rel_residual=0.01, outside_training=False, section_flags=(), maps_estimate={},
                          outside_envelope={})
        return IdentificationResult("elastic", Parameters(**ELASTIC), quality, ())


@pytest.fixture(scope="module")
def report():
    config = CommissioningConfig(tune_evaluations=6, max_samples=1200)
    return commission(sim.SimulatedDrive(ELASTIC), sim.DriveLimits(w_max=20.0, travel=5.0), identifier=_Known(),
                      config=config)


def test_commission_page_content(report):
    fig = commission_figure(report)
    axes = fig.axes[:4]
    assert [ax.get_title().split(":")[0] for ax in axes] == list(COMMISSION_PANELS)
    for ax in axes:
        assert "[" in ax.get_ylabel() and "]" in ax.get_ylabel()  # every quantity with its unit
    assert axes[3].get_xlabel() == "w [rad/s]"
    # test runs: one line per run the drive made, and the speed limit drawn at +-w_max
    assert len(report.excitation.records) >= 1
    assert {round(abs(y), 6) for ln in axes[0].lines if ln.get_linestyle() == "--" for y in ln.get_ydata()} == {20.0}
    # closed loop: motor before and after tuning, and the model's load estimate for this elastic plant
    labels = [ln.get_label() for ln in axes[1].lines]
    assert any(lab.startswith("motor, before") for lab in labels) and any(lab.startswith("motor, after") for lab in labels)
    assert any(lab.startswith("load (model)") for lab in labels)
    # Bode: the worst model's |L| crosses 0 dB at the marked crossover, whose phase margin the title states
    m = report.delivered.margins
    worst = next(ln for ln in axes[2].lines if ln.get_label().startswith("worst"))
    w, mag = worst.get_xdata(), worst.get_ydata()
    assert abs(np.interp(np.log(m.w_c), np.log(w), mag)) < 0.5
    assert f"PM {m.phase_margin:.1f} deg" in axes[2].get_title()
    assert any(ln.get_label().startswith("w_c") and abs(ln.get_xdata()[0] - m.w_c) < 1e-9 for ln in axes[2].lines)
    assert figure_image(fig).shape[2] == 3  # renders headless


def test_commission_command_writes_the_page(tmp_path):
    from training.cli import main

    plant = tmp_path / "plant.json"
    plant.write_text('{"J_sigma": 0.05, "V_J": 1.0, "f_e": 30.0, "d": 0.03, "backlash": 0.0, "M_FC": 0.2, '
                     '"mu_F": 0.001, "name": "p1"}')
    args = ["commission", "--params", str(plant), "--w-limit", "20", "--travel-limit", "5", "--no-tune",
            "--plots", str(tmp_path / "plots"), "--frf", str(tmp_path / "frf"), "--quiet"]
    assert main(args) == 0
    assert (tmp_path / "plots" / "p1.png").stat().st_size > 10_000
    assert (tmp_path / "plots" / "p1_frf.png").stat().st_size > 10_000  # the measured response's Bode page
    header = (tmp_path / "frf" / "p1_frf.csv").read_text().splitlines()[0]
    assert header == "f_Hz,magnitude_dB,phase_deg,coherence,model_magnitude_dB,model_phase_deg"
    assert main(args) == 2  # the page exists: not replaced without --overwrite


def test_commission_without_matplotlib_refuses_plots_before_any_work(tmp_path, monkeypatch, capsys):
    from training.cli import main

    monkeypatch.setitem(__import__("sys").modules, "matplotlib", None)  # as if not installed
    monkeypatch.setitem(__import__("sys").modules, "matplotlib.figure", None)
    plant = tmp_path / "plant.json"
    plant.write_text('{"J_sigma": 0.05, "V_J": 1.0, "f_e": 30.0, "d": 0.03, "backlash": 0.0, "M_FC": 0.2, '
                     '"mu_F": 0.001}')
    args = ["commission", "--params", str(plant), "--w-limit", "20", "--travel-limit", "5", "--no-tune",
            "--plots", str(tmp_path / "plots"), "--json", str(tmp_path / "r.json")]
    assert main(args) == 2
    err = capsys.readouterr().err
    assert "the 'plot' extra: pip install" in err and len(err.strip().splitlines()) == 1
    assert not (tmp_path / "r.json").exists() and not (tmp_path / "plots").exists()


def test_frf_page_shows_measured_beside_model_and_coherence(report):
    from training.figures import FRF_PANELS, frf_figure

    m = report.measured
    assert m is not None  # the default chain measures the response on the chosen loop
    fig = frf_figure(report)
    axes = fig.axes[:3]
    assert [ax.get_title().split(":")[0] for ax in axes] == list(FRF_PANELS)
    labels = [ln.get_label() for ln in axes[0].lines]
    assert labels[:2] == ["measured", "identified model"]
    measured = axes[0].lines[0]
    np.testing.assert_allclose(measured.get_xdata(), m.w / (2 * np.pi))
    np.testing.assert_allclose(measured.get_ydata(), 20 * np.log10(np.abs(m.G)))
    np.testing.assert_allclose(axes[2].lines[0].get_ydata(), m.coherence)
    assert figure_image(fig).shape[2] == 3
