"""The refinement's settings (:class:`RefineConfig`): one frozen settings object per stage of
:data:`._pipeline.PIPELINE`, each holding every threshold its stage uses with its measured reason."""

from __future__ import annotations

from dataclasses import dataclass, fields

from training._settings import INTEGER, InstanceOf, check_settings

from training.identification._refine._angle import AngleSettings
from training.identification._refine._angle_fit import AngleFitSettings
from training.identification._refine._choose import ChooseSettings
from training.identification._refine._climb import ClimbSettings
from training.identification._refine._explore import ExploreSettings
from training.identification._refine._free import FreeSettings
from training.identification._refine._polish import PolishSettings
from training.identification._refine._rattle import RattleSettings
from training.identification._refine._replay import BatchSettings
from training.identification._refine._rescue import RescueSettings
from training.identification._refine._restart import RestartSettings
from training.identification._refine._retry import RetrySettings
from training.identification._refine._search import SearchSettings
from training.identification._refine._split import SplitSettings
from training.identification._refine._space import COORDINATES, FREE_COORDINATES, HIGH, LOW, NO_GAP

__all__ = ["COORDINATES", "FREE_COORDINATES", "HIGH", "LOW", "NO_GAP", "RefineConfig"]


@dataclass(frozen=True)
class RefineConfig:
    """The refinement's settings: each stage's own (the field named as the stage, see
    :data:`._pipeline.STAGES`), the cross-entropy search they share (``search``), how many models
    a replay call takes (``batch``: the wall time, never an answer) and the ``seed`` every search
    starts from. ``RefineConfig()`` is the measured default."""

    explore: ExploreSettings = ExploreSettings()
    rescue: RescueSettings = RescueSettings()
    climb: ClimbSettings = ClimbSettings()
    rattle: RattleSettings = RattleSettings()
    choose: ChooseSettings = ChooseSettings()
    split: SplitSettings = SplitSettings()
    free: FreeSettings = FreeSettings()
    polish: PolishSettings = PolishSettings()
    retry: RetrySettings = RetrySettings()
    restart: RestartSettings = RestartSettings()
    angle_fit: AngleFitSettings = AngleFitSettings()
    angle: AngleSettings = AngleSettings()
    search: SearchSettings = SearchSettings()
    batch: BatchSettings = BatchSettings()
    seed: int = 0  # every search starts from this seed

    def __post_init__(self) -> None:
        stages = {field.name: InstanceOf(type(field.default)) for field in fields(self) if field.name != "seed"}
        check_settings(self, {**stages, "seed": INTEGER}, error=TypeError)
