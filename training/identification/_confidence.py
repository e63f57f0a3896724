"""How sure an answer is (SPEC 4.1): 90 % intervals, class probabilities and the probability that
the answer is right, from the record's own evidence, calibrated on held-out simulated records.

Each answer gets a vector of *confidence features* (:data:`FEATURE_NAMES`: its class, how far its
class quantities lie from the class rule's thresholds, how well the refined model fits, how
visible the oscillation is, whether the maps and the refinement agree, the drive's resolution
and noise, the one-mass fit's parameters' standard deviations from the least
squares' curvature, which uncertainty remarks fired) and, per parameter, a *point* in a transformed
coordinate (``log`` for the positive quantities; ``asinh(value / scale)`` for those that may be
0: backlash, friction). The :class:`Calibration` (shipped with the maps as ``confidence.json``,
made by ``twomass calibrate``) holds

- per parameter a linear model of the log of the record's expected error from the features (the
  normalizing *scale*) and, per reported class, the split-conformal quantile of the error over
  that scale on the calibration records: the interval is ``point +- quantile * scale`` mapped
  back, with the conformal guarantee (over records exchangeable with the calibration's, the
  truth lies inside for at least 90 % of answers of each class);
- two logistic models: P(the class is right) and P(the answer is right: class right, an elastic
  answer within ``E_30``, ``J_sigma`` within 30 %), and the probability below which an answer is
  warned ``likely_wrong``. Besides the features they read the log-odds of the *class rule's
  probability* of the reported class (:func:`rule_probabilities`): SPEC 1's rule applied to the
  answer's ``backlash``, ``f_e``, ``V_J``, ``J_sigma`` scattered as normals of their calibrated
  intervals. A class quantity near its threshold, relative to how sure the record makes it, is a
  probability there, not a warning.

The class probabilities are P(class right) for the reported class and the rest shared among
the other classes by the mean of the rule's probabilities and the structure map's weights (none
above the reported class's).
"""

from __future__ import annotations

import json
import math
import os
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from sim import (CLASS_THRESHOLDS, S_N_ELASTIC, S_N_STIFF_BACKLASH, STRUCTURE_CLASSES, gap_width, normalized_backlash,
                 two_mass_derived)
from training.identification._analysis import Analysis
from training.identification._policy import class_quantities
from training.identification._result import INTERVAL_NAMES, WARNING_CODES, Intervals, Parameters

#: Version of the features and of the calibration file's layout.
CONFIDENCE_VERSION = "twomass-confidence-v4"
#: The calibration's file in a checkpoints folder.
FILE_NAME = "confidence.json"
#: The intervals' coverage (SPEC 4.1).
COVERAGE = 0.9

#: The parameters whose coordinate is ``asinh(value / scale)`` (they may be 0; their values are
#: clipped at 0), the signed load torque's too (not clipped); the others' is ``log``.
ZERO_CAPABLE = ("backlash", "M_FC", "mu_F", "M_FCM", "mu_FM")
SIGNED = ("M_L0",)
#: The parameters whose coordinate is ``asinh`` (:data:`ZERO_CAPABLE` and :data:`SIGNED`).
ASINH = ZERO_CAPABLE + SIGNED
#: The largest coordinate an interval's end takes (``exp``/``sinh`` of it stay finite: 1e86).
COORDINATE_BOUND = 200.0
#: The prefix of the conformal quantiles of the answers more likely from a real axis (SPEC 1.1) than
#: not (:attr:`Calibration.real_axis`): a second Mondrian cell beside each class's.
REAL_AXIS_CELL = "real_axis:"
#: The remarks whose presence is a feature (every code but the calibration's own).
REMARK_CODES = tuple(c for c in WARNING_CODES if c != "likely_wrong")

