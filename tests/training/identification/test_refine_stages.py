"""The refinement's stages (training.identification._refine): registered with their settings, in one
pipeline, the settings frozen, every field documented on its line, and a bad value named by its field."""

import ast
import dataclasses
import inspect
import math
import textwrap

import pytest

from training.identification._refine import (PIPELINE, STAGES, AngleFitSettings, AngleSettings, BatchSettings,
                                             ChooseSettings, ClimbSettings, ExploreSettings, FreeSettings,
                                             PolishSettings, RattleSettings, RefineConfig, RescueSettings, RestartSettings,
                                             RetrySettings, SearchSettings, SplitSettings, Stage)

SETTINGS = (ExploreSettings, RescueSettings, ClimbSettings, RattleSettings, ChooseSettings, SplitSettings,
            FreeSettings, PolishSettings, RetrySettings, RestartSettings, AngleFitSettings, AngleSettings,
            SearchSettings, BatchSettings)


def test_every_stage_of_the_pipeline_is_registered_once_with_its_settings_in_the_config():
    assert sorted(PIPELINE) == sorted(STAGES) and len(set(PIPELINE)) == len(PIPELINE)
    config = RefineConfig()
    for name, stage in STAGES.items():
        assert isinstance(stage, Stage) and stage.name == name
        assert stage.runs_when and "\n" not in stage.runs_when and callable(stage.run)
        assert type(getattr(config, name)) is stage.settings  # the config's field of the stage's name


@pytest.mark.parametrize("settings", SETTINGS, ids=lambda s: s.__name__)
def test_settings_are_frozen_dataclasses_whose_fields_say_what_they_are(settings):
    assert dataclasses.is_dataclass(settings) and settings.__dataclass_params__.frozen
    instance = settings()
    with pytest.raises(dataclasses.FrozenInstanceError):
        setattr(instance, dataclasses.fields(settings)[0].name, 0)
    source = textwrap.dedent(inspect.getsource(settings)).splitlines()
    fields = [node for node in ast.parse("\n".join(source)).body[0].body if isinstance(node, ast.AnnAssign)]
    for node in fields:  # a comment on the field's line or on the line above it
        line = node.lineno - 1
        assert "#" in source[line] or source[line - 1].strip().startswith("#"), source[line]


@pytest.mark.parametrize("settings, field, value", [
    (SearchSettings, "elites", 1), (SearchSettings, "spread", (0.1, 0.1)), (SearchSettings, "memory", -0.1),
    (ExploreSettings, "window_periods", 0.0), (ExploreSettings, "rounds", -1), (ExploreSettings, "grid_f_e", 0),
    (ExploreSettings, "window_max", math.nan), (RescueSettings, "rounds", -1), (ClimbSettings, "grid_f_e", 0),
    (RattleSettings, "finalists", -1), (ChooseSettings, "finalists", 0), (SplitSettings, "steps", 0),
    (SplitSettings, "evidence", -1.0), (FreeSettings, "friction_start", (0.1,)),
    (FreeSettings, "f_e_per_octave", 0), (PolishSettings, "steps", (1e-3,)), (PolishSettings, "samples_per_period", 0),
    (RetrySettings, "damping", 0.0), (RetrySettings, "damping", 1.5), (AngleSettings, "samples", 0),
    (RestartSettings, "above", -1.0), (RestartSettings, "shares", ()), (RestartSettings, "shares", ((0.5,),)),
    (RestartSettings, "shares", ((1.5, 0.0),)), (AngleSettings, "grid_top", 0.0), (BatchSettings, "length_ratio", 0.0),
    (BatchSettings, "led_lanes", 0), (AngleFitSettings, "grid_s_N", (0.0,)), (AngleFitSettings, "rounds", -1),
    (AngleFitSettings, "shares", ((0.5, 1.5),)), (AngleFitSettings, "win", -0.1), (AngleFitSettings, "stream", 0),
])
def test_a_bad_setting_is_refused_with_its_name(settings, field, value):
    with pytest.raises(ValueError, match=rf"^{settings.__name__}\.{field}: expected"):
        settings(**{field: value})


def test_the_config_takes_only_the_stages_own_settings():
    assert RefineConfig() == RefineConfig(seed=0)
    with pytest.raises(TypeError, match=r"RefineConfig\.rescue: expected RescueSettings"):
        RefineConfig(rescue=ClimbSettings())
    with pytest.raises(TypeError, match=r"RefineConfig\.seed: expected an integer, received True"):
        RefineConfig(seed=True)
