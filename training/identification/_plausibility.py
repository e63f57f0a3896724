"""Plausibility of a test-run record: do the signals agree with the metadata and with physics?

:mod:`sim.records` checks the *format* (columns, NaN, uniform time, metadata types). This module
checks what a well-formed record can still get wrong, mostly units off by orders of magnitude,
before the analysis turns it into confident nonsense. :func:`check_record` raises ``ValueError``
with one line that names what looks wrong, the figures, and the likely cause.

Checks (each only when the data it needs is present; thresholds far outside what the SPEC test
signal produces on the default population, measured on 800 simulated systems):

- timing: ``T_s`` at most 20 ms (a speed loop's sample time; ``t`` in ms gives 1000x),
  ``T_Ei`` at most 50 ms (a current loop), ``T_s`` at most 50 x ``T_Ei``;
- torque scale: the 99th percentile of ``|torque|`` (``|current| * K_M``) within 0.3..3 x
  ``M_star`` (simulated: 1.00), else at most 1.5 x ``M_max`` (mA give 1000x);
- speed scale: the peak ``|speed|`` within 0.3..3 x ``w_max`` (simulated: 1.00..1.61; the lower
  bound only when no section timed out) plus one speed quantum of the encoder (a coarse encoder
  read 3.03 x on an envelope drive whose quantum is 1.5 x ``w_max``) plus the overshoot the
  record's own acceleration explains through the current loop's lag (:func:`overshoot_allowance`:
  a small drive with a small inertia overshoots several times ``w_max``); rpm give 9.5x, deg/s
  57x, counts/s ``counts/2pi`` x; at most three samples above it are named as glitches instead;
- speed quantum: when ``encoder_counts`` is given and the speed is exactly quantized, but in
  steps of the encoder's speed quantum expressed in another unit (rpm, deg/s, counts/s...);
- inertia: a one-mass estimate (``J = int M dt / delta w``, least squares over the record;
  simulated: 0.8..1.02 x the true ``J_sigma``) must be positive (else speed and current have
  opposite signs) and within 1e-7..1e4 kg m^2.

The motor torque (``current * K_M``) must be representable: a ``K_M`` that takes a finite current
beyond the float range, or to zero, is refused here, naming ``K_M`` (the section detection would
otherwise misread the result). A peak speed below the lower bound on a record that stops in
section I, before the speed reached ``w_max``, is called an incomplete run, not wrong units
(:func:`._sections.incomplete_run`).

:func:`unit_warnings` says where none of these checks could test a signal's units (coded
``units_unchecked``): the speed without ``w_max`` and without an ``encoder_counts`` whose speed
quantum it steps in, the torque without ``M_star`` and ``M_max``.

A record whose speed is constant passes here (the section detection reports it with a more
specific message); a torque that is zero throughout while the speed moves is refused here (a
``torque_ref`` would still show the sections, and the one-mass fit would fail on it obscurely).
Where that detection fails on a speed quantized in steps of half ``w_max`` or more, :func:`resolution_hint` says why (the one-mass fit still reads
``J_sigma`` from such a coarse speed where the sections show, so it is not refused here).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from sim import Record, speed_quantum
from sim.records import any_timed_out
from training._settings import POSITIVE, SHARE, Pair, check_settings
from training.identification._result import IdentWarning
from training.identification._sections import incomplete_run

__all__ = ["check_record", "unit_warnings", "PlausibilityBounds", "BOUNDS"]


@dataclass(frozen=True)
class PlausibilityBounds:
    """The bounds beyond which a record's units or metadata are implausible (module docstring)."""

    #: the largest plausible sample time of a speed loop [s].
    T_s_max: float = 0.02
    #: the largest plausible current-loop time constant [s].
    T_Ei_max: float = 0.05
    #: the largest plausible ``T_s / T_Ei``.
    T_s_over_T_Ei_max: float = 50.0
    #: the 99th percentile of ``|torque|`` over ``M_star``.
    torque_ratio: tuple[float, float] = (0.3, 3.0)
    #: the 99th percentile of ``|torque|`` over ``M_max`` (when ``M_star`` is not given), at most.
    torque_over_M_max: float = 1.5
    #: the peak ``|speed|`` over ``w_max`` (above: beyond the overshoot the record's acceleration explains).
    speed_ratio: tuple[float, float] = (0.3, 3.0)
    #: the samples over which the acceleration is measured.
    accel_window: int = 8
    #: at most this many samples above the plausible peak are glitches, not units.
    glitch_samples: int = 3
    #: the plausible one-mass inertia [kg m^2].
    J_range: tuple[float, float] = (1e-7, 1e4)
    #: the ``|correlation|`` of torque integral and speed change needed to judge the inertia.
    min_correlation: float = 0.5
    #: the share of nonzero speed samples on a quantum grid that calls the speed quantized.
    quantized_share: float = 0.99
    #: the share of nonzero speed samples on the encoder's rad/s grid that confirms the speed's units.
    on_grid: float = 0.9
    #: the speed quantum over ``w_max`` from which a failed section detection names the encoder.
    resolution: float = 0.5

    def __post_init__(self) -> None:
        check_settings(self, {
            "T_s_max": POSITIVE, "T_Ei_max": POSITIVE, "T_s_over_T_Ei_max": POSITIVE, "torque_ratio": Pair(POSITIVE),
            "torque_over_M_max": POSITIVE, "speed_ratio": Pair(POSITIVE), "accel_window": POSITIVE,
            "glitch_samples": POSITIVE, "J_range": Pair(POSITIVE), "min_correlation": SHARE, "quantized_share": SHARE,
            "on_grid": SHARE, "resolution": POSITIVE})


