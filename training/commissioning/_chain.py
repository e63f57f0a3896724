"""The self-commissioning chain (SPEC 8, the paper's section 2) on one plant.

    adapt the test signal (E1-E7) -> record -> identify (shipped maps) -> validate (re-simulate)
    -> may a controller be proposed? (V1-V6) -> propose (R1-R7) -> fine-tune (Nelder-Mead) -> report

The plant is the simulator behind the plant interfaces a real drive would offer: the test
runner ``signal -> response`` (:func:`training.commissioning._excitation.sim_test_runner`) and the closed-loop
runner (:class:`training.commissioning._tuning.SimRunner`). The chain itself sees only what a drive delivers:
the responses are turned into records *without* ``meta["truth"]``; the true parameters are
used only to simulate the plant and, in the report, for the "true" column and the evaluation
checks (true linear closed loop stable, limits kept), never for a decision.

Tuning in two stages (docs/commissioning.md, "The chain"): a Nelder-Mead search on the exact
linear model of the *identified* mechanics (:class:`LinearRunner`, fast), then the final check
on the plant itself (:class:`SimRunner`, nonlinear): the proposal, the pre-tuned gains and points
between them run side by side in one batch on the plant, and the lowest plant cost wins — so the
tuned cost on the plant is never above the proposal's by construction. An optional short
Nelder-Mead on the plant (``plant_evaluations``) polishes the winner.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np
import torch

from training.commissioning._controller import (ControllerProposal, ControllerSpec, loop_figures, mechanics_from, propose_cautious,
                                 propose_controller)
from training.commissioning._excitation import ExcitationLimits, ExcitationResult, ExcitationRules, adapt_test_signal, sim_test_runner
from training.commissioning._tuning import (LinearRunner, SimRunner, TuningResult, evaluate_gains, make_scenario,
                             response_figures, tune_controller)
from training.commissioning._validation import Permission, ValidationResult, may_propose_controller, validate_model

__all__ = ["CommissioningReport", "commission", "limit_checks", "PARAMETER_KEYS"]

#: The seven model parameters that re-simulation and the controller rules use.
PARAMETER_KEYS: tuple[str, ...] = ("J_sigma", "V_J", "f_e", "d", "backlash", "M_FC", "mu_F")
_SHOWN = ("J_sigma", "V_J", "f_e", "d", "backlash", "M_FC", "mu_F", "C_F")


@dataclass
class CommissioningReport:
    """Everything the chain did on one plant.

    ``excitation``: :class:`ExcitationResult` (log per run); ``record``: the final test record
    (no truth inside); ``identification``: the identifier's dict (with ``quality.validation_*``
    added); ``validation``: :class:`ValidationResult` (None when identification failed);
    ``permission``: :class:`Permission` (``allowed``, ``reason``); ``proposal`` /
    ``tuning``: the model-based proposal and its tuning, or after a refusal the cautious fallback
    F1 and its search on the plant (``fallback`` True; None when no fallback ran); ``plant_costs``: ``{"proposal", "tuned"}`` on the plant;
    ``figures``: step-response figures on the plant ``{"before", "after"}``; ``responses``:
    the plant's speed ``2 x N`` (ref run, load run) before/after and the scenario; ``truth``:
    the plant's true parameters (report only); ``checks``: evaluation checks (limits kept,
    closed loop stable); ``timings`` [s] per stage.
    """

    drive: Any
    limits: ExcitationLimits
    excitation: ExcitationResult
    record: Any
    identification: dict[str, Any]
    validation: ValidationResult | None
    permission: Permission
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

    # ------------------------------------------------------------------ output

    def to_dict(self) -> dict[str, Any]:
        """JSON-able summary (no signal arrays)."""
        ident = self.identification
        out: dict[str, Any] = {
            "name": self.name,
            "limits": {"w_limit": self.limits.w_limit, "travel_limit": self.limits.travel_limit,
                       "M_star_max": self.limits.M_star_max},
            "excitation": {"informative": self.excitation.informative, "reason": self.excitation.reason,
                           "M_star": float(self.excitation.signal.M_star), "w_max": float(self.excitation.signal.w_max),
                           "log": [_jsonable(e) for e in self.excitation.log]},
            "identification": _jsonable({k: ident.get(k) for k in ("structure", "parameters", "quality", "warnings", "error")
                                         if k in ident}),
            "validation": None if self.validation is None else {
                "passed": self.validation.passed, "mode": self.validation.mode, "nrmse": self.validation.nrmse,
                "osc_nrmse": self.validation.osc_nrmse, "threshold": self.validation.threshold,
                "osc_threshold": self.validation.osc_threshold, "reason": self.validation.reason},
            "permission": {"allowed": self.permission.allowed, "reason": self.permission.reason,
                           "notes": list(self.permission.notes)},
            "fallback": self.fallback,
            "proposal": None if self.proposal is None else _jsonable(self.proposal.to_dict()),
            "tuned": None if self.tuning is None else _jsonable(self.tuning.controller.to_dict()),
            "tuning": None if self.tuning is None else {
                "pretune_cost_proposal": self.tuning.cost_proposal, "pretune_cost_tuned": self.tuning.cost_tuned,
                "n_evaluations": self.tuning.n_evaluations, "warnings": list(self.tuning.warnings)},
            "plant_costs": dict(self.plant_costs),
            "improvement": self.improvement,
            "figures": _jsonable(self.figures),
            "truth": _jsonable(self.truth),
            "checks": _jsonable(self.checks),
            "timings": dict(self.timings),
        }
        return out

    def to_text(self) -> str:
        """A readable report (one plant)."""
        L: list[str] = []
        d = self.drive
        L.append(f"== commissioning {self.name} ==")
        L.append(f"limits: |w| <= {self.limits.w_limit:g} rad/s, travel <= {self.limits.travel_limit:g} rad, "
                 f"M* <= {self.limits.M_star_max if self.limits.M_star_max is not None else d.M_max:g} Nm "
                 f"(drive M_max {d.M_max:g} Nm)")
        L.append("1 test signal (rules E1-E7):")
        L.append("   run  M* [Nm]  w_max [rad/s]  peak w [rad/s]  travel [rad]  osc [q_w]  decision")
        for e in self.excitation.log:
            L.append(f"   {e['iteration']:3d}  {e['M_star']:7.3g}  {e['w_max']:13.4g}  {e['peak_speed']:14.4g}  "
                     f"{e['travel']:12.4g}  {e['osc_quanta']:9.3g}  {e['decision']} ({e['reason']})")
        L.append(f"   -> {self.excitation.reason}; record {len(self.record.t)} samples, "
                 f"{len(self.record.t) * float(d.T_s):.3f} s")
        ident = self.identification
        if ident.get("error"):
            L.append(f"2 identification failed: {ident['error']}")
        else:
            p = ident.get("parameters") or {}
            true_cls = self.truth.get("structure", "?")
            L.append(f"2 identification: structure {ident.get('structure')} (true {true_cls})")
            L.append("   parameter        identified          true")
            for k in _SHOWN:
                L.append(f"   {k:<10} {_fmt(p.get(k)):>16} {_fmt(self.truth.get(k)):>13}  {_unit(k)}")
            q = ident.get("quality") or {}
            ratios = q.get("map_distance_ratio") or {}
            if ratios:
                L.append("   map distance / training 99 % quantile: "
                         + ", ".join(f"{k} {v:.2f}" for k, v in ratios.items()))
            for w in ident.get("warnings") or []:
                L.append(f"   warning: {w}")
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
            pr = self.proposal
            if self.fallback:
                L.append(f"5 fallback F1 (cautious, J_sigma only): {pr.concept}, Kp {pr.Kp:.4g} Nm s/rad, "
                         f"Ti {pr.Ti * 1e3:.4g} ms, T_f {pr.T_f * 1e3:.3g} ms, w_c {pr.figures['w_c']:.4g} rad/s")
            else:
                L.append(f"5 proposal: {pr.concept}, Kp {pr.Kp:.4g} Nm s/rad, Ti {pr.Ti * 1e3:.4g} ms, T_f {pr.T_f * 1e3:.3g} ms; "
                         f"on the identified model: w_c {pr.figures['w_c']:.4g} rad/s, PM {pr.figures['phase_margin']:.1f} deg, "
                         f"GM {pr.figures['gain_margin_dB']:.1f} dB")
            for w in pr.warnings:
                L.append(f"   warning: {w}")
            if self.tuning is not None:
                tc = self.tuning.controller
                where = "on the plant" if self.fallback else "on the identified model, final choice on the plant"
                L.append(f"6 tuned: Kp {tc.Kp:.4g} Nm s/rad, Ti {tc.Ti * 1e3:.4g} ms, T_f {tc.T_f * 1e3:.3g} ms "
                         f"({self.tuning.n_evaluations} evaluations {where})")
                L.append(f"   cost on the plant: proposal {self.plant_costs['proposal']:.4g} -> tuned "
                         f"{self.plant_costs['tuned']:.4g} ({100 * (self.improvement or 0):.1f} % better)")
                for w in self.tuning.warnings:
                    L.append(f"   note: {w}")
            if self.figures:
                sc = self.responses.get("scenario")
                head = f"   step response on the plant (step {sc.w_step:.3g} rad/s, load {sc.M_L:.3g} Nm):" if sc else "   step response:"
                L.append(head)
                L.append("                 rise [ms]  overshoot [%]  settling [ms]  load dip [rad/s]  recovery [ms]")
                for k in ("before", "after"):
                    f = self.figures.get(k)
                    if f:
                        L.append(f"   {k:<12} {_ms(f['rise_time']):>10} {f['overshoot_pct']:>14.1f} {_ms(f['settling_time']):>14} "
                                 f"{f['load_dip']:>17.4g} {_ms(f['load_recovery_time']):>14}")
        if self.checks:
            c = self.checks
            L.append("checks: " + ", ".join(f"{k} {_check(v)}" for k, v in c.items()))
        return "\n".join(line.rstrip() for line in L)


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


def _unit(k: str) -> str:
    return {"J_sigma": "kg m^2", "f_e": "Hz", "backlash": "rad (2s)", "M_FC": "Nm", "mu_F": "Nm s/rad",
            "C_F": "Nm/rad"}.get(k, "")


def _jsonable(x: Any) -> Any:
    if isinstance(x, dict):
        return {str(k): _jsonable(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_jsonable(v) for v in x]
    if isinstance(x, torch.Tensor):
        return _jsonable(x.tolist())
    if isinstance(x, np.ndarray):
        return _jsonable(x.tolist())
    if isinstance(x, (np.floating, np.integer, np.bool_)):
        return x.item()
    if isinstance(x, float) and not math.isfinite(x):
        return None if math.isnan(x) else (1e308 if x > 0 else -1e308)
    return x


# --------------------------------------------------------------------------- checks


def limit_checks(excitation: ExcitationResult, limits: ExcitationLimits, drive: Any) -> dict[str, Any]:
    """Were the user limits kept in every test run? From the log's measured peaks (speed,
    travel from start, torque reference) against ``w_limit``, ``travel_limit`` and the torque cap."""
    M_cap = float(drive.M_max) if limits.M_star_max is None else min(float(drive.M_max), limits.M_star_max)
    log = excitation.log
    peak_w = max(e["peak_speed"] for e in log)
    peak_phi = max(e["travel"] for e in log)
    peak_M = max((e["peak_torque_ref"] for e in log if math.isfinite(e["peak_torque_ref"])), default=0.0)
    return {
        "peak_speed": peak_w, "peak_travel": peak_phi, "peak_torque_ref": peak_M,
        "within_limits": bool(peak_w <= limits.w_limit and peak_phi <= limits.travel_limit and peak_M <= M_cap + 1e-6),
    }


# --------------------------------------------------------------------------- the chain


def _record_without_truth(resp: Any, params: Any, drive: Any, signal: Any) -> Any:
    import sim

    rec = sim.responses_to_records(resp, params.reshape(1), drive, signal, names=["commissioning"])[0]
    rec.meta.pop("truth", None)  # the chain sees what a drive delivers, nothing more
    return rec


def _model_params(ident: dict[str, Any]) -> dict[str, float | None]:
    p = ident.get("parameters") or {}
    out: dict[str, float | None] = {k: p.get(k) for k in PARAMETER_KEYS}
    if ident.get("structure") == "stiff":
        out["V_J"], out["f_e"] = None, None  # one-mass model: validation uses its documented stand-in
    return out


def commission(
    plant_params: Any,
    drive: Any,
    limits: ExcitationLimits,
    *,
    identifier: Any,
    spec: ControllerSpec | None = None,
    seed: int = 0,
    tune: bool = True,
    writer: Any = None,
    progress: Callable[[str], None] | None = None,
    rules: ExcitationRules | None = None,
    validation_mode: str = "replay",
    osc_metric: str = "spectrum",
    max_validation_error: float = 0.1,
    max_map_distance_ratio: float | None = 3.0,
    tune_evaluations: int = 30,
    plant_evaluations: int = 0,
    max_samples: int = 2000,
    name: str = "plant",
    tag: str | None = None,
    timeout: float = 10.0,
    fallback_evaluations: int = 20,
) -> CommissioningReport:
    """Run the whole chain on one simulated plant.

    Args:
        plant_params: the plant (one-system ``sim.TwoMassParams``; stands where a real drive would).
        drive: ``sim.DriveConfig``.
        limits: user limits for the test runs.
        identifier: object with ``identify(record) -> dict`` (``training.identification._identifier.Identifier``).
        spec: controller rule constants (``ControllerSpec``).
        seed: noise seed of the test runs.
        tune: run the fine-tuning (else: proposal only, still evaluated on the plant).
        writer: optional TensorBoard ``SummaryWriter``: scalars of the search under ``tag``.
        progress: optional callback with one-line stage messages.
        rules: excitation rule constants.
        validation_mode: "replay" (default: the recorded torque reference open loop through the
            identified model, fused kernel) or "switching" (the test's switching law rerun on the
            identified model: a small error in when a speed threshold is reached moves the later
            sections, which failed 2 more of 50 well-identified plants) (:func:`validate_model`).
        osc_metric: oscillation comparison, "spectrum" (default, phase-insensitive) or "time".
        max_validation_error: refusal rule V3 bound on the speed error.
        max_map_distance_ratio: rule V4: refuse when a used map's distance ratio (recall distance
            over the training 99 % quantile) exceeds it (default 3: the maps were trained on the
            fixed M* = 10 Nm, w_max = 100 rad/s test, adapted tests lie farther; 45 of 50
            population plants exceed 1, docs/commissioning.md); None: the identifier's own
            ``outside_training`` flag (ratio > 1).
        tune_evaluations: Nelder-Mead evaluations on the identified linear model (default 30).
        plant_evaluations: extra Nelder-Mead evaluations on the plant after the pre-tune (0: none).
        max_samples: longest scenario run [samples] (default 2000 = 0.5 s; 25/w_c is cut there
            for loops slower than w_c = 50 rad/s).
        name, tag: report name and TensorBoard tag prefix.
        timeout: safety timeout per test section [s].
        fallback_evaluations: after a refusal, the cautious fallback F1 (PI on ``J_sigma`` alone,
            :func:`training.commissioning._controller.propose_cautious`) is tuned by this many Nelder-Mead
            evaluations on the plant itself (0: no fallback, the chain ends with the refusal).

    Returns :class:`CommissioningReport`. A refused identification is a normal outcome (the
    report says why); errors in the inputs raise ValueError/TypeError.
    """
    import sim

    if not isinstance(plant_params, sim.TwoMassParams):
        raise TypeError(f"plant_params: expected sim.TwoMassParams, received {type(plant_params).__name__}")
    if plant_params.J_sigma.numel() != 1:
        raise ValueError(f"plant_params: expected one system, received batch {tuple(plant_params.batch_shape)}")
    if not isinstance(limits, ExcitationLimits):
        raise TypeError(f"limits: expected ExcitationLimits, received {type(limits).__name__}")
    if not callable(getattr(identifier, "identify", None)):
        raise TypeError(f"identifier: expected an object with identify(record), received {type(identifier).__name__}")
    if tune_evaluations < 1 or plant_evaluations < 0 or fallback_evaluations < 0:
        raise ValueError(f"tune_evaluations >= 1, plant_evaluations >= 0, fallback_evaluations >= 0 expected, "
                         f"received {tune_evaluations}, {plant_evaluations}, {fallback_evaluations}")
    plant = plant_params.reshape(())
    say = progress or (lambda msg: None)
    tag = tag or name
    timings: dict[str, float] = {}
    t0 = time.perf_counter()

    # 1 test signal on the plant (the runner is the plant interface)
    say(f"{name}: adapting the test signal")
    ex = adapt_test_signal(sim_test_runner(plant, drive, seed=seed), drive, limits, rules, timeout=timeout)
    record = _record_without_truth(ex.response, plant, drive, ex.signal)
    truth = plant.reshape(1).truth(drive, float(ex.signal.M_star))[0]
    truth = {k: truth[k] for k in ("J_sigma", "V_J", "f_e", "d", "backlash", "M_FC", "mu_F", "C_F", "s_N", "r_osc", "structure")}
    t1 = time.perf_counter()
    timings["excitation"] = t1 - t0

    # 2 identification (what the maps say) and 3 validation (does the model reproduce the record?)
    say(f"{name}: identifying")
    try:
        ident = dict(identifier.identify(record))
    except (ValueError, RuntimeError) as err:
        ident = {"error": str(err).strip().splitlines()[0] if str(err).strip() else type(err).__name__}
    ident.setdefault("warnings", [])
    ident["warnings"] = list(ident["warnings"])
    if not ex.informative:
        ident["warnings"].append(f"test response not informative: {ex.reason}")
    vr: ValidationResult | None = None
    if not ident.get("error"):
        quality = dict(ident.get("quality") or {})
        if max_map_distance_ratio is not None and quality.get("map_distance_ratio"):
            used = ["structure"] + (["f_e", "V_J"] if ident.get("structure") != "stiff" else []) + \
                   (["backlash"] if ident.get("structure") in ("elastic_backlash", "stiff_backlash") else [])
            ratios = quality["map_distance_ratio"]
            quality["outside_training_identifier"] = quality.get("outside_training")
            quality["outside_training"] = any(ratios.get(n, 0.0) > max_map_distance_ratio for n in used)
        try:
            vr = validate_model(_model_params(ident), drive, record, mode=validation_mode, seed=seed,
                                osc_metric=osc_metric)
            quality.update(validation_error=vr.nrmse, validation_osc_error=vr.osc_nrmse, validation_passed=vr.passed)
        except (ValueError, TypeError) as err:
            quality.update(validation_error=None, validation_passed=False)
            ident["warnings"].append(f"validation failed: {err}")
        ident["quality"] = quality
    t2 = time.perf_counter()
    timings["identification_validation"] = t2 - t1

    # 4 knowledge base: may a controller be proposed?
    perm = may_propose_controller(ident, max_validation_error=max_validation_error)
    if not perm.allowed and vr is not None and not vr.passed and perm.reason.startswith("V3"):
        perm = Permission(False, f"{perm.reason} ({vr.reason})", perm.notes)
    if not perm.allowed and perm.reason.startswith("V4"):
        ratios = (ident.get("quality") or {}).get("map_distance_ratio") or {}
        bound = 1.0 if max_map_distance_ratio is None else max_map_distance_ratio
        far = ", ".join(f"{k} {v:.2f}" for k, v in ratios.items() if v > bound)
        perm = Permission(False, f"{perm.reason} (map distance / training 99 % quantile above {bound:g}: {far})", perm.notes)
    report = CommissioningReport(drive=drive, limits=limits, excitation=ex, record=record, identification=ident,
                                 validation=vr, permission=perm, truth=truth, timings=timings, name=name)
    report.checks = limit_checks(ex, limits, drive)
    J_sigma = ((ident.get("parameters") or {}).get("J_sigma")) if not ident.get("error") else None
    usable_J = isinstance(J_sigma, (int, float)) and math.isfinite(J_sigma) and J_sigma > 0
    if not perm.allowed:
        say(f"{name}: refused ({perm.reason})")
        if not (fallback_evaluations > 0 and usable_J):
            timings["total"] = time.perf_counter() - t0
            return report
        say(f"{name}: fallback F1, a cautious PI tuned on the plant ({fallback_evaluations} evaluations)")

    # 5 proposal from the identified structure and parameters (after a refusal: the fallback F1)
    report.fallback = not perm.allowed
    if report.fallback:
        params = {"J_sigma": float(J_sigma)}
        proposal = propose_cautious(float(J_sigma), drive, spec)
    else:
        params = _model_params(ident)
        proposal = propose_controller(ident["structure"], params, drive, spec)
    report.proposal = proposal
    sc = make_scenario(proposal, drive, max_samples=max_samples)
    plant_runner = SimRunner(plant, drive)
    t3 = time.perf_counter()
    timings["proposal"] = t3 - t2

    # 6 fine-tuning: pre-tune on the identified linear model, final choice on the plant
    cands = [(proposal.Kp, proposal.Ti, proposal.T_f)]
    tuning: TuningResult | None = None
    if tune and not report.fallback:
        say(f"{name}: tuning on the identified model ({tune_evaluations} evaluations)")
        tuning = tune_controller(proposal, LinearRunner(params, drive), drive, scenario=sc,
                                 max_evaluations=tune_evaluations)
        tc = tuning.controller
        if tc is not proposal:
            for frac in (1.0, 2 / 3, 1 / 3):  # the pre-tuned gains and points back towards the proposal
                cands.append(tuple(float(math.exp((1 - frac) * math.log(a) + frac * math.log(b)))
                                   for a, b in ((proposal.Kp, tc.Kp), (proposal.Ti, tc.Ti), (proposal.T_f, tc.T_f))))
        if writer is not None:
            for i, h in enumerate(tuning.history):
                writer.add_scalar(f"{tag}/pretune/cost", h["cost"], i)
                writer.add_scalar(f"{tag}/pretune/Kp", h["Kp"], i)
                writer.add_scalar(f"{tag}/pretune/Ti_ms", h["Ti"] * 1e3, i)
    t4 = time.perf_counter()
    timings["pretune"] = t4 - t3

    say(f"{name}: checking {len(cands)} gain set(s) on the plant")
    K, T, F = (torch.tensor([c[j] for c in cands], dtype=torch.float64) for j in range(3))
    costs, _, speeds = evaluate_gains(plant_runner, proposal, drive, sc, K, T, F)
    costs = costs.tolist()
    best = int(np.argmin(costs))
    if costs[best] >= costs[0]:
        best = 0
    best_cost, best_speed, best_gains = costs[best], speeds[best], cands[best]
    on_plant = fallback_evaluations if report.fallback else plant_evaluations
    if tune and on_plant > 0:
        say(f"{name}: searching on the plant ({on_plant} evaluations)")
        start = replace(proposal, Kp=best_gains[0], Ti=best_gains[1], T_f=best_gains[2])
        pol = tune_controller(start, plant_runner, drive, scenario=sc, max_evaluations=on_plant,
                              span=5.0 if report.fallback else 20.0)
        if report.fallback:
            tuning = pol
        if pol.cost_tuned < best_cost:
            best_gains = (pol.controller.Kp, pol.controller.Ti, pol.controller.T_f)
            _, _, sp = evaluate_gains(plant_runner, proposal, drive, sc, *(torch.tensor([g]) for g in best_gains))
            best_cost, best_speed = pol.cost_tuned, sp[0]
    t5 = time.perf_counter()
    timings["plant_check"] = t5 - t4
    if writer is not None:
        writer.add_scalar(f"{tag}/plant/cost_proposal", costs[0], 0)
        writer.add_scalar(f"{tag}/plant/cost_tuned", best_cost, 0)
    report.plant_costs = {"proposal": float(costs[0]), "tuned": float(best_cost)}
    report.responses = {"scenario": sc, "before": speeds[0].numpy(), "after": best_speed.numpy()}
    report.figures = {"before": response_figures(speeds[0], sc), "after": response_figures(best_speed, sc)}
    if tuning is not None:
        if best == 0 and best_gains == cands[0]:
            final = proposal
            tuning.warnings.append("on the plant no tuned gain set beat the proposal: the proposal is kept")
        else:
            final = proposal.with_gains(drive, *best_gains, rule=(
                f"T2 final choice on the plant: Kp {best_gains[0]:.4g}, Ti {best_gains[1]:.4g} s, T_f {best_gains[2]:.3g} s; "
                f"plant cost {costs[0]:.4g} -> {best_cost:.4g}"))
        tuning.controller = final
        report.tuning = tuning
    # evaluation checks (truth used here only, never for a decision): the chosen loop is stable
    chosen = report.controller or proposal
    true_figs = loop_figures(mechanics_from(plant.to_dicts()[0]), drive, chosen.Kp, chosen.Ti, chosen.T_f, chosen.notch)
    report.checks.update(
        settled_on_plant=bool(best_cost < sc.unstable_cost),
        stable_true_linear=bool(true_figs["stable"]),
        true_phase_margin=float(true_figs["phase_margin"]),
        tuned_not_worse=bool(best_cost <= costs[0]),
    )
    report.checks["stable"] = report.checks["settled_on_plant"] and report.checks["stable_true_linear"]
    timings["total"] = time.perf_counter() - t0
    return report
