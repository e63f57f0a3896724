"""The typed identification result, built once by the identifier and never rewritten downstream.

:meth:`IdentificationResult.to_dict` gives exactly the JSON object of SPEC section 9
(``structure``, ``parameters``, ``quality``, ``warnings`` as a list of strings); decisions in code
key on :attr:`IdentWarning.code`, never on the text.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field, fields
from typing import Any, ClassVar

from training.errors import CodedWarning

#: The parameters of SPEC section 9, in output order (SI units; ``backlash`` = total width ``2s``).
PARAMETER_NAMES: tuple[str, ...] = ("J_sigma", "V_J", "J_M", "J_L", "f_e", "C_F", "d", "backlash", "M_FC", "mu_F",
                                     "M_L0", "M_FCM", "mu_FM")

#: The unit of each parameter of :data:`PARAMETER_NAMES` (SI; ``"-"``: dimensionless).
PARAMETER_UNITS: dict[str, str] = {"J_sigma": "kg m^2", "V_J": "-", "J_M": "kg m^2", "J_L": "kg m^2", "f_e": "Hz",
                                   "C_F": "Nm/rad", "d": "-", "backlash": "rad", "M_FC": "Nm", "mu_F": "Nm s/rad",
                                   "M_L0": "Nm", "M_FCM": "Nm", "mu_FM": "Nm s/rad"}


#: Every warning code the identification emits, with what it means.
WARNING_CODES: dict[str, str] = {
    "unlike_training_data": "a map's recall distance lies above the 99 % quantile of held-out training records",
    "oscillation_below_quantum": "the oscillation is below one speed quantum rms: elastic parameters uncertain",
    "refine_partial_fit": "the refined model reproduces only part of the measured oscillation",
    "one_mass_fit_replaced": "STEP 2's one-mass fit was not trusted; J_sigma, M_FC and mu_F come from the whole-record "
                             "fit",
    "one_mass_fit_residual": "STEP 2's one-mass fit leaves a residual above 5 % of the speed: not one mass",
    "one_mass_fit_short_sections": "a test section holds fewer than two periods of the oscillation (STEP 2 unsure)",
    "one_mass_fit_uninformative": "the one-mass model explains little of the data (residual near its rms): its values "
                                  "cannot be trusted",
    "one_mass_fit_collinear": "two regressors of the one-mass fit are nearly collinear (e.g. Coulomb friction and an "
                              "offset when the speed never reverses): those parameters are not determined",
    "drive_value_mismatch": "a drive value of the metadata contradicts the signals; the value the signals show is "
                            "used",
    "drive_value_default": "a drive value is missing from the record; a documented default stands in for it",
    "test_law_mismatch": "the record's sections do not end where SPEC 2's switching law ends them on its own speed "
                         "with its w_max (a clipped or filtered speed, a wrong w_max, another test)",
    "torque_scale_mismatch": "the measured torque holds the test's levels at another scale than M* (K_M, M_star or "
                             "the current's units wrong): inertias and friction scale with it",
    "record_starts_late": "the record starts inside section I, not at rest: the test's first torque step is missing",
    "run_aborted": "the drive aborted the run at a limit (metadata aborted: true)",
    "units_unchecked": "the record gives no value to check a signal's units against (the speed: neither w_max nor an "
                       "encoder_counts it steps in; the torque: neither M_star nor M_max): a unit error would go "
                       "unnoticed",
    "drive_outside_training": "a drive or test value lies outside what the maps were trained on",
    "outside_envelope": "a drive or test value lies outside the drive envelope (docs/contract.md)",
    "answer_outside_envelope": "an identified value lies outside the drive envelope or what the maps were trained on",
    "backlash_below_resolution": "a backlash narrower than the encoder resolves may hide, or its width is "
                                 "uncertain: an upper bound is given",
    "backlash_from_angle": "the backlash shows in the motor's angle, not in the fit of its speed (a coarse "
                           "encoder, or a gap crossed in a sample or two): structure and width rest on the angle",
    "class_undecided": "the refinement's class fits the record no better than the maps' one (within the record's "
                       "noise): the maps' answer stands, the other class is about as likely",
    "class_near_threshold": "a quantity of the class rule lies near its threshold: the neighbouring class is about "
                            "as likely",
    "implausible_output": "an identified value the record cannot support (above Nyquist or the current loop's "
                          "bandwidth, wider than the travel, off the one-mass fit)",
    "impossible_output": "an identified value no mechanic can have; it is not reported",
    "likely_wrong": "the calibrated probability that the answer is right (class right, elastic values within 30 %, "
                    "J_sigma within 30 %) is low: distrust it, or test again with a larger M* or a finer encoder",
}

#: The codes that say only how uncertain an answer is: with a calibration (SPEC 4.1) they are the
#: answer's ``notes``, not its warnings; the interval and the probabilities carry the uncertainty,
#: and ``likely_wrong`` warns where the answer is likely wrong.
NOTE_CODES: frozenset[str] = frozenset({
    "unlike_training_data", "oscillation_below_quantum", "refine_partial_fit", "one_mass_fit_replaced",
    "one_mass_fit_residual", "one_mass_fit_short_sections", "one_mass_fit_uninformative", "backlash_below_resolution",
    "backlash_from_angle", "class_undecided", "class_near_threshold", "answer_outside_envelope", "implausible_output"})

#: The parameters that carry a 90 % interval (SPEC 4.1), in output order.
INTERVAL_NAMES: tuple[str, ...] = PARAMETER_NAMES


@dataclass(frozen=True)
class IdentWarning(CodedWarning):
    """A warning of the identification (``code`` one of :data:`WARNING_CODES`)."""

    CODES: ClassVar[Mapping[str, str]] = WARNING_CODES


@dataclass(frozen=True)
class Parameters:
    """Identified parameters in SI units; ``None`` where not identified (e.g. ``f_e`` of a stiff mechanic).
    ``M_FC``, ``mu_F``: the load's friction; ``M_L0``: the constant load torque, ``M_FCM``, ``mu_FM``:
    the motor's friction (SPEC 1.1)."""

    J_sigma: float | None = None
    V_J: float | None = None
    J_M: float | None = None
    J_L: float | None = None
    f_e: float | None = None
    C_F: float | None = None
    d: float | None = None
    backlash: float | None = None
    M_FC: float | None = None
    mu_F: float | None = None
    M_L0: float | None = None
    M_FCM: float | None = None
    mu_FM: float | None = None

    def to_dict(self) -> dict[str, float | None]:
        return {n: getattr(self, n) for n in PARAMETER_NAMES}


