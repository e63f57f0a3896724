"""What the commissioning chain did: the report of one plant (text and JSON) and the summary over
many plants."""

from __future__ import annotations

import math
import statistics
from dataclasses import dataclass, field
from typing import Any

import sim
from training._json import json_safe

from ._excitation import ExcitationLimits, ExcitationResult
from ._permission import CommissioningWarning, IdentificationOutcome, Permission
from ._rules import ControllerProposal
from ._tuning import TuningResult
from ._validation import ValidationResult

__all__ = ["CommissioningReport", "summarize", "summary_text"]

#: The parameters shown beside the truth in the text report.
_SHOWN: tuple[str, ...] = sim.PARAM_NAMES + ("C_F",)
_UNITS = {"J_sigma": "kg m^2", "f_e": "Hz", "backlash": "rad (2s)", "M_FC": "Nm", "mu_F": "Nm s/rad", "C_F": "Nm/rad"}


@dataclass(frozen=True)
class CommissioningReport:
    """Everything the chain did on one plant.

    ``excitation``: :class:`ExcitationResult` (log per run); ``record``: the final test record
    (no truth inside); ``identification``: what the identifier answered, unchanged (an
    ``IdentificationResult``, or a failure with ``error``); ``validation``:
    :class:`ValidationResult` (None when the identification failed or the re-simulation could not
    run); ``permission``: :class:`Permission` (``allowed``, ``rule``, ``reason``); the
    commissioning's own findings: ``warnings`` (:class:`CommissioningWarning`) and
    ``outside_training`` (its reading of the map distances with ``max_map_distance_ratio``; None
    when the identification failed); ``proposal`` / ``tuning``: the model-based proposal and its
    tuning, or after a refusal the cautious fallback F1 and its search on the plant (``fallback``
    True; None when no fallback ran); ``plant_costs``: ``{"proposal", "tuned"}`` on the plant;
    ``figures``: step-response figures on the plant ``{"before", "after"}``; ``responses``: the
    plant's speed ``2 x N`` (ref run, load run) before/after and the scenario; ``truth``: the
    plant's true parameters (report only); ``checks``: evaluation checks (limits kept, closed loop
    stable); ``timings`` [s] per stage.
    """

    drive: Any
    limits: ExcitationLimits
    excitation: ExcitationResult
    record: Any
    identification: IdentificationOutcome
    validation: ValidationResult | None
    permission: Permission
    warnings: tuple[CommissioningWarning, ...] = ()
    outside_training: bool | None = None
    max_map_distance_ratio: float | None = None
    proposal: ControllerProposal | None = None
    tuning: TuningResult | None = None
    plant_costs: dict[str, float] = field(default_factory=dict)
    figures: dict[str, dict[str, float]] = field(default_factory=dict)
    responses: dict[str, Any] = field(default_factory=dict)
    truth: dict[str, Any] = field(default_factory=dict)
    checks: dict[str, Any] = field(default_factory=dict)
    timings: dict[str, float] = field(default_factory=dict)
    name: str = "plant"
    fallback: bool = False

    @property
    def refused(self) -> bool:
        """The identification was refused for a model-based controller."""
        return not self.permission.allowed

    @property
    def improvement(self) -> float | None:
        """Relative cost reduction on the plant ``1 - tuned/proposal`` (None without a controller)."""
        c0, c1 = self.plant_costs.get("proposal"), self.plant_costs.get("tuned")
        if c0 is None or c1 is None or not c0 > 0:
            return None
        return 1.0 - c1 / c0

    @property
    def controller(self) -> ControllerProposal | None:
        """The controller to use: the tuned one, else the proposal, else None (refused, no fallback)."""
        return self.tuning.controller if self.tuning is not None else self.proposal

    @property
    def identified_structure(self) -> str | None:
        """The identified structure (None when the identification failed)."""
        return self.identification.structure if self.identification.ok else None

    # ------------------------------------------------------------------ output

    def to_dict(self) -> dict[str, Any]:
        """JSON-able summary (no signal arrays; NaN and inf as None)."""
        v, ex = self.validation, self.excitation
        return json_safe({
            "name": self.name,
            "limits": {"w_limit": self.limits.w_limit, "travel_limit": self.limits.travel_limit,
                       "M_star_max": self.limits.M_star_max},
            "excitation": {"informative": ex.informative, "reason": ex.reason, "M_star": float(ex.signal.M_star),
                           "w_max": float(ex.signal.w_max), "log": ex.log},
            "identification": self.identification.to_dict(),
            "validation": None if v is None else {
                "passed": v.passed, "mode": v.mode, "nrmse": v.nrmse, "osc_nrmse": v.osc_nrmse, "threshold": v.threshold,
                "osc_threshold": v.osc_threshold, "reason": v.reason},
            "assessment": {"outside_training": self.outside_training, "max_map_distance_ratio": self.max_map_distance_ratio,
                           "warnings": [{"code": w.code, "text": w.text} for w in self.warnings]},
            "permission": {"allowed": self.permission.allowed, "rule": self.permission.rule,
                           "reason": self.permission.reason, "notes": list(self.permission.notes)},
            "fallback": self.fallback,
            "proposal": self.proposal,
            "tuned": None if self.tuning is None else self.tuning.controller,
            "tuning": None if self.tuning is None else {
                "pretune_cost_proposal": self.tuning.cost_proposal, "pretune_cost_tuned": self.tuning.cost_tuned,
                "n_evaluations": self.tuning.n_evaluations, "warnings": list(self.tuning.warnings)},
            "plant_costs": self.plant_costs,
            "improvement": self.improvement,
            "figures": self.figures,
            "truth": self.truth,
            "checks": self.checks,
            "timings": self.timings,
        })

    def to_text(self) -> str:
        """A readable report (one plant)."""
        d = self.drive
        M_cap = self.limits.M_star_max if self.limits.M_star_max is not None else d.M_max
        L = [f"== commissioning {self.name} ==",
             f"limits: |w| <= {self.limits.w_limit:g} rad/s, travel <= {self.limits.travel_limit:g} rad, "
             f"M* <= {M_cap:g} Nm (drive M_max {d.M_max:g} Nm)"]
        L += self._excitation_lines() + self._identification_lines()
        if self.validation is not None:
            v = self.validation
            osc = "n/a (oscillation below 3 q_w)" if v.osc_nrmse is None else f"{v.osc_nrmse:.3g} (<= {v.osc_threshold:g})"
            L.append(f"3 validation ({v.mode}): speed error {v.nrmse:.3g} (<= {v.threshold:g}), oscillation error {osc}: "
                     f"{'passed' if v.passed else 'FAILED'} - {v.reason}")
        if self.refused:
            L.append(f"4 REFUSED: no controller from the identified model. {self.permission.reason}")
        else:
            L.append(f"4 permission: {self.permission.reason}")
        if self.proposal is not None:
            L += self._controller_lines()
        if self.checks:
            L.append("checks: " + ", ".join(f"{k} {_check(v)}" for k, v in self.checks.items()))
        return "\n".join(line.rstrip() for line in L)

    def _excitation_lines(self) -> list[str]:
        L = ["1 test signal (rules E1-E7):",
             "   run  M* [Nm]  w_max [rad/s]  peak w [rad/s]  travel [rad]  osc [q_w]  decision"]
        for e in self.excitation.log:
            L.append(f"   {e['iteration']:3d}  {e['M_star']:7.3g}  {e['w_max']:13.4g}  {e['peak_speed']:14.4g}  "
                     f"{e['travel']:12.4g}  {e['osc_quanta']:9.3g}  {e['decision']} ({e['reason']})")
        L.append(f"   -> {self.excitation.reason}; record {len(self.record.t)} samples, "
                 f"{len(self.record.t) * float(self.drive.T_s):.3f} s")
        return L

    def _identification_lines(self) -> list[str]:
        ident = self.identification
        if not ident.ok:
            return [f"2 identification failed: {ident.error}"]
        L = [f"2 identification: structure {ident.structure} (true {self.truth.get('structure', '?')})",
             "   parameter        identified          true"]
        for k in _SHOWN:
            L.append(f"   {k:<10} {_fmt(getattr(ident.parameters, k)):>16} {_fmt(self.truth.get(k)):>13}  {_UNITS.get(k, '')}")
        ratios = ident.quality.map_distance_ratio
        if ratios:
            L.append("   map distance / training 99 % quantile: " + ", ".join(f"{k} {v:.2f}" for k, v in ratios.items()))
        L += [f"   warning: {w.text}" for w in (*ident.warnings, *self.warnings)]
        return L

    def _controller_lines(self) -> list[str]:
        pr = self.proposal
        if self.fallback:
            L = [f"5 fallback F1 (cautious, J_sigma only): {pr.concept}, Kp {pr.Kp:.4g} Nm s/rad, "
                 f"Ti {pr.Ti * 1e3:.4g} ms, T_f {pr.T_f * 1e3:.3g} ms, w_c {pr.figures['w_c']:.4g} rad/s"]
        else:
            L = [f"5 proposal: {pr.concept}, Kp {pr.Kp:.4g} Nm s/rad, Ti {pr.Ti * 1e3:.4g} ms, T_f {pr.T_f * 1e3:.3g} ms; "
                 f"on the identified model: w_c {pr.figures['w_c']:.4g} rad/s, PM {pr.figures['phase_margin']:.1f} deg, "
                 f"GM {pr.figures['gain_margin_dB']:.1f} dB"]
        L += [f"   warning: {w}" for w in pr.warnings]
        if self.tuning is not None:
            tc = self.tuning.controller
            where = "on the plant" if self.fallback else "on the identified model, final choice on the plant"
            L.append(f"6 tuned: Kp {tc.Kp:.4g} Nm s/rad, Ti {tc.Ti * 1e3:.4g} ms, T_f {tc.T_f * 1e3:.3g} ms "
                     f"({self.tuning.n_evaluations} evaluations {where})")
            L.append(f"   cost on the plant: proposal {self.plant_costs['proposal']:.4g} -> tuned "
                     f"{self.plant_costs['tuned']:.4g} ({100 * (self.improvement or 0):.1f} % better)")
            L += [f"   note: {w}" for w in self.tuning.warnings]
        if self.figures:
            sc = self.responses.get("scenario")
            L.append(f"   step response on the plant (step {sc.w_step:.3g} rad/s, load {sc.M_L:.3g} Nm):" if sc
                     else "   step response:")
            L.append("                 rise [ms]  overshoot [%]  settling [ms]  load dip [rad/s]  recovery [ms]")
            for k in ("before", "after"):
                f = self.figures.get(k)
                if f:
                    L.append(f"   {k:<12} {_ms(f['rise_time']):>10} {f['overshoot_pct']:>14.1f} {_ms(f['settling_time']):>14} "
                             f"{f['load_dip']:>17.4g} {_ms(f['load_recovery_time']):>14}")
        return L


