"""The self-commissioning chain (SPEC 8, the paper's section 2) on one plant, one function per stage.

    adapt the test signal (E1-E7) -> record -> identify (shipped maps) -> validate (re-simulate)
    -> may a controller be proposed? (V1-V6) -> propose (R1-R7) -> fine-tune (Nelder-Mead)
    -> check on the plant -> report

The plant is the simulator behind the plant interfaces a real drive would offer: the test
runner ``signal -> response`` (:func:`training.commissioning._excitation.sim_test_runner`) and the
closed-loop runner (:class:`training.commissioning._tuning.SimRunner`). The chain itself sees only
what a drive delivers: the responses are turned into records *without* ``meta["truth"]``; the true
parameters are used only to simulate the plant and, in the report, for the "true" column and the
evaluation checks (true linear closed loop stable, limits kept), never for a decision. The
identifier is an object handed in (``identify(record)``); its answer is kept unchanged in the
report, the commissioning's own findings beside it.

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

import sim
from training.errors import one_line

from ._excitation import ExcitationLimits, ExcitationResult, ExcitationRules, adapt_test_signal, sim_test_runner
from ._loop import loop_figures, mechanics_from
from ._permission import (CommissioningWarning, IdentificationFailed, IdentificationOutcome, may_propose_controller,
                          outside_training)
from ._report import CommissioningReport
from ._rules import ControllerProposal, ControllerSpec, propose_cautious, propose_controller
from ._tuning import (LinearRunner, SimRunner, TuningResult, TuningScenario, evaluate_gains, make_scenario,
                      response_figures, tune_controller)
from ._validation import OSC_METRICS, VALIDATION_MODES, ValidationResult, validate_model

__all__ = ["CommissioningConfig", "commission", "limit_checks"]

#: The plant's true values kept for the report (never used for a decision).
_TRUTH_SHOWN: tuple[str, ...] = sim.PARAM_NAMES + ("C_F", "s_N", "r_osc", "structure")


@dataclass(frozen=True)
class CommissioningConfig:
    """The chain's settings, with their defaults.

    Attributes:
        spec: controller rule constants (:class:`ControllerSpec`).
        rules: excitation rule constants (:class:`ExcitationRules`).
        seed: noise seed of the test runs.
        tune: run the fine-tuning (else: proposal only, still evaluated on the plant).
        validation_mode: "replay" (the recorded torque reference open loop through the identified
            model, fused kernel) or "switching" (the test's switching law rerun on the identified
            model: a small error in when a speed threshold is reached moves the later sections,
            which failed 2 more of 50 well-identified plants) (:func:`validate_model`).
        osc_metric: oscillation comparison, "spectrum" (phase-insensitive) or "time".
        max_validation_error: refusal rule V3's bound on the speed error.
        max_map_distance_ratio: rule V4: refuse when a used map's distance ratio (recall distance
            over the training 99 % quantile) exceeds it (default 3: the maps were trained on the
            fixed M* = 10 Nm, w_max = 100 rad/s test, adapted tests lie farther; 45 of 50
            population plants exceed 1, docs/commissioning.md); None: the identifier's own
            ``outside_training`` flag (ratio > 1).
        tune_evaluations: Nelder-Mead evaluations on the identified linear model.
        plant_evaluations: extra Nelder-Mead evaluations on the plant after the pre-tune (0: none).
        fallback_evaluations: after a refusal, the cautious fallback F1 (PI on ``J_sigma`` alone,
            :func:`propose_cautious`) is tuned by this many Nelder-Mead evaluations on the plant
            itself (0: no fallback, the chain ends with the refusal).
        max_samples: longest scenario run [samples] (2000 = 0.5 s; 25/w_c is cut there for loops
            slower than w_c = 50 rad/s).
        timeout: safety timeout per test section [s].
    """

    spec: ControllerSpec = field(default_factory=ControllerSpec)
    rules: ExcitationRules = field(default_factory=ExcitationRules)
    seed: int = 0
    tune: bool = True
    validation_mode: str = "replay"
    osc_metric: str = "spectrum"
    max_validation_error: float = 0.1
    max_map_distance_ratio: float | None = 3.0
    tune_evaluations: int = 30
    plant_evaluations: int = 0
    fallback_evaluations: int = 20
    max_samples: int = 2000
    timeout: float = 10.0

    def __post_init__(self) -> None:
        if self.tune_evaluations < 1 or self.plant_evaluations < 0 or self.fallback_evaluations < 0:
            raise ValueError(f"tune_evaluations >= 1, plant_evaluations >= 0, fallback_evaluations >= 0 expected, "
                             f"received {self.tune_evaluations}, {self.plant_evaluations}, {self.fallback_evaluations}")
        if self.validation_mode not in VALIDATION_MODES:
            raise ValueError(f"validation_mode: expected one of {VALIDATION_MODES}, received {self.validation_mode!r}")
        if self.osc_metric not in OSC_METRICS:
            raise ValueError(f"osc_metric: expected one of {OSC_METRICS}, received {self.osc_metric!r}")
        bound = self.max_map_distance_ratio
        if not self.max_validation_error > 0 or (bound is not None and not bound > 0):
            raise ValueError(f"max_validation_error > 0 and max_map_distance_ratio > 0 or None expected, "
                             f"received {self.max_validation_error}, {bound}")


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


def _true_loop_checks(plant: Any, drive: Any, chosen: ControllerProposal, choice: _PlantChoice,
                      sc: TuningScenario) -> dict[str, Any]:
    """Evaluation checks of the chosen loop (the truth is used here only, never for a decision)."""
    true_figs = loop_figures(mechanics_from(plant.to_dicts()[0]), drive, chosen.Kp, chosen.Ti, chosen.T_f, chosen.notch)
    settled = bool(choice.cost < sc.unstable_cost)
    stable_true = bool(true_figs["stable"])
    return {"settled_on_plant": settled, "stable_true_linear": stable_true,
            "true_phase_margin": float(true_figs["phase_margin"]), "tuned_not_worse": bool(choice.cost <= choice.cost_proposal),
            "stable": settled and stable_true}


# --------------------------------------------------------------------------- stages


def _excite(plant: Any, drive: Any, limits: ExcitationLimits, cfg: CommissioningConfig) -> tuple[ExcitationResult, Any, dict[str, Any]]:
    """Stage 1: the test signal on the plant (the runner is the plant interface) and its record
    without truth; the truth separately, for the report."""
    ex = adapt_test_signal(sim_test_runner(plant, drive, seed=cfg.seed), drive, limits, cfg.rules, timeout=cfg.timeout)
    record = sim.responses_to_records(ex.response, plant.reshape(1), drive, ex.signal, names=["commissioning"])[0]
    record.meta.pop("truth", None)  # the chain sees what a drive delivers, nothing more
    truth = plant.reshape(1).truth(drive, float(ex.signal.M_star))[0]
    return ex, record, {k: truth[k] for k in _TRUTH_SHOWN}


def _identify(identifier: Any, record: Any) -> IdentificationOutcome:
    """Stage 2: what the maps say; an error the identifier raises becomes a failure (rule V1)."""
    try:
        return identifier.identify(record)
    except (ValueError, RuntimeError) as err:
        return IdentificationFailed(one_line(err))


def _model_params(result: Any) -> dict[str, float | None]:
    """The seven model parameters of an identification result (``V_J``, ``f_e`` None for ``stiff``:
    a one-mass model, validation uses its documented stand-in)."""
    out: dict[str, float | None] = {k: getattr(result.parameters, k) for k in sim.PARAM_NAMES}
    if result.structure == "stiff":
        out["V_J"], out["f_e"] = None, None
    return out


def _validate(result: IdentificationOutcome, drive: Any, record: Any,
              cfg: CommissioningConfig) -> tuple[ValidationResult | None, tuple[CommissioningWarning, ...]]:
    """Stage 3: does the identified model reproduce the record? (None: no result, or the
    re-simulation could not run, with a warning saying why)."""
    if not result.ok:
        return None, ()
    try:
        return validate_model(_model_params(result), drive, record, mode=cfg.validation_mode, seed=cfg.seed,
                              osc_metric=cfg.osc_metric), ()
    except ValueError as err:
        return None, (CommissioningWarning("validation_not_run", f"validation failed: {one_line(err)}"),)


def _propose(result: Any, fallback: bool, drive: Any, spec: ControllerSpec) -> tuple[ControllerProposal, dict[str, Any]]:
    """Stage 5: the proposal from the identified structure and parameters, or after a refusal the
    cautious fallback F1 on ``J_sigma`` alone; with the parameters of the model it assumes."""
    if fallback:
        J_sigma = float(result.parameters.J_sigma)
        return propose_cautious(J_sigma, drive, spec), {"J_sigma": J_sigma}
    params = _model_params(result)
    return propose_controller(result.structure, params, drive, spec), params


def _pretune(proposal: ControllerProposal, params: dict[str, Any], drive: Any, sc: TuningScenario,
             cfg: CommissioningConfig, writer: Any, tag: str) -> tuple[TuningResult, list[tuple[float, float, float]]]:
    """Stage 6a: Nelder-Mead on the identified linear model; the candidates for the plant: the
    proposal, the pre-tuned gains and points back towards the proposal (log-linear)."""
    tuning = tune_controller(proposal, LinearRunner(params, drive), drive, scenario=sc, max_evaluations=cfg.tune_evaluations)
    cands = [(proposal.Kp, proposal.Ti, proposal.T_f)]
    tc = tuning.controller
    if tc is not proposal:
        for frac in (1.0, 2 / 3, 1 / 3):
            cands.append(tuple(float(math.exp((1 - frac) * math.log(a) + frac * math.log(b)))
                               for a, b in ((proposal.Kp, tc.Kp), (proposal.Ti, tc.Ti), (proposal.T_f, tc.T_f))))
    if writer is not None:
        for i, h in enumerate(tuning.history):
            writer.add_scalar(f"{tag}/pretune/cost", h["cost"], i)
            writer.add_scalar(f"{tag}/pretune/Kp", h["Kp"], i)
            writer.add_scalar(f"{tag}/pretune/Ti_ms", h["Ti"] * 1e3, i)
    return tuning, cands


@dataclass(frozen=True)
class _PlantChoice:
    """Stage 6b's outcome: the proposal's and the chosen gains' costs and speeds ``2 x N`` on the
    plant; ``kept``: the proposal won; ``search``: the Nelder-Mead on the plant (or None)."""

    cost_proposal: float
    speed_proposal: torch.Tensor
    cost: float
    speed: torch.Tensor
    gains: tuple[float, float, float]
    kept: bool
    search: TuningResult | None


def _choose_on_plant(runner: SimRunner, proposal: ControllerProposal, cands: list[tuple[float, float, float]],
                     drive: Any, sc: TuningScenario, evaluations: int, span: float) -> _PlantChoice:
    """Stage 6b: the candidates side by side on the plant, the lowest cost wins (the proposal on a
    tie); then an optional Nelder-Mead on the plant from the winner (``evaluations`` > 0)."""
    K, T, F = (torch.tensor([c[j] for c in cands], dtype=torch.float64) for j in range(3))
    costs, _, speeds = evaluate_gains(runner, proposal, drive, sc, K, T, F)
    costs = costs.tolist()
    best = int(np.argmin(costs))
    if costs[best] >= costs[0]:
        best = 0
    cost, speed, gains = costs[best], speeds[best], cands[best]
    search = None
    if evaluations > 0:
        start = replace(proposal, Kp=gains[0], Ti=gains[1], T_f=gains[2])
        search = tune_controller(start, runner, drive, scenario=sc, max_evaluations=evaluations, span=span)
        if search.cost_tuned < cost:
            gains = (search.controller.Kp, search.controller.Ti, search.controller.T_f)
            _, _, sp = evaluate_gains(runner, proposal, drive, sc, *(torch.tensor([g]) for g in gains))
            cost, speed = search.cost_tuned, sp[0]
    return _PlantChoice(float(costs[0]), speeds[0], float(cost), speed, gains,
                        kept=best == 0 and gains == cands[0], search=search)


def _final_tuning(tuning: TuningResult, proposal: ControllerProposal, choice: _PlantChoice, drive: Any) -> TuningResult:
    """The tuning result with the controller chosen on the plant."""
    if choice.kept:
        return replace(tuning, controller=proposal, warnings=[
            *tuning.warnings, "on the plant no tuned gain set beat the proposal: the proposal is kept"])
    g = choice.gains
    final = proposal.with_gains(drive, *g, rule=(
        f"T2 final choice on the plant: Kp {g[0]:.4g}, Ti {g[1]:.4g} s, T_f {g[2]:.3g} s; "
        f"plant cost {choice.cost_proposal:.4g} -> {choice.cost:.4g}"))
    return replace(tuning, controller=final)


# --------------------------------------------------------------------------- the chain


def _check_inputs(plant_params: Any, limits: Any, identifier: Any, config: Any) -> None:
    if not isinstance(plant_params, sim.TwoMassParams):
        raise TypeError(f"plant_params: expected sim.TwoMassParams, received {type(plant_params).__name__}")
    if plant_params.J_sigma.numel() != 1:
        raise ValueError(f"plant_params: expected one system, received batch {tuple(plant_params.batch_shape)}")
    if not isinstance(limits, ExcitationLimits):
        raise TypeError(f"limits: expected ExcitationLimits, received {type(limits).__name__}")
    if not callable(getattr(identifier, "identify", None)):
        raise TypeError(f"identifier: expected an object with identify(record), received {type(identifier).__name__}")
    if not isinstance(config, CommissioningConfig):
        raise TypeError(f"config: expected CommissioningConfig or None, received {type(config).__name__}")


@dataclass
class _Run:
    """One run of the chain: the plant, its settings, the outputs (progress, TensorBoard) and the
    stage timings [s]."""

    plant: Any
    drive: Any
    cfg: CommissioningConfig
    say: Callable[[str], None]
    writer: Any
    name: str
    tag: str
    timings: dict[str, float] = field(default_factory=dict)
    _start: float = field(default_factory=time.perf_counter)
    _last: float = 0.0

    def lap(self, stage: str) -> None:
        """Time since the previous lap (or the start) as ``timings[stage]``."""
        now = time.perf_counter()
        self.timings[stage] = now - (self._last or self._start)
        self._last = now

    def total(self) -> dict[str, float]:
        """The timings with ``total`` (since the start)."""
        self.timings["total"] = time.perf_counter() - self._start
        return self.timings


def commission(
    plant_params: Any,
    drive: Any,
    limits: ExcitationLimits,
    *,
    identifier: Any,
    config: CommissioningConfig | None = None,
    writer: Any = None,
    progress: Callable[[str], None] | None = None,
    name: str = "plant",
    tag: str | None = None,
) -> CommissioningReport:
    """Run the whole chain on one simulated plant.

    Args:
        plant_params: the plant (one-system ``sim.TwoMassParams``; stands where a real drive would).
        drive: ``sim.DriveConfig``.
        limits: user limits for the test runs.
        identifier: object with ``identify(record)`` returning an identification result
            (``training.Identifier``); an error it raises (ValueError, RuntimeError) is rule V1.
        config: the chain's settings (:class:`CommissioningConfig`; default: its defaults).
        writer: optional TensorBoard ``SummaryWriter``: scalars of the search under ``tag``.
        progress: optional callback with one-line stage messages.
        name, tag: report name and TensorBoard tag prefix (default: the name).

    Returns :class:`CommissioningReport`. A refused identification is a normal outcome (the
    report says why); errors in the inputs raise ValueError/TypeError.
    """
    cfg = CommissioningConfig() if config is None else config
    _check_inputs(plant_params, limits, identifier, cfg)
    run = _Run(plant_params.reshape(()), drive, cfg, progress or (lambda msg: None), writer, name, tag or name)
    run.say(f"{name}: adapting the test signal")
    ex, record, truth = _excite(run.plant, drive, limits, cfg)
    run.lap("excitation")
    run.say(f"{name}: identifying")
    result = _identify(identifier, record)
    validation, warnings = _validate(result, drive, record, cfg)
    if not ex.informative:
        warnings = (CommissioningWarning("test_not_informative", f"test response not informative: {ex.reason}"), *warnings)
    run.lap("identification_validation")
    perm = may_propose_controller(result, validation, warnings=warnings, max_validation_error=cfg.max_validation_error,
                                  max_map_distance_ratio=cfg.max_map_distance_ratio)
    report = CommissioningReport(
        drive=drive, limits=limits, excitation=ex, record=record, identification=result, validation=validation,
        permission=perm, warnings=warnings, max_map_distance_ratio=cfg.max_map_distance_ratio, truth=truth,
        outside_training=outside_training(result, cfg.max_map_distance_ratio) if result.ok else None,
        checks=limit_checks(ex, limits, drive), timings=run.timings, name=name)
    if not perm.allowed:
        run.say(f"{name}: refused ({perm.reason})")
        J_sigma = result.parameters.J_sigma if result.ok else None
        if not (cfg.fallback_evaluations > 0 and isinstance(J_sigma, (int, float)) and math.isfinite(J_sigma) and J_sigma > 0):
            run.total()
            return report
        run.say(f"{name}: fallback F1, a cautious PI tuned on the plant ({cfg.fallback_evaluations} evaluations)")
    return _control(run, result, report)


def _control(run: _Run, result: Any, report: CommissioningReport) -> CommissioningReport:
    """Stages 5-7 after the permission: propose (or the fallback F1 after a refusal), pre-tune on
    the identified model, choose on the plant, check; ``report`` completed."""
    cfg, drive, name = run.cfg, run.drive, run.name
    fallback = report.refused
    proposal, params = _propose(result, fallback, drive, cfg.spec)
    sc = make_scenario(proposal, drive, max_samples=cfg.max_samples)
    run.lap("proposal")
    tuning, cands = None, [(proposal.Kp, proposal.Ti, proposal.T_f)]
    if cfg.tune and not fallback:
        run.say(f"{name}: tuning on the identified model ({cfg.tune_evaluations} evaluations)")
        tuning, cands = _pretune(proposal, params, drive, sc, cfg, run.writer, run.tag)
    run.lap("pretune")
    run.say(f"{name}: checking {len(cands)} gain set(s) on the plant")
    on_plant = (cfg.fallback_evaluations if fallback else cfg.plant_evaluations) if cfg.tune else 0
    if on_plant > 0:
        run.say(f"{name}: searching on the plant ({on_plant} evaluations)")
    choice = _choose_on_plant(SimRunner(run.plant, drive), proposal, cands, drive, sc, on_plant,
                              span=5.0 if fallback else 20.0)
    tuning = choice.search if fallback else tuning
    run.lap("plant_check")
    if run.writer is not None:
        run.writer.add_scalar(f"{run.tag}/plant/cost_proposal", choice.cost_proposal, 0)
        run.writer.add_scalar(f"{run.tag}/plant/cost_tuned", choice.cost, 0)
    if tuning is not None:
        tuning = _final_tuning(tuning, proposal, choice, drive)
    chosen = tuning.controller if tuning is not None else proposal
    return replace(
        report, proposal=proposal, tuning=tuning, fallback=fallback, timings=run.total(),
        checks={**report.checks, **_true_loop_checks(run.plant, drive, chosen, choice, sc)},
        plant_costs={"proposal": choice.cost_proposal, "tuned": choice.cost},
        responses={"scenario": sc, "before": choice.speed_proposal.numpy(), "after": choice.speed.numpy()},
        figures={"before": response_figures(choice.speed_proposal, sc), "after": response_figures(choice.speed, sc)},
    )
