"""The confidence calibration (SPEC 4.1; :mod:`training.identification._confidence`): held-out
simulated records of the drive matrix, drives drawn over the envelope and the reference drive's
default population, identified without a calibration; then the logistic model of P(a real axis),
per parameter a log-scale model and split-conformal quantiles in two cells (the answers more
likely from a real axis than not, the others), and the logistic models of P(class right) and
P(answer right).

The calibration's seeds (:data:`CALIBRATION_SEEDS`) are used nowhere else: not by the maps'
training (``twomass generate``, seed 0 and up) nor by ``twomass evaluate`` (seeds 5, 6 and the
drive studies' ``--seed``).
"""

from __future__ import annotations

import json
import math
import os
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from sim import REAL_AXIS_NAMES, DriveConfig, TestSignalConfig, TwoMassParams, iter_records, sample_population
from training.evaluation import DRIVES, answer_wrong, envelope_cases, relative_error, threshold_margin
from training.identification import CONFIDENCE_COVERAGE as COVERAGE
from training.identification import (CONFIDENCE_VERSION, INTERVAL_NAMES, NOTE_CODES, REAL_AXIS_CELL, Calibration,
                                     ConfidenceInputs, Identifier, LinearModel, ASINH, half_width, model_features,
                                     rule_probabilities)

#: The seeds of the calibration's three sets: the drive matrix, the envelope drives, the reference
#: drive's default population.
CALIBRATION_SEEDS = {"matrix": 7101, "envelope": 7102, "reference": 7103, "real_axis": 7104}
#: The matrix drives whose real-axis population (SPEC 1.1) the calibration includes, and how many
#: of them each: the reference drive, the coarsest and the smallest drive.
REAL_AXIS_DRIVES = {"reference": 2, "low_res_1ms": 1, "servo_200w": 1}
#: The group name's prefix of the calibration's real-axis records, on which alone the real-axis parts
#: intervals are calibrated (:data:`sim.REAL_AXIS_NAMES`: elsewhere they are 0, answered 0, and would
#: make the intervals of real axes 0 wide: on the first calibration ``M_L0`` covered 67 %, ``M_FCM`` 63 %).
REAL_AXIS_GROUP = "real_axis"
#: The log-odds of a real axis where the calibration has no real-axis records (P ~ 1e-13).
NO_REAL_AXIS_LOG_ODDS = 30.0
#: The fewest calibration answers of a class for a class's own conformal quantile (else the pooled one).
MIN_CLASS_SAMPLES = 80
#: The share of wrong answers the ``likely_wrong`` threshold may leave unwarned on the calibration
#: (out-of-fold): SPEC 4.1's 1 %. Half of it (0.005) let two wrong answers of 336 set the
#: threshold at P = 0.998 and warn 68 % of the right answers (0.01: P = 0.990, 39 %).
SILENT_WRONG_SHARE = 0.01
#: The ridge penalties of the scale regressions and of the logistic models (standardized features).
RIDGE_SCALE, RIDGE_LOGISTIC = 1.0, 10.0
#: The floors added to a coordinate's error before its log (log coordinates: 0.01 %; asinh: 0.05).
_ERROR_FLOOR = {"log": 1e-4, "asinh": 0.05}


@dataclass(frozen=True)
class CalibrationSample:
    """One identified calibration record: what the calibration reads of its answer, the truth of
    every parameter of :data:`INTERVAL_NAMES`, the true and the answered class, the relative errors
    of ``f_e``, ``V_J``, ``J_sigma`` (NaN: not identified), the codes of the warnings that stay
    warnings, its set (``matrix:reference``, ``envelope_3``, ...) and how far the true system lies
    from the class rule's thresholds (:func:`training.evaluation._metrics.threshold_margin`)."""

    inputs: ConfidenceInputs
    truth: dict[str, float]
    true_class: str
    errors: dict[str, float]
    kept_warnings: tuple[str, ...]
    group: str
    margin: float = math.inf

    def to_dict(self) -> dict[str, Any]:
        return {"features": self.inputs.features.tolist(), "points": self.inputs.points, "scales": self.inputs.scales,
                "structure": self.inputs.structure, "rule": self.inputs.rule, "truth": self.truth,
                "true_class": self.true_class, "errors": self.errors, "kept_warnings": list(self.kept_warnings),
                "group": self.group, "margin": self.margin}

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> "CalibrationSample":
        inputs = ConfidenceInputs(np.asarray(d["features"], dtype=np.float64), d["points"], d["scales"], d["structure"],
                                  d["rule"])
        return cls(inputs, d["truth"], d["true_class"], d["errors"], tuple(d["kept_warnings"]), d["group"],
                   float(d.get("margin", math.inf)))


