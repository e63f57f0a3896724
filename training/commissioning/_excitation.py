"""Test-signal adaptation (knowledge base, SPEC 8): choose ``M_star`` and ``w_max`` for STEP 1.

Start small, run the six-section test through the drive (``drive.run_test``, SPEC 8.1), judge from
the returned record only (measured motor speed, the drive's own torque reference and section
counter, the timeout flags; no truth) whether it is informative, and raise ``M_star`` and/or
``w_max`` by factor-2 steps until it is, never beyond the user's limits (:class:`sim.DriveLimits`:
torque ``M_max``, speed ``w_max``, travel ``travel``). The travel and the peak speed of the next run
are predicted from the current one before it runs (travel ~ ``w_max^2 J / M_star``), so a step that
would cross a limit is shortened first; a run the drive stopped at a limit is never accepted (E8).
Rules in docs/commissioning.md:

* E1 :func:`first_plan`: the first run, small;
* E2 :class:`Deficits`: what a run lacks to be informative;
* E9 :class:`Headroom`, :func:`guarded_limits`: the limits handed to the drive for each run;
* E3-E8, E10, in the order :data:`EXCITATION_RULES` applies them to each run
  (:func:`judge_run`): the first that settles the run (stop, accept, or run again) ends the pass.

Measured figures per run (:class:`RunFigures`, all from the response):

* ``samples_min``: fewest samples in any of the six sections (STEP 2 needs ``>= min_section_samples``),
* ``timed_out``: a section ended by its safety timeout (not by its speed condition),
* ``range_quanta``: speed range ``max - min`` over the speed quantum ``q_w``,
* ``osc_quanta``: RMS of the speed minus a per-section quadratic fit (the oscillating part), in ``q_w``,
* ``peak_speed`` [rad/s], ``travel`` [rad] (largest ``|phi|`` of the integrated measured speed),
  ``peak_torque_ref`` [Nm], ``peak_torque`` [Nm] (measured current x ``K_M``),
* ``aborted``: the drive stopped the run at a limit (rule E8: never accepted, ``w_max`` halved),
* ``f_osc`` [Hz]: the dominant frequency of the oscillating part (summed power spectra of the
  sections), ``longest_section`` [s] (for the fallback F1's eigenfrequency band),
* ``accel`` [rad/s^2]: the larger mean acceleration of sections I and IV (``M*`` over it is a
  one-mass inertia that friction only makes larger; for the headroom after a stop and F1),
* ``along_torque_quanta``: the speed gained in the direction of the torque reference [``q_w``]
  (negative: against it; E10).

Headroom (E9): the drive stops at its limit and the plant runs on: each run hands the drive the
user's limits less the speed a run can gain after the stop (:func:`stop_headroom`, from ``accel``
and the overshoot beyond ``w_max`` measured so far; the first run, before anything is known, a
share ``first_headroom`` of the speed limit), and plans inside those.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field, fields, replace
from typing import Any

import numpy as np

import sim
from training._settings import FLAG, NON_NEGATIVE, POSITIVE, SHARE, Interval, check_settings
from training.errors import CommissioningError, LimitsTooTight

from ._guard import record_peaks

#: How the test-signal adaptation ended (:attr:`ExcitationResult.code`).
EXCITATION_ENDS: dict[str, str] = {
    "informative": "the response is informative (E7)",
    "limits_reached": "no rule can change anything within the limits (E7)",
    "max_iterations": "no informative response after max_iterations runs (E7)",
    "run_repeated": "a stopped run repeated the previous stopped run's peak speed and travel (E8b)",
    "speed_against_torque": "the speed moved against the torque reference: motor or encoder sign reversed (E10)",
    "limit_passed": "a run's record showed one of the user's limits passed: no further run (SPEC 8.2)",
}

#: :attr:`RuleDecision.verdict` of a run that is not the last: run again with the decided plan.
RUN_AGAIN = "run_again"

__all__ = ["EXCITATION_ENDS", "EXCITATION_RULES", "ExcitationRules", "ExcitationResult", "RunFigures", "RunPlan", "Deficits",
           "Headroom", "ExcitationRun", "RuleDecision", "measure_run", "measure_response", "first_plan", "judge_run",
           "adapt_test_signal", "stop_headroom", "guarded_limits", "RigidFit", "rigid_fit", "rigid_travel", "trusted_J",
           "trusted_inertia", "informative_limits", "check_limits", "ProbeBasis", "ProbeOutlook", "plan_probe", "PROBED_ENDS"]


@dataclass(frozen=True)
class ExcitationRules:
    """The test-signal rules' settings (docs/commissioning.md, E0-E13); checked on construction."""

    M_star_start: float = 0.1
    """E1: the first ``M_star`` as a share of the torque cap (small: the plant is unknown)."""
    w_max_start: float = 5.0
    """E1: the first ``w_max`` [rad/s] at most."""
    first_speed_share: float = 0.1
    """E1: the first ``w_max`` at most this share of the user's speed limit."""
    J_prior_max: float = 1.0
    """E1: the largest inertia [kg m^2] assumed before the first run bounds its travel."""
    first_travel_share: float = 0.25
    """E1: the first run's predicted travel may use this share of the usable travel."""
    first_travel_factor: float = 3.0
    """E1: the first run's travel taken as this many times ``w_max^2 J / M_star`` (sections II-VI)."""
    factor: float = 2.0
    """E3-E8: the raise (and lowering) step of ``M_star`` and ``w_max``."""
    min_section_samples: int = 40
    """E2: fewest samples per section that STEP 2 can fit."""
    min_range_quanta: float = 400.0
    """E2: smallest speed range [speed quanta] that resolves the response."""
    min_osc_quanta: float = 2.0
    """E2: smallest RMS oscillation [speed quanta] that counts as visible."""
    speed_margin: float = 0.9
    """E6: share of the speed limit (less the headroom) a predicted peak may use."""
    travel_margin: float = 0.8
    """E1, E6: share of the travel handed to the drive a predicted run may use."""
    max_iterations: int = 10
    """E7: most test runs."""
    coast_factor: float = 2.0
    """E9: the speed gained after a stop counted this many times (a slower current loop, friction)."""
    swing_allowance: float = 1.0
    """E6: the next peak planned at ``w_max' (1 + swing_allowance)`` at least: a soft mode swings the
    load on after section I by far more than the short runs before showed."""
    overshoot_weight: float = 2.0
    """E6: the overshoot beyond ``w_max`` counted this many times (it depends on the phase at the
    switch, not only on ``M_star``)."""
    min_raise_exponent: float = 0.1
    """E6c: a raise of ``w_max`` below ``factor^min_raise_exponent`` is no progress."""
    lower_torque_exponent: float = 0.5
    """E4b: less torque when the limits keep ``w_max`` below ``factor^lower_torque_exponent`` of this run's."""
    stopped_ceiling_exponent: float = 0.5
    """E8: no later run above ``factor^-stopped_ceiling_exponent`` of a stopped one's ``M_star`` and ``w_max``."""
    delay_allowance: int = 1
    """E9: samples of dead time the drive may have beyond its own two."""
    first_headroom: float = 0.25
    """E9: the first run's headroom as a share of the speed limit (nothing measured yet)."""
    max_guard_share: float = 0.5
    """E9: the headroom takes at most this share of the speed limit, the stop's run-on at most this
    share of the travel limit."""
    against_quanta: float = 10.0
    """E10: stop when the speed moves against the torque reference by more than this [speed quanta]."""
    torque_on_share: float = 0.5
    """E10: the samples whose torque reference is at least this share of its peak are summed."""
    repeat_tolerance: float = 0.02
    """E8b: stop when a stopped run's peak speed and travel repeat the previous stopped run's within this share."""
    change_tolerance: float = 1e-9
    """E7: a relative change of ``M_star`` and ``w_max`` at most this is none (the limits are reached)."""
    fit_min_samples: int = 8
    """E2: sections with fewer samples are left out of the oscillating part (no quadratic fit)."""
    spectrum_padding: int = 4
    """E2: the sections' spectra are zero-padded to this many times the longest (``f_osc``'s grid)."""
    refuse_uninformative_limits: bool = True
    """E0: before the first run, refuse limits that no informative test fits within (:func:`check_limits`)."""
    min_travel_factor: float = 0.7
    """E0: the smallest informative test's travel over ``w T`` (speed ``w``, section ``T``): section I
    accelerating evenly (0.5) and section II above ``0.2 w`` (0.2)."""
    max_probes: int = 3
    """E11: most long-section probes after the rules ended without an informative response."""
    slowest_f_e: float = 5.0
    """E11: the envelope's lowest eigenfrequency [Hz]: a probe's sections aim at ``probe_periods`` of it."""
    probe_periods: float = 2.0
    """E11: a probe's section I aims at this many periods of ``slowest_f_e`` (no longer: less travel)."""
    V_J_max: float = 5.0
    """E11: the envelope's largest inertia ratio: ``J_sigma <= (1 + V_J_max) J_M``, and a run from rest
    shows at least ``J_M`` in section I (``M_star`` over its mean acceleration)."""
    probe_range_margin: float = 1.25
    """E11: a probe's ``w_max`` gives this many times the speed range E2 needs (``min_range_quanta``)."""
    probe_untrusted_share: float = 0.5
    """E11: the share of the drive's travel a probe planned on the envelope's inertia bound may use
    (its friction is unknown: the rigid travel holds up to ``rigid_friction_share``)."""
    rigid_friction_share: float = 0.5
    """E11: the rigid six-section travel ``2.21 w^2 J / M_star`` bounds the travel for Coulomb friction
    up to this share of ``M_star``; a probe planned without a friction estimate stays above twice it."""
    trust_margin: float = 0.25
    """E11: a probe planned on a trusted inertia counts it this much larger."""
    trust_max_residual: float = 0.35
    """Trusted inertia: the rigid-body fit's speed residual (RMS over the speed's RMS) at most this."""
    trust_min_periods: float = 2.5
    """Trusted inertia: the record spans at least this many periods of the fit residual's dominant
    frequency (a slow mode the run did not complete leaves a residual of about one period)."""
    trust_exact_residual: float = 0.03
    """Trusted inertia: a fit this close explains the speed whatever the residual's frequency."""
    probe_max_residual: float = 0.8
    """E11: a probe may be planned on the rigid-body fit's inertia up to this residual (a large
    visible oscillation) ..."""
    probe_min_periods: float = 2.0
    """E11: ... and where the record spans this many periods of the residual's dominant frequency (a
    mode the run did not complete leaves about one)."""
    min_time_scale: float = 0.02
    """E12: the envelope's shortest test time scale ``J_sigma w_max / M_star`` [s] (what the maps were
    trained on): an informative run below it on a trusted inertia gets one probe inside it."""
    time_scale_margin: float = 1.15
    """E12: that probe aims at this many times ``min_time_scale`` (room for the identified inertia's
    difference from the rigid-body fit's, a few %; more would cost torque, and a probe at less torque
    may no longer show the oscillation)."""
    probe_min_lengthening: float = 1.2
    """E11: a probe must make section I at least this many times longer than the run it is planned from."""
    max_friction_share: float = sim.EnvelopeRanges().M_FC[1]
    """E13: the envelope's largest Coulomb friction over ``M_star`` (what the maps were trained on): an
    informative run whose rigid-body friction lies above it gets one probe at more torque."""
    friction_share_margin: float = 0.8
    """E13: that probe aims at this share of ``max_friction_share`` (room for the rigid-body fit's
    friction against the identified one)."""

    def __post_init__(self) -> None:
        check_settings(self, _RULE_INTERVALS, CommissioningError)


