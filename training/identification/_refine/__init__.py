"""The model-based refinement of the maps' answer on the record itself (:func:`refine`: explore,
choose, free one-mass stage, polish; :mod:`._stages`) and the backlash found in the motor's angle
(:func:`find_hidden_gap`). The settings and their measured reasons: :class:`RefineConfig`."""

from ._angle import HiddenGap, find_hidden_gap
from ._config import RefineConfig
from ._problem import RefineProblem, Refined, torque_reference
from ._stages import refine

__all__ = ["HiddenGap", "RefineConfig", "RefineProblem", "Refined", "find_hidden_gap", "refine", "torque_reference"]