@dataclass(frozen=True)
class Intervals:
    """The 90 % interval ``(low, high)`` [SI] of every parameter of :data:`INTERVAL_NAMES` (SPEC 4.1),
    calibrated on held-out simulated records (``docs/identification.md``, "Confidence"). A
    parameter the record cannot show has the interval it can support (a backlash below the
    resolution: ``(0, bound)``; a stiff answer's ``f_e``: from the class's lower bound up; a load
    torque not detected: at least +- the detection's threshold, ``_policy.load_torque_threshold``)."""

    J_sigma: tuple[float, float]
    V_J: tuple[float, float]
    J_M: tuple[float, float]
    J_L: tuple[float, float]
    f_e: tuple[float, float]
    C_F: tuple[float, float]
    d: tuple[float, float]
    backlash: tuple[float, float]
    M_FC: tuple[float, float]
    mu_F: tuple[float, float]
    M_L0: tuple[float, float]
    M_FCM: tuple[float, float]
    mu_FM: tuple[float, float]

    def __getitem__(self, name: str) -> tuple[float, float]:
        if name not in INTERVAL_NAMES:
            raise KeyError(f"interval: expected one of {list(INTERVAL_NAMES)}, received {name!r}")
        return getattr(self, name)

    def to_dict(self) -> dict[str, list[float]]:
        return {n: list(getattr(self, n)) for n in INTERVAL_NAMES}