_RULE_INTERVALS: dict[str, Interval] = {
    "M_star_start": SHARE, "w_max_start": POSITIVE, "first_speed_share": SHARE, "J_prior_max": POSITIVE,
    "first_travel_share": SHARE, "first_travel_factor": POSITIVE, "factor": Interval(1.0, open_low=True),
    "min_section_samples": Interval(1, integer=True), "min_range_quanta": NON_NEGATIVE, "min_osc_quanta": NON_NEGATIVE,
    "speed_margin": SHARE, "travel_margin": SHARE, "max_iterations": Interval(1, integer=True), "coast_factor": NON_NEGATIVE,
    "swing_allowance": NON_NEGATIVE, "overshoot_weight": NON_NEGATIVE, "min_raise_exponent": NON_NEGATIVE,
    "lower_torque_exponent": NON_NEGATIVE, "stopped_ceiling_exponent": NON_NEGATIVE,
    "delay_allowance": Interval(0, integer=True), "first_headroom": Interval(0.0, 1.0), "max_guard_share": SHARE,
    "against_quanta": NON_NEGATIVE, "torque_on_share": SHARE, "repeat_tolerance": NON_NEGATIVE,
    "change_tolerance": NON_NEGATIVE, "fit_min_samples": Interval(3, integer=True), "spectrum_padding": Interval(1, integer=True),
    "refuse_uninformative_limits": FLAG, "min_travel_factor": NON_NEGATIVE, "max_probes": Interval(0, integer=True),
    "slowest_f_e": POSITIVE, "probe_periods": POSITIVE, "V_J_max": NON_NEGATIVE, "probe_range_margin": Interval(1.0),
    "probe_untrusted_share": SHARE, "rigid_friction_share": Interval(0.0, 0.5), "trust_margin": NON_NEGATIVE,
    "trust_max_residual": NON_NEGATIVE, "trust_min_periods": NON_NEGATIVE, "trust_exact_residual": NON_NEGATIVE,
    "probe_max_residual": NON_NEGATIVE, "probe_min_periods": NON_NEGATIVE, "min_time_scale": NON_NEGATIVE,
    "time_scale_margin": Interval(1.0), "probe_min_lengthening": Interval(1.0, open_low=True),
    "max_friction_share": POSITIVE, "friction_share_margin": Interval(0.0, 1.0, open_low=True),
}


@dataclass
class ExcitationResult:
    """``record``: the last test record that the drive did not stop (else the last one); ``records``:
    every test record;
    ``log``: one dict per run (``iteration, M_star, w_max, stop_at``, the measured figures of
    :class:`RunFigures`, ``predicted_peak_speed, predicted_travel`` where E6 planned a next run,
    ``decision``, ``reason``); ``informative``: the final run passed."""

    record: Any
    records: list[Any] = field(default_factory=list)
    log: list[dict[str, Any]] = field(default_factory=list)
    informative: bool = False
    reason: str = ""
    code: str = ""
    """How the adaptation ended: a key of :data:`EXCITATION_ENDS`."""
    probes: list[dict[str, Any]] = field(default_factory=list)
    """The log entries of the E11 probes whose records are not used (not informative); an informative
    probe's entry ends ``log``."""
    needed: dict[str, float] = field(default_factory=dict)
    """Where no informative test fitted: the limits to raise (``"w_max"`` [rad/s], ``"travel"`` [rad])
    and the smallest value that lets one fit."""
    replaced: Any = None
    """The informative run's record that an E12/E13 probe replaced as ``record`` (None: no such probe);
    the chain identifies both and keeps the answer more likely right."""


# --------------------------------------------------------------------------- measuring one run


@dataclass(frozen=True)
class RunFigures:
    """The measured figures of one test run (module docstring); from the record alone, no truth."""

    along_torque_quanta: float
    samples_per_section: tuple[int, ...]
    samples_min: int
    timed_out: bool
    aborted: bool
    range_quanta: float
    osc_quanta: float
    f_osc: float
    longest_section: float
    accel: float
    peak_speed: float
    travel: float
    peak_torque_ref: float
    peak_torque: float
    duration: float
    accel_first: float = 0.0
    """Section I's mean acceleration [rad/s^2] (from rest: ``M_star`` over it is at least ``J_M``)."""
    rigid_J: float = 0.0
    """The rigid-body fit's inertia [kg m^2] (:class:`RigidFit`; 0: no fit)."""
    rigid_M_F: float = 0.0
    """The rigid-body fit's Coulomb friction [Nm]."""
    rigid_residual: float = 1.0
    """The rigid-body fit's speed residual, RMS over the speed's RMS (1: nothing explained)."""
    rigid_periods: float = 0.0
    """How many periods of the residual's dominant frequency the record spans."""

    def as_dict(self) -> dict[str, Any]:
        """The figures as the keys of a log entry (``samples_per_section`` a list)."""
        out = {f.name: getattr(self, f.name) for f in fields(self)}
        out["samples_per_section"] = list(self.samples_per_section)
        return out


