"""What the commissioning chain did: the report of one drive (text and JSON) and the summary over
many.

Wording rules: a loop that did not settle within the experiment is "not settled" (slow or
unstable: the margins say which), never called unstable from the record alone; an improvement
percentage is given only against a proposal that settled on the drive; rules, refusals and
warnings carry their codes. Figures computed from a simulated drive's truth stand apart, under
"simulation only".
"""

from __future__ import annotations

import math
import statistics
from dataclasses import dataclass, field
from typing import Any

import numpy as np

import sim
from training._json import json_safe

from ._excitation import ExcitationResult
from ._frf import MeasuredResponse
from ._guard import LimitBreach
from ._rest import RestCheck
from ._permission import CommissioningWarning, IdentificationOutcome, Permission
from ._rules import ControllerProposal
from ._tuning import BOUNDED_VERDICTS, UNSCORED_VERDICTS, USABLE_VERDICTS, Gains, TuningResult, TuningScenario
from ._validation import ValidationResult

__all__ = ["CommissioningReport", "PlantRun", "summarize", "summary_text"]

_SHOWN: tuple[str, ...] = sim.PARAM_NAMES
_UNITS = {"J_sigma": "kg m^2", "f_e": "Hz", "backlash": "rad (2s)", "M_FC": "Nm", "mu_F": "Nm s/rad"}

#: Where the text report prints a commissioning warning, by its code: with the test runs, after the
#: closed-loop runs on the drive (before what was delivered), or under the permission (the others:
#: what the permission and the design read).
_WARNING_SECTION: dict[str, str] = {
    "test_not_informative": "test", "speed_against_torque": "test",
    "run_stopped": "drive", "loop_rejected": "drive", "loop_not_settled": "drive", "loop_unlike_model": "drive",
    "scenario_small": "drive",
}


@dataclass(frozen=True)
class PlantRun:
    """One closed-loop experiment on the drive: the gains, the cost from the measured record
    (``motor`` + ``load`` terms; the load estimated by the identified model), ``settled``
    (``verdict`` None: not stopped, finite, inside the settling band at the end of the first step,
    so ``figures["settling_time"]`` is finite; not saturated, no limit cycle, not far worse than
    ``model_cost``, what the identified model predicts), ``aborted`` (the drive stopped it),
    ``bounded`` (at worst slow: ``verdict`` None, ``slow`` or ``not_settled``), ``verdict`` (a code of
    :data:`LOOP_VERDICTS`) and ``verdict_text``, the figures (:func:`response_figures`) and the
    measured speed ``N``; ``settled`` and ``bounded`` follow from ``verdict``."""

    gains: Gains
    cost: float
    motor: float
    load: float
    aborted: bool
    figures: dict[str, float]
    speed: np.ndarray = field(repr=False)
    verdict: str | None = None
    verdict_text: str = "settled"
    model_cost: float = math.nan

    @property
    def settled(self) -> bool:
        """``verdict`` None: it settled on the drive."""
        return self.verdict is None

    @property
    def bounded(self) -> bool:
        """At worst slow: not stopped, not diverging, not saturated, no limit cycle, not unlike its model."""
        return self.verdict in BOUNDED_VERDICTS

    @property
    def usable(self) -> bool:
        """May be delivered as a model-based loop: settled, or near its reference and only slow."""
        return self.verdict in USABLE_VERDICTS

    def to_dict(self) -> dict[str, Any]:
        return {"Kp": self.gains[0], "Ti": self.gains[1], "T_f": self.gains[2], "cost": self.cost, "motor": self.motor,
                "load": self.load, "settled": self.settled, "bounded": self.bounded, "aborted": self.aborted,
                "verdict": self.verdict, "verdict_text": self.verdict_text, "model_cost": self.model_cost,
                "figures": self.figures}