#: The plausibility checks' bounds.
BOUNDS = PlausibilityBounds()


def check_record(record: Record) -> None:
    """Raise ``ValueError`` (one line) when the record's signals and metadata are implausible.

    Args:
        record: a ``sim.Record``, normally already validated by ``sim.records.validate`` (which
            fills in ``T_s``).
    """
    meta = record.meta
    speed = np.asarray(record.speed, dtype=np.float64)
    if record.torque is None and (record.current is None or meta.get("K_M") is None):
        return  # no torque to check: the analysis reports what is missing
    name = "torque" if record.torque is not None else "current"
    with np.errstate(over="ignore", under="ignore"):
        torque = record.motor_torque
    if name == "current":
        _check_torque_constant(np.asarray(record.current, dtype=np.float64), torque, float(meta["K_M"]))
    if speed.size < 2 or not (np.all(np.isfinite(speed)) and np.all(np.isfinite(torque))):
        return  # format problems: sim.records / the analysis report them
    T_s = record.T_s
    _check_timing(T_s, meta.get("T_Ei"))
    moves = np.ptp(speed) > 0
    if not np.any(torque != 0) and moves:  # a torque_ref would still show the sections
        raise ValueError(f"{name}: expected the test's torque steps, received zeros throughout while the speed moves "
                         f"(the {name} was not recorded?)")
    if not moves:
        return  # constant speed: the section detection says so
    _check_torque_scale(torque, name, meta)
    _check_speed_scale(speed, T_s, meta, record)
    _check_speed_quantum(speed, T_s, meta)
    _check_inertia(torque, speed, T_s, name)


def _check_torque_constant(current: np.ndarray, torque: np.ndarray, K_M: float) -> None:
    """``current * K_M`` must stay a number: finite where the current is, and not zero throughout
    where the current is not (``K_M`` beyond the float range either way)."""
    finite = np.isfinite(current)
    peak = float(np.max(np.abs(current[finite]))) if finite.any() else 0.0
    if not np.all(np.isfinite(torque[finite])):
        raise ValueError(f"metadata K_M looks implausible (K_M = {K_M:.4g} Nm/A times |current| up to {peak:.4g} A "
                         f"overflows to an infinite torque; expected the torque constant in Nm/A)")
    if peak > 0 and not np.any(torque[finite]):
        raise ValueError(f"metadata K_M looks implausible (K_M = {K_M:.4g} Nm/A times |current| up to {peak:.4g} A "
                         f"underflows to a zero torque; expected the torque constant in Nm/A)")