def _dominant_frequency(resid: list[np.ndarray], T_s: float, padding: int) -> float:
    """The frequency [Hz] of the largest summed power of the sections' oscillating parts (each
    zero-padded to one length; 0 when there is nothing to analyse)."""
    if not resid:
        return 0.0
    n = 1 << int(math.ceil(math.log2(max(len(r) for r in resid) * padding)))
    power = sum(np.abs(np.fft.rfft(r * np.hanning(len(r)), n)) ** 2 for r in resid)
    freqs = np.fft.rfftfreq(n, T_s)
    return float(freqs[1 + int(np.argmax(power[1:]))])


def _oscillating_parts(speed: np.ndarray, section: np.ndarray | None, min_samples: int) -> list[np.ndarray]:
    """Per section with at least ``min_samples`` samples, the speed less its quadratic fit."""
    parts: list[np.ndarray] = []
    if section is None:
        return parts
    for k in range(1, 7):
        idx = np.nonzero(section == k)[0]
        if len(idx) >= min_samples:
            t = (idx - idx[0]).astype(np.float64)
            coef = np.polyfit(t, speed[idx], 2)
            parts.append(speed[idx] - np.polyval(coef, t))
    return parts


def _mean_acceleration(speed: np.ndarray, section: np.ndarray | None, T_s: float, sections: tuple[int, ...] = (1, 4)) -> float:
    """The largest mean acceleration [rad/s^2] of ``sections`` (default I and IV; 0 without sections)."""
    accel = 0.0
    if section is None:
        return accel
    for k in sections:
        idx = np.nonzero(section == k)[0]
        if len(idx) >= 2:
            accel = max(accel, abs(float(speed[idx[-1]] - speed[idx[0]])) / ((len(idx) - 1) * T_s))
    return accel


@dataclass(frozen=True)
class RigidFit:
    """The test record read as one rigid body with Coulomb friction, ``J dw/dt = M - M_F sign(w)``,
    fitted by least squares to the measured speed over the whole record: ``J`` [kg m^2], ``M_F``
    [Nm], ``residual`` (RMS of the speed left unexplained over the speed's RMS) and ``periods`` (the
    record's duration over the period of the residual's dominant frequency). Where the load moved
    with the motor, ``J`` is ``J_sigma`` and ``M_F`` the load's friction (a visible oscillation is
    averaged out over several periods); where a slow mode did not complete, the residual is a trend
    of about one period and ``J`` lies between ``J_M`` and ``J_sigma``."""

    J: float = 0.0
    M_F: float = 0.0
    residual: float = 1.0
    periods: float = 0.0


def _measured_torque(record: Any, K_M: float) -> np.ndarray | None:
    """The measured air-gap torque [Nm] (``torque``, or ``current * K_M``), else the torque reference."""
    for torque, scale in ((record.torque, 1.0), (record.current, K_M), (record.torque_ref, 1.0)):
        if torque is not None:
            return np.asarray(torque, dtype=np.float64) * scale
    return None


def rigid_fit(record: Any, config: Any, padding: int = 4) -> RigidFit:
    """:class:`RigidFit` of a test record (the speed against the integrated measured torque, the
    integrated sign of the speed and a constant); an empty fit where the record has no torque or
    the fit has no positive inertia."""
    T_s = float(config.T_s)
    speed = np.asarray(record.speed, dtype=np.float64)
    torque = _measured_torque(record, float(config.K_M))
    if torque is None or len(torque) != len(speed) or len(speed) < 8 or not np.isfinite(torque).all():
        return RigidFit()
    impulse = np.concatenate([[0.0], np.cumsum(0.5 * (torque[1:] + torque[:-1])) * T_s])
    friction = np.concatenate([[0.0], np.cumsum(np.sign(speed[:-1])) * T_s])
    design = np.stack([impulse, -friction, np.ones_like(speed)], axis=1)
    coef, *_ = np.linalg.lstsq(design, speed, rcond=None)
    speed_rms = float(np.sqrt(np.mean(speed**2)))
    if not (coef[0] > 0 and speed_rms > 0):
        return RigidFit()
    resid = speed - design @ coef
    return RigidFit(J=float(1.0 / coef[0]), M_F=float(coef[1] / coef[0]), residual=float(np.sqrt(np.mean(resid**2))) / speed_rms,
                    periods=_dominant_frequency([resid], T_s, padding) * len(speed) * T_s)


def _along_torque(record: Any, speed: np.ndarray, q_w: float, on_share: float) -> float:
    """The speed gained in the direction of the torque reference [``q_w``], summed over the samples
    whose reference is at least ``on_share`` of its peak (NaN without a reference)."""
    if record.torque_ref is None or len(record.torque_ref) != len(speed):
        return math.nan
    torque = np.asarray(record.torque_ref, dtype=np.float64)
    peak = np.abs(torque).max()
    on = np.abs(torque[:-1]) >= on_share * float(peak) if peak > 0 else np.zeros(len(speed) - 1, dtype=bool)
    return float(np.sum(np.sign(torque[:-1][on]) * np.diff(speed)[on])) / q_w


def measure_run(record: Any, config: Any, rules: ExcitationRules | None = None) -> RunFigures:
    """The measured figures of one test record (:class:`RunFigures`); uses no truth.

    ``record``: a :class:`sim.Record` (``speed`` ``N`` [rad/s], ``section`` ``N`` (1..6, 0 = tail),
    optional ``torque_ref``, ``current``/``torque``; ``meta``: optional ``timed_out`` (six flags)
    and ``aborted``). ``config``: the drive's ``T_s``, ``K_M``, ``encoder_counts``.
    """
    rules = rules or ExcitationRules()
    T_s = float(config.T_s)
    q_w = sim.speed_quantum(float(config.encoder_counts), T_s)
    speed = np.asarray(record.speed, dtype=np.float64)
    if len(speed) < 2 or not np.isfinite(speed).all():
        raise ValueError("record: expected a finite speed with at least 2 samples")
    section = None if record.section is None else np.asarray(record.section)
    counts = tuple(int((section == k).sum()) for k in range(1, 7)) if section is not None else (0,) * 6
    parts = _oscillating_parts(speed, section, rules.fit_min_samples)
    meta = record.meta or {}
    fit = rigid_fit(record, config, rules.spectrum_padding)
    return RunFigures(
        along_torque_quanta=_along_torque(record, speed, q_w, rules.torque_on_share),
        samples_per_section=counts, samples_min=min(counts),
        timed_out=bool(np.any(meta.get("timed_out", False))), aborted=bool(meta.get("aborted", False)),
        range_quanta=float((speed.max() - speed.min()) / q_w),
        osc_quanta=float(np.sqrt(np.mean(np.concatenate(parts) ** 2))) / q_w if parts else 0.0,
        f_osc=_dominant_frequency(parts, T_s, rules.spectrum_padding), longest_section=max(counts) * T_s,
        accel=_mean_acceleration(speed, section, T_s), **record_peaks(record, T_s, float(config.K_M)),
        duration=len(speed) * T_s, accel_first=_mean_acceleration(speed, section, T_s, (1,)), rigid_J=fit.J,
        rigid_M_F=fit.M_F, rigid_residual=fit.residual, rigid_periods=fit.periods)


def measure_response(record: Any, config: Any) -> dict[str, Any]:
    """The measured figures of one test record as a log entry's keys (:func:`measure_run`)."""
    return measure_run(record, config).as_dict()


# --------------------------------------------------------------------------- E1, E9: the plan and the limits of a run


@dataclass(frozen=True)
class RunPlan:
    """A test run's ``M_star`` [Nm] and ``w_max`` [rad/s], with the ceilings earlier runs set on both."""

    M_star: float
    w_max: float
    M_ceiling: float = math.inf
    w_ceiling: float = math.inf


def first_plan(limits: sim.DriveLimits, M_cap: float, rules: ExcitationRules) -> RunPlan:
    """E1: start small; the first travel is bounded by an a-priori inertia bound
    (``w^2 J / M*`` x ``first_travel_factor``)."""
    M_star = rules.M_star_start * M_cap
    w_travel = math.sqrt(rules.travel_margin * rules.first_travel_share * limits.travel * M_star
                         / (rules.first_travel_factor * rules.J_prior_max))
    return RunPlan(M_star, min(rules.w_max_start, rules.first_speed_share * limits.w_max, w_travel))


def stop_headroom(accel: float, config: Any, rules: ExcitationRules) -> float:
    """The speed [rad/s] a run can still gain after the drive stops it (torque reference 0) at the
    measured limit, accelerating at ``accel`` [rad/s^2]: over the current loop's ``T_Ei``, the
    computation and speed-measurement delays (2 ``T_s``) and ``delay_allowance`` more samples,
    times ``coast_factor`` (a slower current loop, friction that made ``accel`` small)."""
    return rules.coast_factor * accel * (float(config.T_Ei) + (2 + rules.delay_allowance) * float(config.T_s))