@dataclass(frozen=True)
class CommissioningReport:
    """Everything the chain did on one drive.

    ``config``: the drive's own description; ``excitation``: the test runs (log per run, records);
    ``identification``: the identifier's answer, unchanged; ``validation``; ``permission``
    (``rule`` code when refused); ``warnings``: the commissioning's own (with codes);
    ``proposal`` / ``tuning``: the model-based proposal and its tuning on the identified model;
    ``runs``: its candidates on the drive (the proposal first); ``fallback``: the cautious F1 when
    it ran, ``fallback_reason`` (``refused``, ``margins_not_reached`` or ``loop_not_settled``) and
    ``fallback_runs``; ``delivered``: the controller to use (None: none) and ``delivered_run``;
    ``scenario`` and ``prediction`` (the model's predicted peaks); ``checks``: the limits in every
    experiment, from the measured records; ``truth``: simulation-only figures (None for a drive
    without truth); ``timings`` [s]. ``measured``: the plant's frequency response measured on the
    drive (None: not measured); ``redesign``: the design made again with it (None: not made, or the
    same law), ``redesign_runs`` its candidates on the drive, ``redesign_kept`` (it is delivered) and
    ``redesign_reason``; ``load_peak_dB``: the delivered loop's worst reference-to-load-speed peak over the
    design set (None: not known, or none delivered); ``limited_by``: why the delivered loop is below
    what the identified model allows (empty: nothing limits it but the model). ``rest``: the rest
    check before the first test run (SPEC 1.1: the drive held the axis; None: not run). ``breach``: the record that showed one of the user's limits
    passed (SPEC 8.2; None: none did): the experiments ended there, nothing is delivered, and the
    stages the chain had not reached are None (``identification``, ``validation``, ``permission``)
    or empty.
    """

    config: sim.DriveConfig
    limits: sim.DriveLimits
    excitation: ExcitationResult
    identification: IdentificationOutcome | None
    validation: ValidationResult | None
    permission: Permission | None
    warnings: tuple[CommissioningWarning, ...] = ()
    max_map_distance_ratio: float | None = None
    outside_training: bool | None = None
    proposal: ControllerProposal | None = None
    tuning: TuningResult | None = None
    fallback: ControllerProposal | None = None
    fallback_reason: str | None = None
    runs: list[PlantRun] = field(default_factory=list)
    fallback_runs: list[PlantRun] = field(default_factory=list)
    delivered: ControllerProposal | None = None
    delivered_run: PlantRun | None = None
    scenario: TuningScenario | None = None
    prediction: dict[str, float] = field(default_factory=dict)
    checks: dict[str, Any] = field(default_factory=dict)
    truth: dict[str, Any] | None = None
    timings: dict[str, float] = field(default_factory=dict)
    name: str = "plant"
    breach: LimitBreach | None = None
    measured: MeasuredResponse | None = None
    redesign: ControllerProposal | None = None
    redesign_runs: list[PlantRun] = field(default_factory=list)
    redesign_kept: bool = False
    redesign_reason: str = ""
    load_peak_dB: float | None = None
    limited_by: str = ""
    rest: RestCheck | None = None

    def __post_init__(self) -> None:
        if self.breach is not None and self.delivered is not None:
            raise ValueError("CommissioningReport: a chain stopped at a passed limit delivers no controller")

    @property
    def record(self) -> Any:
        """The final test record (what was identified)."""
        return self.excitation.record

    @property
    def refused(self) -> bool:
        """A refusal rule said no (False where the chain stopped before asking)."""
        return self.permission is not None and not self.permission.allowed

    @property
    def controller(self) -> ControllerProposal | None:
        """The delivered controller (None: none delivered)."""
        return self.delivered

    @property
    def model_runs(self) -> list[PlantRun]:
        """The candidate runs of the model-based plan delivered (the redesign's where it is kept, else
        the design's): one scenario, so their costs compare."""
        return self.redesign_runs if self.redesign_kept else self.runs

    @property
    def improvement(self) -> float | None:
        """``1 - cost(delivered) / cost(proposal)`` on the drive, the proposal of the same plan
        (:attr:`model_runs`), only where it settled or is only slow (:attr:`PlantRun.usable`; a
        model-based delivery); None otherwise."""
        runs = self.model_runs
        if self.delivered_run is None or self.fallback is not None or not runs or not runs[0].usable:
            return None
        return 1.0 - self.delivered_run.cost / runs[0].cost

    @property
    def identified_structure(self) -> str | None:
        ident = self.identification
        return ident.structure if ident is not None and ident.ok else None

    # ------------------------------------------------------------------ output

    def to_dict(self) -> dict[str, Any]:
        """JSON-able summary (no signal arrays; NaN and inf as None)."""
        v, ex = self.validation, self.excitation
        return json_safe({
            "name": self.name,
            "drive": self.config.to_dict(),
            "limits": {"w_max": self.limits.w_max, "travel": self.limits.travel, "M_max": self.limits.M_max},
            "rest_check": None if self.rest is None else self.rest.to_dict(),
            "excitation": {"informative": ex.informative, "reason": ex.reason, "log": ex.log},
            "identification": None if self.identification is None else self.identification.to_dict(),
            "validation": None if v is None else {
                "passed": v.passed, "mode": v.mode, "nrmse": v.nrmse, "osc_nrmse": v.osc_nrmse, "threshold": v.threshold,
                "osc_threshold": v.osc_threshold, "reason": v.reason},
            "assessment": {"outside_training": self.outside_training, "max_map_distance_ratio": self.max_map_distance_ratio,
                           "warnings": [{"code": w.code, "text": w.text} for w in self.warnings]},
            "permission": None if self.permission is None else {
                "allowed": self.permission.allowed, "rule": self.permission.rule, "reason": self.permission.reason,
                "notes": list(self.permission.notes)},
            "proposal": None if self.proposal is None else self.proposal.to_dict(),
            "tuning": None if self.tuning is None else {
                "model_cost_proposal": self.tuning.cost_proposal, "model_cost_tuned": self.tuning.cost_tuned,
                "n_evaluations": self.tuning.n_evaluations, "rejected_for_margins": self.tuning.rejected,
                "rejected_for_load_peak": self.tuning.rejected_load,
                "rejected_for_crossover": self.tuning.rejected_crossover, "changed": self.tuning.changed,
                "gains_before": _gains(self.tuning.proposal), "gains_after": _gains(self.tuning.controller),
                "load_peak_dB_before": self.tuning.load_peak_proposal, "load_peak_dB_after": self.tuning.load_peak_tuned,
                "changes": self.tuning.changes(), "warnings": list(self.tuning.warnings)},
            "runs": [r.to_dict() for r in self.runs],
            "fallback": None if self.fallback is None else {"reason": self.fallback_reason, **self.fallback.to_dict(),
                                                           "runs": [r.to_dict() for r in self.fallback_runs]},
            "frequency_response": None if self.measured is None else self.measured.to_dict(),
            "redesign": None if not (self.redesign or self.redesign_reason) else {
                "kept": self.redesign_kept, "reason": self.redesign_reason,
                "controller": None if self.redesign is None else self.redesign.to_dict(),
                "runs": [r.to_dict() for r in self.redesign_runs]},
            "delivered": None if self.delivered is None else {**self.delivered.to_dict(), "load_peak_dB": self.load_peak_dB,
                                                               "limited_by": self.limited_by},
            "scenario": None if self.scenario is None else self.scenario.to_dict(),
            "prediction": self.prediction,
            "improvement": self.improvement,
            "checks": self.checks,
            "breach": None if self.breach is None else self.breach.to_dict(),
            "simulation_only": self.truth,
            "timings": self.timings,
        })

    def to_text(self) -> str:
        """A readable report (one drive)."""
        c, lim = self.config, self.limits
        L = [f"== commissioning {self.name} ==",
             f"limits: |w| <= {lim.w_max:g} rad/s, travel <= {lim.travel:g} rad, |M_ref| <= {lim.torque_cap(c):g} Nm "
             f"(drive M_max {c.M_max:g} Nm, T_s {c.T_s * 1e6:g} us, T_Ei {c.T_Ei * 1e3:g} ms)"]
        if self.breach is not None:
            L.append(f"STOPPED: {self.breach.text()}")
        notes = self._warning_lines()
        if self.rest is not None:
            L.append(f"0 rest check: {self.rest.text()}")
        L += self._excitation_lines() + notes["test"] + self._identification_lines()
        if self.validation is not None:
            v = self.validation
            osc = "n/a (oscillation below 3 q_w)" if v.osc_nrmse is None else f"{v.osc_nrmse:.3g} (<= {v.osc_threshold:g})"
            L.append(f"3 validation ({v.mode}): speed error {v.nrmse:.3g} (<= {v.threshold:g}), oscillation error {osc}: "
                     f"{'passed' if v.passed else 'FAILED'} - {v.reason}")
        if self.permission is not None:
            L.append(f"4 REFUSED [{self.permission.rule}]: no controller from the identified model. {self.permission.reason}"
                     if self.refused else f"4 permission: {self.permission.reason}")
        L += notes["permission"]
        if self.proposal is not None:
            L += self._proposal_lines()
        L += self._frf_lines()
        if self.fallback is not None:
            L += self._fallback_lines()
        L += notes["drive"] + self._delivered_lines() + self._limit_lines() + self._truth_lines()
        return "\n".join(line.rstrip() for line in L)

    def _warning_lines(self) -> dict[str, list[str]]:
        """The commissioning's warnings by the section of the report they belong to (by code,
        :data:`_WARNING_SECTION`). ``run_stopped`` is said of a test run and of a closed-loop run
        alike: the first one goes with the test runs when a test run was stopped (the chain warns
        in its order), the others with the runs on the drive."""
        out: dict[str, list[str]] = {"test": [], "permission": [], "drive": []}
        test_stopped = any(e.get("aborted") for e in self.excitation.log)
        for w in self.warnings:
            section = _WARNING_SECTION.get(w.code, "permission")
            if w.code == "run_stopped" and test_stopped:
                section, test_stopped = "test", False
            out[section].append(f"   warning [{w.code}]: {w.text}")
        return out

    def _excitation_lines(self) -> list[str]:
        L = ["1 test signal (rules E0-E13; stop at: the speed limit handed to the drive, the user's less the headroom after a stop):",
             "   run  M* [Nm]  w_max [rad/s]  stop at [rad/s]  peak w [rad/s]  travel [rad]  osc [q_w]  decision"]
        for e in self.excitation.log:
            L.append(f"   {e['iteration']:3d}  {e['M_star']:7.3g}  {e['w_max']:13.4g}  {e.get('stop_at', math.nan):15.4g}  {e['peak_speed']:14.4g}  "
                     f"{e['travel']:12.4g}  {e['osc_quanta']:9.3g}  {e['decision']} ({e['reason']})")
        L.append(f"   -> {self.excitation.reason}; record {len(self.record.t)} samples, "
                 f"{len(self.record.t) * float(self.config.T_s):.3f} s")
        return L

    def _identification_lines(self) -> list[str]:
        ident = self.identification
        if ident is None:
            return ["2 identification: not run (the chain stopped at a passed limit)"]
        if not ident.ok:
            return [f"2 identification failed: {ident.error}"]
        L = [f"2 identification: structure {ident.structure}"]
        L += [f"   {k:<10} {_fmt(getattr(ident.parameters, k)):>12}  {_UNITS.get(k, '')}" for k in _SHOWN]
        ratios = ident.quality.map_distance_ratio
        if ratios:
            L.append("   map distance / training 99 % quantile: " + ", ".join(f"{k} {v:.2f}" for k, v in ratios.items()))
        L.append(_interval_line(getattr(ident, "intervals", None)))
        L += [f"   warning [{w.code}]: {w.text}" for w in ident.warnings]
        L += [f"   note [{w.code}]: {w.text}" for w in getattr(ident, "notes", ())]
        return L

    def _proposal_lines(self) -> list[str]:
        L = _design_lines("5 proposal", self.proposal)
        if self.tuning is not None:
            t = self.tuning
            L.append(f"6 tuning on the identified model ({t.n_evaluations} evaluations, {t.rejected} rejected for the margins, "
                     f"{t.rejected_load} for the load peak, {t.rejected_crossover} for the crossover): {t.changes()}")
        L += self._runs_lines(self.runs, ("proposal", "tuned", "between"), experiment=not self.redesign_kept)
        return L

    def _frf_lines(self) -> list[str]:
        """The measured frequency response and the redesign made with it."""
        m = self.measured
        if m is None:
            return [f"7b frequency response: {self.redesign_reason}"] if self.redesign_reason else []
        info = m.to_dict()
        res = ", ".join(f"{f:.4g} Hz" for f in info["resonances_Hz"]) or "none"
        L = [f"7b frequency response on the chosen loop: {info['lines']} lines {info['f_min_Hz']:.3g}-{info['f_max_Hz']:.4g} Hz, "
             f"multisine {info['amplitude_Nm']:.3g} Nm per line, coherence >= 0.8 on {100 * info['coherent_share']:.0f} % of the lines; "
             f"resonances the model lacks: {res}"]
        if self.redesign is not None:
            L += _design_lines("   redesign", self.redesign)
            L += self._runs_lines(self.redesign_runs, ("redesign", "tuned", "between"), experiment=self.redesign_kept)
        if self.redesign_reason:
            L.append(f"   redesign: {self.redesign_reason}")
        return L

    def _fallback_lines(self) -> list[str]:
        return _design_lines(f"5 fallback F1 ({self.fallback_reason})", self.fallback) + self._runs_lines(self.fallback_runs, ("F1",))

    def _runs_lines(self, runs: list[PlantRun], names: tuple[str, ...], experiment: bool = True) -> list[str]:
        """The runs' table; ``experiment``: headed by the experiment of :attr:`scenario` (False: the
        runs of another plan, the table only)."""
        if not runs or self.scenario is None:
            return []
        scenario = self.scenario
        L = [] if not experiment else [f"7 on the drive (steps +-{scenario.w_step:.3g} rad/s, disturbance {scenario.M_dist:.3g} Nm, {scenario.n_samples} samples; "
             f"predicted peak {self.prediction.get('peak_speed', math.nan):.3g} rad/s, travel {self.prediction.get('travel', math.nan):.3g} rad; "
             f"the drive stops at {self.prediction.get('stop_at', math.nan):.3g} rad/s):"]
        L += ["   run       Kp      Ti [ms]  cost (motor+load)  rise [ms]  overshoot [%]  load overshoot [%]  settled"]
        for name, r in zip(names, runs):
            f = r.figures
            cost = "-" if r.verdict in UNSCORED_VERDICTS else f"{r.cost:.4g} ({r.motor:.3g}+{r.load:.3g})"
            state = "yes" if r.settled else ("NO: stopped by the drive at a limit" if r.aborted else
                                               f"no [{r.verdict}]: slow ({r.verdict_text})" if r.bounded else
                                               f"NO [{r.verdict}]: {r.verdict_text}")
            L.append(f"   {name:<8} {r.gains[0]:8.4g} {r.gains[1] * 1e3:9.4g}  {cost:>18}  {_ms(f['rise_time']):>9}  "
                     f"{f['overshoot_pct']:13.1f}  {f['load_overshoot_pct']:18.1f}  {state}")
        return L

    def _delivered_lines(self) -> list[str]:
        d = self.delivered
        if d is None:
            why = (f" (limit passed in experiment {self.breach.experiment})" if self.breach is not None else
                   f" ({self.permission.rule})" if self.refused else "")
            return ["8 delivered: none" + why]
        m = d.margins
        L = [f"8 delivered: {_controller_text(d)}",
             f"   guaranteed margins (worst of {len(d.models.plants)} models: {m.model}): PM {m.phase_margin:.1f} deg, "
             f"GM {m.gain_margin_dB:.1f} dB; crossover w_c {d.figures['w_c']:.4g} rad/s on the design model"]
        if d.M_hold != 0.0:
            L.append(f"   holding torque M_hold {d.M_hold:.4g} Nm (the identified M_L0): the law's integrator starts there "
                     f"(the drive's holding-torque feedforward)")
        if self.load_peak_dB is not None:
            L.append(f"   reference-to-load-speed peak {self.load_peak_dB:.2f} dB, the worst over the design set")
        if self.limited_by:
            L.append(f"   below what the model allows: {self.limited_by}")
        imp = self.improvement
        if imp is not None:
            L.append(f"   cost on the drive: proposal {self.model_runs[0].cost:.4g} -> delivered {self.delivered_run.cost:.4g} "
                     f"({100 * imp:.1f} % better)")
        elif self.fallback is None and self.model_runs and not self.model_runs[0].usable:
            L.append("   the proposal did not settle on the drive: no improvement percentage")
        return L

    def _limit_lines(self) -> list[str]:
        ch = self.checks
        if not ch:
            return []
        bad = [f"{r['kind']} (peak {r['peak_speed']:.3g} rad/s, travel {r['travel']:.3g} rad, torque ref "
               f"{r['peak_torque_ref']:.3g} Nm, measured torque {r['peak_torque']:.3g} Nm"
               + (f"; passed: {', '.join(r['passed'])}" if r.get("passed") else "")
               + ")" for r in ch["runs"] if not r["within_limits"]]
        stopped = [r["kind"] for r in ch["runs"] if r["aborted"] and r["within_limits"]]
        return [f"limits kept in every experiment ({len(ch['runs'])}, from the measured records): "
                f"{'yes' if ch['within_limits'] else 'NO'}; peak speed {ch['peak_speed']:.4g} rad/s, peak travel {ch['peak_travel']:.4g} rad"]\
            + [f"   outside the limits: {b}" for b in bad]\
            + ([f"   stopped by the drive at the limit it was handed, inside yours: {', '.join(stopped)}"] if stopped else [])

    def _truth_lines(self) -> list[str]:
        t = self.truth
        if t is None:
            return []
        ident = self.identification
        ok = ident is not None and ident.ok
        L = ["-- simulation only (from the drive's truth, never used by the chain) --",
             f"   true structure {t['structure']}" + (f" (identified {ident.structure})" if ok else ""),
             "   parameter     identified          true"]
        for k in _SHOWN:
            got = getattr(ident.parameters, k) if ok else None
            L.append(f"   {k:<10} {_fmt(got):>13} {_fmt(t['parameters'].get(k)):>13}  {_UNITS.get(k, '')}")
        if "stable" in t:
            L.append(f"   delivered loop on the true linear model: {'stable' if t['stable'] else 'UNSTABLE'}, "
                     f"PM {t['phase_margin']:.1f} deg, GM {t['gain_margin_dB']:.1f} dB, w_c {t['w_c']:.4g} rad/s")
        return L


