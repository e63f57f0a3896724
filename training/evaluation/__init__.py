"""The paper's study (SPEC 7): evaluation sets, the SOM and IV4 methods side by side, metrics, report."""

from ._iv4 import ARXResult, IV4Result, arx, identify_iv4, iv4, mean_torque, two_mass_from_discrete
from ._metrics import confusion_matrix, recognition_rate, recognized, relative_error, threshold_margin
from ._report import render_markdown, write_report
from ._study import EvalSet, grid_set, population_set, run_set, summarize

__all__ = [
    "EvalSet", "grid_set", "population_set", "run_set", "summarize", "render_markdown", "write_report",
    "relative_error", "recognized", "recognition_rate", "confusion_matrix", "threshold_margin",
    "iv4", "arx", "identify_iv4", "two_mass_from_discrete", "mean_torque", "ARXResult", "IV4Result",
]
