"""The closed-loop experiment (scenario), its cost, and the fine-tuning of a proposed speed
controller by a Nelder-Mead simplex search on the identified model.

The scenario (one run, from rest, SPEC 8.1): six segments of ``n_segment`` samples: speed steps
``+w_step``, ``0``, ``-w_step``, ``0`` (the travel returns to the start), then a disturbance torque
``M_dist`` added to the torque reference, and its removal. ``w_step`` and ``M_dist`` are planned
from the identified model (:func:`plan_scenario`) so that the predicted peak speed and travel use
at most ``limit_use`` of the user's limits, and the P-kick at most 20 % of the torque cap.

The cost of a measured run (dimensionless; docs/commissioning.md, "Tuning cost")::

    cost = ITAE_steps + load_weight ITAE_dist
         + overshoot_weight (max(0, overshoot - 0.05)^2 + max(0, load_overshoot - 0.05)^2)
         + oscillation_weight (E_osc + E_osc,load)

``ITAE`` per segment over ``tau = t w_c`` (time restarts at each segment), errors over ``w_step``
(steps) or over the expected dip ``M_dist / (J_sigma w_c)`` (disturbance); ``E_osc`` = mean square
of the speed minus its mean over the last quarter of each segment, over ``w_step^2``. The load
terms use the load speed that the identified model estimates from the measured motor speed
(:func:`load_estimate`; for one-mass mechanics there are none). A run that the drive stopped at a
limit, that is not finite, exceeds ``divergence_factor w_step`` or does not settle near its
reference costs ``unstable_cost`` (+ a term that grows with the excursion): it is never a good one.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np
import scipy.optimize
import scipy.signal

import sim
from training._settings import AT_LEAST_ONE, NON_NEGATIVE, POSITIVE_OR_INF, SHARE, check_settings

from ._loop import Mechanics, closed_loop_matrices, frequency_grid, linear_plant
from ._rules import ControllerProposal, ControllerSpec

__all__ = [
    "TuningScenario", "TuningResult", "plan_scenario", "closed_loop_cost", "response_figures", "load_estimate",
    "model_response", "tune_controller", "applied_torque_gain", "Gains", "loop_verdict", "LOOP_VERDICTS", "BOUNDED_VERDICTS",
    "USABLE_VERDICTS", "UNSCORED_VERDICTS", "ScenarioSizing", "SearchSettings", "SCENARIO_SIZING", "SEARCH",
]

#: (Kp [Nm s/rad], Ti [s], T_f [s]).
Gains = tuple[float, float, float]
_SEGMENTS = 6  # +w, 0, -w, 0, disturbance on, off


@dataclass(frozen=True)
class ScenarioSizing:
    """How :func:`plan_scenario` sizes the closed-loop experiment beyond its arguments."""

    min_segment: int = 100
    """Fewest samples of one segment (a fast loop still gets a readable step)."""
    kick_share: float = 0.2
    """The P-kick ``Kp w_step`` and the disturbance ``M_dist`` at most this share of the torque cap."""

    def __post_init__(self) -> None:
        check_settings(self, {"min_segment": AT_LEAST_ONE, "kick_share": SHARE})


@dataclass(frozen=True)
class SearchSettings:
    """The cost landscape and the stopping rule of :func:`tune_controller`'s Nelder-Mead search."""

    max_load_peak_dB: float = 6.0
    """A candidate may trade the motor against the load only while its reference-to-load-speed peak on
    the identified model stays within this (SPEC 8.2: the load must not ring), or within the
    proposal's own peak where that is higher; beyond it, it is not a solution."""
    min_crossover: float = 1.0
    """A candidate's crossover on the identified model is at least this share of the proposal's (the
    design placed it at the largest the guarantee allows: SPEC 8.2's deliverable); below it, it is not a
    solution. The search shapes the loop within that bandwidth (the integral time, the filter, a higher
    gain where the margins allow), never by giving it back for a lower ITAE (docs/commissioning.md,
    section 4, measures what that cost)."""
    phase_deficit_per_dB: float = 10.0
    """A candidate that misses the margins pays its phase deficit [deg] over this plus its gain deficit [dB]."""
    unstable_penalty: float = 100.0
    """What an unstable candidate (or one with no finite deficit) pays above ``unstable_cost``."""
    xatol: float = 0.01
    """The simplex stops when its points lie within this of each other in ``log`` gains ..."""
    fatol: float = 1e-4
    """... and their costs within this."""

    def __post_init__(self) -> None:
        check_settings(self, {"max_load_peak_dB": POSITIVE_OR_INF, "min_crossover": NON_NEGATIVE,
                              "phase_deficit_per_dB": POSITIVE_OR_INF,
                              "unstable_penalty": POSITIVE_OR_INF, "xatol": POSITIVE_OR_INF, "fatol": POSITIVE_OR_INF})


