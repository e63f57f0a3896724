"""The refusal rules (knowledge base, docs/commissioning.md): may a speed controller be proposed
from an identification result and its validation, and if not, by which rule (V1-V6) and why.

Decisions key on codes: the rule that refused (:attr:`Permission.rule`) and the warning codes
(the identification's ``IdentWarning.code`` and the commissioning's own
:class:`CommissioningWarning` codes), never on message text.

The identification result is read through its attributes (``ok``, ``structure``, ``parameters``,
``quality``, ``warnings``, or ``error`` for a failure: :class:`IdentificationOutcome`); this room
does not import the identification room. Its ``notes`` (remarks on the uncertainty its calibrated
intervals already carry) never refuse; neither does its ``likely_wrong`` warning by default: the
chain's design limits such an answer instead (rules R7b and R7c: the set widened, the resonances
the test cannot exclude added), and a design that then misses the margins falls back to F1.
"""

from __future__ import annotations

import math
from collections.abc import Collection, Mapping, Sequence
from dataclasses import dataclass
from typing import Any, ClassVar, Protocol

from training.errors import CodedWarning

from ._validation import ValidationResult

__all__ = [
    "REFUSAL_RULES", "COMMISSIONING_WARNING_CODES", "BLOCKING_WARNING_CODES", "CommissioningWarning",
    "IdentificationOutcome", "IdentificationFailed", "Permission", "may_propose_controller", "used_maps",
    "outside_training",
]

#: The refusal rules, with what each one checks.
REFUSAL_RULES: dict[str, str] = {
    "V1": "the identification failed or named no known structure",
    "V2": "a parameter the structure needs is missing, not finite or not positive",
    "V3": "the identified model does not reproduce the record (validation)",
    "V4": "the record lies outside what the maps were trained on",
    "V6": "a warning with a blocking code",
}

#: The commissioning's own warning codes (beside the identification's), with what they mean.
COMMISSIONING_WARNING_CODES: dict[str, str] = {
    "test_not_informative": "the test signal adaptation ended without an informative response",
    "validation_not_run": "the identified model could not be re-simulated under the record's test signal",
    "margins_not_reached": "no model-based design keeps the guaranteed margins on the identified model's spread (R7)",
    "loop_not_settled": "no candidate loop settled on the drive within the scenario",
    "loop_unlike_model": "the delivered loop costs far more on the drive than the identified model predicts: its "
                         "guaranteed margins may not hold there",
    "loop_rejected": "a loop on the drive saturated, kept swinging or was far worse than its model: not delivered",
    "speed_against_torque": "the speed moved against the torque reference in a test run (motor or encoder sign reversed?)",
    "run_stopped": "the drive stopped an experiment at a limit (never scored as a good run)",
    "scenario_small": "the limits leave a scenario speed step of few speed quanta: the figures on the drive are coarse",
}

#: Warning codes that refuse a controller (rule V6). No identification code blocks by default (an
#: uncertain or likely wrong answer limits the design instead: see the module's docstring).
BLOCKING_WARNING_CODES: frozenset[str] = frozenset({"test_not_informative", "validation_not_run"})

_REQUIRED = {
    "stiff": ("J_sigma",),
    "stiff_backlash": ("J_sigma",),
    "elastic": ("J_sigma", "V_J", "f_e"),
    "elastic_backlash": ("J_sigma", "V_J", "f_e"),
}
_BACKLASH = ("elastic_backlash", "stiff_backlash")


class IdentificationOutcome(Protocol):
    """What the rules read of an identification: ``ok``; for a result ``structure``, ``parameters``
    (attributes ``J_sigma``, ``V_J``, ``f_e``, ...), ``quality`` (``map_distance_ratio``,
    ``outside_training``) and ``warnings`` (items with ``code`` and ``text``), and where calibrated
    ``intervals`` and ``notes`` (read by the chain's design, never refusing); for a failure ``error``."""

    @property
    def ok(self) -> bool: ...


@dataclass(frozen=True)
class IdentificationFailed:
    """The identifier raised instead of answering: ``error`` is the one-line reason."""

    error: str

    @property
    def ok(self) -> bool:
        return False

    def to_dict(self) -> dict[str, str]:
        return {"error": self.error}


@dataclass(frozen=True)
class CommissioningWarning(CodedWarning):
    """A warning of the commissioning itself (``code`` one of :data:`COMMISSIONING_WARNING_CODES`)."""

    CODES: ClassVar[Mapping[str, str]] = COMMISSIONING_WARNING_CODES


@dataclass(frozen=True)
class Permission:
    """``allowed``; ``reason`` (one line: why not, or what was checked); ``notes``: non-blocking
    warnings; ``rule``: the refusal rule (a key of :data:`REFUSAL_RULES`), None when allowed."""

    allowed: bool
    reason: str
    notes: tuple[str, ...] = ()
    rule: str | None = None

    def __post_init__(self) -> None:
        if self.allowed != (self.rule is None) or (self.rule is not None and self.rule not in REFUSAL_RULES):
            raise ValueError(f"Permission: expected rule None when allowed, else one of {sorted(REFUSAL_RULES)}; "
                             f"received allowed={self.allowed}, rule={self.rule!r}")

    def __bool__(self) -> bool:
        return self.allowed


