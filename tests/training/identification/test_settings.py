"""The identification's settings objects: frozen dataclasses whose every threshold is checked, with
an error that names the failing field."""

from __future__ import annotations

import dataclasses

import pytest

from training.identification._consistency import ConsistencyTolerances
from training.identification._drive import DriveEstimates
from training.identification._envelope import EnvelopeTolerances
from training.identification._limits import AnswerLimits
from training.identification._one_mass import OneMassTrust
from training.identification._plausibility import PlausibilityBounds
from training.identification._policy import IdentificationPolicy
from training.identification._sections import SectionRules

SETTINGS = (IdentificationPolicy, SectionRules, PlausibilityBounds, ConsistencyTolerances, DriveEstimates,
            EnvelopeTolerances, AnswerLimits, OneMassTrust)


@pytest.mark.parametrize("settings", SETTINGS, ids=lambda s: s.__name__)
def test_settings_are_frozen_dataclasses_with_defaults(settings):
    default = settings()
    assert dataclasses.is_dataclass(default) and settings.__dataclass_params__.frozen
    name = dataclasses.fields(default)[0].name
    with pytest.raises(dataclasses.FrozenInstanceError):
        setattr(default, name, 1.0)


@pytest.mark.parametrize("settings", SETTINGS, ids=lambda s: s.__name__)
def test_every_field_is_checked_and_named(settings):
    for field in dataclasses.fields(settings):
        bad = (0.0, 1.0) if isinstance(getattr(settings(), field.name), tuple) else -1.0
        with pytest.raises(ValueError, match=rf"^{settings.__name__}\.{field.name}: expected"):
            settings(**{field.name: bad})


def test_a_range_must_rise_and_a_share_stay_below_one():
    with pytest.raises(ValueError, match=r"^PlausibilityBounds\.speed_ratio: expected a pair"):
        PlausibilityBounds(speed_ratio=(3.0, 0.3))
    with pytest.raises(ValueError, match=r"^IdentificationPolicy\.stiff_sure: expected a finite number in \(0, 1\], received 1\.5"):
        IdentificationPolicy(stiff_sure=1.5)
    with pytest.raises(ValueError, match=r"^SectionRules\.noisy: expected a finite number > 0, received nan"):
        SectionRules(noisy=float("nan"))
