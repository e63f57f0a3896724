"""Test-signal adaptation (knowledge base, SPEC 8): choose ``M_star`` and ``w_max`` for STEP 1.

Start small, run the six-section test through the drive (``drive.run_test``, SPEC 8.1), judge from
the returned record only (measured motor speed, the drive's own torque reference and section
counter, the timeout flags; no truth)
whether it is informative, and raise ``M_star`` and/or ``w_max`` by factor-2 steps until it is,
never beyond the user's limits (:class:`sim.DriveLimits`: torque ``M_max``, speed ``w_max``, travel
``travel``). The travel and the peak speed of the next run are predicted from the
current one before it runs (travel ~ ``w_max^2 J / M_star``), so a step that would cross a limit
is shortened first; a run the drive stopped at a limit is never accepted (E8). Rules E1-E9 in
docs/commissioning.md.

Measured figures per run (all from the response):

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
  one-mass inertia that friction only makes larger; for the headroom after a stop and F1).

Headroom (E9): the drive stops at its limit and the plant runs on: each run hands the drive the
user's limits less the speed a run can gain after the stop (:func:`stop_headroom`, from ``accel``
and the overshoot beyond ``w_max`` measured so far; the first run, before anything is known, a
share ``first_headroom`` of the speed limit), and plans inside those.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

import sim

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

__all__ = ["EXCITATION_ENDS", "ExcitationRules", "ExcitationResult", "measure_response", "adapt_test_signal", "stop_headroom", "guarded_limits"]


@dataclass(frozen=True)
class ExcitationRules:
    """Rule constants (docs/commissioning.md, E1-E9).

    ``M_star_start``: first ``M_star`` as a fraction of the torque cap. ``w_max_start`` [rad/s]:
    first ``w_max`` (further bounded by ``0.1 w_limit`` and by the travel of an inertia
    ``J_prior_max`` [kg m^2]). ``factor``: raise step. ``min_section_samples``,
    ``min_range_quanta``, ``min_osc_quanta``: what "informative" means. ``speed_margin``,
    ``travel_margin``: fractions of the limits a predicted run may use. ``max_iterations``.
    Headroom after a stop (E9, :func:`stop_headroom`): ``coast_factor``, ``delay_allowance``
    [samples of dead time the drive may have beyond its own], ``first_headroom`` (share of the
    speed limit for the first run). ``swing_allowance``: E6 plans the next peak at ``w_max' (1 +
    swing_allowance)`` at least: once a section lasts longer than half a period of a soft mode, the
    load swings the motor on after section I (the torque is 0 there, a stop changes nothing) by far
    more than the short runs before showed. ``against_quanta``: E10 stops when a run's speed moves
    against the torque reference by more than this many speed quanta (summed over the samples at
    more than half the peak torque reference). ``repeat_tolerance``: E8b stops when a stopped run's
    peak speed and travel repeat the previous stopped run's within this share.
    """

    M_star_start: float = 0.1
    w_max_start: float = 5.0
    J_prior_max: float = 1.0
    factor: float = 2.0
    min_section_samples: int = 40
    min_range_quanta: float = 400.0
    min_osc_quanta: float = 2.0
    speed_margin: float = 0.9
    travel_margin: float = 0.8
    max_iterations: int = 10
    coast_factor: float = 2.0
    swing_allowance: float = 1.0
    delay_allowance: int = 1
    first_headroom: float = 0.25
    against_quanta: float = 10.0
    repeat_tolerance: float = 0.02


@dataclass
class ExcitationResult:
    """``record``: the last test record that the drive did not stop (else the last one); ``records``:
    every test record;
    ``log``: one dict per run (``iteration, M_star, w_max``, the measured figures of
    :func:`measure_response`, ``decision``, ``reason``); ``informative``: the final run passed."""

    record: Any
    records: list[Any] = field(default_factory=list)
    log: list[dict[str, Any]] = field(default_factory=list)
    informative: bool = False
    reason: str = ""
    code: str = ""
    """How the adaptation ended: a key of :data:`EXCITATION_ENDS`."""


def _dominant_frequency(resid: list[np.ndarray], T_s: float) -> float:
    """The frequency [Hz] of the largest summed power of the sections' oscillating parts (each
    zero-padded to one length; 0 when there is nothing to analyse)."""
    if not resid:
        return 0.0
    n = 1 << int(math.ceil(math.log2(max(len(r) for r in resid) * 4)))
    power = sum(np.abs(np.fft.rfft(r * np.hanning(len(r)), n)) ** 2 for r in resid)
    f = np.fft.rfftfreq(n, T_s)
    return float(f[1 + int(np.argmax(power[1:]))])


def measure_response(record: Any, config: Any) -> dict[str, Any]:
    """Measured figures of one test record (see module docstring); uses no truth.

    ``record``: a :class:`sim.Record` (``speed`` ``N`` [rad/s], ``section`` ``N`` (1..6, 0 = tail),
    optional ``torque_ref``, ``current``/``torque``; ``meta``: optional ``timed_out`` (six flags)
    and ``aborted``). ``config``: the drive's ``T_s``, ``K_M``, ``encoder_counts``.
    """
    T_s = float(config.T_s)
    q_w = sim.speed_quantum(float(config.encoder_counts), T_s)
    w = np.asarray(record.speed, dtype=np.float64)
    if len(w) < 2 or not np.isfinite(w).all():
        raise ValueError("record: expected a finite speed with at least 2 samples")
    sec = None if record.section is None else np.asarray(record.section)
    counts = [int((sec == k).sum()) for k in range(1, 7)] if sec is not None else [0] * 6
    resid: list[np.ndarray] = []
    if sec is not None:
        for k in range(1, 7):
            idx = np.nonzero(sec == k)[0]
            if len(idx) >= 8:
                t = (idx - idx[0]).astype(np.float64)
                coef = np.polyfit(t, w[idx], 2)
                resid.append(w[idx] - np.polyval(coef, t))
    osc = float(np.sqrt(np.mean(np.concatenate(resid) ** 2))) / q_w if resid else 0.0
    accel = 0.0
    if sec is not None:
        for k in (1, 4):
            idx = np.nonzero(sec == k)[0]
            if len(idx) >= 2:
                accel = max(accel, abs(float(w[idx[-1]] - w[idx[0]])) / ((len(idx) - 1) * T_s))
    meta = record.meta or {}
    along = math.nan  # speed gained in the direction of the torque reference [q_w] (negative: against it)
    if record.torque_ref is not None and len(record.torque_ref) == len(w):
        M = np.asarray(record.torque_ref, dtype=np.float64)
        on = np.abs(M[:-1]) >= 0.5 * float(np.abs(M).max()) if np.abs(M).max() > 0 else np.zeros(len(w) - 1, dtype=bool)
        along = float(np.sum(np.sign(M[:-1][on]) * np.diff(w)[on])) / q_w
    peaks = record_peaks(record, T_s, float(config.K_M))
    return {
        "along_torque_quanta": along,
        "samples_per_section": counts,
        "samples_min": min(counts),
        "timed_out": bool(np.any(meta.get("timed_out", False))),
        "aborted": bool(meta.get("aborted", False)),
        "range_quanta": float((w.max() - w.min()) / q_w),
        "osc_quanta": osc,
        "f_osc": _dominant_frequency(resid, T_s),
        "longest_section": max(counts) * T_s,
        "accel": accel,
        **peaks,
        "duration": len(w) * T_s,
    }


def stop_headroom(accel: float, config: Any, rules: ExcitationRules) -> float:
    """The speed [rad/s] a run can still gain after the drive stops it (torque reference 0) at the
    measured limit, accelerating at ``accel`` [rad/s^2]: over the current loop's ``T_Ei``, the
    computation and speed-measurement delays (2 ``T_s``) and ``delay_allowance`` more samples,
    times ``coast_factor`` (a slower current loop, friction that made ``accel`` small)."""
    return rules.coast_factor * accel * (float(config.T_Ei) + (2 + rules.delay_allowance) * float(config.T_s))


def guarded_limits(limits: sim.DriveLimits, headroom: float, config: Any, rules: ExcitationRules) -> sim.DriveLimits:
    """The limits handed to the drive for one experiment: the user's speed limit less ``headroom``
    [rad/s] (at most half of it), the travel less what the stop's delays let the plant run on."""
    w = limits.w_max - min(headroom, 0.5 * limits.w_max)
    t_stop = stop_headroom(1.0, config, rules)  # the stop's delay [s]: the headroom per unit acceleration
    return sim.DriveLimits(w_max=w, travel=max(limits.travel - limits.w_max * t_stop, 0.5 * limits.travel), M_max=limits.M_max)