# -- the calibration records -------------------------------------------------------------------
Task = tuple[str, DriveConfig, TestSignalConfig, TwoMassParams, int]


def calibration_tasks(per_drive: int = 300, envelope_drives: int = 40, per_envelope_drive: int = 25,
                      reference: int = 1000, seeds: dict[str, int] = CALIBRATION_SEEDS) -> list[Task]:
    """The calibration's simulation tasks: (group, drive, test, systems, noise seed), each at most
    100 systems: ``per_drive`` systems of each matrix drive's population, as many of the real-axis
    population on :data:`REAL_AXIS_DRIVES` (times its weight), ``envelope_drives`` drives of the
    envelope, ``reference`` systems of the default population on the reference drive."""
    tasks: list[Task] = []
    for name, case in DRIVES.items() if per_drive > 0 else ():
        tasks += _split(f"matrix:{name}", case.drive, case.signal, sample_population(per_drive, seeds["matrix"],
                                                                                     case.ranges()), seeds["matrix"])
    for name, weight in REAL_AXIS_DRIVES.items() if per_drive > 0 else ():
        case = DRIVES[name]
        tasks += _split(f"{REAL_AXIS_GROUP}:{name}", case.drive, case.signal,
                        case.population(weight * per_drive, seeds["real_axis"], real_axis=True), seeds["real_axis"])
    for name, drive, signal, params, seed in (envelope_cases(envelope_drives, per_envelope_drive, seeds["envelope"])
                                              if envelope_drives > 0 else ()):
        tasks += _split(name, drive, signal, params, seed)
    if reference > 0:
        reference_drive = DRIVES["reference"]
        tasks += _split("reference_population", reference_drive.drive, reference_drive.signal,
                        sample_population(reference, seeds["reference"]), seeds["reference"])
    return tasks


