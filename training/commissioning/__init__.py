"""Self-commissioning (SPEC 8): adapt the test signal, identify, validate, propose a speed
controller, fine-tune it on the closed loop.

Rooms: ``_chain`` (the chain and its settings), ``_excitation`` (test signal E1-E7),
``_validation`` (re-simulation), ``_permission`` (refusal rules V1-V6), ``_law`` (the PI speed
controller), ``_loop`` (linear loop analysis), ``_rules`` (controller rules R1-R7, F1),
``_tuning`` (Nelder-Mead on the closed loop), ``_report`` (one plant's report, the summary over many).
"""

from ._chain import CommissioningConfig, commission, limit_checks
from ._excitation import ExcitationLimits, ExcitationResult, ExcitationRules, adapt_test_signal, measure_response
from ._law import NotchSpec, PISpeedController
from ._loop import LinearPlant, Mechanics, linear_plant, loop_figures, mechanics_from
from ._permission import (BLOCKING_WARNING_CODES, COMMISSIONING_WARNING_CODES, REFUSAL_RULES, CommissioningWarning,
                          Permission, may_propose_controller)
from ._report import CommissioningReport, summarize, summary_text
from ._rules import ControllerProposal, ControllerSpec, propose_cautious, propose_controller
from ._tuning import LinearRunner, SimRunner, TuningResult, TuningScenario, closed_loop_cost, make_scenario, tune_controller
from ._validation import ValidationResult, validate_model

__all__ = [
    "commission", "CommissioningConfig", "CommissioningReport", "limit_checks", "summarize", "summary_text",
    "ExcitationLimits", "ExcitationRules", "ExcitationResult", "adapt_test_signal", "measure_response",
    "validate_model", "ValidationResult", "may_propose_controller", "Permission", "REFUSAL_RULES",
    "CommissioningWarning", "COMMISSIONING_WARNING_CODES", "BLOCKING_WARNING_CODES",
    "ControllerSpec", "ControllerProposal", "propose_controller", "propose_cautious", "PISpeedController",
    "NotchSpec", "Mechanics", "mechanics_from", "LinearPlant", "linear_plant", "loop_figures",
    "tune_controller", "TuningResult", "TuningScenario", "make_scenario", "closed_loop_cost", "LinearRunner",
    "SimRunner",
]