def adapt_test_signal(drive: Any, limits: sim.DriveLimits, rules: ExcitationRules | None = None, *,
                      log: list[dict[str, Any]] | None = None) -> ExcitationResult:
    """Adapt ``M_star`` and ``w_max`` until the test record is informative (rules E1-E9).

    Args:
        drive: a SPEC 8.1 drive (``config``, ``run_test(M_star, w_max, limits) -> Record``).
        limits: the user's limits (torque, speed, travel), handed to every run.
        rules: rule constants.
        log: a list each run's log entry is appended to as it is decided (the result's ``log``), so
            that a caller keeps the entries of the runs before one whose ``run_test`` raised.

    Returns :class:`ExcitationResult` with the last run's record (every run planned within the
    limits by prediction; the log records the measured peaks of each run and whether the drive
    stopped it at a limit).
    """
    rules = rules or ExcitationRules()
    if not isinstance(limits, sim.DriveLimits) or not isinstance(rules, ExcitationRules):
        raise TypeError(f"limits, rules: expected sim.DriveLimits, ExcitationRules, received "
                        f"{type(limits).__name__}, {type(rules).__name__}")
    if not callable(getattr(drive, "run_test", None)):
        raise TypeError(f"drive: expected a SPEC 8.1 drive with run_test(M_star, w_max, limits), received {type(drive).__name__}")
    if rules.factor <= 1 or rules.max_iterations < 1:
        raise ValueError(f"rules: expected factor > 1 and max_iterations >= 1, received {rules.factor}, {rules.max_iterations}")
    config = drive.config
    w_limit, travel_limit = limits.w_max, limits.travel
    M_cap = limits.torque_cap(config)
    # E1: start small; the first travel is bounded by an a-priori inertia bound (w^2 J / M* x 3)
    M_star = rules.M_star_start * M_cap
    w_travel0 = math.sqrt(rules.travel_margin * 0.25 * travel_limit * M_star / (3.0 * rules.J_prior_max))
    w_max = min(rules.w_max_start, 0.1 * w_limit, w_travel0)
    log = [] if log is None else log
    records: list[Any] = []
    w_ceiling = M_ceiling = math.inf
    informative, reason, code = False, "", ""
    accel_per_M = over_per_M = 0.0  # E9: what a stop can add, per Nm of M*, from the runs so far

    def headroom(M: float) -> float:
        if accel_per_M == 0.0:
            return rules.first_headroom * w_limit
        return stop_headroom(accel_per_M * M, config, rules) + over_per_M * M

    for it in range(rules.max_iterations):
        guarded = guarded_limits(limits, headroom(M_star), config, rules)
        rec = drive.run_test(M_star, w_max, guarded)
        records.append(rec)
        m = measure_response(rec, config)
        entry: dict[str, Any] = {"iteration": it, "M_star": M_star, "w_max": w_max, "stop_at": guarded.w_max, **m}
        accel_per_M = max(accel_per_M, m["accel"] / M_star)
        if not m["aborted"]:
            over_per_M = max(over_per_M, max(m["peak_speed"] - w_max, 0.0) / M_star)
        if m["along_torque_quanta"] < -rules.against_quanta:
            # E10: the speed moves against the torque reference: a reversed motor or encoder sign; no
            # rule can make such a run informative, and every further run would go the wrong way
            code, reason = "speed_against_torque", (f"the speed moved against the torque reference ({-m['along_torque_quanta']:.0f} "
                                                    f"speed quanta): motor or encoder sign reversed?")
            entry.update(decision="stop", reason=reason)
            log.append(entry)
            break
        if m["aborted"]:
            prev = next((e for e in reversed(log) if e["aborted"]), None)
            if prev is not None and all(abs(m[k] - prev[k]) <= rules.repeat_tolerance * max(abs(prev[k]), 1e-300)
                                        for k in ("peak_speed", "travel")):
                # E8b: a smaller test changed nothing: the limit is passed before the signal matters
                code, reason = "run_repeated", (f"the drive stopped the run at a limit again with the same peak speed "
                                                f"{m['peak_speed']:.4g} rad/s and travel {m['travel']:.4g} rad: a smaller test "
                                                f"signal changes nothing")
                entry.update(decision="stop", reason=reason)
                log.append(entry)
                break
            # E8: the drive stopped the run at a limit: never accepted; half the speed target and the
            # torque (not below E1's start), no later run above factor^-0.5 of the stopped one's
            w_next = w_max / rules.factor
            M_next = max(M_star / rules.factor, min(M_star, rules.M_star_start * M_cap))
            w_ceiling = min(w_ceiling, w_max / math.sqrt(rules.factor))
            M_ceiling = min(M_ceiling, max(M_star / math.sqrt(rules.factor), M_next))
            parts = [f"M_star {M_star:.4g} -> {M_next:.4g} Nm"] if M_next != M_star else []
            entry.update(decision="; ".join(parts + [f"w_max {w_max:.4g} -> {w_next:.4g} rad/s"]),
                         reason="stopped by the drive at a limit")
            log.append(entry)
            w_max, M_star = w_next, M_next
            continue
        # E2: what is missing
        short = m["samples_min"] < rules.min_section_samples
        small = m["range_quanta"] < rules.min_range_quanta
        hidden = m["osc_quanta"] < rules.min_osc_quanta
        want_M, want_w = False, False
        if m["timed_out"]:
            want_M = True  # E3: a section did not reach its speed: more torque
        if short or small:
            want_w = True  # E4: sections too short / speed range too small: higher w_max
        if hidden and not m["timed_out"]:
            want_M = True  # E5: oscillation below resolution: r_osc ~ M_star, raise it
        M_next = min(M_star * rules.factor, M_cap, M_ceiling) if want_M else M_star
        w_next = w_max * rules.factor if want_w else w_max
        if m["timed_out"] and M_next <= M_star:
            w_next = w_max / rules.factor  # E3b: torque at its cap: lower the speed target instead
        # E6: predict the next run's peak speed and travel from this one; shorten the step
        # the overshoot beyond w_max (an elastic mode swinging on after section I) depends on the
        # phase at the switch, not only on M*: counted twice; at least the swing allowance
        over = 2.0 * max(m["peak_speed"] - w_max, 0.0)
        # travel ~ w_max^2 J / M_star; the benefit of a larger M_star is counted with exponent
        # 1/2 only (friction and the coasting section II do not scale): conservative
        travel_per = m["travel"] / w_max**2 if m["travel"] > 0 else 0.0
        # E6d: travel ~ peak^2 as well, the peak w_max' + (peak - w_max) M'/M_star: where w_max lies
        # below what the encoder resolves, the speed runs on to the first quanta it shows (a peak
        # many times w_max, growing with M_star) and the travel follows the peak, not w_max
        travel_per_peak = m["travel"] / m["peak_speed"]**2 if m["travel"] > 0 else 0.0  # the travel sums the speed: peak > 0
        run_on = max(m["peak_speed"] - w_max, 0.0)

        def travel_gain(M_new: float) -> float:
            return math.sqrt(M_star / M_new)

        def travel_cap(M_new: float) -> float:
            """The largest w_max' whose predicted travel (both models) fits; <= 0: none at M_new."""
            if travel_per == 0.0:
                return math.inf
            # the travel at which the drive stops the run (it coasts on from there; guarded_limits' travel
            # does not depend on the headroom, so not on M_new): the plan stays below it
            room = rules.travel_margin * guarded.travel / travel_gain(M_new)
            return min(math.sqrt(room / travel_per), math.sqrt(room / travel_per_peak) - run_on * M_new / M_star)

        def cap(M_new: float) -> float:
            """The largest w_max' whose predicted peak w_max' + max(swing w_max', over) and travel fit."""
            room = rules.speed_margin * (w_limit - headroom(M_new))
            speed = min(room / (1 + rules.swing_allowance), max(room - over * M_new / M_star, 0.0), w_ceiling)
            return min(speed, travel_cap(M_new))

        if want_w and cap(M_next) < w_next and M_next < M_cap:
            # E6b: travel ~ w_max^2 / M_star: more torque buys speed range within the same travel
            M_up = min(M_next * rules.factor, M_cap, M_ceiling)
            M_next = M_up if cap(M_up) > cap(M_next) else M_next
        if short and not (hidden or m["timed_out"]) and cap(M_next) < w_max * rules.factor**0.5 \
                and M_star / rules.factor >= rules.M_star_start * M_cap:
            # E4b: the limits keep w_max from rising: less torque makes the sections longer (and
            # the headroom after a stop smaller); no later raise above it
            M_next = M_ceiling = M_star / rules.factor
        if M_next > M_star and travel_cap(M_next) <= 0.0 < travel_cap(M_star):
            M_next = M_star  # E6d: more torque alone would run past the travel limit
        w_next = min(w_next, cap(M_next))  # may lower w_max: the limits come first
        if w_max < w_next < w_max * rules.factor**0.1 and M_next <= M_star:
            w_next = w_max  # E6c: a raise of less than factor^0.1 is no progress
        entry["predicted_peak_speed"] = w_next + max(rules.swing_allowance * w_next, over * M_next / M_star)
        entry["predicted_travel"] = max(travel_per * w_next**2, travel_per_peak * (w_next + run_on * M_next / M_star)**2) \
            * travel_gain(M_next)
        problems = [p for p, on in (("section timed out", m["timed_out"]), ("sections too short", short),
                                    ("speed range too small", small), ("oscillation not visible", hidden)) if on]
        if not problems:
            informative, reason, code = True, "informative", "informative"
            entry.update(decision="accept", reason=reason)
            log.append(entry)
            break
        if hidden and not (m["timed_out"] or short or small) and M_star >= M_cap:
            # E7: oscillation still below resolution at the torque cap: stiff or weakly coupled mechanics
            informative, reason, code = True, "informative (oscillation not visible at the torque cap: stiff or weakly coupled)", "informative"
            entry.update(decision="accept", reason=reason)
            log.append(entry)
            break
        changed = abs(M_next - M_star) > 1e-9 * M_star or abs(w_next - w_max) > 1e-9 * w_max
        if not changed or w_next <= 0:
            code, reason = "limits_reached", f"limits reached before the response was informative: {', '.join(problems)}"
            entry.update(decision="stop", reason=reason)
            log.append(entry)
            break
        parts = []
        if M_next != M_star:
            parts.append(f"M_star {M_star:.4g} -> {M_next:.4g} Nm")
        if w_next != w_max:
            parts.append(f"w_max {w_max:.4g} -> {w_next:.4g} rad/s")
        entry.update(decision="; ".join(parts), reason=", ".join(problems))
        log.append(entry)
        M_star, w_max = M_next, w_next
    else:
        code, reason = "max_iterations", f"no informative response after {rules.max_iterations} runs"
    kept = [r for r, e in zip(records, log) if not e["aborted"]]
    return ExcitationResult(record=kept[-1] if kept else records[-1], records=records, log=log, informative=informative,
                            reason=reason, code=code)