FEATURE_NAMES: tuple[str, ...] = (
    *(f"class_{c}" for c in STRUCTURE_CLASSES), "maps_agree", "refined", "log_refine_residual",
    "log_refine_evidence", "log_osc_quanta", "r2_fit", "log_one_mass_residual", "log_map_distance", "p_map_class",
    "class_margin", "class_margin_maps", *(f"margin_{q}" for q in CLASS_THRESHOLDS),
    *(f"margin_maps_{q}" for q in CLASS_THRESHOLDS), "refine_gain", "log_f_e_T_s", "log_f_e_T_Ei", "log_V_J",
    "log_d", "log_s_N", "maps_refined_f_e", "maps_refined_V_J", "log_noise", "log_T_s", "log_counts",
    "log_time_scale", "log_T_Ei_T_s", "friction", "viscous", "log_backlash_bound", "log_std_J_sigma",
    "log_std_M_FC", "log_std_mu_F", "load_torque", "held", "motor_friction",
    *(f"remark_{c}" for c in REMARK_CODES))


#: What :attr:`ConfidenceInputs.rule` holds: the backlash widths [rad] at which ``s_N`` reaches its
#: two thresholds (at the answer's ``C_F``), and ``ln(w_e T_Ei)``, ``ln(r_osc)`` of the answer's point.
RULE_NAMES: tuple[str, ...] = ("backlash_low", "backlash_high", "ln_w_e_T_Ei", "ln_r_osc")
#: The logistic models' inputs: the features and the log-odds of the class rule's probability.
MODEL_FEATURE_NAMES: tuple[str, ...] = FEATURE_NAMES + ("rule_log_odds",)
#: A normal's 90 % half-width in standard deviations (``NormalDist().inv_cdf(0.95)``).
Z_90 = 1.6448536269514722


@dataclass(frozen=True)
class ConfidenceInputs:
    """What the calibration reads of one answer: ``features`` ``(F,)`` in the order of
    :data:`FEATURE_NAMES`; per parameter of :data:`INTERVAL_NAMES` its ``points`` (the answer's
    value, or what stands in for one the answer leaves out: the maps' elastic values of a stiff
    answer, 0 for a backlash not identified), the ``scales`` of the zero-capable coordinates, and
    where the point lies against the class rule (``rule``: :data:`RULE_NAMES`)."""

    features: np.ndarray
    points: dict[str, float]
    scales: dict[str, float]
    structure: str
    rule: dict[str, float]

    def coordinate(self, name: str, value: float) -> float:
        """``value`` of parameter ``name`` in its coordinate (:data:`ZERO_CAPABLE`, :data:`SIGNED`: asinh;
        else log)."""
        if name in ASINH:
            return math.asinh(value / self.scales[name])
        return math.log(max(value, 1e-300))

    def value(self, name: str, coordinate: float) -> float:
        """The inverse of :meth:`coordinate` (a zero-capable value clipped at 0; the coordinate clipped
        to +-:data:`COORDINATE_BOUND`, so that a record far from the calibration's gets a vast but
        finite interval, not an overflow)."""
        coordinate = min(max(coordinate, -COORDINATE_BOUND), COORDINATE_BOUND)
        if name in SIGNED:
            return self.scales[name] * math.sinh(coordinate)
        if name in ZERO_CAPABLE:
            return max(self.scales[name] * math.sinh(coordinate), 0.0)
        return math.exp(coordinate)


def stand_in_points(parameters: Parameters, maps_elastic: tuple[float, float, float], J_sigma_fit: float,
                    friction_fit: tuple[float, float]) -> dict[str, float]:
    """Every parameter's point: the answer's value, else its stand-in (``maps_elastic`` =
    ``(f_e, V_J, d)`` of the maps, the one-mass fit's ``J_sigma`` and ``(M_FC, mu_F)``, backlash and
    the real-axis parts 0;
    the derived ``J_M``, ``J_L``, ``C_F`` of those)."""
    J_sigma = parameters.J_sigma if parameters.J_sigma is not None else abs(J_sigma_fit)
    f_e, V_J, d = (v if v is not None else m for v, m in zip((parameters.f_e, parameters.V_J, parameters.d),
                                                              maps_elastic))
    derived = two_mass_derived(J_sigma, V_J, f_e, d)
    return {"J_sigma": J_sigma, "V_J": V_J, "J_M": derived.J_M, "J_L": derived.J_L, "f_e": f_e, "C_F": derived.C_F,
            "d": d, "backlash": parameters.backlash or 0.0,
            "M_FC": parameters.M_FC if parameters.M_FC is not None else max(friction_fit[0], 0.0),
            "mu_F": parameters.mu_F if parameters.mu_F is not None else max(friction_fit[1], 0.0),
            "M_L0": parameters.M_L0 or 0.0, "M_FCM": parameters.M_FCM or 0.0, "mu_FM": parameters.mu_FM or 0.0}


