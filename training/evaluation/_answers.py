"""Which answers of the drive study are right, in one place (SPEC 4.1's "wrong", the drive figures'
silent-wrong rate, the confidence report's warned shares and ``answer_probability`` calibration).

An answer is **wrong** where its class is wrong, or where an elastic system's elastic answer lies
outside ``E_30`` (``f_e``, ``V_J``, ``J_sigma`` within 30 %), or where ``J_sigma`` is off by 30 %.
A failed analysis (``som["error"]``) has no class: it counts as wrong, and as no answer.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from training.evaluation._metrics import ELASTIC_CLASSES as ELASTIC
from training.evaluation._metrics import RECOGNITION_PARAMS, answer_wrong, recognized, relative_error


def row_values(rows: Sequence[dict[str, Any]], part: str, key: str) -> np.ndarray:
    """``rows[i][part][key]`` as float ``N`` (NaN where missing or ``None``)."""
    return np.array([np.nan if r[part].get(key) is None else float(r[part][key]) for r in rows])


@dataclass(frozen=True)
class AnswerScores:
    """Per system (all arrays ``N``): the true and reported class, the relative errors of
    :data:`RECOGNITION_PARAMS` (NaN where missing), and the verdicts."""

    true_class: np.ndarray  # str
    reported_class: np.ndarray  # str; "None" where the analysis failed
    errors: dict[str, np.ndarray]  # parameter -> |estimate - truth| / |truth|
    class_right: np.ndarray  # bool
    elastic: np.ndarray  # bool: the true class is elastic
    failed: np.ndarray  # bool: the analysis gave no answer
    warned: np.ndarray  # bool: the answer carries at least one warning
    wrong: np.ndarray  # bool: SPEC 4.1's wrong answer (module docstring)

    def recognized(self, x_percent: float) -> np.ndarray:
        """``E_x``: ``f_e``, ``V_J`` and ``J_sigma`` all within ``x_percent`` (bool ``N``)."""
        return recognized(self.errors, x_percent)


def score_rows(rows: Sequence[dict[str, Any]]) -> AnswerScores:
    """The verdicts of the drive study's ``rows`` (``{"truth": ..., "som": ...}``, see
    :func:`training.evaluation.drive_rows`)."""
    true_class = np.array([r["truth"]["structure"] for r in rows], dtype=str)
    reported = np.array([str(r["som"]["structure"]) for r in rows], dtype=str)
    errors = {k: relative_error(row_values(rows, "som", k), row_values(rows, "truth", k)) for k in RECOGNITION_PARAMS}
    class_right = true_class == reported
    elastic = np.isin(true_class, ELASTIC)
    wrong = answer_wrong(true_class, reported, errors)
    failed = np.array([r["som"]["error"] is not None for r in rows], dtype=bool)
    warned = np.array([r["som"]["n_warnings"] > 0 for r in rows], dtype=bool)
    return AnswerScores(true_class, reported, errors, class_right, elastic, failed, warned, wrong)
