"""Self-commissioning (SPEC 8) through a SPEC 8.1 drive: adapt the test signal, identify, validate,
design a speed controller by optimization over an uncertainty set, fine-tune it on the identified
model, run the candidates on the drive inside the limits, measure the plant's frequency response
on the running loop and design again with it, deliver, report.

Rooms: ``_chain`` (the chain as named stages applied in order, :data:`STAGES`; its settings; the
identifier's protocol, :class:`RecordIdentifier`; the drive's is :class:`sim.Drive`),
``_excitation`` (test signal E0-E13, the rules applied in the order of ``EXCITATION_RULES``),
``_bands`` (what a test run cannot exclude), ``_validation`` (re-simulation), ``_permission``
(refusal rules V1-V6, warning codes), ``_law`` (the PI speed law of SPEC 8.1), ``_loop`` (linear
loop analysis, margins, load peak, model sets), ``_rules`` (controller rules R6, R7 with R7b and R7c,
R4, R5 in the order of ``CONTROLLER_RULES``, fallback F1), ``_design`` (the uncertainty set, design
by optimization), ``_narrow`` (R7d: the set narrowed to what the measured response does not
invalidate), ``_frf`` (the measured frequency response,
:class:`MeasuredResponse`: the multisine and the estimate), ``_measure`` (its experiment planned
on the identified model's loop), ``_tuning`` (scenario, cost, Nelder-Mead), ``_report`` (one
drive's report, the summary over many), ``_rest`` (the rest check before the first test: does the drive hold the axis? SPEC 1.1),
``_filedrive`` (a drive that exchanges experiments as files
with a person at a real drive), ``_guard`` (every drive call bounded in time, every record checked
at once and held against the user's limits: a passed limit ends the experiments,
:class:`LimitBreach`). docs/design.md lists the stages and rules in order.
"""

from ._chain import STAGES, CommissioningConfig, RecordIdentifier, commission, drive_config, limit_checks
from ._design import DesignSearch, MechanicsBounds, UncertaintySet, optimize_loop
from ._excitation import ExcitationResult, ExcitationRules, adapt_test_signal, check_limits, measure_response, trusted_inertia
from ._filedrive import ExperimentPending, FileDrive
from ._frf import FRF_SETTINGS, FRFSettings, MeasuredResponse
from ._guard import MEASURED_TORQUE_ALLOWANCE, LimitBreach, PassedLimit, close_drive
from ._law import HoldLaw, NotchSpec, PISpeedLaw
from ._loop import (LinearPlant, Margins, Mechanics, ModelSet, bode, linear_plant, load_peak_dB, loop_figures, margins, mechanics_from,
                    model_set, reference_to_load)
from ._permission import (BLOCKING_WARNING_CODES, COMMISSIONING_WARNING_CODES, REFUSAL_RULES, CommissioningWarning,
                          Permission, may_propose_controller)
from ._report import CommissioningReport, PlantRun, summarize, summary_text
from ._rest import REST_SETTINGS, RestCheck, RestSettings
from ._rules import ControllerProposal, ControllerSpec, propose_cautious, propose_controller, robust_models, uncertainty_set
from ._tuning import (LOOP_VERDICTS, TuningResult, TuningScenario, closed_loop_cost, load_estimate, loop_verdict, plan_scenario,
                      tune_controller)
from ._validation import ValidationResult, validate_model

__all__ = [
    "commission", "CommissioningConfig", "RecordIdentifier", "STAGES", "CommissioningReport", "PlantRun", "limit_checks", "drive_config", "summarize",
    "summary_text", "FileDrive", "ExperimentPending", "LimitBreach", "PassedLimit", "MEASURED_TORQUE_ALLOWANCE",
    "close_drive",
    "ExcitationRules", "ExcitationResult", "adapt_test_signal", "measure_response",
    "validate_model", "ValidationResult", "may_propose_controller", "Permission", "REFUSAL_RULES",
    "CommissioningWarning", "COMMISSIONING_WARNING_CODES", "BLOCKING_WARNING_CODES",
    "ControllerSpec", "ControllerProposal", "propose_controller", "propose_cautious", "robust_models", "PISpeedLaw",
    "NotchSpec", "Mechanics", "mechanics_from", "LinearPlant", "linear_plant", "loop_figures", "Margins", "margins",
    "ModelSet", "model_set", "bode", "tune_controller", "TuningResult", "TuningScenario", "plan_scenario",
    "closed_loop_cost", "load_estimate", "loop_verdict", "LOOP_VERDICTS", "UncertaintySet", "MechanicsBounds",
    "uncertainty_set", "DesignSearch",
    "optimize_loop", "load_peak_dB", "reference_to_load", "MeasuredResponse", "FRFSettings", "FRF_SETTINGS", "check_limits",
    "trusted_inertia", "HoldLaw", "RestCheck", "RestSettings", "REST_SETTINGS",
]