def class_margins(quantities: Mapping[str, float]) -> dict[str, float]:
    """Per quantity of the class rule (:data:`sim.CLASS_THRESHOLDS`): ``min |ln(q / t)|`` over its
    thresholds, clipped to 0..3 (3 where it is missing or not finite)."""
    return {name: min([3.0, *(abs(math.log(quantities[name] / t)) for t in thresholds
                              if name in quantities and math.isfinite(quantities[name]) and quantities[name] > 0)])
            for name, thresholds in CLASS_THRESHOLDS.items()}


def _unit(x: float) -> float:
    return min(max(x, 0.0), 1.0) if math.isfinite(x) else 0.0


def _log10(x: float | None, low: float, high: float) -> float:
    return 0.0 if x is None or not math.isfinite(x) else math.log10(min(max(x, low), high))


def confidence_inputs(analysis: Analysis, structure: str, parameters: Parameters, points: dict[str, float], *,
                      maps_structure: str, maps_probabilities: Mapping[str, float], map_distance: float,
                      margins: tuple[Mapping[str, float], Mapping[str, float]],
                      maps_elastic: tuple[float, float, float],
                      refine: tuple[float, float, float] | None, backlash_bound: float | None,
                      remarks: Sequence[str]) -> ConfidenceInputs:
    """One answer's :class:`ConfidenceInputs` (``margins``: :func:`class_margins` of the answer's and
    the maps' class quantities; ``refine``: the refined model's residual, evidence and start
    residual, ``None`` where no refinement ran; ``remarks``: the codes of its warnings)."""
    drive, fit = analysis.drive, analysis.fit
    f_e, V_J, d = points["f_e"], points["V_J"], points["d"]
    s_N = (normalized_backlash(points["backlash"], drive.M_N, points["C_F"]) if points["backlash"] > 0 else 1e-3)
    codes = set(remarks)
    values = [*(float(structure == c) for c in STRUCTURE_CLASSES), float(structure == maps_structure),
              float(refine is not None), _log10(refine[0] if refine else None, 1e-3, 1e3),
              _log10(1.0 + refine[1] if refine else None, 1.0, 1e6), _log10(analysis.osc_quanta, 1e-3, 1e4),
              _unit(analysis.feature("r2_fit")), _log10(fit.rel_residual, 1e-4, 10.0), _log10(map_distance, 1e-2, 1e2),
              float(maps_probabilities.get(structure, 0.0)), min(margins[0].values()), min(margins[1].values()),
              *(margins[0][q] for q in CLASS_THRESHOLDS), *(margins[1][q] for q in CLASS_THRESHOLDS),
              _log10(refine[2] / refine[0] if refine and refine[0] > 0 else None, 1e-2, 1e4),
              _log10(f_e * drive.T_s, 1e-5, 10.0), _log10(f_e * drive.T_Ei, 1e-5, 10.0), _log10(V_J, 1e-2, 1e2),
              _log10(d, 1e-4, 1.0), _log10(s_N, 1e-3, 1e2),
              min(abs(math.log(f_e / maps_elastic[0])), 3.0), min(abs(math.log(V_J / maps_elastic[1])), 3.0),
              _log10(drive.current_noise / drive.M_star, 1e-6, 1.0), _log10(drive.T_s / 250e-6, 1e-2, 1e2),
              math.log2(max(drive.encoder_counts, 2)) / 20.0, _log10(drive.time_scale(points["J_sigma"]), 1e-3, 1e2),
              _log10(drive.T_Ei / drive.T_s, 1e-2, 1e3), min(points["M_FC"] / drive.M_star, 1.0),
              min(points["mu_F"] * drive.w_max / drive.M_star, 1.0),
              _log10(backlash_bound / drive.q_phi if backlash_bound else None, 1e-2, 1e6),
              _log10(fit.std[0] / abs(fit.J_sigma), 1e-7, 10.0),
              _log10(fit.std[2] / drive.M_star, 1e-7, 10.0),
              _log10(fit.std[1] * drive.w_max / drive.M_star, 1e-7, 10.0),
              min(abs(points["M_L0"]) / drive.M_star, 1.0), float(drive.M_hold != 0.0),
              min(points["M_FCM"] / drive.M_star, 1.0), *(float(c in codes) for c in REMARK_CODES)]
    torque, viscous = 0.01 * drive.M_star, 0.01 * drive.M_star / drive.w_max
    scales = {"backlash": 2.0 * drive.q_phi, "M_FC": torque, "mu_F": viscous, "M_L0": torque, "M_FCM": torque,
              "mu_FM": viscous}
    q = class_quantities(analysis, points["J_sigma"], V_J, f_e, d, s_N)
    rule = {"backlash_low": float(gap_width(S_N_ELASTIC, drive.M_N, points["C_F"])),
            "backlash_high": float(gap_width(S_N_STIFF_BACKLASH, drive.M_N, points["C_F"])),
            "ln_w_e_T_Ei": math.log(q["w_e_T_Ei"]), "ln_r_osc": math.log(max(q["r_osc"], 1e-300))}
    return ConfidenceInputs(np.asarray(values, dtype=np.float64), dict(points), scales, structure, rule)


