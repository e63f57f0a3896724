"""Identification of one record: sections -> one-mass fit (STEP 2) -> features -> maps recall ->
model-based refinement -> one typed result (SPEC sections 4 and 9)."""

from ._analysis import FEATURE_NAMES, FEATURE_VERSION, REFERENCE_DRIVE, Analysis, analyze
from ._drive import DriveValues
from ._envelope import FILE_NAME as ENVELOPE_FILE, SPEC_ENVELOPE, Envelope, inside_envelope, trained_envelope
from ._batch import CHUNK, ReadRecord
from ._confidence import COVERAGE as CONFIDENCE_COVERAGE
from ._confidence import (ASINH, CONFIDENCE_VERSION, ZERO_CAPABLE, Calibration, ConfidenceInputs, LinearModel,
                          REAL_AXIS_CELL, half_width, maps_digests, model_features, rule_probabilities)
from ._confidence import FILE_NAME as CONFIDENCE_FILE
from ._features import eigenfrequency_features, extra_features, structure_and_peaks, structure_features
from ._identifier import Identifier
from ._limits import BACKLASH_VISIBLE_COUNTS, backlash_resolution, motor_lead
from ._maps import CORRECTIONS, MAP_SPECS, SUBSETS, TARGETS, from_correction, MapSpec, TrainedMap, load_map, recall_targets
from ._maps import CHECKPOINT_FILES, DISTANCE_QUANTILES, EIG_BINS, MapMetadata
from ._policy import IdentificationPolicy
from ._one_mass import FORMULATIONS, OneMassFit, fit_one_mass, speed_from_position
from ._oscillation import OscillationFit, fit_oscillation
from ._plausibility import check_record
from ._refine import RefineConfig, RefineProblem, Refined, refine, torque_reference
from ._result import (INTERVAL_NAMES, NOTE_CODES, PARAMETER_NAMES, PARAMETER_UNITS, WARNING_CODES, IdentificationFailure,
                      IdentificationResult, Intervals,
                      IdentWarning, Outcome, Parameters, Quality)
from ._sections import SectionSplit, detect_sections
from ._interval_text import MAY_BE_ZERO, interval_text

__all__ = [
    "Identifier", "IdentificationPolicy", "Calibration", "ConfidenceInputs", "CONFIDENCE_FILE", "CONFIDENCE_VERSION",
    "CONFIDENCE_COVERAGE", "LinearModel", "maps_digests", "half_width", "REAL_AXIS_CELL", "model_features", "rule_probabilities", "ZERO_CAPABLE", "ASINH", "ReadRecord", "CHUNK", "IdentificationResult", "IdentificationFailure", "Outcome", "Parameters", "Quality",
    "IdentWarning", "WARNING_CODES", "NOTE_CODES", "PARAMETER_NAMES", "PARAMETER_UNITS", "INTERVAL_NAMES", "Intervals",
    "interval_text", "MAY_BE_ZERO",
    "analyze", "Analysis", "FEATURE_NAMES", "FEATURE_VERSION", "REFERENCE_DRIVE", "DriveValues",
    "Envelope", "SPEC_ENVELOPE", "ENVELOPE_FILE", "inside_envelope", "trained_envelope",
    "detect_sections", "SectionSplit", "fit_one_mass", "FORMULATIONS", "OneMassFit", "speed_from_position",
    "eigenfrequency_features", "structure_features", "structure_and_peaks", "extra_features", "fit_oscillation",
    "OscillationFit",
    "check_record", "MAP_SPECS", "MapSpec", "TrainedMap", "TARGETS", "CORRECTIONS", "from_correction", "SUBSETS", "load_map", "recall_targets",
    "CHECKPOINT_FILES", "DISTANCE_QUANTILES", "EIG_BINS", "MapMetadata",
    "refine", "RefineConfig", "RefineProblem", "Refined", "torque_reference",
    "BACKLASH_VISIBLE_COUNTS", "backlash_resolution", "motor_lead",
]
