"""The chain's shape: its stages in the documented order, its settings frozen dataclasses whose
errors name the failing field, the drive and the identifier typed by protocols."""

from __future__ import annotations

import dataclasses
import inspect

import pytest

sim = pytest.importorskip("sim")

from training.commissioning import STAGES, CommissioningConfig, RecordIdentifier, commission, mechanics_from  # noqa: E402
from training.commissioning import _chain  # noqa: E402
from training.commissioning._frf import FRFSettings  # noqa: E402
from training.commissioning._loop import LoopAnalysis  # noqa: E402
from training.commissioning._tuning import ScenarioSizing, SearchSettings  # noqa: E402

ORDER = ("hold", "excite", "identify", "validate", "guard", "permit", "design", "try", "measure", "redesign", "fallback", "deliver")


def test_the_stages_run_in_the_documented_order():
    assert tuple(name for name, _ in STAGES) == ORDER
    assert all(callable(stage) for _, stage in STAGES)
    listed = [line.split()[0] for line in _chain.__doc__.splitlines() if line.startswith("    ") and line.split()]
    assert tuple(listed[:len(ORDER)]) == ORDER


def test_the_chain_is_typed_by_protocols():
    hints = inspect.signature(commission).parameters
    assert hints["drive"].annotation == "sim.Drive"
    assert hints["identifier"].annotation == "RecordIdentifier"
    assert RecordIdentifier.identify


@pytest.mark.parametrize("settings", [CommissioningConfig, ScenarioSizing, SearchSettings, LoopAnalysis, FRFSettings])
def test_settings_are_frozen_dataclasses(settings):
    assert dataclasses.is_dataclass(settings) and settings.__dataclass_params__.frozen
    with pytest.raises(dataclasses.FrozenInstanceError):
        setattr(settings(), dataclasses.fields(settings)[0].name, None)


@pytest.mark.parametrize("settings, name, value", [
    (CommissioningConfig, "tune_evaluations", 0),
    (CommissioningConfig, "max_samples", 599),
    (CommissioningConfig, "max_validation_error", 0.0),
    (CommissioningConfig, "max_map_distance_ratio", -1.0),
    (CommissioningConfig, "limit_use", 1.5),
    (CommissioningConfig, "fallback_limit_use", 0.0),
    (CommissioningConfig, "uncertain_spread", 1.0),
    (CommissioningConfig, "uncertain_damping", 0.0),
    (CommissioningConfig, "fallback_resonance_factor", 0.5),
    (CommissioningConfig, "min_scenario_quanta", -1.0),
    (CommissioningConfig, "drive_timeout", float("inf")),
    (CommissioningConfig, "validation_mode", "guess"),
    (CommissioningConfig, "measure_response", 1),
    (CommissioningConfig, "frf", None),
    (FRFSettings, "periods", 2),
    (FRFSettings, "limit_share", 0.0),
    (FRFSettings, "min_coherence", 1.5),
    (ScenarioSizing, "min_segment", 0),
    (ScenarioSizing, "kick_share", 0.0),
    (SearchSettings, "max_load_peak_dB", 0.0),
    (SearchSettings, "fatol", -1.0),
    (LoopAnalysis, "grid_points", 1),
    (LoopAnalysis, "settle_band", 0.0),
])
def test_a_bad_setting_is_named(settings, name, value):
    with pytest.raises(ValueError, match=rf"^{settings.__name__}\.{name}: expected"):
        settings(**{name: value})


@pytest.mark.parametrize("params, name", [
    ({"J_sigma": 0.0}, "J_sigma"), ({"J_sigma": 1.0, "V_J": -1.0}, "V_J"), ({"J_sigma": 1.0, "f_e": 0.0}, "f_e"),
    ({"J_sigma": 1.0, "d": 1.0}, "d"), ({"J_sigma": 1.0, "backlash": -1e-3}, "backlash"), ({"J_sigma": 1.0, "mu_F": -1.0}, "mu_F"),
])
def test_mechanics_out_of_range_are_named(params, name):
    with pytest.raises(ValueError, match=f"^{name}: expected"):
        mechanics_from(params)


class _Answer:
    """An identification answer stub: ``ok`` and a calibrated ``quality.answer_probability``."""

    def __init__(self, p):
        self.ok, self.quality = True, type("Quality", (), {"answer_probability": p})()


class _ByRecord:
    """An identifier whose answer's probability is the record's own (a dict ``{"p": ...}``)."""

    def identify(self, record):
        return _Answer(record["p"])


def _identified(p_probe, p_before):
    """``_identify_record`` on an excitation whose E12/E13 probe (P ``p_probe``) replaced a run (P ``p_before``)."""
    from training.commissioning._excitation import ExcitationResult

    probe, before = {"p": p_probe}, {"p": p_before}
    excitation = ExcitationResult(record=probe, informative=True, reason="informative (E13 probe)", code="informative",
                                  replaced=before)
    state = type("State", (), {"excitation": excitation, "identification": None})()
    run = type("Run", (), {"excitation": excitation, "state": state, "identifier": _ByRecord(), "name": "p",
                           "say": lambda self, msg: None, "warn": lambda self, code, text: None})()
    _chain._identify_record(run)
    return state


def test_the_record_an_envelope_probe_replaced_is_identified_too_and_the_answer_more_likely_right_kept():
    kept = _identified(0.3, 0.9)  # the probe's answer is less likely right: the run before it is identified
    assert kept.identification.quality.answer_probability == 0.9 and kept.excitation.record == {"p": 0.9}
    assert "30.0%" in kept.excitation.reason and "90.0%" in kept.excitation.reason
    probe = _identified(0.9, 0.3)
    assert probe.identification.quality.answer_probability == 0.9 and probe.excitation.record == {"p": 0.9}
    assert probe.excitation.reason == "informative (E13 probe)"
    uncalibrated = _identified(None, 0.9)  # no calibrated number: the probe's record stands
    assert uncalibrated.excitation.record == {"p": None}