def rule_probabilities(inputs: ConfidenceInputs, half_width: Callable[[str], float]) -> dict[str, float]:
    """The four classes' probabilities under SPEC 1's class rule where ``backlash``, ``f_e``,
    ``V_J`` and ``J_sigma`` scatter independently as normals in their coordinates, each with the
    standard deviation of its 90 % interval's ``half_width(name)`` (coordinate units) around the
    answer's point: ``s_N`` from the backlash (``C_F``'s own scatter, a few %, left out),
    ``w_e T_Ei`` from ``f_e``, ``r_osc ~ V_J / (J_sigma f_e)`` from all three. They sum to 1."""
    sd = {n: half_width(n) / Z_90 for n in ("backlash", "f_e", "V_J", "J_sigma")}
    r, u = inputs.rule, inputs.coordinate("backlash", inputs.points["backlash"])
    no_gap = _below(inputs.coordinate("backlash", r["backlash_low"]) - u, sd["backlash"])  # s_N < 0.1
    large_gap = _below(u - inputs.coordinate("backlash", r["backlash_high"]), sd["backlash"])  # s_N >= 1
    gap = max(1.0 - no_gap - large_gap, 0.0)
    soft = _below(-r["ln_w_e_T_Ei"], sd["f_e"])
    visible = _below(r["ln_r_osc"], math.sqrt(sd["V_J"] ** 2 + sd["f_e"] ** 2 + sd["J_sigma"] ** 2))
    return {"stiff": no_gap * (1.0 - soft * visible), "elastic": no_gap * soft * visible,
            "elastic_backlash": soft * gap, "stiff_backlash": large_gap + (1.0 - soft) * gap}


def _below(x: float, sd: float) -> float:
    """P(a normal of standard deviation ``sd`` lies below ``x``) (a step at 0 where ``sd`` is 0; 1/2
    where it is infinite)."""
    if sd > 0:
        return 0.5 * math.erfc(-x / (sd * math.sqrt(2.0))) if math.isfinite(sd) else 0.5
    return 1.0 if x > 0 else 0.0 if x < 0 else 0.5


# -- the calibration ---------------------------------------------------------------------------
@dataclass(frozen=True)
class LinearModel:
    """``y = coef . (x - mean) / std + intercept`` over :data:`FEATURE_NAMES` (``std`` 1 where constant)."""

    mean: np.ndarray
    std: np.ndarray
    coef: np.ndarray
    intercept: float

    def __call__(self, x: np.ndarray) -> np.ndarray:
        """``x``: ``*batch x F`` -> ``*batch``."""
        return ((x - self.mean) / self.std) @ self.coef + self.intercept

    def to_dict(self) -> dict[str, Any]:
        return {"mean": self.mean.tolist(), "std": self.std.tolist(), "coef": self.coef.tolist(),
                "intercept": self.intercept}

    @classmethod
    def from_dict(cls, d: Mapping[str, Any], n: int = len(FEATURE_NAMES)) -> "LinearModel":
        """The model of ``d`` over ``n`` features."""
        arrays = [np.asarray(d[k], dtype=np.float64) for k in ("mean", "std", "coef")]
        if any(a.shape != (n,) for a in arrays):
            raise ValueError(f"confidence model: expected {n} features, received {[a.shape for a in arrays]}")
        return cls(*arrays, float(d["intercept"]))