def guarded_limits(limits: sim.DriveLimits, headroom: float, config: Any, rules: ExcitationRules) -> sim.DriveLimits:
    """The limits handed to the drive for one experiment: the user's speed limit less ``headroom``
    [rad/s] (at most ``max_guard_share`` of it), the travel less what the stop's delays let the
    plant run on (at most ``max_guard_share`` of it)."""
    w = limits.w_max - min(headroom, rules.max_guard_share * limits.w_max)
    t_stop = stop_headroom(1.0, config, rules)  # the stop's delay [s]: the headroom per unit acceleration
    return sim.DriveLimits(w_max=w, travel=max(limits.travel - limits.w_max * t_stop, rules.max_guard_share * limits.travel),
                           M_max=limits.M_max)


@dataclass(frozen=True)
class Headroom:
    """E9: what a stop can add, per Nm of ``M_star``, learned from the runs so far (0: nothing yet)."""

    accel_per_M: float = 0.0
    over_per_M: float = 0.0

    def at(self, M_star: float, w_limit: float, config: Any, rules: ExcitationRules) -> float:
        """The headroom [rad/s] of a run at ``M_star`` below the user's speed limit ``w_limit``."""
        if self.accel_per_M == 0.0:
            return rules.first_headroom * w_limit
        return stop_headroom(self.accel_per_M * M_star, config, rules) + self.over_per_M * M_star

    def learned(self, plan: RunPlan, figures: RunFigures) -> Headroom:
        """With the run ``plan`` measured as ``figures`` (its overshoot only when the drive did not stop it)."""
        over = self.over_per_M if figures.aborted else max(self.over_per_M, max(figures.peak_speed - plan.w_max, 0.0) / plan.M_star)
        return Headroom(max(self.accel_per_M, figures.accel / plan.M_star), over)


# --------------------------------------------------------------------------- E2, E6: what a run lacks, what the next one will do


@dataclass(frozen=True)
class Deficits:
    """E2: what keeps a run from being informative."""

    timed_out: bool
    short: bool
    small: bool
    hidden: bool

    @classmethod
    def of(cls, figures: RunFigures, rules: ExcitationRules) -> Deficits:
        return cls(timed_out=figures.timed_out, short=figures.samples_min < rules.min_section_samples,
                   small=figures.range_quanta < rules.min_range_quanta, hidden=figures.osc_quanta < rules.min_osc_quanta)

    @property
    def any(self) -> bool:
        """Something is missing."""
        return self.timed_out or self.short or self.small or self.hidden

    @property
    def only_hidden(self) -> bool:
        """Only the oscillation is missing."""
        return self.hidden and not (self.timed_out or self.short or self.small)

    def names(self) -> tuple[str, ...]:
        """The deficits in words, in a fixed order (the log's reason)."""
        named = (("section timed out", self.timed_out), ("sections too short", self.short),
                 ("speed range too small", self.small), ("oscillation not visible", self.hidden))
        return tuple(name for name, on in named if on)


@dataclass(frozen=True)
class PeakModel:
    """E6: the figures of one run the next run's peak speed and travel are predicted from.

    ``over`` [rad/s]: the overshoot beyond ``w_max``, ``overshoot_weight`` times; ``travel_per``:
    travel over ``w_max^2`` (travel ~ ``w_max^2 J / M_star``); ``travel_per_peak``: travel over the
    peak squared (E6d: where ``w_max`` lies below what the encoder resolves, the speed runs on to the
    first quanta it shows and the travel follows the peak); ``run_on`` [rad/s]: the peak beyond ``w_max``.
    """

    over: float
    travel_per: float
    travel_per_peak: float
    run_on: float

    @classmethod
    def of(cls, figures: RunFigures, w_max: float, rules: ExcitationRules) -> PeakModel:
        has_travel = figures.travel > 0  # the travel sums the speed: then the peak > 0
        return cls(over=rules.overshoot_weight * max(figures.peak_speed - w_max, 0.0),
                   travel_per=figures.travel / w_max**2 if has_travel else 0.0,
                   travel_per_peak=figures.travel / figures.peak_speed**2 if has_travel else 0.0,
                   run_on=max(figures.peak_speed - w_max, 0.0))


@dataclass(frozen=True)
class Prediction:
    """E6: the next run's predicted peak speed [rad/s] and travel [rad]."""

    peak_speed: float
    travel: float


@dataclass(frozen=True)
class ExcitationRun:
    """One test run as the rules see it: its plan, the limits the drive had, what it measured, what
    the runs so far taught (the headroom includes this run) and the previous stopped run's figures."""

    plan: RunPlan
    figures: RunFigures
    guarded: sim.DriveLimits
    w_limit: float
    M_cap: float
    headroom: Headroom
    previous_stopped: RunFigures | None
    config: Any
    rules: ExcitationRules
    deficits: Deficits
    model: PeakModel

    @classmethod
    def of(cls, plan: RunPlan, figures: RunFigures, guarded: sim.DriveLimits, limits: sim.DriveLimits, M_cap: float,
           headroom: Headroom, previous_stopped: RunFigures | None, config: Any, rules: ExcitationRules) -> ExcitationRun:
        """The run with its deficits (E2) and its peak model (E6)."""
        return cls(plan, figures, guarded, limits.w_max, M_cap, headroom, previous_stopped, config, rules,
                   Deficits.of(figures, rules), PeakModel.of(figures, plan.w_max, rules))

    def raised_torque(self, M_ceiling: float) -> float:
        """E3, E5: one step more torque, at most the cap and ``M_ceiling``."""
        return min(self.plan.M_star * self.rules.factor, self.M_cap, M_ceiling)

    def travel_gain(self, M_new: float) -> float:
        """The travel's factor at ``M_new``: the benefit of more torque counted with exponent 1/2
        only (friction and the coasting section II do not scale): conservative."""
        return math.sqrt(self.plan.M_star / M_new)

    def travel_cap(self, M_new: float) -> float:
        """The largest ``w_max'`` whose predicted travel (both models) fits below the travel at which
        the drive stops the run (inf: nothing measured; <= 0: none at ``M_new``)."""
        model = self.model
        if model.travel_per == 0.0:
            return math.inf
        room = self.rules.travel_margin * self.guarded.travel / self.travel_gain(M_new)
        return min(math.sqrt(room / model.travel_per), math.sqrt(room / model.travel_per_peak) - model.run_on * M_new / self.plan.M_star)

    def speed_cap(self, M_new: float, w_ceiling: float) -> float:
        """The largest ``w_max'`` whose predicted peak ``w_max' + max(swing w_max', over)`` and travel fit."""
        rules = self.rules
        room = rules.speed_margin * (self.w_limit - self.headroom.at(M_new, self.w_limit, self.config, rules))
        speed = min(room / (1 + rules.swing_allowance), max(room - self.model.over * M_new / self.plan.M_star, 0.0), w_ceiling)
        return min(speed, self.travel_cap(M_new))

    def predicted(self, w_next: float, M_next: float) -> Prediction:
        model, M_star = self.model, self.plan.M_star
        return Prediction(w_next + max(self.rules.swing_allowance * w_next, model.over * M_next / M_star),
                          max(model.travel_per * w_next**2, model.travel_per_peak * (w_next + model.run_on * M_next / M_star)**2)
                          * self.travel_gain(M_next))


# --------------------------------------------------------------------------- E3-E8, E10: the rules


@dataclass(frozen=True)
class RuleDecision:
    """What the rules decided so far: the next run's plan and, once a rule settles the run, the
    ``verdict`` (:data:`RUN_AGAIN` or a key of :data:`EXCITATION_ENDS`), the log's ``decision`` and
    ``reason``, and E6's prediction of the next run."""

    plan: RunPlan
    verdict: str = ""
    decision: str = ""
    reason: str = ""
    prediction: Prediction | None = None

    def planned(self, **changes: float) -> RuleDecision:
        """With the next run's plan changed."""
        return replace(self, plan=replace(self.plan, **changes))

    def ended(self, code: str, reason: str) -> RuleDecision:
        """Settled: the adaptation ends with ``code`` (accepted when informative)."""
        return replace(self, verdict=code, decision="accept" if code == "informative" else "stop", reason=reason)