def _design_lines(title: str, p: ControllerProposal) -> list[str]:
    """A design, its rule lines (codes first) and its warnings."""
    return [f"{title}: {_controller_text(p)}", *(f"   rule {r}" for r in p.rules), *(f"   warning: {w}" for w in p.warnings)]


def _controller_text(p: ControllerProposal) -> str:
    notch = "".join(f", notch f_n {n.f_n:.4g} Hz (D_z {n.D_z:.3g}, D_p {n.D_p:.3g})" for n in p.notches)
    return (f"{p.concept}, Kp {p.Kp:.4g} Nm s/rad, Ti {p.Ti * 1e3:.4g} ms, T_f {p.T_f * 1e3:.3g} ms{notch}; "
            f"w_c {p.figures['w_c']:.4g} rad/s, PM {p.margins.phase_margin:.1f} deg, GM {p.margins.gain_margin_dB:.1f} dB (guarantee set)")


def _gains(p: ControllerProposal) -> dict[str, float]:
    return {"Kp": p.Kp, "Ti": p.Ti, "T_f": p.T_f}


#: The parameters whose 90 % interval the identification section names (the design reads them).
_INTERVALS_SHOWN: tuple[str, ...] = ("f_e", "V_J", "J_sigma")


def _interval_line(intervals: Any) -> str:
    """One line: the identification's 90 % intervals (SPEC 4.1) of :data:`_INTERVALS_SHOWN`, each
    ``low .. high`` [SI]; ``intervals`` ``None`` (maps without a calibration, or an identifier that
    gives none) is said so."""
    if intervals is None:
        return "   90 % intervals: none (the maps carry no calibration): the design's set is the interim spread"
    parts = []
    for k in _INTERVALS_SHOWN:
        low, high = intervals[k]
        parts.append(f"{k} {_fmt(low)} .. {_fmt(high)}" + (f" {_UNITS[k]}" if k in _UNITS else ""))
    return "   90 % intervals: " + ", ".join(parts)