def half_width(scale: Mapping[str, LinearModel], quantile: Mapping[str, Mapping[str, float]],
               inputs: ConfidenceInputs, name: str, real_axis: bool) -> float:
    """The 90 % interval's half-width of parameter ``name`` in its coordinate: the conformal quantile
    of the answer's cell (its class, among the answers likely from a ``real_axis`` or among the others;
    ``"*"``: all classes of the cell) times the record's scale."""
    cell = REAL_AXIS_CELL if real_axis else ""
    q = quantile[name].get(cell + inputs.structure, quantile[name][cell + "*"])
    return q * math.exp(float(scale[name](inputs.features)))


def model_features(inputs: ConfidenceInputs, rule: Mapping[str, float]) -> np.ndarray:
    """``(F + 1,)``: the features and the log-odds of ``rule`` (:func:`rule_probabilities`) for the
    reported class (:data:`MODEL_FEATURE_NAMES`)."""
    p = min(max(rule[inputs.structure], 1e-6), 1.0 - 1e-6)
    return np.append(inputs.features, math.log(p / (1.0 - p)))


@dataclass(frozen=True)
class Calibration:
    """The calibration of :mod:`this module <training.identification._confidence>`: per parameter
    the log-scale model and the conformal quantile per cell: the reported class among the answers
    more likely from a real axis than not (keys :data:`REAL_AXIS_CELL` + class) or among the others
    (the class), ``"*"`` for a class with too few calibration records; the logistic models of
    P(a real axis) over :data:`FEATURE_NAMES`, of P(class right) and P(answer right) over
    :data:`MODEL_FEATURE_NAMES` (their ``y`` is the log-odds); the answer probability below which
    an answer is warned; and where it came from (``provenance``: seeds, counts, the maps' digests)."""

    scale: dict[str, LinearModel]
    quantile: dict[str, dict[str, float]]
    real_axis: LinearModel
    class_right: LinearModel
    answer_right: LinearModel
    warn_below: float
    provenance: dict[str, Any]

    def is_real_axis(self, inputs: ConfidenceInputs) -> bool:
        """The answer is more likely from a real axis (SPEC 1.1: a load torque, motor friction) than not."""
        return float(self.real_axis(inputs.features)) > 0.0

    def half_width(self, inputs: ConfidenceInputs, name: str) -> float:
        """:func:`half_width` in the answer's cell."""
        return half_width(self.scale, self.quantile, inputs, name, self.is_real_axis(inputs))

    def intervals(self, inputs: ConfidenceInputs) -> Intervals:
        """The answer's 90 % intervals."""
        out = {}
        for name in INTERVAL_NAMES:
            half = self.half_width(inputs, name)
            centre = inputs.coordinate(name, inputs.points[name])
            out[name] = (inputs.value(name, centre - half), inputs.value(name, centre + half))
        return Intervals(**out)

    def rule_probabilities(self, inputs: ConfidenceInputs) -> dict[str, float]:
        """:func:`rule_probabilities` with this calibration's intervals."""
        return rule_probabilities(inputs, lambda name: self.half_width(inputs, name))

    def probabilities(self, inputs: ConfidenceInputs, map_probabilities: Mapping[str, float]) -> dict[str, float]:
        """The four classes' probabilities: P(class right) for the answer's, the rest shared by the
        mean of the class rule's probabilities and the structure map's weights (each normalized over
        the other classes), none above the answer's (they sum to 1)."""
        rule = self.rule_probabilities(inputs)
        p = max(_sigmoid(float(self.class_right(model_features(inputs, rule)))), 1.0 / len(STRUCTURE_CLASSES))
        others = [c for c in STRUCTURE_CLASSES if c != inputs.structure]
        weights = {c: 0.0 for c in STRUCTURE_CLASSES}
        for source in (rule, map_probabilities):
            total = sum(max(float(source.get(c, 0.0)), 0.0) for c in others)
            for c in others if total > 0 else ():
                weights[c] += max(float(source.get(c, 0.0)), 0.0) / total
        return share_rest(inputs.structure, p, weights)

    def answer_probability(self, inputs: ConfidenceInputs) -> float:
        """P(the answer is right: class, ``E_30`` of an elastic answer, ``J_sigma`` within 30 %)."""
        return _sigmoid(float(self.answer_right(model_features(inputs, self.rule_probabilities(inputs)))))

    def to_dict(self) -> dict[str, Any]:
        return {"version": CONFIDENCE_VERSION, "features": list(FEATURE_NAMES), "coverage": COVERAGE,
                "scale": {n: m.to_dict() for n, m in self.scale.items()}, "quantile": self.quantile,
                "real_axis": self.real_axis.to_dict(),
                "class_right": self.class_right.to_dict(), "answer_right": self.answer_right.to_dict(),
                "warn_below": self.warn_below, "provenance": self.provenance}

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> "Calibration":
        if d.get("version") != CONFIDENCE_VERSION or list(d.get("features", ())) != list(FEATURE_NAMES):
            raise ValueError(f"confidence calibration: version {d.get('version')!r} does not match this toolkit's "
                             f"{CONFIDENCE_VERSION!r}: rerun `twomass calibrate`")
        missing = [n for n in INTERVAL_NAMES if n not in d["scale"]
                   or not {"*", REAL_AXIS_CELL + "*"} <= set(d["quantile"].get(n, {}))]
        if missing:
            raise ValueError(f"confidence calibration: parameters missing: {missing}")
        return cls({n: LinearModel.from_dict(d["scale"][n]) for n in INTERVAL_NAMES},
                   {n: {k: float(v) for k, v in d["quantile"][n].items()} for n in INTERVAL_NAMES},
                   LinearModel.from_dict(d["real_axis"]),
                   LinearModel.from_dict(d["class_right"], len(MODEL_FEATURE_NAMES)),
                   LinearModel.from_dict(d["answer_right"], len(MODEL_FEATURE_NAMES)),
                   float(d["warn_below"]), dict(d.get("provenance", {})))

    @classmethod
    def load(cls, path: str | os.PathLike[str]) -> "Calibration":
        try:
            return cls.from_dict(json.loads(Path(path).read_text()))
        except (OSError, json.JSONDecodeError, KeyError, TypeError) as err:
            raise ValueError(f"confidence calibration {path}: unreadable ({err})") from None