ExcitationRule = Callable[[ExcitationRun, RuleDecision], RuleDecision]


def _changes(run: ExcitationRun, plan: RunPlan, *, speed_always: bool = False) -> str:
    """The log's decision: the changes of ``M_star`` and ``w_max`` from ``run``'s plan to ``plan``."""
    old = run.plan
    parts = [f"M_star {old.M_star:.4g} -> {plan.M_star:.4g} Nm"] if plan.M_star != old.M_star else []
    if speed_always or plan.w_max != old.w_max:
        parts.append(f"w_max {old.w_max:.4g} -> {plan.w_max:.4g} rad/s")
    return "; ".join(parts)


def e10_speed_against_torque(run: ExcitationRun, decision: RuleDecision) -> RuleDecision:
    """E10, runs when the speed moved against the torque reference by more than ``against_quanta``:
    a reversed motor or encoder sign; no rule can make such a run informative: stop."""
    along = run.figures.along_torque_quanta
    if not along < -run.rules.against_quanta:
        return decision
    return decision.ended("speed_against_torque", f"the speed moved against the torque reference ({-along:.0f} "
                                                  f"speed quanta): motor or encoder sign reversed?")


def _repeats(now: RunFigures, before: RunFigures, tolerance: float) -> bool:
    """Whether ``now``'s peak speed and travel equal ``before``'s within the share ``tolerance``."""
    return all(abs(a - b) <= tolerance * max(abs(b), 1e-300)
               for a, b in ((now.peak_speed, before.peak_speed), (now.travel, before.travel)))


def e8b_stopped_run_repeated(run: ExcitationRun, decision: RuleDecision) -> RuleDecision:
    """E8b, runs when the drive stopped this run and the previous stopped run with the same peak
    speed and travel: a smaller test changed nothing, the limit is passed before the signal matters: stop."""
    now, before = run.figures, run.previous_stopped
    if not now.aborted or before is None or not _repeats(now, before, run.rules.repeat_tolerance):
        return decision
    return decision.ended("run_repeated", f"the drive stopped the run at a limit again with the same peak speed "
                                          f"{now.peak_speed:.4g} rad/s and travel {now.travel:.4g} rad: a smaller test "
                                          f"signal changes nothing")


def e8_stopped_by_drive(run: ExcitationRun, decision: RuleDecision) -> RuleDecision:
    """E8, runs when the drive stopped this run at a limit: never accepted; half the speed target and
    the torque (not below E1's start), no later run above ``factor^-stopped_ceiling_exponent`` of this one."""
    if not run.figures.aborted:
        return decision
    rules, plan, M_start = run.rules, run.plan, run.rules.M_star_start * run.M_cap
    ceiling_step = rules.factor ** rules.stopped_ceiling_exponent
    M_next = max(plan.M_star / rules.factor, min(plan.M_star, M_start))
    decided = decision.planned(M_star=M_next, w_max=plan.w_max / rules.factor,
                               w_ceiling=min(decision.plan.w_ceiling, plan.w_max / ceiling_step),
                               M_ceiling=min(decision.plan.M_ceiling, max(plan.M_star / ceiling_step, M_next)))
    return replace(decided, verdict=RUN_AGAIN, decision=_changes(run, decided.plan, speed_always=True),
                   reason="stopped by the drive at a limit")


def e3_section_timed_out(run: ExcitationRun, decision: RuleDecision) -> RuleDecision:
    """E3, runs when a section did not reach its speed (timed out): more torque."""
    if not run.deficits.timed_out:
        return decision
    return decision.planned(M_star=run.raised_torque(decision.plan.M_ceiling))


def e4_short_or_small(run: ExcitationRun, decision: RuleDecision) -> RuleDecision:
    """E4, runs when the sections are too short or the speed range too small: a higher ``w_max``."""
    if not (run.deficits.short or run.deficits.small):
        return decision
    return decision.planned(w_max=run.plan.w_max * run.rules.factor)


def e5_oscillation_hidden(run: ExcitationRun, decision: RuleDecision) -> RuleDecision:
    """E5, runs when the oscillation is below resolution and no section timed out: the oscillation
    grows with ``M_star``, raise it."""
    if not run.deficits.hidden or run.deficits.timed_out:
        return decision
    return decision.planned(M_star=run.raised_torque(decision.plan.M_ceiling))


def e3b_torque_at_cap(run: ExcitationRun, decision: RuleDecision) -> RuleDecision:
    """E3b, runs when a section timed out and the torque cannot rise: a lower speed target instead."""
    if not (run.deficits.timed_out and decision.plan.M_star <= run.plan.M_star):
        return decision
    return decision.planned(w_max=run.plan.w_max / run.rules.factor)


def e6b_torque_for_speed(run: ExcitationRun, decision: RuleDecision) -> RuleDecision:
    """E6b, runs when E4 wants more speed than the limits allow at the planned torque, below the
    torque cap: travel ~ ``w_max^2 / M_star``, so one step more torque when it allows more speed."""
    plan = decision.plan
    wants_speed = run.deficits.short or run.deficits.small
    if not (wants_speed and run.speed_cap(plan.M_star, plan.w_ceiling) < plan.w_max and plan.M_star < run.M_cap):
        return decision
    M_up = min(plan.M_star * run.rules.factor, run.M_cap, plan.M_ceiling)
    if run.speed_cap(M_up, plan.w_ceiling) > run.speed_cap(plan.M_star, plan.w_ceiling):
        return decision.planned(M_star=M_up)
    return decision


def e4b_less_torque_longer_sections(run: ExcitationRun, decision: RuleDecision) -> RuleDecision:
    """E4b, runs when the sections are too short (nothing else missing), the limits keep ``w_max``
    from rising and ``M_star`` can step down above E1's start: less torque makes the sections longer
    (and the headroom after a stop smaller); no later raise above it."""
    rules, plan, deficits = run.rules, decision.plan, run.deficits
    if not deficits.short or deficits.hidden or deficits.timed_out:
        return decision
    M_lower = run.plan.M_star / rules.factor
    if run.speed_cap(plan.M_star, plan.w_ceiling) < run.plan.w_max * rules.factor**rules.lower_torque_exponent \
            and M_lower >= rules.M_star_start * run.M_cap:
        return decision.planned(M_star=M_lower, M_ceiling=M_lower)
    return decision


def e6d_torque_past_travel(run: ExcitationRun, decision: RuleDecision) -> RuleDecision:
    """E6d, runs when more torque alone would run past the travel limit (none fits at the planned
    torque, some at this run's): keep this run's torque."""
    M_star = run.plan.M_star
    if decision.plan.M_star > M_star and run.travel_cap(decision.plan.M_star) <= 0.0 < run.travel_cap(M_star):
        return decision.planned(M_star=M_star)
    return decision


def e6_speed_within_limits(run: ExcitationRun, decision: RuleDecision) -> RuleDecision:
    """E6, runs always: the planned ``w_max`` at most what the predicted peak and travel allow (may
    lower it: the limits come first)."""
    plan = decision.plan
    return decision.planned(w_max=min(plan.w_max, run.speed_cap(plan.M_star, plan.w_ceiling)))


def e6c_no_small_raise(run: ExcitationRun, decision: RuleDecision) -> RuleDecision:
    """E6c, runs when ``w_max`` alone would rise by less than ``factor^min_raise_exponent``: no progress, keep it."""
    rules, w_max, plan = run.rules, run.plan.w_max, decision.plan
    if w_max < plan.w_max < w_max * rules.factor**rules.min_raise_exponent and plan.M_star <= run.plan.M_star:
        return decision.planned(w_max=w_max)
    return decision


def e6_prediction(run: ExcitationRun, decision: RuleDecision) -> RuleDecision:
    """E6, runs always: the next run's predicted peak speed and travel, for the log."""
    return replace(decision, prediction=run.predicted(decision.plan.w_max, decision.plan.M_star))


def e7_informative(run: ExcitationRun, decision: RuleDecision) -> RuleDecision:
    """E7, runs when nothing is missing: accept."""
    if run.deficits.any:
        return decision
    return decision.ended("informative", "informative")


def e7_stiff_at_cap(run: ExcitationRun, decision: RuleDecision) -> RuleDecision:
    """E7, runs when only the oscillation is missing at the torque cap: stiff or weakly coupled
    mechanics; accept."""
    if not run.deficits.only_hidden or run.plan.M_star < run.M_cap:
        return decision
    return decision.ended("informative", "informative (oscillation not visible at the torque cap: stiff or weakly coupled)")