#: How :func:`plan_scenario` sizes the experiment.
SCENARIO_SIZING = ScenarioSizing()
#: How :func:`tune_controller` searches.
SEARCH = SearchSettings()


@dataclass(frozen=True)
class TuningScenario:
    """The closed-loop experiment and the weights of its cost (module docstring)."""

    T_s: float
    w_step: float
    """Speed step [rad/s]; also the scale of the speed errors."""
    M_dist: float
    """Disturbance torque [Nm] added to the torque reference in segment 5."""
    n_segment: int
    T_ref: float
    """Time scale [s] of the ITAE terms (``1/w_c`` of the proposal)."""
    dip_ref: float
    """Expected disturbance dip [rad/s]: the scale of the disturbance errors."""
    two_mass: bool = False
    """The load terms count (elastic mechanics)."""
    load_weight: float = 0.5
    overshoot_allowed: float = 0.05
    overshoot_weight: float = 20.0
    oscillation_weight: float = 100.0
    divergence_factor: float = 20.0
    unstable_cost: float = 1e4
    q_w: float = 0.0
    """The drive's speed quantum [rad/s]: the settling band is never narrower than ``settle_quanta`` of it."""
    settle_band: float = 0.05
    """Settling band around the reference, as a share of ``w_step`` (at least ``settle_quanta q_w``)."""
    settle_quanta: float = 3.0
    saturated_share: float = 0.05
    """A run whose torque reference sits at the torque cap in more than this share of its samples is saturated."""
    limit_cycle_share: float = 0.1
    """A run whose speed, over the last quarter of the segments, swings (RMS about its mean, median of the six
    segments) by more than this share of ``w_step`` (and more than ``settle_quanta q_w``) is in a limit cycle."""
    model_cost_factor: float = 20.0
    """A run that costs more than this many times what the identified model predicts for the same gains is unlike
    its model (the guarantee, computed on the model, does not describe it)."""
    model_warn_factor: float = 8.0
    """A delivered run above this many times its model's cost gets ``loop_unlike_model`` (the 50-plant studies'
    delivered and candidate runs: at most 6.7 x, median 0.9-1.3 x; a drive applying 20 x the law's torque: 18.5 x)."""
    torque_gain_tolerance: float = 1.25
    """A run whose recorded torque is more than this factor off the law replayed on its record
    (:func:`applied_torque_gain`) was not run with the law as given: ``loop_unlike_model``."""
    not_settled_error: float = 0.5
    """A first step that ends (mean over the last quarter of its segment) more than this share of ``w_step`` off its
    reference does not settle: it costs ``unstable_cost``."""
    at_cap: float = 0.99
    """A torque reference at or above this share of the torque cap sits at the cap (``saturated_share``)."""

    @property
    def band(self) -> float:
        """The settling band [rad/s]."""
        return max(self.settle_band * self.w_step, self.settle_quanta * self.q_w)

    @property
    def n_samples(self) -> int:
        return _SEGMENTS * self.n_segment

    @property
    def n_tail(self) -> int:
        """The samples at the end of each segment where it should have settled: its last quarter, at least 4."""
        return max(self.n_segment // 4, 4)

    def references(self) -> np.ndarray:
        """Speed reference per segment [rad/s] (``6``)."""
        return np.array([1.0, 0.0, -1.0, 0.0, 0.0, 0.0]) * self.w_step

    def scenario(self) -> sim.Scenario:
        """The per-sample arrays a drive runs (:class:`sim.Scenario`)."""
        w_ref = np.repeat(self.references(), self.n_segment)
        M = np.zeros(_SEGMENTS)
        M[4] = self.M_dist
        return sim.Scenario(w_ref=w_ref, M_dist=np.repeat(M, self.n_segment))

    def to_dict(self) -> dict[str, float]:
        return {"w_step": self.w_step, "M_dist": self.M_dist, "n_segment": self.n_segment, "T_s": self.T_s,
                "duration": self.n_samples * self.T_s}


def load_estimate(mech: Mechanics | None, speed: np.ndarray, T_s: float) -> np.ndarray | None:
    """The load speed ``*batch x N`` [rad/s] that the two-mass model ``mech`` gives for the measured
    motor speed (the load side driven through the shaft: ``(D_F s + C_F) / (J_L s^2 + (D_F + mu_F)
    s + C_F)``, Tustin with pre-warping at ``sqrt(C_F/J_L)``); None for one-mass mechanics."""
    if mech is None or not mech.two_mass:
        return None
    dv = mech.derived
    w_n = math.sqrt(dv.C_F / dv.J_L)
    c = w_n / math.tan(min(w_n * T_s / 2, 1.5))
    b, a = scipy.signal.bilinear([dv.D_F, dv.C_F], [dv.J_L, dv.D_F + mech.mu_F, dv.C_F], fs=c / 2)
    return scipy.signal.lfilter(b, a, speed, axis=-1)


def model_response(mech: Mechanics, config: Any, gains: Sequence[Gains], notch: Any, scenario: TuningScenario,
                   w_step: float | None = None, M_dist: float | None = None) -> np.ndarray:
    """The measured motor speed ``B x N`` [rad/s] of each gain set on the linear model of ``mech``
    (:func:`closed_loop_matrices`: the law without its torque clamp) over the experiment ``scenario`` (its
    ``w_step`` and ``M_dist`` replaced where given)."""
    plant = linear_plant(mech, config)
    n, m = scenario.n_segment, scenario.n_samples
    refs = scenario.references() / scenario.w_step * (scenario.w_step if w_step is None else w_step)
    dist = np.zeros(_SEGMENTS)
    dist[4] = scenario.M_dist if M_dist is None else M_dist
    out = np.zeros((len(gains), m))
    for j, (Kp, Ti, T_f) in enumerate(gains):
        A, b_r, b_d, c, _ = closed_loop_matrices(plant, Kp, Ti, T_f, notch)
        s = np.zeros(A.shape[0])
        y = out[j]
        with np.errstate(over="ignore", invalid="ignore"):
            for k in range(m):
                y[k] = c @ s
                s = A @ s + b_r * refs[k // n] + b_d * dist[k // n]
                if not np.isfinite(s).all():
                    y[k:] = np.inf
                    break
    return out


def plan_scenario(proposal: ControllerProposal, extra: Sequence[Gains], config: Any, limits: sim.DriveLimits, *,
                  limit_use: float = 0.5, settle_factor: float = 25.0, max_samples: int = 6000) -> tuple[TuningScenario, dict[str, float]]:
    """The scenario for ``proposal`` and the gain sets ``extra``, sized on the proposal's model.

    ``n_segment = settle_factor / w_c`` (within ``[100, max_samples / 6]`` samples); ``w_step`` and
    ``M_dist`` the largest for which every gain set's predicted peak speed and travel (motor, and
    the estimated load) stay within ``limit_use`` of the limits (half each), with the P-kick
    ``Kp w_step`` and ``M_dist`` at most 20 % of the torque cap. Returns the scenario and the
    prediction (``peak_speed``, ``travel``, ``speed_quanta`` of the step).
    """
    T_s = float(config.T_s)
    mech = proposal.mechanics
    w_c = proposal.figures.get("w_c", math.nan)
    if not (math.isfinite(w_c) and w_c > 0):
        raise ValueError(f"proposal figures: expected a finite crossover w_c > 0, received {w_c}")
    n_seg = int(min(max(settle_factor / (w_c * T_s), SCENARIO_SIZING.min_segment), max_samples // _SEGMENTS))
    M_cap = limits.torque_cap(config)
    unit = TuningScenario(T_s=T_s, w_step=1.0, M_dist=1.0, n_segment=n_seg, T_ref=1 / w_c,
                          dip_ref=1.0 / (mech.J_sigma * w_c), two_mass=mech.two_mass)
    gains = [(proposal.Kp, proposal.Ti, proposal.T_f), *extra]

    def peaks(w: np.ndarray) -> tuple[float, float]:
        loads = [w] + ([load_estimate(mech, w, T_s)] if mech.two_mass else [])
        return (max(float(np.abs(v).max()) for v in loads), max(float(np.abs(np.cumsum(v, -1) * T_s).max()) for v in loads))

    pw_r, pt_r = peaks(model_response(mech, config, gains, proposal.notch, unit, 1.0, 0.0))
    pw_d, pt_d = peaks(model_response(mech, config, gains, proposal.notch, unit, 0.0, 1.0))
    half = 0.5 * limit_use
    kick = SCENARIO_SIZING.kick_share * M_cap
    w_step = min(kick / max(g[0] for g in gains), half * limits.w_max / pw_r, half * limits.travel / pt_r)
    M_dist = min(kick, half * limits.w_max / max(pw_d, 1e-300), half * limits.travel / max(pt_d, 1e-300))
    if not (math.isfinite(w_step) and w_step > 0 and math.isfinite(M_dist) and M_dist > 0):
        raise ValueError(f"scenario: the model predicts no bounded response (w_step {w_step}, M_dist {M_dist})")
    q_w = sim.speed_quantum(float(config.encoder_counts), T_s)
    scenario = replace(unit, w_step=float(w_step), M_dist=float(M_dist), dip_ref=M_dist / (mech.J_sigma * w_c), q_w=q_w)
    pw, pt = peaks(model_response(mech, config, gains, proposal.notch, scenario))
    return scenario, {"peak_speed": pw, "travel": pt, "speed_quanta": w_step / q_w}


#: Where a diverging run's speeds are clipped for scoring [rad/s] (finite arithmetic; it is unstable anyway).
_CLIP = 1e30


def _clipped(speed: np.ndarray) -> np.ndarray:
    """``speed`` with NaN and inf replaced and every value within ``+-_CLIP``."""
    return np.clip(np.nan_to_num(speed, nan=_CLIP, posinf=_CLIP, neginf=-_CLIP), -_CLIP, _CLIP)


def _segments(w: np.ndarray, scenario: TuningScenario) -> np.ndarray:
    """``*batch x N`` -> ``*batch x 6 x n_segment`` (N must be the scenario's length)."""
    return w.reshape(*w.shape[:-1], _SEGMENTS, scenario.n_segment)


def closed_loop_cost(speed: np.ndarray, scenario: TuningScenario, mech: Mechanics | None = None,
                     aborted: Any = False) -> tuple[np.ndarray, dict[str, np.ndarray]]:
    """Cost ``*batch`` of measured motor speeds ``*batch x N`` [rad/s] over ``scenario`` (module docstring);
    ``aborted``: the drive stopped the run (bool ``*batch``). A run shorter than the scenario (the
    drive stopped it) is padded with its last value and counts as stopped.

    Returns ``(cost, terms)`` with terms ``itae_steps, itae_dist, overshoot, load_overshoot, osc,
    load_osc, motor, load, unstable`` (``motor`` + ``load`` = cost of a settled run).
    """
    w = np.asarray(speed, dtype=np.float64)
    N = scenario.n_samples
    short = w.shape[-1] < N
    if short:
        w = np.concatenate([w, np.repeat(w[..., -1:], N - w.shape[-1], -1)], -1) if w.shape[-1] else np.zeros((*w.shape[:-1], N))
    w = w[..., :N]
    aborted = np.asarray(aborted, dtype=bool) | short
    seg = _segments(_clipped(w), scenario)
    n, ws = scenario.n_segment, scenario.w_step
    dt = scenario.T_s / scenario.T_ref
    tau = np.arange(n) * dt
    refs = scenario.references()
    prev = np.concatenate([[0.0], refs[:-1]])
    direction = np.sign(refs - prev)[:4]

    def overshoot(s: np.ndarray) -> np.ndarray:
        return np.max((s[..., :4, :] - refs[:4, None]) * direction[:, None], axis=(-1, -2)).clip(0) / ws

    def osc(s: np.ndarray) -> np.ndarray:
        tail = s[..., -scenario.n_tail:]
        return ((tail - tail.mean(-1, keepdims=True)) ** 2).mean(-1).sum(-1) / ws**2

    with np.errstate(over="ignore", invalid="ignore"):  # a diverging run: inf terms, scored as unstable below
        return _cost(w, seg, scenario, mech, aborted, tau, dt, refs, direction, overshoot, osc)


def _cost(w: np.ndarray, seg: np.ndarray, scenario: TuningScenario, mech: Mechanics | None, aborted: np.ndarray, tau: np.ndarray,
          dt: float, refs: np.ndarray, direction: np.ndarray, overshoot: Callable[[np.ndarray], np.ndarray],
          osc: Callable[[np.ndarray], np.ndarray]) -> tuple[np.ndarray, dict[str, np.ndarray]]:
    ws = scenario.w_step
    err = np.abs(seg - refs[:, None])
    itae_steps = (tau * err[..., :4, :] / ws).sum(-1).mean(-1) * dt
    itae_dist = (tau * err[..., 4:, :] / scenario.dip_ref).sum(-1).mean(-1) * dt
    os_m, osc_m = overshoot(seg), osc(seg)
    load = load_estimate(mech, w, scenario.T_s) if scenario.two_mass else None
    if load is not None:
        ls = _segments(_clipped(load), scenario)
        os_l, osc_l = overshoot(ls), osc(ls)
    else:
        os_l = osc_l = np.zeros_like(os_m)
    ow, oa = scenario.overshoot_weight, scenario.overshoot_allowed
    motor = itae_steps + scenario.load_weight * itae_dist + ow * (os_m - oa).clip(0) ** 2 + scenario.oscillation_weight * osc_m
    load_part = ow * (os_l - oa).clip(0) ** 2 + scenario.oscillation_weight * osc_l
    excursion = np.abs(seg).max(axis=(-1, -2)) / ws
    end_error = np.abs(seg[..., 0, -scenario.n_tail:].mean(-1) - ws) / ws
    unstable = aborted | ~np.isfinite(w).all(-1) | (excursion > scenario.divergence_factor) | (end_error > scenario.not_settled_error)
    cost = motor + load_part
    bad = scenario.unstable_cost + np.log1p(np.minimum(excursion, _CLIP))
    cost = np.where(unstable | ~np.isfinite(cost), bad, cost)
    return cost, {"itae_steps": itae_steps, "itae_dist": itae_dist, "overshoot": os_m, "load_overshoot": os_l,
                  "osc": osc_m, "load_osc": osc_l, "motor": motor, "load": load_part, "unstable": unstable.astype(float)}


def response_figures(speed: np.ndarray, scenario: TuningScenario, mech: Mechanics | None = None) -> dict[str, float]:
    """Figures of one run ``N`` [rad/s]: first step ``rise_time`` (10-90 %) [s], ``overshoot_pct``,
    ``settling_time`` (inside ``scenario.band``: 5 % of ``w_step``, at least 3 speed quanta) [s]; ``load_overshoot_pct`` (estimated load speed, two-mass);
    disturbance ``dist_peak`` [rad/s] (largest speed change) and ``dist_recovery_time`` [s] (back
    inside the band). inf where a run never got there."""
    w = np.asarray(speed, dtype=np.float64)
    if len(w) < scenario.n_samples or not np.isfinite(w).all():
        return {k: math.inf for k in ("rise_time", "overshoot_pct", "settling_time", "load_overshoot_pct",
                                      "dist_peak", "dist_recovery_time")}
    seg = _segments(w[:scenario.n_samples], scenario)
    T_s, r = scenario.T_s, scenario.w_step
    y = seg[0] / r

    def first(mask: np.ndarray) -> float:
        return float(np.argmax(mask)) * T_s if mask.any() else math.inf

    def settle(out: np.ndarray) -> float:
        idx = np.nonzero(out)[0]
        return math.inf if len(idx) and idx[-1] == len(out) - 1 else (float(idx[-1] + 1) * T_s if len(idx) else 0.0)

    load = load_estimate(mech, w[:scenario.n_samples], T_s) if scenario.two_mass else None
    return {
        "rise_time": first(y >= 0.9) - first(y >= 0.1),
        "overshoot_pct": float(max(0.0, y.max() - 1.0) * 100.0),
        "settling_time": settle(np.abs(y - 1) * r > scenario.band),
        "load_overshoot_pct": float(max(0.0, _segments(load, scenario)[0].max() / r - 1.0) * 100.0) if load is not None else math.nan,
        "dist_peak": float(np.abs(seg[4]).max()),
        "dist_recovery_time": settle(np.abs(seg[4]) > scenario.band),
    }


#: Why a closed-loop run on the drive did not settle (:func:`loop_verdict`); a run with none of these settled.
LOOP_VERDICTS: dict[str, str] = {
    "stopped": "stopped by the drive at a limit",
    "diverging": "not finite or beyond divergence_factor w_step",
    "saturated": "the torque reference sits at the torque cap in more than saturated_share of the samples",
    "limit_cycle": "the speed keeps swinging at the end of the segments (RMS above limit_cycle_share w_step)",
    "not_settled": "the first step ends more than half a step off its reference (slow or unstable)",
    "unlike_model": "the measured cost is more than model_cost_factor times the identified model's prediction",
    "slow": "near its reference, but the first step is not inside the settling band by the end of its segment",
}
#: Verdicts of a run that may be delivered as a model-based loop (it settled, or it is close and only slow).
USABLE_VERDICTS: frozenset[str | None] = frozenset({None, "slow"})
#: Verdicts of a run that stayed bounded: at worst slow, not unstable (enough for the fallback F1).
BOUNDED_VERDICTS: frozenset[str | None] = USABLE_VERDICTS | {"not_settled"}
#: Verdicts of a run whose cost measures nothing (the drive stopped it, or it diverged): the report shows none.
UNSCORED_VERDICTS: frozenset[str | None] = frozenset({"stopped", "diverging"})


def applied_torque_gain(law: Any, speed: np.ndarray, torque_ref: np.ndarray | None, scenario: sim.Scenario,
                        cap: float) -> float | None:
    """How many times the law's torque the drive applied in a closed-loop run: the least-squares
    factor between the recorded torque reference less the injected disturbance and ``law`` (fresh,
    reset here) replayed on the recorded speed and the scenario's reference, at the lag of 0-2
    samples that fits best, samples near the torque cap left out (1 for a drive that runs the law
    as given; a clamp at the cap may lower it). None without a torque record, or where the law's torque is too small to tell."""
    n = min(len(speed), len(scenario))
    if torque_ref is None or n < 3:
        return None
    law.reset()
    replay = np.array([law.step(float(w), float(r)) for w, r in zip(speed[:n], scenario.w_ref[:n])])
    recorded, dist = np.asarray(torque_ref[:n], dtype=np.float64), scenario.M_dist[:n]
    best: tuple[float, float] | None = None  # (relative residual, gain)
    for lag in (0, 1, 2):
        rec, rep = recorded[lag:] - dist[:n - lag], replay[:n - lag]
        free = (np.abs(rec) < 0.95 * cap) & (np.abs(recorded[lag:]) < 0.95 * cap) & (np.abs(rep) < 0.95 * cap)
        rec, rep = rec[free], rep[free]
        power = float(rep @ rep)
        if not power > 1e-12 * len(recorded) * cap * cap:
            continue
        gain = float(rec @ rep) / power
        residual = float(np.linalg.norm(rec - gain * rep)) / max(float(np.linalg.norm(rec)), 1e-300)
        best = min(best, (residual, gain)) if best is not None else (residual, gain)
    return None if best is None else best[1]


def loop_verdict(speed: np.ndarray, torque_ref: np.ndarray | None, scenario: TuningScenario, M_cap: float, cost: float,
                 model_cost: float, aborted: bool) -> tuple[str | None, str]:
    """Did a measured run settle? ``(code, text)``: ``code`` a key of :data:`LOOP_VERDICTS` (the first
    that applies, in its order), None when it settled (not saturated, no limit cycle, not unlike its
    model, the first step inside the band at the end of its segment: ``settling_time`` finite);
    ``text`` says what was measured."""
    w = np.asarray(speed, dtype=np.float64)
    N = scenario.n_samples
    if aborted or len(w) < N:
        return "stopped", LOOP_VERDICTS["stopped"]
    w = w[:N]
    if not np.isfinite(w).all() or float(np.abs(w).max()) > scenario.divergence_factor * scenario.w_step:
        return "diverging", LOOP_VERDICTS["diverging"]
    if torque_ref is not None and len(torque_ref) and M_cap > 0:
        share = float(np.mean(np.abs(np.asarray(torque_ref, dtype=np.float64)) >= scenario.at_cap * M_cap))
        if share > scenario.saturated_share:
            return "saturated", f"the torque reference sits at the torque cap {M_cap:.3g} Nm in {100 * share:.0f} % of the samples"
    tail = _segments(w, scenario)[:, -scenario.n_tail:]
    swing = float(np.median(tail.std(-1)))
    if swing > max(scenario.limit_cycle_share * scenario.w_step, scenario.settle_quanta * scenario.q_w):
        return "limit_cycle", (f"the speed keeps swinging by {swing:.3g} rad/s RMS at the end of the segments "
                               f"({100 * swing / scenario.w_step:.0f} % of the step {scenario.w_step:.3g} rad/s)")
    if cost >= scenario.unstable_cost:
        return "not_settled", "the first step ends more than half a step off its reference"
    if math.isfinite(model_cost) and model_cost > 0 and cost > scenario.model_cost_factor * model_cost:
        return "unlike_model", f"measured cost {cost:.4g} is {cost / model_cost:.3g} x the model's {model_cost:.4g}"
    if not math.isfinite(response_figures(w, scenario)["settling_time"]):
        return "slow", f"the first step is not inside +-{scenario.band:.3g} rad/s of its reference by the end of its segment"
    return None, "settled"


@dataclass
class TuningResult:
    """Outcome of :func:`tune_controller` on the identified model.

    ``controller``: the tuned :class:`ControllerProposal` (or the proposal, when the search found
    nothing better that keeps the guarantee); ``cost_proposal``, ``cost_tuned`` on the model;
    ``history``: one dict per evaluation (``Kp, Ti, T_f, cost, feasible, load_peak_dB``);
    ``rejected``: how many candidates missed the margins, ``rejected_load`` how many the load peak,
    ``rejected_crossover`` how many fell below the proposal's crossover (:attr:`SearchSettings.min_crossover`);
    ``load_peak_proposal`` / ``load_peak_tuned`` [dB] on the identified model (None: one-mass);
    ``message`` / ``warnings``; :meth:`changes` says what the search changed, or why nothing.
    """

    controller: ControllerProposal
    proposal: ControllerProposal
    cost_proposal: float
    cost_tuned: float
    history: list[dict[str, float]]
    scenario: TuningScenario
    n_evaluations: int
    rejected: int
    message: str
    warnings: list[str] = field(default_factory=list)
    rejected_load: int = 0
    load_peak_proposal: float | None = None
    load_peak_tuned: float | None = None
    rejected_crossover: int = 0

    @property
    def changed(self) -> bool:
        """The search found gains other than the proposal's."""
        return self.controller is not self.proposal

    def changes(self) -> str:
        """One line: the gains, the model cost and the load peak before -> after, or why the
        proposal was kept."""
        p, c = self.proposal, self.controller
        if not self.changed:
            return (f"kept the proposal: {self.warnings[0] if self.warnings else 'no better gain set found'} "
                    f"({self.n_evaluations} evaluations, {self.rejected} missed the margins, {self.rejected_load} the load peak, "
                    f"{self.rejected_crossover} the crossover)")
        peak = ("" if self.load_peak_proposal is None or self.load_peak_tuned is None else
                f"; load peak {self.load_peak_proposal:.2f} -> {self.load_peak_tuned:.2f} dB")
        return (f"Kp {p.Kp:.4g} -> {c.Kp:.4g} Nm s/rad (x{c.Kp / p.Kp:.3g}), Ti {p.Ti * 1e3:.4g} -> {c.Ti * 1e3:.4g} ms, "
                f"T_f {p.T_f * 1e3:.3g} -> {c.T_f * 1e3:.3g} ms; model cost {self.cost_proposal:.4g} -> {self.cost_tuned:.4g}{peak}")


def tune_controller(
    proposal: ControllerProposal,
    config: Any,
    scenario: TuningScenario,
    spec: ControllerSpec,
    *,
    max_evaluations: int = 30,
    span: float = 5.0,
    initial_step: float = 0.4,
    progress: Callable[[int, float], None] | None = None,
) -> TuningResult:
    """Nelder-Mead on ``log([Kp, Ti(, T_f)])`` from ``proposal`` on its identified linear model.

    A candidate that misses the guarantee (``spec``'s margins on the proposal's model set) is not
    a solution: it costs ``scenario.unstable_cost`` plus its deficit, so the simplex moves back; the
    result always keeps the margins (else the proposal is kept). It may trade
    the motor against the load (the cost counts both) only within the load peak: a candidate whose
    reference-to-load-speed peak (the worst over the proposal's model set) passes ``SEARCH.max_load_peak_dB`` (or the
    proposal's own peak, where higher) is not a solution either, nor one whose crossover on the
    identified model falls below ``SEARCH.min_crossover`` x the proposal's. ``span``: each gain stays within
    ``[start / span, start * span]``.
    """
    if max_evaluations < 1 or not span > 1:
        raise ValueError(f"max_evaluations >= 1 and span > 1 expected, received {max_evaluations}, {span}")
    mech, models = proposal.mechanics, proposal.models
    use_f = proposal.T_f > 0
    x0 = np.log([proposal.Kp, proposal.Ti] + ([proposal.T_f] if use_f else []))
    history: list[dict[str, float]] = []
    rejected = rejected_load = rejected_crossover = 0

    def load_peak(gains: Gains) -> float | None:  # the worst over the guarantee's set, as ControllerProposal.meets
        peak = float(models.load_peaks_dB(*gains, proposal.notch).max())
        return peak if math.isfinite(peak) else None

    peak_0 = load_peak((proposal.Kp, proposal.Ti, proposal.T_f))
    peak_bound = math.inf if peak_0 is None else max(SEARCH.max_load_peak_dB, peak_0)
    w_c_floor = SEARCH.min_crossover * models.margins(proposal.Kp, proposal.Ti, proposal.T_f, proposal.notch).w_c

    def gains_at(x: np.ndarray) -> Gains:
        return float(math.exp(x[0])), float(math.exp(x[1])), float(math.exp(x[2])) if use_f else proposal.T_f

    def cost_at(x: np.ndarray) -> float:
        nonlocal rejected, rejected_load, rejected_crossover
        gains = gains_at(x)
        worst = models.margins(*gains, proposal.notch)
        feasible = worst.meets(spec.min_phase_margin, spec.min_gain_margin_dB)
        peak = load_peak(gains) if feasible else None
        if feasible and worst.w_c < w_c_floor:  # NaN (no crossover) passes: the margins judged it
            rejected_crossover += 1
            feasible = False
            cost = scenario.unstable_cost + min(math.log(w_c_floor / worst.w_c), SEARCH.unstable_penalty)
        elif feasible and peak is not None and not peak <= peak_bound:
            rejected_load += 1
            feasible = False
            cost = scenario.unstable_cost + min(peak - peak_bound, SEARCH.unstable_penalty)
        elif feasible:
            cost = float(closed_loop_cost(model_response(mech, config, [gains], proposal.notch, scenario)[0], scenario, mech)[0])
        else:
            rejected += 1
            deficit = (max(spec.min_phase_margin - worst.phase_margin, 0.0) / SEARCH.phase_deficit_per_dB
                       + max(spec.min_gain_margin_dB - worst.gain_margin_dB, 0.0))
            cost = scenario.unstable_cost + (deficit if worst.stable and math.isfinite(deficit) else SEARCH.unstable_penalty)
        history.append({"Kp": gains[0], "Ti": gains[1], "T_f": gains[2], "cost": cost, "feasible": float(feasible),
                        "load_peak_dB": math.nan if peak is None else peak})
        if progress is not None:
            progress(len(history), cost)
        return cost

    cost0 = cost_at(x0)
    simplex = np.vstack([x0] + [x0 + initial_step * np.eye(len(x0))[i] for i in range(len(x0))])
    bounds = [(xi - math.log(span), xi + math.log(span)) for xi in x0]
    res = scipy.optimize.minimize(cost_at, x0, method="Nelder-Mead", bounds=bounds,
                                  options={"maxfev": max_evaluations, "initial_simplex": simplex, "xatol": SEARCH.xatol,
                                           "fatol": SEARCH.fatol})
    best = min(history, key=lambda h: h["cost"])
    warnings: list[str] = []
    if not best["feasible"] or best["cost"] >= cost0:
        warnings.append("the search found no gain set better than the proposal that keeps the margins, the crossover"
                        + ("" if peak_0 is None else f" and the load peak (<= {peak_bound:.3g} dB)") + ": the proposal is kept")
        cand, best_cost, peak_1 = proposal, cost0, peak_0
    else:
        best_cost, peak_1 = best["cost"], (None if peak_0 is None else best["load_peak_dB"])
        cand = proposal.with_gains(config, best["Kp"], best["Ti"], best["T_f"], rule=(
            f"T1 Nelder-Mead on the identified model: Kp {proposal.Kp:.4g} -> {best['Kp']:.4g}, Ti {proposal.Ti:.4g} -> "
            f"{best['Ti']:.4g}, T_f {proposal.T_f:.3g} -> {best['T_f']:.3g}; model cost {cost0:.4g} -> {best_cost:.4g}"))
    return TuningResult(controller=cand, proposal=proposal, cost_proposal=cost0, cost_tuned=best_cost, history=history,
                        scenario=scenario, n_evaluations=len(history), rejected=rejected, message=str(res.message), warnings=warnings,
                        rejected_load=rejected_load, load_peak_proposal=peak_0, load_peak_tuned=peak_1,
                        rejected_crossover=rejected_crossover)