def _check(v: Any) -> str:
    if isinstance(v, bool):
        return "yes" if v else "NO"
    return f"{v:.4g}" if isinstance(v, float) else str(v)


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


# --------------------------------------------------------------------------- many plants


def summarize(reports: list[CommissioningReport], wall_s: float) -> dict[str, Any]:
    """Figures over many plants: refusals by rule, limit checks, stability over the plants that end
    with a controller (model-based or fallback), improvement over the model-based proposals
    (improvement = 1 - tuned/proposal cost on the plant; a fallback starts from a loop too slow to
    settle in the test window, so its 'improvement' says little)."""
    acc = [r for r in reports if r.controller is not None]
    by_rule: dict[str, int] = {}
    for r in reports:
        if r.refused:
            by_rule[r.permission.rule] = by_rule.get(r.permission.rule, 0) + 1
    imps = [(r.improvement, r.name) for r in acc if r.improvement is not None and not r.fallback]
    worst = min(imps) if imps else (None, None)
    return {
        "plants": len(reports),
        "with_controller": len(acc),
        "model_based": sum(1 for r in acc if not r.fallback),
        "fallback": sum(1 for r in acc if r.fallback),
        "refused": sum(by_rule.values()),
        "refused_by_rule": by_rule,
        "within_limits": sum(bool(r.checks.get("within_limits")) for r in reports),
        "stable": sum(bool(r.checks.get("stable")) for r in acc),
        "tuned_not_worse": sum(bool(r.checks.get("tuned_not_worse")) for r in acc),
        "median_improvement": statistics.median(i for i, _ in imps) if imps else None,
        "worst_improvement": worst[0],
        "worst_plant": worst[1],
        "best_improvement": max(i for i, _ in imps) if imps else None,
        "structure_correct": sum(r.identified_structure == r.truth.get("structure") for r in reports),
        "wall_s": wall_s,
    }


