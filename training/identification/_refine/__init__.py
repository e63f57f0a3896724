"""The model-based refinement of the maps' answer on the record itself (:func:`refine`: the stages
of :data:`PIPELINE`, registered in :data:`STAGES`) and the backlash found in the motor's angle
(:func:`find_hidden_gap`). The settings, stage by stage, and their measured reasons: :class:`RefineConfig`."""

from ._angle import AngleSettings, HiddenGap
from ._angle_fit import AngleFitSettings
from ._choose import ChooseSettings
from ._climb import ClimbSettings
from ._config import RefineConfig
from ._explore import ExploreSettings
from ._free import FreeSettings
from ._pipeline import PIPELINE, STAGES, find_hidden_gap, refine
from ._polish import PolishSettings
from ._problem import RefineProblem, Refined, torque_reference
from ._rattle import RattleSettings
from ._replay import BatchSettings
from ._rescue import RescueSettings
from ._restart import RestartSettings
from ._retry import RetrySettings
from ._search import SearchSettings
from ._split import SplitSettings
from ._stage import Stage

__all__ = ["AngleFitSettings", "AngleSettings", "BatchSettings", "ChooseSettings", "ClimbSettings",
           "ExploreSettings", "FreeSettings", "HiddenGap", "PIPELINE", "PolishSettings", "RattleSettings",
           "RefineConfig", "RefineProblem", "Refined", "RescueSettings", "RestartSettings", "RetrySettings",
           "STAGES", "SearchSettings", "SplitSettings", "Stage", "find_hidden_gap", "refine", "torque_reference"]