def e7_limits_reached(run: ExcitationRun, decision: RuleDecision) -> RuleDecision:
    """E7, runs when the rules changed neither ``M_star`` nor ``w_max`` (or left no speed): stop."""
    old, new, tolerance = run.plan, decision.plan, run.rules.change_tolerance
    changed = abs(new.M_star - old.M_star) > tolerance * old.M_star or abs(new.w_max - old.w_max) > tolerance * old.w_max
    if not changed or new.w_max <= 0:
        return decision.ended("limits_reached", f"limits reached before the response was informative: "
                                                f"{', '.join(run.deficits.names())}")
    return decision


def run_again(run: ExcitationRun, decision: RuleDecision) -> RuleDecision:
    """Last, runs always: run again with the plan the rules decided (the log names the changes and the deficits)."""
    return replace(decision, verdict=RUN_AGAIN, decision=_changes(run, decision.plan), reason=", ".join(run.deficits.names()))


#: The rules applied to each run, in this order; the first to settle the run ends the pass (:func:`judge_run`).
EXCITATION_RULES: tuple[ExcitationRule, ...] = (
    e10_speed_against_torque,
    e8b_stopped_run_repeated,
    e8_stopped_by_drive,
    e3_section_timed_out,
    e4_short_or_small,
    e5_oscillation_hidden,
    e3b_torque_at_cap,
    e6b_torque_for_speed,
    e4b_less_torque_longer_sections,
    e6d_torque_past_travel,
    e6_speed_within_limits,
    e6c_no_small_raise,
    e6_prediction,
    e7_informative,
    e7_stiff_at_cap,
    e7_limits_reached,
    run_again,
)


def judge_run(run: ExcitationRun) -> RuleDecision:
    """:data:`EXCITATION_RULES` on ``run``, from its own plan, up to the first that settles it."""
    decision = RuleDecision(run.plan)
    for rule in EXCITATION_RULES:
        decision = rule(run, decision)
        if decision.verdict:
            break
    return decision


# --------------------------------------------------------------------------- E0, E11: informative within the limits


def trusted_J(figures: RunFigures, rules: ExcitationRules, max_residual: float | None = None,
              min_periods: float | None = None) -> float | None:
    """The rigid-body fit's inertia [kg m^2] of a run that accelerated the load with the motor (the fit
    explains the speed to ``max_residual``, default ``trust_max_residual``, and what it leaves is an
    oscillation of at least ``min_periods`` (default ``trust_min_periods``) periods in the record, or
    nearly nothing); None otherwise (a slow mode the run did not complete: the motor moved alone,
    and ``M_star / accel`` is about ``J_M``)."""
    bound = rules.trust_max_residual if max_residual is None else max_residual
    periods = rules.trust_min_periods if min_periods is None else min_periods
    if figures.aborted or figures.rigid_J <= 0 or figures.rigid_residual > bound:
        return None
    if figures.rigid_periods >= periods or figures.rigid_residual <= rules.trust_exact_residual:
        return figures.rigid_J
    return None


def trusted_inertia(excitation: ExcitationResult, rules: ExcitationRules | None = None) -> float | None:
    """The inertia [kg m^2] the accepted test run (the last one the drive did not stop) shows as a
    rigid body, where that run accelerated the load with the motor (:func:`trusted_J`); None where it
    did not (the fallback F1 then designs on the identified ``J_sigma``)."""
    rules = rules or ExcitationRules()
    kept = [e for e in excitation.log if not e.get("aborted", False)]
    if not kept:
        return None
    names = {f.name for f in fields(RunFigures)} - {"samples_per_section"}
    entry = kept[-1]
    figures = RunFigures(samples_per_section=tuple(entry.get("samples_per_section", ())),
                         **{k: entry[k] for k in names if k in entry})
    return trusted_J(figures, rules)


def rigid_travel(w_max: float, M_star: float, J: float, M_F: float = 0.0) -> float:
    """The largest travel [rad] of the six-section test (SPEC section 2) on a rigid body ``J`` with
    Coulomb friction ``M_F``: section I up to ``w_max``, II coasting as long as I (or down to
    ``0.2 w_max``), III braking at ``0.7 M_star`` to rest; IV-VI come back. Without friction
    ``2.21 w_max^2 J / M_star``, the most for any ``M_F`` up to ``M_star / 2``; inf where ``M_F >= M_star``."""
    a1 = (M_star - M_F) / J
    if not a1 > 0:
        return math.inf
    t1 = w_max / a1
    a2 = M_F / J
    t2 = t1 if a2 <= 0 else min(t1, 0.8 * w_max / a2)
    w2 = w_max - a2 * t2
    return w_max * t1 / 2 + w_max * t2 - a2 * t2**2 / 2 + w2**2 / (2 * (0.7 * M_star + M_F) / J)


def informative_limits(limits: sim.DriveLimits, config: Any, rules: ExcitationRules) -> dict[str, float]:
    """E0: the smallest speed [rad/s] and travel [rad] limits within which an informative test can
    fit at all, from the drive's ``config`` alone: the speed range of ``min_range_quanta`` speed
    quanta needs a peak of half of it both ways; a rigid run at that speed with sections of
    ``min_section_samples`` travels ``min_travel_factor`` times speed times section, inside the
    travel the drive is handed (less the stop's run-on, :func:`guarded_limits`)."""
    T_s = float(config.T_s)
    w_min = rules.min_range_quanta * sim.speed_quantum(float(config.encoder_counts), T_s) / 2
    travel = rules.min_travel_factor * w_min * rules.min_section_samples * T_s
    run_on = max(limits.w_max, w_min) * stop_headroom(1.0, config, rules)
    return {"w_max": w_min, "travel": min(travel + run_on, travel / rules.max_guard_share)}


def _raise_text(needed: dict[str, float]) -> str:
    names = {"w_max": ("speed", "rad/s"), "travel": ("travel", "rad")}
    return " and ".join(f"the {names[k][0]} limit to >= {v:.3g} {names[k][1]}" for k, v in needed.items())


def check_limits(limits: sim.DriveLimits, config: Any, rules: ExcitationRules) -> None:
    """E0, before the first run: raise :class:`LimitsTooTight` (one line naming the limit to raise
    and to what) where no informative test fits within the user's limits (:func:`informative_limits`)."""
    need = informative_limits(limits, config, rules)
    short = {k: v for k, v in need.items() if getattr(limits, k) < v}
    if short:
        q_w = sim.speed_quantum(float(config.encoder_counts), float(config.T_s))
        raise LimitsTooTight(f"limits: no informative test fits within {limits.w_max:g} rad/s and {limits.travel:g} rad: raise "
                             f"{_raise_text(short)} (a test spans {rules.min_range_quanta:g} speed quanta of {q_w:.3g} rad/s "
                             f"with sections of {rules.min_section_samples} samples)", short)


@dataclass(frozen=True)
class ProbeBasis:
    """E11: what a long-section probe is planned on: an inertia ``J`` [kg m^2] that bounds the
    plant's, its friction ``M_F`` [Nm], the share of the drive's travel the probe may use, and
    whether ``J`` is a trusted one (else the envelope's bound ``(1 + V_J_max) M_star / accel_first``)."""

    J: float
    M_F: float
    share: float
    trusted: bool

    @classmethod
    def of(cls, plan: RunPlan, figures: RunFigures, rules: ExcitationRules) -> ProbeBasis | None:
        J = trusted_J(figures, rules, rules.probe_max_residual, rules.probe_min_periods)
        if J is not None:
            return cls(J * (1 + rules.trust_margin), max(figures.rigid_M_F, 0.0), rules.travel_margin, True)
        if not figures.accel_first > 0:
            return None
        return cls((1 + rules.V_J_max) * plan.M_star / figures.accel_first, 0.0, rules.probe_untrusted_share, False)

    def torque_for(self, w_max: float, travel: float, M_high: float) -> float:
        """The smallest ``M_star`` up to ``M_high`` whose rigid travel at ``w_max`` fits in ``travel``
        (``M_high`` where none does)."""
        lo, hi = self.M_F / (1 - 1e-9) if self.M_F > 0 else 1e-9 * M_high, M_high
        if rigid_travel(w_max, hi, self.J, self.M_F) > travel:
            return hi
        for _ in range(60):
            mid = math.sqrt(lo * hi)
            lo, hi = (lo, mid) if rigid_travel(w_max, mid, self.J, self.M_F) <= travel else (mid, hi)
        return hi