def summary_text(s: dict[str, Any]) -> str:
    """The summary of :func:`summarize` as readable lines."""
    def pct(v: float | None) -> str:
        return "-" if v is None else f"{100 * v:.1f} %"
    rules = ", ".join(f"{k} {v}" for k, v in sorted(s["refused_by_rule"].items())) or "none"
    return "\n".join([
        f"== summary over {s['plants']} plants ==",
        f"limits kept in every test run: {s['within_limits']}/{s['plants']}",
        f"identified structure = true class: {s['structure_correct']}/{s['plants']}",
        f"refused for a model-based controller: {s['refused']}/{s['plants']} ({rules}); "
        f"ended with a controller: {s['with_controller']}/{s['plants']} "
        f"({s['model_based']} model-based, {s['fallback']} cautious fallback F1 tuned on the plant)",
        f"over those: stable closed loop {s['stable']}/{s['with_controller']}, "
        f"tuned cost <= proposal cost on the plant {s['tuned_not_worse']}/{s['with_controller']}",
        f"cost improvement of the model-based proposals on the plant (1 - tuned/proposal): "
        f"median {pct(s['median_improvement'])}, "
        f"worst {pct(s['worst_improvement'])} ({s['worst_plant']}), best {pct(s['best_improvement'])}",
        f"wall time {s['wall_s']:.0f} s",
    ])
