"""From one record to everything the maps need: sections, one-mass fit (STEP 2), named features.

:func:`analyze` is the single place where a record becomes numbers, so that training data and
identification can never disagree on the feature definition (``FEATURE_VERSION``).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, replace
from typing import Any

import numpy as np
from scipy.signal import lfilter

from sim import SECTION_LEVELS, Record
from sim.records import as_record
from training.errors import IdentificationError, one_line
from training.identification._consistency import consistency_warnings, torque_scale_hint
from training.identification._drive import REFERENCE_DRIVE, DriveValues, drive_values
from training.identification._features import (EIG_NAMES, EXTRA_NAMES, STRUCT_NAMES, ExtraColumn,
                                               eigenfrequency_features, extra_features, structure_and_peaks)
from training.identification._one_mass import OneMassFit, fit_one_mass
from training.identification._oscillation import fit_oscillation
from training.identification._plausibility import check_record, resolution_hint, unit_warnings
from training.identification._result import IdentWarning
from training.identification._sections import SectionSplit, detect_sections

#: Version of the whole feature vector below; stored in checkpoints and checked at recall.
FEATURE_VERSION = "twomass-features-v3"

#: The record's drive and test in the units of the oscillation and of the test itself (all
#: dimensionless, so that one map serves every drive of SPEC 3.1's envelope): the fitted
#: oscillation's frequency ``f_fit`` times the sample time ``T_s`` (Nyquist at 0.5), times
#: ``2 pi T_Ei`` (the current loop's lag) and times the test's time scale ``tau = J_sigma w_max /
#: M*`` (periods per time scale); ``w_max`` in speed quanta ``q_w``; the measured torque's noise
#: over ``M*``. Without a fitted oscillation (``f_fit = 0``) the three ``f_fit`` ratios read
#: :data:`NO_FREQUENCY`.
CONTEXT_NAMES: tuple[str, ...] = ("log10_f_T_s", "log10_w_T_Ei", "log10_f_tau", "log10_w_max_quanta", "log10_noise")
NO_FREQUENCY = -6.0

#: The gap crossing, seen in the motor's angle (which a coarse encoder resolves far better than
#: its speed): while the motor crosses a backlash alone after the torque reverses (sections III and
#: VI), it runs ahead of the one-mass motion by ``2s J_L / J_sigma`` of angle, then the load takes
#: it along at the one-mass speed (momentum). ``log10_gap_lead``: that lead (the extreme of the
#: integrated ``w_osc`` in the torque's direction over the first half of III and VI, mean of the
#: two) over the test's angle scale ``w_max tau``; ``log10_q_phi_rel``: one encoder count over
#: the same scale (how much of the lead the record can resolve).
GAP_NAMES: tuple[str, ...] = ("log10_gap_lead", "log10_q_phi_rel")
_GAP_FLOOR = 1e-9  # lead over the angle scale below which the log reads the floor

#: The oscillation's own features: its rms over the speed quantum and the eq.-1 fit's frequency,
#: ``V_J`` (both log10), damping and ``r^2`` (:func:`training.identification._oscillation.fit_oscillation`).
OSCILLATION_NAMES: tuple[str, ...] = ("log10_osc_quanta", "log10_f_fit", "log10_V_J_fit", "d_fit", "r2_fit")

#: Names of the feature vector's components, in order.
FEATURE_NAMES: tuple[str, ...] = (
    EIG_NAMES + STRUCT_NAMES + EXTRA_NAMES + OSCILLATION_NAMES + CONTEXT_NAMES + GAP_NAMES
)
#: Each feature's column in the feature vector, by name.
FEATURE_INDEX: dict[str, int] = {name: column for column, name in enumerate(FEATURE_NAMES)}


def feature_columns(names: Sequence[str]) -> list[int]:
    """The feature vector's columns of the features ``names``, in their order."""
    return [FEATURE_INDEX[name] for name in names]


__all__ = ["FEATURE_VERSION", "FEATURE_NAMES", "FEATURE_INDEX", "feature_columns", "REFERENCE_DRIVE", "Analysis", "analyze"]


class _FromDrive:
    """A drive value of an :class:`Analysis`: the attribute of the same name of its ``drive``."""

    def __set_name__(self, owner: type, name: str) -> None:
        self.name = name

    def __get__(self, obj: Any, owner: type | None = None) -> Any:
        return self if obj is None else getattr(obj.drive, self.name)