def unit_warnings(record: Record) -> list[IdentWarning]:
    """``units_unchecked`` for each signal whose units none of :func:`check_record`'s checks could
    test: the speed without ``w_max`` and without an ``encoder_counts`` on whose speed quantum (in
    rad/s) it lies, the torque without ``M_star`` and ``M_max``; else none."""
    meta, out = record.meta, []
    counts = meta.get("encoder_counts")
    speed = np.asarray(record.speed, dtype=np.float64)
    if meta.get("w_max") is None and (counts is None or not _on_encoder_grid(speed, record.T_s, counts)):
        given = ("neither w_max nor encoder_counts" if counts is None
                 else "no w_max, and its speed does not step in the quantum of its encoder_counts")
        out.append(IdentWarning("units_unchecked", f"the speed's units could not be checked: the record gives {given} "
                                                   "(a speed in rpm would read 9.55 x too fast); give w_max"))
    if meta.get("M_star") is None and meta.get("M_max") is None:
        what, wrong = ("current", "a current in mA") if record.torque is None else ("torque", "a torque in Nmm")
        out.append(IdentWarning("units_unchecked", f"the {what}'s units could not be checked: the record gives neither "
                                                   f"M_star nor M_max ({wrong} would read 1000 x); give one"))
    return out


def _check_timing(T_s: float, T_Ei: Any) -> None:
    if T_s > BOUNDS.T_s_max:
        raise ValueError(f"time looks like wrong units (sample time T_s = {T_s:.4g} s, "
                         f"expected <= {BOUNDS.T_s_max:g} s "
                         f"for a drive's speed loop; t in ms instead of s?)")
    if T_Ei is None:
        return
    T_Ei = float(T_Ei)
    if T_Ei > BOUNDS.T_Ei_max:
        raise ValueError(f"metadata T_Ei looks like wrong units (T_Ei = {T_Ei:.4g} s, expected a current-loop "
                         f"time constant <= {BOUNDS.T_Ei_max:g} s; given in ms instead of s?)")
    if T_Ei > 0 and T_s > BOUNDS.T_s_over_T_Ei_max * T_Ei:
        raise ValueError(f"time looks like wrong units (T_s = {T_s:.4g} s is {T_s / T_Ei:.3g} x T_Ei = {T_Ei:.4g} s, "
                         f"expected <= {BOUNDS.T_s_over_T_Ei_max:g} x; t and T_Ei in different units?)")


def _check_torque_scale(torque: np.ndarray, name: str, meta: dict[str, Any]) -> None:
    peak = float(np.percentile(np.abs(torque), 99.0))
    what = "|current| * K_M" if name == "current" else "|torque|"
    hint = "expected A with K_M in Nm/A; mA would give 1000 x" if name == "current" else "expected Nm"
    M_star = meta.get("M_star")
    if M_star is not None:
        ratio = peak / float(M_star)
        lo, hi = BOUNDS.torque_ratio
        if not lo <= ratio <= hi:
            raise ValueError(f"{name} looks like wrong units ({what} reaches {peak:.4g} Nm, {ratio:.3g} x metadata "
                             f"M_star = {float(M_star):.4g} Nm, expected {lo:g}..{hi:g} x; {hint})")
        return
    M_max = meta.get("M_max")
    if M_max is not None and peak > BOUNDS.torque_over_M_max * float(M_max):
        raise ValueError(f"{name} looks like wrong units ({what} reaches {peak:.4g} Nm, {peak / float(M_max):.3g} x "
                         f"metadata M_max = {float(M_max):.4g} Nm, expected <= {BOUNDS.torque_over_M_max:g} x; {hint})")


