"""Test-signal adaptation (knowledge base, SPEC 8): choose ``M_star`` and ``w_max`` for STEP 1.

Start small, run the six-section test on the plant, judge from the response only (measured
motor speed, the drive's own torque reference and section counter, the timeout flags; no truth)
whether it is informative, and raise ``M_star`` and/or ``w_max`` by factor-2 steps until it is,
never beyond the user's limits on torque (``M_max``, ``M_star_max``), speed (``w_limit``) and
travel (``travel_limit``). The travel and the peak speed of the next run are predicted from the
current one before it runs (travel ~ ``w_max^2 J / M_star``), so a step that would cross a limit
is shortened first. Rules E1-E7 in docs/commissioning.md.

Measured figures per run (all from the response):

* ``samples_min``: fewest samples in any of the six sections (STEP 2 needs ``>= min_section_samples``),
* ``timed_out``: a section ended by its safety timeout (not by its speed condition),
* ``range_quanta``: speed range ``max - min`` over the speed quantum ``q_w``,
* ``osc_quanta``: RMS of the speed minus a per-section quadratic fit (the oscillating part), in ``q_w``,
* ``peak_speed`` [rad/s], ``travel`` [rad] (largest ``|phi|`` of the integrated measured speed),
  ``peak_torque_ref`` [Nm], ``peak_torque`` [Nm] (measured current x ``K_M``).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import torch

__all__ = [
    "ExcitationLimits",
    "ExcitationRules",
    "ExcitationResult",
    "measure_response",
    "adapt_test_signal",
    "sim_test_runner",
]


@dataclass(frozen=True)
class ExcitationLimits:
    """User limits. ``M_star_max`` [Nm] (None: the drive's ``M_max``), ``w_limit`` [rad/s] on
    ``|speed|``, ``travel_limit`` [rad] on ``|phi|`` (motor angle from the start position)."""

    w_limit: float
    travel_limit: float
    M_star_max: float | None = None

    def __post_init__(self) -> None:
        for name in ("w_limit", "travel_limit"):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and math.isfinite(v) and v > 0):
                raise ValueError(f"ExcitationLimits.{name}: expected a finite number > 0, received {v!r}")
        if self.M_star_max is not None and not (math.isfinite(self.M_star_max) and self.M_star_max > 0):
            raise ValueError(f"ExcitationLimits.M_star_max: expected > 0 or None, received {self.M_star_max!r}")


@dataclass(frozen=True)
class ExcitationRules:
    """Rule constants (docs/commissioning.md, E1-E7).

    ``M_star_start``: first ``M_star`` as a fraction of the torque cap. ``w_max_start`` [rad/s]:
    first ``w_max`` (further bounded by ``0.1 w_limit`` and by the travel of an inertia
    ``J_prior_max`` [kg m^2]). ``factor``: raise step. ``min_section_samples``,
    ``min_range_quanta``, ``min_osc_quanta``: what "informative" means. ``speed_margin``,
    ``travel_margin``: fractions of the limits a predicted run may use. ``max_iterations``.
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


@dataclass
class ExcitationResult:
    """``signal``: the final TestSignalConfig; ``response``: its response (as the plant returned
    it); ``log``: one dict per run (``iteration, M_star, w_max``, the measured figures of
    :func:`measure_response`, ``decision``, ``reason``); ``informative``: the final run passed."""

    signal: Any
    response: Any
    log: list[dict[str, Any]] = field(default_factory=list)
    informative: bool = False
    reason: str = ""


def _np(x: Any) -> np.ndarray:
    if isinstance(x, torch.Tensor):
        return x.detach().to(torch.float64).cpu().numpy()
    return np.asarray(x, dtype=np.float64)


def _signals(resp: Any) -> dict[str, np.ndarray]:
    """One system's signals from a Response (batch ``()`` or ``(1,)``) or a Record-like object."""
    def get(name: str) -> Any:
        if isinstance(resp, dict):
            return resp.get(name)
        return getattr(resp, name, None)

    speed = get("speed")
    if speed is None:
        raise TypeError(f"response: expected a Response/Record with 'speed', received {type(resp).__name__}")
    speed = _np(speed).reshape(-1, _np(speed).shape[-1])
    if speed.shape[0] != 1:
        raise ValueError(f"response: expected one system, received a batch of {speed.shape[0]}")
    n = speed.shape[1]
    length = get("length")
    if length is not None:
        n = int(_np(length).reshape(-1)[0])
    out = {"speed": speed[0, :n]}
    for name in ("torque_ref", "current", "torque", "section", "timed_out"):
        v = get(name)
        if v is not None:
            a = _np(v)
            out[name] = a.reshape(-1)[:n] if name != "timed_out" else a.reshape(-1)
    return out


def measure_response(resp: Any, drive: Any) -> dict[str, Any]:
    """Measured figures of one test response (see module docstring); uses no truth.

    ``resp``: the plant's answer for one system (``speed`` ``N`` [rad/s], ``section`` ``N`` (1..6,
    0 = tail), optional ``torque_ref``, ``current``/``torque``, ``timed_out``, ``length``).
    """
    s = _signals(resp)
    T_s, q_w = float(drive.T_s), float(drive.q_w)
    w = s["speed"]
    if len(w) < 2 or not np.isfinite(w).all():
        raise ValueError("response: expected a finite speed with at least 2 samples")
    sec = s.get("section")
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
    phi = np.cumsum(w) * T_s
    timed = s.get("timed_out")
    torque = s.get("torque")
    if torque is None and s.get("current") is not None:
        torque = s["current"] * float(drive.K_M)
    return {
        "samples_per_section": counts,
        "samples_min": min(counts),
        "timed_out": bool(timed is not None and np.any(timed)),
        "range_quanta": float((w.max() - w.min()) / q_w),
        "osc_quanta": osc,
        "peak_speed": float(np.abs(w).max()),
        "travel": float(np.abs(phi).max()),
        "peak_torque_ref": float(np.abs(s["torque_ref"]).max()) if "torque_ref" in s else math.nan,
        "peak_torque": float(np.abs(torque).max()) if torque is not None else math.nan,
        "duration": len(w) * T_s,
    }


def sim_test_runner(params: Any, drive: Any, *, seed: int = 0, **kwargs: Any) -> Callable[[Any], Any]:
    """``signal -> Response`` running ``sim.simulate_test`` on one simulated plant (a stand-in
    for the real drive; a real drive adapter has the same shape)."""
    import sim

    counter = {"n": 0}

    def run(signal: Any) -> Any:
        counter["n"] += 1
        return sim.simulate_test(params, drive, signal, seed=seed + counter["n"], **kwargs)

    return run


def adapt_test_signal(
    run_test: Callable[[Any], Any],
    drive: Any,
    limits: ExcitationLimits,
    rules: ExcitationRules | None = None,
    *,
    signal_type: Any = None,
    timeout: float = 10.0,
    tail: float = 0.05,
) -> ExcitationResult:
    """Adapt ``M_star`` and ``w_max`` until the test response is informative (rules E1-E7).

    Args:
        run_test: the plant: ``signal -> response`` (e.g. :func:`sim_test_runner` or a real drive).
        drive: DriveConfig (``M_max``, ``T_s``, ``K_M``, ``q_w``).
        limits: user limits (torque, speed, travel).
        rules: rule constants.
        signal_type: the TestSignalConfig class (default ``sim.TestSignalConfig``).
        timeout, tail: passed to every TestSignalConfig [s].

    Returns :class:`ExcitationResult` with the last run's signal and response (every run stayed
    within the limits by prediction; the log records the measured peaks of each run).
    """
    rules = rules or ExcitationRules()
    if not isinstance(limits, ExcitationLimits) or not isinstance(rules, ExcitationRules):
        raise TypeError(f"limits, rules: expected ExcitationLimits, ExcitationRules, received "
                        f"{type(limits).__name__}, {type(rules).__name__}")
    if not callable(run_test):
        raise TypeError(f"run_test: expected a callable signal -> response, received {type(run_test).__name__}")
    if signal_type is None:
        import sim

        signal_type = sim.TestSignalConfig
    if rules.factor <= 1 or rules.max_iterations < 1:
        raise ValueError(f"rules: expected factor > 1 and max_iterations >= 1, received {rules.factor}, {rules.max_iterations}")
    M_cap = float(drive.M_max) if limits.M_star_max is None else min(float(drive.M_max), limits.M_star_max)
    # E1: start small; the first travel is bounded by an a-priori inertia bound (w^2 J / M* x 3)
    M_star = rules.M_star_start * M_cap
    w_travel0 = math.sqrt(rules.travel_margin * 0.25 * limits.travel_limit * M_star / (3.0 * rules.J_prior_max))
    w_max = min(rules.w_max_start, 0.1 * limits.w_limit, w_travel0)
    log: list[dict[str, Any]] = []
    signal = resp = None
    informative, reason = False, ""
    for it in range(rules.max_iterations):
        signal = signal_type(M_star=M_star, w_max=w_max, timeout=timeout, tail=tail)
        resp = run_test(signal)
        m = measure_response(resp, drive)
        entry: dict[str, Any] = {"iteration": it, "M_star": M_star, "w_max": w_max, **m}
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
        M_next = min(M_star * rules.factor, M_cap) if want_M else M_star
        w_next = w_max * rules.factor if want_w else w_max
        if m["timed_out"] and M_next <= M_star:
            w_next = w_max / rules.factor  # E3b: torque at its cap: lower the speed target instead
        # E6: predict the next run's peak speed and travel from this one; shorten the step
        over = max(m["peak_speed"] - w_max, 0.0)
        w_cap_speed = (rules.speed_margin * limits.w_limit - over * M_next / M_star)
        # travel ~ w_max^2 J / M_star; the benefit of a larger M_star is counted with exponent
        # 1/2 only (friction and the coasting section II do not scale): conservative
        travel_per = m["travel"] / w_max**2 if m["travel"] > 0 else 0.0
        def travel_gain(M_new: float) -> float:
            return math.sqrt(M_star / M_new)
        w_cap_travel = math.sqrt(rules.travel_margin * limits.travel_limit / (travel_per * travel_gain(M_next))) if travel_per > 0 else math.inf
        if want_w and w_cap_travel < w_next and M_next < M_cap:
            # E6b: travel ~ w_max^2 / M_star: more torque buys speed range within the same travel
            M_next = min(M_next * rules.factor, M_cap)
            w_cap_speed = rules.speed_margin * limits.w_limit - over * M_next / M_star
            w_cap_travel = math.sqrt(rules.travel_margin * limits.travel_limit / (travel_per * travel_gain(M_next)))
        w_next = min(w_next, w_cap_speed, w_cap_travel)  # may lower w_max: the limits come first
        if w_max < w_next < w_max * rules.factor**0.1 and M_next <= M_star:
            w_next = w_max  # E6c: a raise of less than factor^0.1 is no progress
        entry["predicted_peak_speed"] = w_next + over * M_next / M_star
        entry["predicted_travel"] = travel_per * w_next**2 * travel_gain(M_next)
        problems = [p for p, on in (("section timed out", m["timed_out"]), ("sections too short", short),
                                    ("speed range too small", small), ("oscillation not visible", hidden)) if on]
        if not problems:
            informative, reason = True, "informative"
            entry.update(decision="accept", reason=reason)
            log.append(entry)
            break
        if hidden and not (m["timed_out"] or short or small) and M_star >= M_cap:
            # E7: oscillation still below resolution at the torque cap: stiff or weakly coupled mechanics
            informative, reason = True, "informative (oscillation not visible at the torque cap: stiff or weakly coupled)"
            entry.update(decision="accept", reason=reason)
            log.append(entry)
            break
        changed = (M_next > M_star * (1 + 1e-9)) or abs(w_next - w_max) > 1e-9 * w_max
        if not changed or w_next <= 0:
            reason = f"limits reached before the response was informative: {', '.join(problems)}"
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
        reason = f"no informative response after {rules.max_iterations} runs"
    return ExcitationResult(signal=signal, response=resp, log=log, informative=informative, reason=reason)