@dataclass(frozen=True)
class ProbeOutlook:
    """E11: the next probe's plan, or None with ``needed``: the limits to raise, and to what, for a
    probe whose sections last ``probe_periods`` periods of ``slowest_f_e``."""

    plan: RunPlan | None
    needed: dict[str, float]
    why: str


def _probe_at_cap(basis: ProbeBasis, limits: sim.DriveLimits, config: Any, rules: ExcitationRules,
                  headroom: Headroom) -> ProbeOutlook:
    """E11 for a run that moved as one rigid body (its fit explains the speed to
    ``trust_exact_residual``): longer sections show nothing more; E7 accepts a hidden oscillation at
    the torque cap, so the probe runs at the cap with sections of ``min_section_samples`` (+1) and
    the speed range E2 needs, where the limits allow it; else the limits that would."""
    T_s, M_cap = float(config.T_s), limits.torque_cap(config)
    J = basis.J / (1 + rules.trust_margin)
    w_range = rules.probe_range_margin * rules.min_range_quanta * sim.speed_quantum(float(config.encoder_counts), T_s) / 2
    w_max = max(w_range, (rules.min_section_samples + 1) * T_s * (M_cap - basis.M_F) / J)
    over = headroom.at(M_cap, limits.w_max, config, rules)
    speed = w_max * (1 + rules.swing_allowance) / rules.speed_margin + over
    travel = rigid_travel(w_max, M_cap, basis.J, basis.M_F) / rules.travel_margin
    run_on = limits.w_max * stop_headroom(1.0, config, rules)
    needed = {"w_max": speed, "travel": min(travel + run_on, travel / rules.max_guard_share)}
    needed = {k: v for k, v in needed.items() if v > getattr(limits, k)}
    if needed:
        return ProbeOutlook(None, needed, f"a rigid response: a hidden oscillation is accepted at the torque cap {M_cap:.3g} Nm, "
                                          f"whose sections of {rules.min_section_samples} samples need w_max {w_max:.3g} rad/s")
    return ProbeOutlook(RunPlan(M_cap, w_max), {}, "")


def plan_probe(plan: RunPlan, figures: RunFigures, limits: sim.DriveLimits, config: Any, rules: ExcitationRules,
               headroom: Headroom, stopped: bool = False) -> ProbeOutlook:
    """E11: a test with longer sections at lower ``M_star`` than ``plan`` (measured as ``figures``):
    ``w_max`` the smallest that resolves the speed range (``probe_range_margin``), ``M_star`` the
    smallest whose rigid travel (:func:`rigid_travel` on :class:`ProbeBasis`) fits in the travel the
    drive is handed, no smaller than sections of ``probe_periods`` periods of ``slowest_f_e`` need;
    None where the sections would not get longer by ``probe_min_lengthening``, with the limits that
    would let them. A rigid response gets a probe at the torque cap instead (not after a run the
    drive ``stopped``); ``w_max`` stays below the ceiling a stopped run set (E8)."""
    basis = ProbeBasis.of(plan, figures, rules)
    if basis is None:
        return ProbeOutlook(None, {}, "no acceleration measured")
    if basis.trusted and figures.rigid_residual <= rules.trust_exact_residual:
        if stopped:  # a run the drive stopped: no run at more torque than the rules allowed
            return ProbeOutlook(None, {}, "a rigid response, and a run was stopped by the drive")
        return _probe_at_cap(basis, limits, config, rules, headroom)
    w_need = rules.probe_range_margin * rules.min_range_quanta * sim.speed_quantum(float(config.encoder_counts), float(config.T_s)) / 2
    room = rules.speed_margin * (limits.w_max - headroom.at(plan.M_star, limits.w_max, config, rules)) / (1 + rules.swing_allowance)
    if w_need > plan.w_ceiling:
        return ProbeOutlook(None, {}, f"a run the drive stopped keeps w_max below {plan.w_ceiling:.3g} rad/s")
    if w_need > room:
        w_limit = w_need * (1 + rules.swing_allowance) / rules.speed_margin + headroom.at(plan.M_star, limits.w_max, config, rules)
        return ProbeOutlook(None, {"w_max": w_limit}, f"a speed range of {rules.min_range_quanta:g} speed quanta needs w_max "
                                                      f"{w_need:.3g} rad/s")
    section = rules.probe_periods / rules.slowest_f_e
    J_nominal = basis.J / (1 + rules.trust_margin) if basis.trusted else basis.J
    M_target = basis.M_F + J_nominal * w_need / section
    guarded = guarded_limits(limits, 0.0, config, rules)
    M_travel = basis.torque_for(w_need, basis.share * guarded.travel, plan.M_star)
    M_star = max(M_travel, M_target, basis.M_F / rules.rigid_friction_share)
    if M_star <= plan.M_star / rules.probe_min_lengthening:
        return ProbeOutlook(RunPlan(M_star, w_need), {}, "")
    travel = rigid_travel(w_need, M_target, basis.J, basis.M_F) / basis.share
    run_on = limits.w_max * stop_headroom(1.0, config, rules)
    needed = {"travel": min(travel + run_on, travel / rules.max_guard_share)}
    if needed["travel"] <= limits.travel:  # not the travel: friction, or the sections are as long as the probe aims at
        why = (f"the friction {basis.M_F:.3g} Nm keeps M_star above {M_star:.3g} Nm" if M_star > max(M_travel, M_target) else
               f"the sections already last about {section:.3g} s ({rules.probe_periods:g} periods of {rules.slowest_f_e:g} Hz)")
        return ProbeOutlook(None, {}, why)
    return ProbeOutlook(None, needed, f"sections of {section:.3g} s ({rules.probe_periods:g} periods of {rules.slowest_f_e:g} Hz) at "
                                      f"{w_need:.3g} rad/s on J {basis.J:.3g} kg m^2 "
                                      f"({'measured' if basis.trusted else 'bound from the motor inertia'})")


# --------------------------------------------------------------------------- the adaptation


def _checked(drive: Any, limits: Any, rules: Any) -> ExcitationRules:
    """``rules`` (default :class:`ExcitationRules`) after checking the types of the inputs."""
    rules = rules or ExcitationRules()
    if not isinstance(limits, sim.DriveLimits) or not isinstance(rules, ExcitationRules):
        raise TypeError(f"limits, rules: expected sim.DriveLimits, ExcitationRules, received "
                        f"{type(limits).__name__}, {type(rules).__name__}")
    if not callable(getattr(drive, "run_test", None)):
        raise TypeError(f"drive: expected a SPEC 8.1 drive with run_test(M_star, w_max, limits), received {type(drive).__name__}")
    return rules


def _log_entry(iteration: int, run: ExcitationRun, decision: RuleDecision) -> dict[str, Any]:
    """One run's log entry (:attr:`ExcitationResult.log`)."""
    entry: dict[str, Any] = {"iteration": iteration, "M_star": run.plan.M_star, "w_max": run.plan.w_max,
                             "stop_at": run.guarded.w_max, **run.figures.as_dict()}
    if decision.prediction is not None:
        entry["predicted_peak_speed"] = decision.prediction.peak_speed
        entry["predicted_travel"] = decision.prediction.travel
    entry.update(decision=decision.decision, reason=decision.reason)
    return entry