def _speed_units(meta: dict[str, Any], T_s: float | None) -> dict[str, float]:
    """Speed units a record might wrongly use, as multiples of rad/s."""
    units = {"rpm": 60.0 / (2.0 * math.pi), "deg/s": 180.0 / math.pi, "rev/s": 1.0 / (2.0 * math.pi)}
    counts = meta.get("encoder_counts")
    if counts is not None:
        units["counts/s"] = float(counts) / (2.0 * math.pi)
        if T_s is not None:
            units["counts per sample"] = float(counts) * T_s / (2.0 * math.pi)
    return units


def _guess(ratio: float, units: dict[str, float]) -> str:
    """``"; rpm?"`` when ``ratio`` lies near one unit's factor (the test overshoots w_max by up to 1.6)."""
    best = min(units, key=lambda u: abs(math.log(ratio / units[u]) - 0.2))
    return f"; {best} instead of rad/s?" if abs(math.log(ratio / units[best]) - 0.2) < 0.6 else ""


def overshoot_allowance(speed: np.ndarray, T_s: float, T_Ei: float | None) -> float:
    """The speed [units of ``speed``] a motor can still gain after the switching law has taken its
    torque away: the record's own acceleration times the current loop's lag and the sampling delays
    (a first-order current loop adds ``M* T_Ei / J``; detection and application add up to ~2.5
    samples). Small drives with small inertias overshoot ``w_max`` by several times this way."""
    m = BOUNDS.accel_window
    if speed.size <= m or T_Ei is None:
        return 0.0
    accel = np.abs(speed[m:] - speed[:-m]) / (m * T_s)  # window of m samples: quantization / m
    return float(np.percentile(accel, 99)) * (2.0 * float(T_Ei) + 3.0 * T_s)


def _check_speed_scale(speed: np.ndarray, T_s: float, meta: dict[str, Any], record: Record) -> None:
    w_max = meta.get("w_max")
    if w_max is None:
        return
    abs_speed = np.abs(speed)
    peak = float(np.max(abs_speed))
    ratio = peak / float(w_max)
    lo, hi = BOUNDS.speed_ratio
    timed_out = any_timed_out(meta)
    counts = meta.get("encoder_counts")
    quantum = speed_quantum(float(counts), T_s) if counts else 0.0  # an encoder's speed reads up to one count high
    allowed = hi * float(w_max) + overshoot_allowance(speed, T_s, meta.get("T_Ei")) + quantum
    above = np.flatnonzero(abs_speed > allowed)
    if 0 < above.size <= BOUNDS.glitch_samples:  # a few samples far above the rest: no unit does that
        rest = float(np.max(np.delete(abs_speed, above)))
        at = float(record.t[int(above[np.argmax(abs_speed[above])])])  # a time, as the file's rows and a record's index agree on
        raise ValueError(f"speed has {above.size} sample(s) far above the rest (peak |speed| {peak:.4g} rad/s at "
                         f"t = {at:.9g} s, the others at most {rest:.4g}; metadata "
                         f"w_max = {float(w_max):.4g} rad/s): glitches in the recording?")
    if ratio < lo and not timed_out and peak <= allowed:
        incomplete = incomplete_run(record, upto=1)  # cut in I, before the speed reached w_max: not its units
        if incomplete is not None:
            raise ValueError(incomplete)
    if peak > allowed or (ratio < lo and not timed_out):
        guess = _guess(ratio, _speed_units(meta, meta.get("T_s")))
        raise ValueError(f"speed looks like wrong units (peak |speed| {peak:.4g} is {ratio:.3g} x metadata "
                         f"w_max = {float(w_max):.4g} rad/s, expected {lo:g}..{hi:g} x{guess})")


