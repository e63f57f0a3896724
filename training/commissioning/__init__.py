"""Self-commissioning (SPEC 8): adapt the test signal, identify, validate, propose a speed
controller, fine-tune it on the closed loop."""

from ._chain import CommissioningReport, commission
from ._controller import (ControllerProposal, ControllerSpec, LinearPlant, Mechanics, NotchSpec, PISpeedController,
                          linear_plant, loop_figures, mechanics_from, propose_cautious, propose_controller)
from ._excitation import ExcitationLimits, ExcitationResult, ExcitationRules, adapt_test_signal, measure_response
from ._tuning import LinearRunner, SimRunner, TuningResult, TuningScenario, closed_loop_cost, make_scenario, tune_controller
from ._validation import Permission, ValidationResult, may_propose_controller, validate_model

__all__ = [
    "commission", "CommissioningReport",
    "ExcitationLimits", "ExcitationRules", "ExcitationResult", "adapt_test_signal", "measure_response",
    "validate_model", "ValidationResult", "may_propose_controller", "Permission",
    "ControllerSpec", "ControllerProposal", "propose_controller", "propose_cautious", "PISpeedController",
    "NotchSpec", "Mechanics", "mechanics_from", "LinearPlant", "linear_plant", "loop_figures",
    "tune_controller", "TuningResult", "TuningScenario", "make_scenario", "closed_loop_cost", "LinearRunner",
    "SimRunner",
]