@dataclass(frozen=True)
class Quality:
    """Figures that say how far to trust a result (``docs/identification.md``). The refinement's
    figures are ``None`` where it did not run, and then absent from :meth:`to_dict`."""

    structure_probabilities: dict[str, float]  # class -> the structure map's probability
    map_distance_ratio: dict[str, float]  # map -> recall distance over its training 99 % quantile
    osc_quanta: float  # rms of the oscillation in speed quanta (below 1: elastic values uncertain)
    oscillation_fit_r2: float  # R^2 of the eq.-1 oscillation fit
    one_mass_rel_residual: float  # STEP 2's residual over the speed's rms
    outside_training: bool  # a map the answer rests on lies beyond its 99 % quantile, or the drive beyond its training
    section_flags: tuple[str, ...]  # the section detection's notes
    maps_estimate: dict[str, float]  # f_e, V_J, d, s_N as the maps said them
    outside_envelope: dict[str, dict[str, Any]]  # quantity -> value, trained and envelope ranges, which it leaves
    maps_structure: str | None = None  # the maps' class (the refined values decide the structure)
    refine_residual: float | None = None  # refined model's detrended speed error over the oscillation
    refine_start_residual: float | None = None  # the same for the maps' answer
    refined_s_N: float | None = None  # the refined normalized backlash
    angle_ratio: float | None = None  # where the angle showed a gap: its angle error over the best gapless model's
    backlash_upper_bound: float | None = None  # [rad] the widest backlash the record cannot show, where it matters
    stiff_mode_Hz: float | None = None  # [Hz] a stiff answer: the mode its record still shows (the oscillation fit's)
    stiff_mode_note: str | None = None  # why that mode does not make the answer elastic, in words
    answer_probability: float | None = None  # calibrated P(answer right: class, E_30, J_sigma 30 %); None uncalibrated

    def to_dict(self) -> dict[str, Any]:
        out: dict[str, Any] = {}
        for f in fields(self):
            v = getattr(self, f.name)
            if v is None and f.default is None:
                continue
            out[f.name] = list(v) if isinstance(v, tuple) else v
        return out


@dataclass(frozen=True)
class IdentificationResult:
    """One identified record: ``structure`` (a class of ``sim.STRUCTURE_CLASSES``), ``parameters``,
    ``quality``, ``warnings`` (what the user must act on), ``intervals`` (90 %, SPEC 4.1; ``None``
    where the maps carry no calibration) and ``notes`` (coded remarks on the uncertainty that the
    intervals and probabilities already carry); ``record`` names its file where it came from one."""

    structure: str
    parameters: Parameters
    quality: Quality
    warnings: tuple[IdentWarning, ...] = ()
    record: str | None = None
    intervals: Intervals | None = None
    notes: tuple[IdentWarning, ...] = ()
    #: what the calibration read of the answer (``training.identification._confidence``; not in the JSON)
    confidence: Any = field(default=None, repr=False, compare=False)

    @property
    def ok(self) -> bool:
        return True

    def has_warning(self, code: str) -> bool:
        if code not in WARNING_CODES:
            raise ValueError(f"code: expected one of {sorted(WARNING_CODES)}, received {code!r}")
        return any(w.code == code for w in self.warnings)

    def has_note(self, code: str) -> bool:
        """Whether ``code`` is among the warnings or the notes (an uncertainty remark of :data:`NOTE_CODES`)."""
        return self.has_warning(code) or any(w.code == code for w in self.notes)

    def to_dict(self) -> dict[str, Any]:
        """The JSON object of SPEC section 9 (with ``record`` first where known)."""
        out: dict[str, Any] = {} if self.record is None else {"record": self.record}
        out.update(structure=self.structure, parameters=self.parameters.to_dict())
        if self.intervals is not None:
            out["intervals"] = self.intervals.to_dict()
        out.update(quality=self.quality.to_dict(), warnings=[w.text for w in self.warnings],
                   notes=[w.text for w in self.notes])
        return out


@dataclass(frozen=True)
class IdentificationFailure:
    """A record that could not be identified: ``error`` is the one-line reason."""

    error: str
    record: str | None = None

    @property
    def ok(self) -> bool:
        return False

    def to_dict(self) -> dict[str, Any]:
        return ({} if self.record is None else {"record": self.record}) | {"error": self.error}


Outcome = IdentificationResult | IdentificationFailure