def _split(group: str, drive: DriveConfig, signal: TestSignalConfig, params: TwoMassParams, seed: int,
           size: int = 100) -> list[Task]:
    n = params.J_sigma.shape[0]
    return [(group, drive, signal, params[k:k + size], seed * 1000 + k // size) for k in range(0, n, size)]


def task_samples(task: Task, checkpoints: str | os.PathLike[str] | None = None) -> list[CalibrationSample]:
    """Simulate and identify one task's systems without a calibration; one sample per answer."""
    group, drive, signal, params, seed = task
    identifier = Identifier.load(checkpoints, calibrated=False)
    records = list(iter_records(params, drive, signal, seed=seed))
    out = []
    for record, result in zip(records, identifier.identify_records(records)):
        if not result.ok:
            continue
        truth = record.info.truth
        estimates = result.parameters.to_dict()
        errors = {k: float(relative_error(np.array([np.nan if estimates[k] is None else estimates[k]]),
                                          np.array([truth[k]]))[0]) for k in ("f_e", "V_J", "J_sigma")}
        kept = tuple(w.code for w in result.warnings if w.code not in NOTE_CODES)
        margin = threshold_margin({"s_N": np.array([truth["s_N"]]), "r_osc": np.array([truth["r_osc"]]),
                                   "w_e_T_Ei": np.array([truth["w_e"] * drive.T_Ei])})
        out.append(CalibrationSample(result.confidence, {k: float(truth[k]) for k in INTERVAL_NAMES},
                                     str(truth["structure"]), errors, kept, group, float(margin[0])))
    return out


def save_samples(samples: Sequence[CalibrationSample], path: str | os.PathLike[str]) -> None:
    Path(path).write_text("\n".join(json.dumps(s.to_dict()) for s in samples) + "\n")


def load_samples(path: str | os.PathLike[str]) -> list[CalibrationSample]:
    """The samples :func:`save_samples` wrote; ``ValueError`` (one line naming the file and line) else."""
    out = []
    for k, line in enumerate(Path(path).read_text().splitlines(), 1):
        try:
            if line:
                out.append(CalibrationSample.from_dict(json.loads(line)))
        except (ValueError, KeyError, TypeError, AttributeError) as err:
            raise ValueError(f"{path}: line {k}: not a calibration sample of `twomass calibrate --samples` "
                             f"({type(err).__name__}: {err})") from None
    return out


# -- the fit -----------------------------------------------------------------------------------
def answer_right(samples: Sequence[CalibrationSample]) -> np.ndarray:
    """``N`` bool: the answer is right (:func:`training.evaluation._metrics.answer_wrong` negated)."""
    errors = {k: np.array([s.errors[k] for s in samples]) for k in ("f_e", "V_J", "J_sigma")}
    return ~answer_wrong(np.array([s.true_class for s in samples]), np.array([s.inputs.structure for s in samples]),
                         errors)


def coordinate_errors(samples: Sequence[CalibrationSample], name: str) -> np.ndarray:
    """``N``: each answer's error of parameter ``name`` in its coordinate, ``|c(point) - c(truth)|``."""
    return np.array([abs(s.inputs.coordinate(name, s.inputs.points[name]) - s.inputs.coordinate(name, s.truth[name]))
                     for s in samples])


def fit_calibration(samples: Sequence[CalibrationSample], provenance: dict[str, Any]) -> Calibration:
    """The :class:`Calibration` of ``samples`` (module docstring); ``provenance`` is stored with it."""
    if len(samples) < 200:
        raise ValueError(f"fit_calibration: expected at least 200 calibration answers, received {len(samples)}")
    X = np.stack([s.inputs.features for s in samples])  # N x F
    classes = np.array([s.inputs.structure for s in samples])
    real_axis = np.array([s.group.startswith(REAL_AXIS_GROUP) for s in samples])  # N: the real-axis records
    real_axis_model = _real_axis_model(X, real_axis)
    like = real_axis_model(X) > 0.0  # N: more likely from a real axis than not
    scale, quantile = _fit_intervals(samples, X, classes, real_axis, like)
    # the logistic models read the class rule's log-odds too, from the intervals just fitted
    X = np.stack([model_features(s.inputs, rule_probabilities(
        s.inputs, lambda name, s=s, r=r: half_width(scale, quantile, s.inputs, name, r)))
        for s, r in zip(samples, like)])  # N x (F + 1)
    mean, std = _standardization(X)
    Z = (X - mean) / std  # N x (F + 1), standardized
    class_right = np.array([s.inputs.structure == s.true_class for s in samples])
    right = answer_right(samples)
    class_model = LinearModel(mean, std, *_logistic(Z, class_right, RIDGE_LOGISTIC))
    answer_model = LinearModel(mean, std, *_logistic(Z, right, RIDGE_LOGISTIC))
    warned = np.array([bool(s.kept_warnings) for s in samples])
    p_out_of_fold = _out_of_fold_probability(Z, right)
    warn_below = warn_threshold(p_out_of_fold[~right & ~warned], int((~right).sum()), SILENT_WRONG_SHARE)
    counts = {str(c): int((classes == c).sum()) for c in np.unique(classes)}
    provenance = {**provenance, "n": len(samples), "classes": counts, "version": CONFIDENCE_VERSION,
                  "right": float(right.mean()), "right_warned_out_of_fold": float(
                      ((p_out_of_fold < warn_below) | warned)[right].mean())}
    return Calibration(scale, quantile, real_axis_model, class_model, answer_model, warn_below, provenance)


def _standardization(X: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The columns' mean and standard deviation (1 where a column is constant)."""
    std = X.std(axis=0)
    return X.mean(axis=0), np.where(std > 1e-9, std, 1.0)


def _real_axis_model(X: np.ndarray, real_axis: np.ndarray) -> LinearModel:
    """The logistic model of P(the record is from a real axis) (``real_axis``, ``N`` bool: the
    calibration's real-axis records) on the features ``X`` (``N x F``); without any, P = 0."""
    mean, std = _standardization(X)
    if not real_axis.any():
        return LinearModel(mean, std, np.zeros(X.shape[1]), -NO_REAL_AXIS_LOG_ODDS)
    return LinearModel(mean, std, *_logistic((X - mean) / std, real_axis, RIDGE_LOGISTIC))


def _fit_intervals(samples: Sequence[CalibrationSample], X: np.ndarray, classes: np.ndarray, real_axis: np.ndarray,
                   like: np.ndarray) -> tuple[dict[str, LinearModel], dict[str, dict[str, float]]]:
    """Per parameter the ridge model of the log error's scale on the features ``X`` (``N x F``) and
    the conformal quantiles of the normalized errors in each cell (:func:`cell_quantiles`;
    ``real_axis``, ``like``: ``N`` bool, the real-axis records and the answers more likely from a
    real axis than not)."""
    mean, std = _standardization(X)
    Z = (X - mean) / std  # N x F, standardized
    scale, quantile = {}, {}
    for name in INTERVAL_NAMES:
        floor = _ERROR_FLOOR["asinh" if name in ASINH else "log"]
        e = coordinate_errors(samples, name)
        # its calibration records: the real-axis parts' on the real-axis records (all where there are none)
        on = real_axis if name in REAL_AXIS_NAMES and real_axis.any() else np.ones(len(samples), dtype=bool)
        coef, intercept = _ridge(Z[on], np.log(e[on] + floor), RIDGE_SCALE)
        model = LinearModel(mean, std, coef, intercept)
        scale[name] = model
        scores = e[on] / np.exp(model(X[on]))
        if name in REAL_AXIS_NAMES and real_axis.any():  # calibrated on real axes alone: one cell, in both
            per_class = class_quantiles(scores, classes[on])
            quantile[name] = {**per_class, **{REAL_AXIS_CELL + k: q for k, q in per_class.items()}}
        else:
            quantile[name] = cell_quantiles(scores, classes[on], like[on])
    return scale, quantile


def class_quantiles(scores: np.ndarray, classes: np.ndarray, prefix: str = "") -> dict[str, float]:
    """The conformal quantiles of ``scores`` (``N``) over all (``"*"``) and per reported class where
    it has :data:`MIN_CLASS_SAMPLES` records; keys prefixed ``prefix``."""
    out = {prefix + "*": conformal_quantile(scores, COVERAGE)}
    for c in np.unique(classes):
        if (classes == c).sum() >= MIN_CLASS_SAMPLES:
            out[prefix + str(c)] = conformal_quantile(scores[classes == c], COVERAGE)
    return out


def cell_quantiles(scores: np.ndarray, classes: np.ndarray, like: np.ndarray) -> dict[str, float]:
    """The conformal quantiles of ``scores`` (``N``) per Mondrian cell: the answers more likely
    from a real axis than not (``like``; keys prefixed :data:`REAL_AXIS_CELL`) and the others, in
    each per reported class where it has :data:`MIN_CLASS_SAMPLES` records, and over all classes
    (``"*"``; over every record where the cell has too few)."""
    out = {}
    for prefix, cell in (("", ~like), (REAL_AXIS_CELL, like)):
        out.update(class_quantiles(scores[cell], classes[cell], prefix) if cell.sum() >= MIN_CLASS_SAMPLES
                   else {prefix + "*": conformal_quantile(scores, COVERAGE)})
    return out


def conformal_quantile(scores: np.ndarray, coverage: float) -> float:
    """The split-conformal quantile: the ``ceil((n + 1) coverage)``-th smallest of ``n`` scores
    (inf where that exceeds ``n``): a new exchangeable score lies at or below it with probability
    at least ``coverage``."""
    n = len(scores)
    k = math.ceil((n + 1) * coverage)
    return float(np.sort(scores)[k - 1]) if k <= n else math.inf


def warn_threshold(p_silent_wrong: np.ndarray, n_wrong: int, share: float) -> float:
    """The smallest answer probability threshold that leaves at most ``share`` of the ``n_wrong``
    wrong answers unwarned (``p_silent_wrong``: the probabilities of the wrong answers no other
    warning covers; an answer below the threshold is warned)."""
    allowed = int(math.floor(share * n_wrong))
    p = np.sort(p_silent_wrong)[::-1]
    if len(p) <= allowed:
        return 0.0
    return float(np.nextafter(p[allowed], 1.0))


def _ridge(Z: np.ndarray, y: np.ndarray, lam: float) -> tuple[np.ndarray, float]:
    """Ridge regression of ``y`` on standardized ``Z`` (intercept unpenalized)."""
    y0 = float(y.mean())
    F = Z.shape[1]
    coef = np.linalg.solve(Z.T @ Z + lam * np.eye(F), Z.T @ (y - y0))
    return coef, y0 - float(Z.mean(axis=0) @ coef)


def _logistic(Z: np.ndarray, y: np.ndarray, lam: float, iterations: int = 50) -> tuple[np.ndarray, float]:
    """Ridge-penalized logistic regression by Newton's method: ``(coef, intercept)`` of the log-odds."""
    A = np.hstack([Z, np.ones((len(Z), 1))])  # N x (F + 1)
    penalty = lam * np.eye(A.shape[1])
    penalty[-1, -1] = 0.0
    w = np.zeros(A.shape[1])
    t = y.astype(np.float64)
    for _ in range(iterations):
        p = 1.0 / (1.0 + np.exp(-np.clip(A @ w, -40, 40)))
        grad = A.T @ (p - t) + penalty @ w
        hess = (A * (p * (1 - p))[:, None]).T @ A + penalty
        step = np.linalg.solve(hess, grad)
        w -= step
        if np.max(np.abs(step)) < 1e-8:
            break
    return w[:-1], float(w[-1])


def _out_of_fold_probability(Z: np.ndarray, y: np.ndarray, folds: int = 5, seed: int = 0) -> np.ndarray:
    """Each answer's P(right) from a logistic model fitted without its fold."""
    fold = np.random.default_rng(seed).integers(0, folds, len(y))
    p = np.empty(len(y))
    for k in range(folds):
        coef, intercept = _logistic(Z[fold != k], y[fold != k], RIDGE_LOGISTIC)
        p[fold == k] = 1.0 / (1.0 + np.exp(-np.clip(Z[fold == k] @ coef + intercept, -40, 40)))
    return p