def _fmt(v: Any) -> str:
    if v is None:
        return "-"
    if isinstance(v, str):
        return v
    try:
        return f"{float(v):.4g}"
    except (TypeError, ValueError):
        return str(v)


def _ms(v: float) -> str:
    return "inf" if not math.isfinite(v) else f"{v * 1e3:.1f}"


# --------------------------------------------------------------------------- many drives


def _refusals(reports: list[CommissioningReport]) -> dict[str, int]:
    """How many drives each refusal rule refused, by its code."""
    by_rule: dict[str, int] = {}
    for report in reports:
        if report.refused:
            by_rule[report.permission.rule] = by_rule.get(report.permission.rule, 0) + 1
    return by_rule


def _improvements(delivered: list[CommissioningReport]) -> dict[str, Any]:
    """The median and the worst improvement over the model-based deliveries whose proposal settled,
    and the drive of the worst (None where there is none)."""
    found = [(r.improvement, r.name) for r in delivered if r.improvement is not None]
    worst = min(found) if found else (None, None)
    return {"median_improvement": statistics.median(i for i, _ in found) if found else None,
            "worst_improvement": worst[0], "worst_plant": worst[1]}


def _truth_figures(reports: list[CommissioningReport], delivered: list[CommissioningReport]) -> dict[str, Any]:
    """Simulation only: identified structure against the true class, the delivered loops stable on
    the true linear model and their smallest margins there."""
    truths = [r.truth for r in delivered if r.truth is not None and "stable" in r.truth]
    return {
        "structure_correct": sum(r.truth is not None and r.identified_structure == r.truth["structure"] for r in reports),
        "with_truth": sum(r.truth is not None for r in reports),
        "true_stable": sum(bool(t["stable"]) for t in truths),
        "true_min_phase_margin": min((t["phase_margin"] for t in truths), default=None),
        "true_min_gain_margin_dB": min((t["gain_margin_dB"] for t in truths), default=None),
    }


