"""Figures of merit for identification results (SPEC section 7 and its targets).

All functions take numpy arrays of one length ``N`` (one entry per system) and return plain
numbers or arrays, so that evaluation, tests and reports share one definition.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

from sim import CLASS_THRESHOLDS

#: The parameters whose relative errors define the recognition rate ``E_x`` (paper section 4).
RECOGNITION_PARAMS: tuple[str, ...] = ("f_e", "V_J", "J_sigma")


def finite_or_none(x: Any) -> float | None:
    """``x`` as a float where it is finite, else ``None`` (a JSON-able figure; missing = ``None``)."""
    if x is None:
        return None
    x = float(x)
    return x if math.isfinite(x) else None


def relative_error(estimate: np.ndarray, truth: np.ndarray) -> np.ndarray:
    """``|estimate - truth| / |truth|`` (``N``); NaN where the estimate is missing, inf or NaN where
    the truth is 0 (a system without the quantity: the figures leave it out)."""
    estimate = np.asarray(estimate, dtype=float)
    truth = np.asarray(truth, dtype=float)
    if estimate.shape != truth.shape:
        raise ValueError(f"relative_error: shapes differ, estimate {estimate.shape} vs truth {truth.shape}")
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.abs(estimate - truth) / np.abs(truth)


def recognized(errors: Mapping[str, np.ndarray], x_percent: float,
               params: Sequence[str] = RECOGNITION_PARAMS) -> np.ndarray:
    """Boolean ``N``: all ``params`` within ``x_percent`` relative error (NaN counts as a miss)."""
    missing = [p for p in params if p not in errors]
    if missing:
        raise ValueError(f"recognized: relative errors missing for {missing}; received {sorted(errors)}")
    ok = np.ones(np.shape(errors[params[0]]), dtype=bool)
    for p in params:
        ok &= np.nan_to_num(np.asarray(errors[p], dtype=float), nan=np.inf) <= x_percent / 100.0
    return ok


def recognition_rate(errors: Mapping[str, np.ndarray], x_percent: float,
                     params: Sequence[str] = RECOGNITION_PARAMS) -> float:
    """``E_x`` in percent: share of systems with all ``params`` within ``x_percent``; NaN if empty."""
    ok = recognized(errors, x_percent, params)
    return float(100.0 * ok.mean()) if ok.size else float("nan")


def confusion_matrix(truth: np.ndarray, predicted: np.ndarray, n_classes: int) -> np.ndarray:
    """``n_classes x n_classes`` counts, rows = true class, columns = predicted class."""
    truth = np.asarray(truth, dtype=int)
    predicted = np.asarray(predicted, dtype=int)
    if truth.shape != predicted.shape:
        raise ValueError(f"confusion_matrix: shapes differ, truth {truth.shape} vs predicted {predicted.shape}")
    for name, idx in (("truth", truth), ("predicted", predicted)):
        if idx.size and (idx.min() < 0 or idx.max() >= n_classes):
            raise ValueError(f"confusion_matrix: {name} holds labels outside 0..{n_classes - 1}")
    out = np.zeros((n_classes, n_classes), dtype=int)
    np.add.at(out, (truth, predicted), 1)
    return out


#: The classes whose elastic values an answer is scored on (``E_x``).
ELASTIC_CLASSES = ("elastic", "elastic_backlash")


def answer_wrong(true_class: np.ndarray, answer_class: np.ndarray, errors: Mapping[str, np.ndarray]) -> np.ndarray:
    """Which answers are wrong (SPEC 4.1): the class wrong, or an elastic answer of an elastic
    system outside ``E_30`` (``f_e``, ``V_J``, ``J_sigma`` within 30 %), or ``J_sigma`` off by 30 %.
    ``errors``: the relative errors of ``f_e``, ``V_J``, ``J_sigma`` (NaN: not identified)."""
    elastic = np.isin(true_class, ELASTIC_CLASSES) & np.isin(answer_class, ELASTIC_CLASSES)
    J_sigma_off = np.nan_to_num(errors["J_sigma"], nan=np.inf) > 0.3
    return (true_class != answer_class) | (elastic & ~recognized(errors, 30)) | J_sigma_off


def threshold_margin(quantities: Mapping[str, np.ndarray]) -> np.ndarray:
    """Smallest relative distance ``|q - thr| / thr`` of each system to any class threshold (``N``).

    ``quantities`` maps each key of :data:`CLASS_THRESHOLDS` (``w_e_T_Ei``, ``s_N``, ``r_osc``)
    to its true values. Issue 4 scores the structure accuracy over systems with margin >= 0.2.
    """
    missing = [k for k in CLASS_THRESHOLDS if k not in quantities]
    if missing:
        raise ValueError(f"threshold_margin: missing {missing}; received {sorted(quantities)}")
    margins = [np.abs(np.asarray(quantities[k], dtype=float) - thr) / thr
               for k, thrs in CLASS_THRESHOLDS.items() for thr in thrs]
    return np.min(np.stack(margins), axis=0)
