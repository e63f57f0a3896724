"""The paper's study (SPEC 7): evaluation sets, the SOM and IV4 methods side by side, metrics,
report, the cache of per-system results, and the confidence study of the drive rows (SPEC 4.1)."""

from ._answers import AnswerScores, score_rows
from ._confidence import (ProbabilityCalibration, ConfidenceReport, Coverage, CoverageCell, CoverageTable, Reliability,
                          WarnedShares, answer_calibration, confidence_files, confidence_markdown, confidence_report,
                          coverage_table, expected_calibration_error, median_half_width, reliability,
                          reliability_figure, structure_calibration, warned_shares, write_confidence)
from ._drives import (DRIVES, REAL_AXIS_EFFECTS, REAL_AXIS_FIGURES, DriveCase, drive_figures, drive_rows, drives_markdown,
                      envelope_cases, envelope_rows, real_axis_effect, real_axis_figures)
from ._cache import load_cached, method_config, save_cached, source_digest
from ._iv4 import (ARXResult, IV4Result, IV4TwoMass, TwoMassEstimate, arx, identify_iv4, iv4, mean_torque,
                   two_mass_from_discrete)
from ._metrics import (CLASS_THRESHOLDS, ELASTIC_CLASSES, answer_wrong, confusion_matrix, recognition_rate, recognized, relative_error,
                       threshold_margin)
from ._report import render_markdown, report_files, write_report
from ._sets import GRID_BACKLASH_DEG, GRID_F_E, METHODS, EvalSet, grid_set, population_set
from ._study import iv4_result, run_set, run_study, som_result
from ._summary import summarize

__all__ = [
    "DRIVES", "DriveCase", "drive_rows", "drive_figures", "drives_markdown", "envelope_rows", "envelope_cases",
    "REAL_AXIS_EFFECTS", "real_axis_effect", "REAL_AXIS_FIGURES", "real_axis_figures",
    "answer_wrong", "ELASTIC_CLASSES",
    "score_rows", "AnswerScores", "confidence_report", "coverage_table", "median_half_width",
    "expected_calibration_error", "reliability", "structure_calibration", "answer_calibration", "warned_shares",
    "confidence_markdown", "reliability_figure", "write_confidence", "confidence_files", "ConfidenceReport",
    "CoverageTable", "CoverageCell", "Coverage", "Reliability", "ProbabilityCalibration", "WarnedShares",
    "EvalSet", "grid_set", "population_set", "GRID_F_E", "GRID_BACKLASH_DEG", "METHODS",
    "run_set", "run_study", "som_result", "iv4_result", "summarize", "render_markdown", "report_files", "write_report",
    "method_config", "load_cached", "save_cached", "source_digest",
    "relative_error", "recognized", "recognition_rate", "confusion_matrix", "threshold_margin", "CLASS_THRESHOLDS",
    "iv4", "arx", "identify_iv4", "two_mass_from_discrete", "mean_torque", "ARXResult", "IV4Result",
    "IV4TwoMass", "TwoMassEstimate",
]
