"""Builders shared by the commissioning tests: identification results as the identifier gives
them (typed), and validation results."""

from __future__ import annotations

import numpy as np
import pytest

from training.commissioning import ValidationResult
from training.identification import IdentificationResult, Intervals, IdentWarning, Parameters, Quality


def _quality_extras() -> dict:
    """Fields of ``Quality`` that some versions of the identification room have (none outside the envelope)."""
    import dataclasses
    names = {f.name for f in dataclasses.fields(Quality)}
    return {"outside_envelope": {}} if "outside_envelope" in names else {}


def identification_result(structure: str, params: dict, *, outside_training: bool = False,
                          ratios: dict | None = None, warnings: tuple = (), notes: tuple = (),
                          intervals: Intervals | None = None, answer_probability: float | None = None) -> IdentificationResult:
    """A typed identification result; ``warnings`` and ``notes`` as ``(code, text)`` pairs; ``intervals``
    the calibrated 90 % intervals (None: uncalibrated maps)."""
    quality = Quality(structure_probabilities={}, map_distance_ratio=dict(ratios or {}), osc_quanta=5.0,
                      oscillation_fit_r2=0.9, one_mass_rel_residual=0.01, outside_training=outside_training,
                      section_flags=(), maps_estimate={}, answer_probability=answer_probability, **_quality_extras())
    return IdentificationResult(structure, Parameters(**params), quality, tuple(IdentWarning(c, t) for c, t in warnings),
                                intervals=intervals, notes=tuple(IdentWarning(c, t) for c, t in notes))


def validation_result(nrmse: float = 0.03, passed: bool = True, reason: str = "model reproduces the record") -> ValidationResult:
    return ValidationResult(passed=passed, nrmse=nrmse, osc_nrmse=None, threshold=0.1, osc_threshold=0.5,
                            simulated=np.zeros(3), measured=np.zeros(3), mode="replay", reason=reason)


class StubIdentifier:
    """Answers fixed parameters (scaled by ``factors``) for any record; keeps the records it saw
    (to check that the chain does not hand it the truth)."""

    def __init__(self, structure: str, params: dict, *, outside_training: bool = False, ratios: dict | None = None,
                 warnings: tuple = (), **factors: float) -> None:
        params = {k: (v * factors.get(k, 1.0) if v is not None else None) for k, v in params.items()}
        self.result = identification_result(structure, params, outside_training=outside_training, ratios=ratios,
                                            warnings=warnings)
        self.records: list = []

    def identify(self, record):
        self.records.append(record)
        return self.result


@pytest.fixture
def stub():
    return StubIdentifier


@pytest.fixture
def make_result():
    return identification_result


@pytest.fixture
def make_validation():
    return validation_result