@dataclass(frozen=True)
class Analysis:
    """One record, analysed.

    ``features``: ``(F,)`` float64 in the order of :data:`FEATURE_NAMES`.
    ``fit``: the STEP 2 one-mass fit (``J_sigma``, ``M_FC``, ``mu_F``, ``M_0``, ``w_osc``).
    ``drive``: the drive and test values (SPEC 3: from the record, else estimated or defaulted;
    :mod:`training.identification._drive`); ``M_star``, ``T_s``, ``T_Ei``, ``encoder_counts``,
    ``M_N``, ``q_w`` read from it.
    ``osc_quanta``: rms of ``w_osc`` over the speed quantum :attr:`q_w` (how visible the oscillation is).
    ``warnings``: STEP 2's and the drive values' (coded); ``section_flags``: the section detection's notes.
    """

    sections: SectionSplit
    fit: OneMassFit
    features: np.ndarray
    drive: DriveValues
    osc_quanta: float
    warnings: tuple[IdentWarning, ...] = ()
    section_flags: tuple[str, ...] = ()

    M_star, T_s, T_Ei, encoder_counts, M_N, q_w = (_FromDrive() for _ in range(6))  # read from ``drive``

    def feature(self, name: str) -> float:
        return float(self.features[FEATURE_INDEX[name]])

    @property
    def M_L0(self) -> float:
        """The constant load torque [Nm] (SPEC 1.1): the holding torque the levels ran around plus
        STEP 2's constant torque ``M_0`` over them."""
        return self.drive.M_hold + self.fit.M_0


def analyze(record: Record) -> Analysis:
    """Sections, one-mass fit and features of one record (a validated copy of it: columns may be
    numpy arrays, torch tensors or sequences; ``T_s`` may be left to the ``t`` column).

    Raises:
        TypeError: ``record`` is no ``sim.Record``.
        IdentificationError: one line, when the record cannot be analysed (implausible units,
            no recognisable test run, more than one run or an incomplete one, an uninformative
            one-mass fit, a missing ``K_M``).
    """
    try:
        return _analyze(as_record(record))
    except IdentificationError:
        raise
    except ValueError as err:  # RecordError, plausibility, sections, fit
        raise IdentificationError(one_line(err)) from err


def _context(f_fit: float, J_sigma: float, drive: DriveValues) -> list[float]:
    """The :data:`CONTEXT_NAMES` features of a record whose oscillation fit found ``f_fit`` [Hz]."""
    tau = drive.time_scale(abs(J_sigma))
    per = ([math.log10(f_fit * drive.T_s), math.log10(2.0 * math.pi * f_fit * drive.T_Ei),
            math.log10(max(f_fit * tau, 1e-6))] if f_fit > 0 else [NO_FREQUENCY] * 3)
    return per + [math.log10(max(drive.w_max / drive.q_w, 1e-3)),
                  math.log10(max(drive.current_noise / drive.M_star, 1e-6))]