def summarize(reports: list[CommissioningReport], wall_s: float) -> dict[str, Any]:
    """Figures over many drives: refusals by rule code, limits kept in every experiment, the drives
    whose experiments ended at a passed limit (``stopped_at_limit``, names), delivered
    loops (model-based, F1), improvement over the model-based deliveries whose proposal settled,
    the F1 crossovers; with simulated drives the truth checks (stable, margins on the true linear
    model). ``wall_s``: the time the caller measured over the drives [s] (``summary_text`` calls it
    the chain time)."""
    by_rule = _refusals(reports)
    delivered = [r for r in reports if r.delivered is not None]
    return {
        "plants": len(reports),
        "delivered": len(delivered),
        "model_based": sum(1 for r in delivered if r.fallback is None),
        "fallback": sum(1 for r in delivered if r.fallback is not None),
        "fallback_w_c": [r.fallback.figures["w_c"] for r in reports if r.fallback is not None],
        "refused": sum(by_rule.values()),
        "refused_by_rule": by_rule,
        "within_limits": sum(bool(r.checks.get("within_limits")) for r in reports),
        "stopped_at_limit": [r.name for r in reports if r.breach is not None],
        **_improvements(delivered),
        **_truth_figures(reports, delivered),
        "wall_s": wall_s,
    }