def _refuse(rule: str, text: str) -> Permission:
    return Permission(False, f"{rule} {text}", rule=rule)


def used_maps(structure: str) -> list[str]:
    """The maps whose recall a result of ``structure`` uses."""
    return ["structure"] + (["f_e", "V_J"] if structure != "stiff" else []) + (["backlash"] if structure in _BACKLASH else [])


def outside_training(result: Any, max_map_distance_ratio: float | None) -> bool:
    """Does the record lie outside what the maps were trained on? With a bound: a used map's
    distance ratio (recall distance over the training 99 % quantile) lies above it; without one,
    or where the result has no ratios: the identifier's own ``quality.outside_training``."""
    ratios = result.quality.map_distance_ratio
    if max_map_distance_ratio is None or not ratios:
        return bool(result.quality.outside_training)
    return any(ratios.get(n, 0.0) > max_map_distance_ratio for n in used_maps(result.structure))


def _unusable_parameter(result: Any) -> Permission | None:
    """V1 (failure, unknown structure) and V2 (a needed parameter missing or not positive)."""
    if not result.ok:
        return _refuse("V1", f"identification failed: {result.error}")
    structure = result.structure
    if structure not in _REQUIRED:
        return _refuse("V1", f"unknown structure {structure!r}: expected one of {tuple(_REQUIRED)}")
    for key in _REQUIRED[structure]:
        v = getattr(result.parameters, key)
        try:
            ok = v is not None and math.isfinite(float(v)) and float(v) > 0
        except (TypeError, ValueError):
            ok = False
        if not ok:
            return _refuse("V2", f"parameter {key} = {v!r} not usable for structure {structure!r}")
    return None


def _invalid_model(validation: ValidationResult | None, max_validation_error: float) -> Permission | None:
    """V3: no validation, a failed one, or a speed error above ``max_validation_error``."""
    if validation is None:
        return _refuse("V3", "the identified model could not be validated by re-simulation")
    if not validation.passed:
        return _refuse("V3", f"validation failed: the identified model does not reproduce the record ({validation.reason})")
    if not math.isfinite(validation.nrmse) or validation.nrmse > max_validation_error:
        return _refuse("V3", f"validation error {validation.nrmse:.3g} above {max_validation_error:g}")
    return None


def may_propose_controller(
    result: IdentificationOutcome,
    validation: ValidationResult | None,
    *,
    warnings: Sequence[CommissioningWarning] = (),
    max_validation_error: float = 0.1,
    max_map_distance_ratio: float | None = None,
    blocking_codes: Collection[str] = BLOCKING_WARNING_CODES,
) -> Permission:
    """Decide whether a speed controller may be proposed from an identification result.

    Args:
        result: the identification (``IdentificationResult``, or a failure with ``ok`` False and ``error``).
        validation: the re-simulation of the identified model (:func:`validate_model`; None: not run).
        warnings: the commissioning's own warnings (test signal, validation).
        max_validation_error: V3's bound on the speed error ``validation.nrmse``.
        max_map_distance_ratio: V4's bound on a used map's distance ratio; None: the identifier's
            own ``quality.outside_training`` (ratio > 1).
        blocking_codes: V6: warning codes (identification's or commissioning's) that refuse.

    Refused (``Permission.rule``) when: V1 the identification failed or its structure is unknown;
    V2 a parameter the structure needs is missing, not finite or not positive (``J_sigma``; plus
    ``V_J``, ``f_e`` for elastic); V3 the validation is missing, failed or its error is above the
    bound; V4 the record lies outside the maps' training data; V6 a warning has a blocking code.
    The other warnings' texts are passed on as ``notes``; the identification's own ``notes`` are
    not read here (they never refuse).
    """
    if not isinstance(getattr(result, "ok", None), bool):
        raise TypeError(f"result: expected an identification result with 'ok', received {type(result).__name__}")
    if validation is not None and not isinstance(validation, ValidationResult):
        raise TypeError(f"validation: expected ValidationResult or None, received {type(validation).__name__}")
    refused = _unusable_parameter(result)
    if refused is None:
        refused = _invalid_model(validation, max_validation_error)
    if refused is not None:  # (a refusal is falsy: no `or` chain here)
        return refused
    if outside_training(result, max_map_distance_ratio):
        bound = 1.0 if max_map_distance_ratio is None else max_map_distance_ratio
        ratios: Mapping[str, float] = result.quality.map_distance_ratio or {}
        listed = ", ".join(f"{k} {v:.2f}" for k, v in ratios.items() if v > bound)
        return _refuse("V4", f"the record lies outside what the maps were trained on "
                             f"(map distance / training 99 % quantile above {bound:g}: {listed})")
    every = [*result.warnings, *warnings]
    for w in every:
        if w.code in blocking_codes:
            return _refuse("V6", f"blocking warning: {w.text}")
    return Permission(True, f"structure {result.structure}, validation error {validation.nrmse:.3g} <= "
                            f"{max_validation_error:g}", tuple(w.text for w in every))