def _gap(w_osc: np.ndarray, split: SectionSplit, T_s: float, J_sigma: float, drive: DriveValues) -> list[float]:
    """The :data:`GAP_NAMES` features of a record."""
    angle_scale = drive.w_max * drive.time_scale(abs(J_sigma))  # [rad]
    leads = []
    for k in (2, 5):  # III and VI: the torque reverses against the motion
        a, b = (int(v) for v in split.bounds[k])
        half = w_osc[a:a + max(1, (b - a) // 2)]
        leads.append(max(0.0, float(np.max(np.sign(split.levels[k]) * np.cumsum(half))) * T_s))
    return [math.log10(max(float(np.mean(leads)) / angle_scale, _GAP_FLOOR)),
            math.log10(max(drive.q_phi / angle_scale, _GAP_FLOOR))]


#: The measured torque's noise, integrated over the longest section by the one-mass fit, may shift
#: the speed by this many speed quanta before the fit runs on the applied torque instead
#: (:func:`applied_torque`): above it the noise would read as an oscillation in ``w_osc``.
NOISE_QUANTA = 0.5


def applied_torque(record: Record, split: SectionSplit, T_Ei: float) -> np.ndarray:
    """The torque the motor applies, without the measurement's noise: the test's reference through
    SPEC 1's current loop, a first-order lag ``T_Ei`` with the reference held over each sample:
    ``M[k] = a M[k-1] + (1 - a) M_ref[k-1]``, ``a = exp(-T_s / T_Ei)``. The reference is the
    record's ``torque_ref``, else SPEC 2's levels ``x M*`` over the sections (0 at the first
    sample: the test starts from rest). ``(N,)`` [Nm]."""
    n = record.speed.size
    if record.torque_ref is not None:
        ref = np.asarray(record.torque_ref, dtype=np.float64)
    else:
        ref = np.zeros(n)
        for (lo, hi), level in zip(split.bounds.tolist(), SECTION_LEVELS):
            ref[max(lo, 1):hi] = level * split.M_star
    a = math.exp(-record.T_s / T_Ei)
    return lfilter([0.0, 1.0 - a], [1.0, -a], ref)


def around_hold(record: Record) -> Record:
    """A held axis's record (SPEC 1.1: metadata ``M_hold`` [Nm], the levels ran around it) as SPEC 2's
    test: its torque (or current) and ``torque_ref`` less the holding torque; any other record itself.
    The analysis reads this view (its one-mass offset ``M_0`` is then ``M_L0 - M_hold``)."""
    M_hold = record.meta.get("M_hold")
    K_M = record.meta.get("K_M")
    if not M_hold or (record.torque is None and not K_M):  # (a current without K_M is refused later)
        return record
    shifted = {"torque": record.torque - M_hold} if record.torque is not None else {
        "current": record.current - M_hold / K_M}
    ref = None if record.torque_ref is None else record.torque_ref - M_hold
    return replace(record, torque_ref=ref, **shifted)


def _test_length_hint(split: SectionSplit, T_s: float) -> str:
    """What the test's length says of the mechanics it can show: section I lasts about the test's
    time scale ``tau = J_sigma w_max / M*``, and a mechanic below ``0.5 / tau`` hardly moves its
    load in that time (``docs/identification.md``, Known gaps: tests shorter than the period)."""
    tau = float(split.bounds[0, 1] - split.bounds[0, 0]) * T_s
    return (f"section I lasted {tau * 1e3:.3g} ms, so a mechanic below {0.5 / tau:.3g} Hz hardly moves its load during "
            "the test; a larger w_max or a lower M* lengthens it")


def _analyze(record: Record) -> Analysis:
    record = around_hold(record)
    check_record(record)  # units and metadata against the signals
    T_s = record.T_s
    torque = record.motor_torque
    try:
        split = detect_sections(record)
    except ValueError as err:
        hint = resolution_hint(record) or torque_scale_hint(record)
        if hint is None:
            raise
        raise ValueError(f"{err}; {hint}") from err
    drive, drive_warnings = drive_values(record, split, torque)
    drive_warnings += consistency_warnings(record, split, drive, torque) + unit_warnings(record)
    try:
        fit = fit_one_mass(torque, record.speed, T_s, sections=split.bounds)
    except ValueError as err:
        raise ValueError(f"{err}; {_test_length_hint(split, T_s)}") from err
    longest = int(np.max(split.bounds[:, 1] - split.bounds[:, 0]))
    if drive.current_noise * T_s * math.sqrt(longest) > NOISE_QUANTA * drive.q_w * abs(fit.J_sigma):
        torque = applied_torque(record, split, drive.T_Ei)
        fit = fit_one_mass(torque, record.speed, T_s, sections=split.bounds)
    w_osc = fit.w_osc
    eig = eigenfrequency_features(w_osc, T_s, split.bounds)
    struct, peaks = structure_and_peaks(w_osc, T_s, split.bounds)
    steps = np.diff(np.r_[0.0, split.levels])  # torque step at each section start [Nm]
    extra = extra_features(w_osc, T_s, split.bounds, J_sigma=fit.J_sigma, torque_steps=steps,
                           speed_span=float(np.ptp(record.speed)), structure=struct, peaks=peaks)
    q_w = drive.q_w
    sel = np.concatenate([w_osc[a:b] for a, b in split.bounds.tolist()])
    osc_quanta = float(np.sqrt(np.mean(sel * sel))) / q_w if sel.size else 0.0
    log10_f_peak = extra[ExtraColumn.log10_f_peak]
    osc = fit_oscillation(torque, w_osc, split.bounds, T_s, 10.0 ** log10_f_peak if log10_f_peak else 0.0)
    V_J_fit = osc.gain * fit.J_sigma  # eq. 1: gain = V_J / J_sigma
    oscillation = {"log10_osc_quanta": math.log10(max(osc_quanta, 1e-3)),
                   "log10_f_fit": math.log10(osc.f_0) if osc.f_0 > 0 else 0.0,
                   "log10_V_J_fit": math.log10(V_J_fit) if V_J_fit > 1e-3 else -3.0,
                   "d_fit": osc.d, "r2_fit": osc.r2}
    features = np.concatenate([eig, struct, extra, [oscillation[name] for name in OSCILLATION_NAMES],
                               _context(osc.f_0, fit.J_sigma, drive), _gap(w_osc, split, T_s, fit.J_sigma, drive)])
    return Analysis(sections=split, fit=fit, features=features, drive=drive, osc_quanta=osc_quanta,
                    warnings=fit.warnings + tuple(drive_warnings), section_flags=split.flags)