def adapt_test_signal(drive: Any, limits: sim.DriveLimits, rules: ExcitationRules | None = None, *,
                      log: list[dict[str, Any]] | None = None) -> ExcitationResult:
    """Adapt ``M_star`` and ``w_max`` until the test record is informative (rules E0-E13).

    Args:
        drive: a SPEC 8.1 drive (``config``, ``run_test(M_star, w_max, limits) -> Record``).
        limits: the user's limits (torque, speed, travel), handed to every run.
        rules: rule settings.
        log: a list each run's log entry is appended to as it is decided (the result's ``log``), so
            that a caller keeps the entries of the runs before one whose ``run_test`` raised.

    Returns :class:`ExcitationResult` with the last run's record (every run planned within the
    limits by prediction; the log records the measured peaks of each run and whether the drive
    stopped it at a limit).
    """
    rules = _checked(drive, limits, rules)
    config = drive.config
    if rules.refuse_uninformative_limits:
        check_limits(limits, config, rules)
    session = _Session(drive, limits, rules, config, [] if log is None else log)
    plan, stopped = first_plan(limits, session.M_cap, rules), None
    for iteration in range(rules.max_iterations):
        run = session.run(plan, stopped)
        decision = judge_run(run)
        session.log.append(_log_entry(iteration, run, decision))
        if decision.verdict != RUN_AGAIN:
            code, reason = decision.verdict, decision.reason
            break
        plan, stopped = decision.plan, run.figures if run.figures.aborted else stopped
    else:
        code, reason = "max_iterations", f"no informative response after {rules.max_iterations} runs"
    kept, probes, needed = session.kept[-1] if session.kept else session.records[-1], [], {}
    outcome = None
    if code in PROBED_ENDS and session.last_kept is not None and not session.last_kept.figures.timed_out:
        outcome = session.probe(code, reason)
    elif code == "informative" and session.last_kept is not None:
        outcome = session.into_envelope(reason)
    if outcome is not None:
        code, reason, needed, probes = outcome.code, outcome.reason, outcome.needed, outcome.unused
        kept = kept if outcome.record is None else outcome.record
    return ExcitationResult(record=kept, records=session.records, log=session.log, informative=code == "informative",
                            reason=reason, code=code, probes=probes, needed=needed,
                            replaced=None if outcome is None else outcome.replaced)


#: The ends of the rules after which E11 plans long-section probes.
PROBED_ENDS: frozenset[str] = frozenset({"limits_reached", "max_iterations"})


@dataclass
class _Session:
    """One adaptation on a drive: the runs so far (records, those the drive did not stop, the log,
    the last run it did not stop) and what they taught about the headroom after a stop (E9)."""

    drive: Any
    limits: sim.DriveLimits
    rules: ExcitationRules
    config: Any
    log: list[dict[str, Any]]
    records: list[Any] = field(default_factory=list)
    kept: list[Any] = field(default_factory=list)
    headroom: Headroom = field(default_factory=Headroom)
    last_kept: ExcitationRun | None = None
    stopped: bool = False
    """The drive stopped a run at a limit."""

    @property
    def M_cap(self) -> float:
        return self.limits.torque_cap(self.config)

    def run(self, plan: RunPlan, stopped: RunFigures | None) -> ExcitationRun:
        """One test run on the drive at ``plan``, inside the limits less the headroom (E9), measured."""
        config, rules = self.config, self.rules
        guarded = guarded_limits(self.limits, self.headroom.at(plan.M_star, self.limits.w_max, config, rules), config, rules)
        record = self.drive.run_test(plan.M_star, plan.w_max, guarded)
        self.records.append(record)
        figures = measure_run(record, config, rules)
        self.headroom = self.headroom.learned(plan, figures)
        run = ExcitationRun.of(plan, figures, guarded, self.limits, self.M_cap, self.headroom, stopped, config, rules)
        if not figures.aborted:
            self.kept.append(record)
            self.last_kept = run
        self.stopped = self.stopped or figures.aborted
        return run

    def accepted(self, run: ExcitationRun) -> bool:
        """A probe is accepted as E7 accepts a run: not stopped, nothing missing, or only the
        oscillation at the torque cap."""
        deficits = run.deficits
        return not run.figures.aborted and (not deficits.any or (deficits.only_hidden and run.plan.M_star >= self.M_cap))

    def into_envelope(self, reason: str) -> ProbeOutcome | None:
        """E12, E13: an informative run on a trusted inertia ``J`` whose time scale ``J w_max / M_star``
        lies below ``min_time_scale`` (E12), or whose rigid-body friction lies above
        ``max_friction_share`` of ``M_star`` (E13), gets one probe inside the envelope: the torque
        raised to ``friction_share_margin`` of that share where the friction asks for it (within the
        torque cap), the speed raised towards ``time_scale_margin`` times ``min_time_scale`` where the
        run's speed cap (E6) allows it (the oscillation stays as visible), else that cap's speed and
        less torque; where its rigid travel fits, used when informative; None: no probe."""
        rules, base, base_record = self.rules, self.last_kept, self.kept[-1]
        J = trusted_J(base.figures, rules)
        if J is None:
            return None
        M_F = max(base.figures.rigid_M_F, 0.0)
        short = J * base.plan.w_max / base.plan.M_star < rules.min_time_scale
        rubbing = M_F > rules.max_friction_share * base.plan.M_star
        if not (short or rubbing):
            return None
        target = rules.time_scale_margin * rules.min_time_scale  # [s]
        M_star = max(base.plan.M_star, min(M_F / (rules.friction_share_margin * rules.max_friction_share), self.M_cap))
        w_max = max(min(target * M_star / J, base.speed_cap(M_star, base.plan.w_ceiling)), base.plan.w_max)
        M_star = min(J * w_max / target, M_star) if target > 0 else M_star
        room = rules.travel_margin * guarded_limits(self.limits, 0.0, self.config, rules).travel
        if M_star < M_F / rules.rigid_friction_share or rigid_travel(w_max, M_star, J * (1 + rules.trust_margin), M_F) > room:
            return None
        if (M_star, w_max) == (base.plan.M_star, base.plan.w_max):  # the envelope asks for more than the limits allow
            return None
        rule, aim = ("E12", "inside the envelope's time scale") if short else ("E13", "inside the envelope's friction share")
        run = self.run(RunPlan(M_star, w_max, w_ceiling=base.plan.w_ceiling), None)
        done = self.accepted(run)
        lacks = ", ".join(run.deficits.names()) if not run.figures.aborted else "stopped by the drive"
        entry = _log_entry(len(self.log), run, RuleDecision(run.plan, verdict="informative" if done else RUN_AGAIN,
                                                            decision="accept" if done else "not used",
                                                            reason=f"{rule} probe {aim}" + ("" if done else f": {lacks}")))
        if done:
            self.log.append(entry)
            return ProbeOutcome("informative", f"informative ({rule} probe at M_star {M_star:.3g} Nm, {aim})", {}, [],
                                self.records[-1], base_record)
        return ProbeOutcome("informative", reason, {}, [entry])

    def probe(self, code: str, reason: str) -> ProbeOutcome:
        """E11: up to ``max_probes`` tests with longer sections at lower ``M_star`` (:func:`plan_probe`,
        each from the last run the drive did not stop); the first informative one is accepted (its
        entry ends the log), a stopped one ends the probing. Without one: ``code``, and ``reason``
        with the limits to raise; the probes' entries apart (their records are not used)."""
        rules, unused = self.rules, []
        for _ in range(rules.max_probes):
            base = self.last_kept
            outlook = plan_probe(base.plan, base.figures, self.limits, self.config, rules, self.headroom, self.stopped)
            if outlook.plan is None:
                return ProbeOutcome(code, _probe_reason(reason, outlook), outlook.needed, unused)
            run = self.run(outlook.plan, None)
            done = self.accepted(run)
            lacks = ", ".join(run.deficits.names()) if not run.figures.aborted else "stopped by the drive"
            decision = RuleDecision(run.plan, verdict="informative" if done else RUN_AGAIN,
                                    decision="accept" if done else "not used",
                                    reason="E11 long-section probe" + ("" if done else f": {lacks}"))
            entry = _log_entry(len(self.log) + len(unused), run, decision)
            if done:
                self.log.append(entry)
                return ProbeOutcome("informative", f"informative (E11 long-section probe at M_star {run.plan.M_star:.3g} Nm)",
                                    {}, unused, self.records[-1])
            unused.append(entry)
            if run.figures.aborted:
                return ProbeOutcome(code, f"{reason}; an E11 long-section probe was stopped by the drive", {}, unused)
        return ProbeOutcome(code, f"{reason}; {rules.max_probes} E11 long-section probes not informative", {}, unused)


@dataclass(frozen=True)
class ProbeOutcome:
    """How E11's probes ended: the adaptation's ``code`` and ``reason``, the limits to raise
    (``needed``), the unused probes' log entries and the informative probe's record (None: none)."""

    code: str
    reason: str
    needed: dict[str, float]
    unused: list[dict[str, Any]]
    record: Any = None
    replaced: Any = None
    """The record an accepted E12/E13 probe replaced."""


def _probe_reason(reason: str, outlook: ProbeOutlook) -> str:
    """The adaptation's reason where no (further) probe fits: the limits to raise, and to what."""
    if not outlook.needed:
        return f"{reason}; no longer-section probe: {outlook.why}"
    return f"{reason}; raise {_raise_text(outlook.needed)} for an informative test ({outlook.why})"