def share_rest(structure: str, p: float, weights: Mapping[str, float]) -> dict[str, float]:
    """``p`` for ``structure`` and ``1 - p`` shared among the other classes in proportion to
    ``weights`` (equally where they are all 0), none above ``p`` (water-filling: a share capped at
    ``p`` passes its excess to the others). ``p`` >= 1/4 so that this is always possible."""
    others = [c for c in STRUCTURE_CLASSES if c != structure]
    w = {c: max(float(weights.get(c, 0.0)), 0.0) for c in others}
    out, rest, free = {structure: p}, 1.0 - p, list(others)
    while free:
        total = sum(w[c] for c in free)
        share = {c: rest * (w[c] / total if total > 0 else 1.0 / len(free)) for c in free}
        capped = [c for c in free if share[c] > p]
        if not capped:
            out.update(share)
            break
        for c in capped:
            out[c] = p
            rest -= p
            free.remove(c)
    return {c: out[c] for c in STRUCTURE_CLASSES}


def _sigmoid(z: float) -> float:
    return 1.0 / (1.0 + math.exp(-z)) if z >= 0 else math.exp(z) / (1.0 + math.exp(z))


def maps_digests(digests: Mapping[str, str]) -> dict[str, str]:
    """The maps' SHA-256 of a manifest listing (every ``.pt`` file): what a calibration is made for."""
    return {name: digest for name, digest in sorted(digests.items()) if name.endswith(".pt")}


def check_calibrated_for(calibration: Calibration, digests: Mapping[str, str], folder: str | os.PathLike[str]) -> None:
    """Raise ``ValueError`` (one line) where ``calibration`` was made for other maps than those of
    the manifest listing ``digests``."""
    if calibration.provenance.get("maps_sha256") != maps_digests(digests):
        raise ValueError(f"{folder}: {FILE_NAME} was calibrated for other maps: rerun `twomass calibrate "
                         f"--checkpoints {folder}`")