def on_grid(x: np.ndarray, quantum: float) -> float:
    """Share of ``x`` within rounding of an integer multiple of ``quantum`` (float32 speeds included;
    at most 0.01 quanta off, so that huge multiples do not pass by their relative rounding)."""
    u = x / quantum
    return float(np.mean(np.abs(u - np.round(u)) <= np.minimum(0.01, 1e-3 + 2e-7 * np.abs(u))))


def _check_speed_quantum(speed: np.ndarray, T_s: float, meta: dict[str, Any]) -> None:
    counts = meta.get("encoder_counts")
    if counts is None:
        return
    if _on_encoder_grid(speed, T_s, counts):
        return  # quantized in rad/s: its units are right
    x = speed[speed != 0]
    if x.size < 32:
        return  # too few moving samples to judge
    q_w = speed_quantum(float(counts), T_s)
    for unit, factor in _speed_units(meta, T_s).items():
        if on_grid(x, q_w * factor) >= BOUNDS.quantized_share:
            raise ValueError(f"speed looks like wrong units (its values are multiples of {q_w * factor:.6g}, the "
                             f"encoder's speed quantum 2*pi/(encoder_counts*T_s) = {q_w:.6g} rad/s in {unit}; "
                             f"expected rad/s)")


def _on_encoder_grid(speed: np.ndarray, T_s: float, counts: float) -> bool:
    """Whether ``speed`` steps in the speed quantum of ``counts`` in rad/s (:attr:`PlausibilityBounds.on_grid` of its
    nonzero samples, at least 32 of them): the encoder then confirms its units. A speed not
    quantized at all (filtered) is not judged by the encoder."""
    x = speed[speed != 0]
    return x.size >= 32 and on_grid(x, speed_quantum(float(counts), T_s)) >= BOUNDS.on_grid


def resolution_hint(record: Record) -> str | None:
    """Why the test's sections may not show, where the encoder hardly resolves the test: a speed
    quantized in rad/s in steps ``2 pi / (encoder_counts T_s)`` of :attr:`PlausibilityBounds.resolution` x ``w_max``
    (or of the peak speed) or more; else None."""
    counts, speed = record.meta.get("encoder_counts"), np.asarray(record.speed, dtype=np.float64)
    x = speed[speed != 0]
    if counts is None or not x.size:
        return None
    q_w = speed_quantum(float(counts), record.T_s)
    w_max = float(record.meta.get("w_max") or np.abs(speed).max())
    if q_w < BOUNDS.resolution * w_max or on_grid(x, q_w) < BOUNDS.quantized_share:
        return None
    return (f"the encoder hardly resolves this test: its speed quantum 2*pi/(encoder_counts*T_s) = {q_w:.4g} rad/s "
            f"is {q_w / w_max:.2g} x w_max = {w_max:.4g} rad/s; raise w_max, or record a finer speed")


def _check_inertia(torque: np.ndarray, speed: np.ndarray, T_s: float, name: str) -> None:
    impulse = np.cumsum(torque) * T_s  # int M dt [Nm s]
    dw = speed - speed[0]
    den = float(dw @ dw) * float(impulse @ impulse)
    if not den > 0:
        return
    corr = float(impulse @ dw) / math.sqrt(den)
    if corr < -BOUNDS.min_correlation:
        raise ValueError(f"speed does not follow the {name} (it falls under positive {name}: correlation "
                         f"{corr:.2f} of speed change and {name} integral); check the sign of speed or {name}")
    if corr < BOUNDS.min_correlation:
        return  # no clear one-mass behaviour: the section detection and fit judge it
    J = float(impulse @ dw) / float(dw @ dw)
    lo, hi = BOUNDS.J_range
    if not lo <= J <= hi:
        raise ValueError(f"speed/{name} look like wrong units (one-mass inertia estimate {J:.3g} kg m^2, "
                         f"expected {lo:g}..{hi:g} kg m^2)")