def summary_text(s: dict[str, Any]) -> str:
    """The summary of :func:`summarize` as readable lines."""
    def pct(v: float | None) -> str:
        return "-" if v is None else f"{100 * v:.1f} %"
    rules = ", ".join(f"{k} {v}" for k, v in sorted(s["refused_by_rule"].items())) or "none"
    w_c = s["fallback_w_c"]
    L = [f"== summary over {s['plants']} drives ==",
         f"limits kept in every experiment (test, tuning, validation): {s['within_limits']}/{s['plants']}"
         + (f"; stopped at a passed limit: {', '.join(s['stopped_at_limit'])}" if s.get("stopped_at_limit") else ""),
         f"refused for a model-based controller: {s['refused']}/{s['plants']} ({rules}); delivered: {s['delivered']}/{s['plants']} "
         f"({s['model_based']} model-based, {s['fallback']} fallback F1)",
         "F1 crossovers [rad/s]: " + (", ".join(f"{v:.3g}" for v in sorted(w_c)) if w_c else "none"),
         "improvement on the drive over the model-based deliveries with a settled proposal (1 - delivered/proposal cost): "
         + ("none to summarize (no such delivery)" if s["worst_plant"] is None else
            f"median {pct(s['median_improvement'])}, worst {pct(s['worst_improvement'])} ({s['worst_plant']})")]
    if s["with_truth"]:
        pm, gm = s["true_min_phase_margin"], s["true_min_gain_margin_dB"]
        L += ["-- simulation only --",
              f"identified structure = true class: {s['structure_correct']}/{s['with_truth']}",
              f"delivered loops stable on the true linear model: {s['true_stable']}/{s['delivered']}; smallest true PM "
              f"{'-' if pm is None else f'{pm:.1f} deg'}, GM {'-' if gm is None else f'{gm:.1f} dB'}"]
    L.append(f"chain time {s['wall_s']:.1f} s (the drives' experiments and analysis; the command's start-up and "
             "loading the maps not counted)")
    return "\n".join(L)
