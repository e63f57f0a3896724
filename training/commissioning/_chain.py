"""The self-commissioning chain (SPEC 8, the paper's section 2) through a SPEC 8.1 drive, one
function per stage.

    adapt the test signal (E1-E9, drive.run_test) -> identify (shipped maps) -> validate
    (re-simulate) -> may a controller be proposed? (V1-V6) -> propose (R1-R8, margins guaranteed)
    or the fallback F1 -> tune on the identified model (Nelder-Mead, margins kept) -> plan the
    closed-loop experiment inside the limits -> run the candidates on the drive
    (drive.run_closed_loop) -> deliver the best that is not worse than the proposal -> report

The chain reaches the plant only through the drive (``config``, ``run_test``,
``run_closed_loop``); everything it decides comes from the records these return. Every call goes
through :class:`training.commissioning._guard.CheckedDrive`: bounded in time, each record checked
as it comes and held against the user's limits; the first passed limit ends the experiments (the
report's ``breach``, nothing delivered). A drive that
offers ``truth()`` (a simulator) gets truth-based figures in the report, apart, marked
"simulation only"; they are never used for a decision.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

import sim
from training.errors import CommissioningError, LimitPassed, one_line

from ._bands import f1_bands, hidden_bands, widen
from ._excitation import ExcitationResult, ExcitationRules, adapt_test_signal, guarded_limits, measure_response, stop_headroom
from ._guard import CONFIG_KEYS, CheckedDrive, passed_limits, record_peaks
from ._loop import linear_plant, margins
from ._permission import (CommissioningWarning, IdentificationFailed, IdentificationOutcome, may_propose_controller,
                          outside_training)
from ._report import CommissioningReport, PlantRun
from ._rules import ControllerProposal, ControllerSpec, propose_cautious, propose_controller
from ._tuning import (BOUNDED_VERDICTS, Gains, TuningScenario, closed_loop_cost, loop_verdict, model_response, plan_scenario,
                      response_figures, tune_controller)
from ._validation import OSC_METRICS, VALIDATION_MODES, ValidationResult, validate_model

__all__ = ["CommissioningConfig", "commission", "limit_checks", "drive_config", "check_resolution", "MIN_LIMIT_QUANTA"]

#: Identification warning codes that make the elastic parameters uncertain (rule R7c widens the spread).
UNCERTAIN_CODES: frozenset[str] = frozenset({"unlike_training_data", "oscillation_below_quantum", "refine_partial_fit",
                                             "implausible_output", "drive_outside_training", "outside_envelope",
                                             "class_undecided", "backlash_from_angle"})
#: Identification warning codes that say the oscillation is not determined at all (rule R7b as for ``stiff``).
UNDETERMINED_CODES: frozenset[str] = frozenset({"refine_partial_fit", "oscillation_below_quantum"})


@dataclass(frozen=True)
class CommissioningConfig:
    """The chain's settings, with their defaults.

    Attributes:
        spec: controller rule constants and the guaranteed margins (:class:`ControllerSpec`).
        rules: excitation rule constants (:class:`ExcitationRules`).
        tune: run the fine-tuning on the identified model (else: the proposal only, still run on
            the drive).
        validation_mode, osc_metric: :func:`validate_model`'s re-simulation and oscillation check.
        max_validation_error: refusal rule V3's bound on the speed error.
        max_map_distance_ratio: rule V4's bound on a used map's distance ratio (None: the
            identifier's own ``outside_training`` flag).
        tune_evaluations: Nelder-Mead evaluations on the identified model.
        fallback: after a refusal (or when no design keeps the margins), deliver the cautious
            fallback F1 (:func:`propose_cautious`); False: end with the refusal.
        limit_use: the share of the speed and travel limits a closed-loop experiment may use by the
            model's prediction (``fallback_limit_use`` for F1, planned on the one-mass model).
        max_samples: longest closed-loop experiment [samples] (six segments).
        osc_visible_ratio: F1's eigenfrequency band: an oscillation below resolution in the test
            means ``r_osc < osc_visible_ratio`` (SPEC 1), a lower bound on ``f_e`` per ``V_J``.
        uncertain_spread: rule R7c: the guarantee's spread of ``f_e`` and ``V_J`` when the
            identification's own quality figures say the elastic values are uncertain (a warning
            code of :data:`UNCERTAIN_CODES`, or a map beyond its training); the damping ``d`` is
            then halved (a lighter damped resonance).
        hidden_resonances: rule R7b: the guarantee of a ``stiff`` answer, or of one whose
            oscillation is not determined (:data:`UNDETERMINED_CODES`), also covers the resonances
            the test could not show (:func:`training.commissioning._bands.hidden_bands`).
        drive_timeout: the longest a drive call may take [s] (a test run of six sections of up to
            10 s each on a real drive, with its upload, fits the default); past it the drive is a
            fault (:func:`training.commissioning._guard.call_drive`). None: no bound, the drive is
            called in the calling thread.
    """

    spec: ControllerSpec = field(default_factory=ControllerSpec)
    rules: ExcitationRules = field(default_factory=ExcitationRules)
    tune: bool = True
    validation_mode: str = "replay"
    osc_metric: str = "spectrum"
    max_validation_error: float = 0.1
    max_map_distance_ratio: float | None = 3.0
    tune_evaluations: int = 30
    fallback: bool = True
    limit_use: float = 0.5
    fallback_limit_use: float = 0.3
    max_samples: int = 6000
    osc_visible_ratio: float = 20.0
    uncertain_spread: float = 0.5
    hidden_resonances: bool = True
    drive_timeout: float | None = 600.0

    def __post_init__(self) -> None:
        t = self.drive_timeout
        if t is not None and (isinstance(t, bool) or not isinstance(t, (int, float)) or not math.isfinite(t) or t <= 0):
            raise ValueError(f"drive_timeout: expected a finite number of seconds > 0 or None, received {t!r}")
        if self.tune_evaluations < 1 or self.max_samples < 600:
            raise ValueError(f"tune_evaluations >= 1 and max_samples >= 600 expected, received "
                             f"{self.tune_evaluations}, {self.max_samples}")
        if self.validation_mode not in VALIDATION_MODES:
            raise ValueError(f"validation_mode: expected one of {VALIDATION_MODES}, received {self.validation_mode!r}")
        if self.osc_metric not in OSC_METRICS:
            raise ValueError(f"osc_metric: expected one of {OSC_METRICS}, received {self.osc_metric!r}")
        bound = self.max_map_distance_ratio
        if not self.max_validation_error > 0 or (bound is not None and not bound > 0):
            raise ValueError(f"max_validation_error > 0 and max_map_distance_ratio > 0 or None expected, "
                             f"received {self.max_validation_error}, {bound}")
        if not (0 < self.limit_use <= 1 and 0 < self.fallback_limit_use <= 1):
            raise ValueError(f"limit_use, fallback_limit_use: expected in (0, 1], received {self.limit_use}, {self.fallback_limit_use}")


# --------------------------------------------------------------------------- the drive


def drive_config(drive: Any) -> sim.DriveConfig:
    """The drive's ``config`` (SPEC 8.1: ``T_s``, ``K_M``, ``T_Ei``, ``encoder_counts``, ``M_N``,
    ``M_max``, from attributes or a dict) as a :class:`sim.DriveConfig` for the chain's models;
    raises :class:`CommissioningError` naming what is missing or wrong."""
    for name in ("config", "run_test", "run_closed_loop"):
        if not hasattr(drive, name):
            raise CommissioningError(f"drive: expected a SPEC 8.1 drive with config, run_test and run_closed_loop; "
                                     f"{type(drive).__name__} has no {name!r}")
    cfg = drive.config
    get = cfg.get if isinstance(cfg, dict) else (lambda k: getattr(cfg, k, None))
    missing = [k for k in CONFIG_KEYS if get(k) is None]
    if missing:
        raise CommissioningError(f"drive.config: missing {missing}; expected {list(CONFIG_KEYS)}")
    try:
        return sim.DriveConfig(**{k: get(k) for k in CONFIG_KEYS}, current_noise_std=0.0)
    except (TypeError, ValueError) as err:
        raise CommissioningError(f"drive.config: {one_line(err)}") from None


#: The smallest speed limit, in speed quanta of the drive's encoder, a test can be resolved within.
MIN_LIMIT_QUANTA: float = 10.0


def check_resolution(limits: sim.DriveLimits, config: sim.DriveConfig) -> None:
    """Refuse (:class:`CommissioningError`) a speed limit below :data:`MIN_LIMIT_QUANTA` speed quanta
    ``q_w`` of the drive's encoder: no run within it could show a response."""
    q_w = config.q_w
    if not limits.w_max >= MIN_LIMIT_QUANTA * q_w:
        raise CommissioningError(f"limits: the speed limit {limits.w_max:g} rad/s is {limits.w_max / q_w:.3g} speed quanta of the "
                                 f"drive's encoder (q_w {q_w:.3g} rad/s); at least {MIN_LIMIT_QUANTA:g} are needed to resolve a test")


def limit_checks(experiments: list[tuple[str, Any]], limits: sim.DriveLimits, config: Any) -> dict[str, Any]:
    """Were the limits kept in every experiment? From each measured record
    (:func:`training.commissioning._guard.record_peaks`): peak ``|speed|``, travel (largest ``|phi|``
    of the integrated measured speed), peak ``|torque_ref|``, peak measured torque, the limits it
    passed (``passed``: the names of :func:`training.commissioning._guard.passed_limits`) and the
    drive's ``aborted`` flag. A run is ``within_limits`` when it passed none of the user's limits: a
    drive that stopped a run at the tighter limit the chain handed it, and stayed inside the user's,
    has kept them (the run is listed as stopped)."""
    runs = []
    cap = limits.torque_cap(config)
    for kind, rec in experiments:
        peaks = record_peaks(rec, float(config.T_s), float(config.K_M))
        stopped = bool(rec.meta.get("aborted", False))
        passed = [p.limit for p in passed_limits(peaks, limits, cap)]
        runs.append({"kind": kind, **peaks, "aborted": stopped, "passed": passed, "within_limits": not passed})
    return {"runs": runs, "within_limits": all(r["within_limits"] for r in runs),
            "peak_speed": max(r["peak_speed"] for r in runs), "peak_travel": max(r["travel"] for r in runs)}


# --------------------------------------------------------------------------- stages


def _identify(identifier: Any, record: Any) -> IdentificationOutcome:
    """What the maps say; an error the identifier raises becomes a failure (rule V1)."""
    try:
        return identifier.identify(record)
    except (ValueError, RuntimeError) as err:
        return IdentificationFailed(one_line(err))


def _model_params(result: Any) -> dict[str, float | None]:
    """The seven model parameters of an identification result (``V_J``, ``f_e`` None for ``stiff``)."""
    out: dict[str, float | None] = {k: getattr(result.parameters, k) for k in sim.PARAM_NAMES}
    if result.structure == "stiff":
        out["V_J"], out["f_e"] = None, None
    return out


def _validate(result: IdentificationOutcome, config: sim.DriveConfig, record: Any,
              cfg: CommissioningConfig) -> tuple[ValidationResult | None, tuple[CommissioningWarning, ...]]:
    """Does the identified model reproduce the record? (None: no result, or the re-simulation
    could not run, with a warning saying why)."""
    if not result.ok:
        return None, ()
    try:
        return validate_model(_model_params(result), config, record, mode=cfg.validation_mode,
                              osc_metric=cfg.osc_metric), ()
    except ValueError as err:
        return None, (CommissioningWarning("validation_not_run", f"validation failed: {one_line(err)}"),)


def _accepted(ex: ExcitationResult) -> dict[str, Any]:
    """The log entry of the test record the identification used (the last one the drive did not stop)."""
    kept = [e for e in ex.log if not e["aborted"]]
    return kept[-1] if kept else ex.log[-1]


def _test_J(ex: ExcitationResult) -> float:
    """The one-mass inertia the accepted test run's mean acceleration gives, ``M* / accel`` [kg m^2]
    (friction makes it larger, never smaller; inf when the run had no acceleration to measure)."""
    e = _accepted(ex)
    return e["M_star"] / e["accel"] if e.get("accel", 0.0) > 0 else math.inf


def _run_candidates(run: _Run, proposal: ControllerProposal, gains: list[Gains], sc: TuningScenario,
                    kind: str) -> list[PlantRun]:
    """Each gain set on the drive over ``sc`` (one experiment each), scored from its record and judged
    (:func:`loop_verdict`) against what the identified model predicts for the same gains."""
    out = []
    mech = proposal.mechanics
    cap = run.limits.torque_cap(run.config)
    model_costs = closed_loop_cost(model_response(mech, run.config, gains, proposal.notch, sc), sc, mech)[0]
    for i, g in enumerate(gains):
        law = proposal.law(run.config, Kp=g[0], Ti=g[1], T_f=g[2])
        rec = run.drive.run_closed_loop(law, sc.scenario(), run.loop_limits, f"{kind} {i}")
        stopped = bool(rec.meta.get("aborted", False))
        w = np.asarray(rec.speed, dtype=np.float64)
        cost, terms = closed_loop_cost(w, sc, mech, stopped)
        model_cost = float(model_costs[i])
        verdict, why = loop_verdict(w, rec.torque_ref, sc, cap, float(cost), model_cost, stopped)
        out.append(PlantRun(gains=g, cost=float(cost), motor=float(terms["motor"]), load=float(terms["load"]),
                            aborted=stopped, figures=response_figures(w, sc, mech), speed=w, verdict=verdict,
                            verdict_text=why, model_cost=model_cost))
        if stopped:
            run.warn("run_stopped", f"the drive stopped the closed-loop run {kind} {i} at a limit")
        elif verdict not in BOUNDED_VERDICTS:
            run.warn("loop_rejected", f"{kind} {i} not delivered [{verdict}]: {why}")
    return out


def _choose(runs: list[PlantRun]) -> int | None:
    """The delivered candidate: the lowest cost among the usable runs (:attr:`PlantRun.usable`:
    settled, or near the reference and only slow) that are not worse than the proposal's (index 0)
    on the motor nor on the (estimated) load; with an unusable proposal the lowest usable one; None
    when none is usable."""
    settled = [i for i, r in enumerate(runs) if r.usable]
    if not settled:
        return None
    if runs[0].usable:
        settled = [i for i in settled if runs[i].motor <= runs[0].motor and runs[i].load <= runs[0].load]
    return min(settled, key=lambda i: (runs[i].cost, i))


@dataclass
class _Run:
    """One run of the chain: the drive, its settings, the outputs and the stage timings [s]."""

    drive: CheckedDrive
    config: sim.DriveConfig
    limits: sim.DriveLimits
    cfg: CommissioningConfig
    say: Callable[[str], None]
    writer: Any
    name: str
    tag: str
    warnings: list[CommissioningWarning] = field(default_factory=list)
    timings: dict[str, float] = field(default_factory=dict)
    loop_limits: sim.DriveLimits | None = None
    """The limits handed to the drive for the closed-loop runs (E9: less the headroom after a stop)."""
    test_log: list[dict[str, Any]] = field(default_factory=list)
    """The test runs' log entries as they are decided (kept when a run passes a limit)."""
    known: dict[str, Any] = field(default_factory=dict)
    """The report's fields as the stages produce them (what a report of a chain stopped at a passed
    limit can show)."""
    _start: float = field(default_factory=time.perf_counter)
    _last: float = 0.0

    def lap(self, stage: str) -> None:
        now = time.perf_counter()
        self.timings[stage] = now - (self._last or self._start)
        self._last = now

    def warn(self, code: str, text: str) -> None:
        self.warnings.append(CommissioningWarning(code, text))


def _model_based(run: _Run, result: Any, ex: ExcitationResult) -> tuple[ControllerProposal, Any, list[PlantRun], int | None, TuningScenario, dict[str, float]] | None:
    """Propose, tune on the identified model, run the candidates on the drive, choose; None when no
    design keeps the margins (R7)."""
    cfg, config = run.cfg, run.config
    params = _model_params(result)
    spec, hidden, notch_at, why = cfg.spec, None, None, _uncertain(result)
    if cfg.hidden_resonances and (params["f_e"] is None or UNDETERMINED_CODES.intersection(why)):
        hidden, notch_at = hidden_bands(_accepted(ex), float(params["J_sigma"]), config, spec.class_V_J,
                                        f_lo=spec.class_f_e[0], min_osc_quanta=cfg.rules.min_osc_quanta)
    if why and params["f_e"] is not None:
        spec = replace(spec, spread=max(spec.spread, cfg.uncertain_spread))
        params["d"] = 0.5 * float(params["d"] or 0.0)
    proposal = propose_controller(result.structure, params, config, spec, hidden=hidden, notch_at=notch_at)
    if why and params["f_e"] is not None:
        proposal = replace(proposal, rules=(f"R7c identification uncertain ({', '.join(why)}): the guarantee's spread of "
                                            f"f_e and V_J is +-{spec.spread:.0%}, d halved to {params['d']:.3g}",) + proposal.rules)
    if not proposal.meets(cfg.spec):
        run.warn("margins_not_reached", f"R7: {proposal.warnings[-1]}")
        return None
    run.lap("proposal")
    tuning = None
    gains: list[Gains] = [(proposal.Kp, proposal.Ti, proposal.T_f)]
    if cfg.tune:
        sc0, _ = plan_scenario(proposal, [], config, run.limits, limit_use=cfg.limit_use, max_samples=cfg.max_samples)
        run.say(f"{run.name}: tuning on the identified model ({cfg.tune_evaluations} evaluations)")
        tuning = tune_controller(proposal, config, sc0, spec, max_evaluations=cfg.tune_evaluations)
        tc = tuning.controller
        if tc is not proposal:
            gains.append((tc.Kp, tc.Ti, tc.T_f))
            mid = tuple(math.sqrt(a * b) for a, b in zip(gains[0], gains[1]))
            if proposal.models.margins(*mid, proposal.notch).meets(cfg.spec.min_phase_margin, cfg.spec.min_gain_margin_dB):
                gains.append(mid)
        if run.writer is not None:
            for i, h in enumerate(tuning.history):
                run.writer.add_scalar(f"{run.tag}/tune/cost", h["cost"], i)
                run.writer.add_scalar(f"{run.tag}/tune/Kp", h["Kp"], i)
    run.lap("tuning")
    sc, prediction = plan_scenario(proposal, gains[1:], config, run.limits, limit_use=cfg.limit_use, max_samples=cfg.max_samples)
    if prediction["speed_quanta"] < 20:
        run.warn("scenario_small", f"the scenario's speed step is {prediction['speed_quanta']:.3g} speed quanta")
    run.say(f"{run.name}: running {len(gains)} gain set(s) on the drive")
    run.known.update(proposal=proposal, tuning=tuning, scenario=sc, prediction=prediction)
    runs = _run_candidates(run, proposal, gains, sc, "closed loop")
    run.lap("drive_runs")
    return proposal, tuning, runs, _choose(runs), sc, prediction


def _positive(x: Any) -> bool:
    return isinstance(x, (int, float)) and math.isfinite(x) and x > 0


def _uncertain(result: Any) -> list[str]:
    """Why the identified elastic values are uncertain (warning codes of :data:`UNCERTAIN_CODES`,
    ``outside_training``); empty when nothing says so."""
    why = sorted({w.code for w in result.warnings if w.code in UNCERTAIN_CODES})
    if result.quality.outside_training and "outside_training" not in why:
        why.append("outside_training")
    return why


def _fallback(run: _Run, result: Any, ex: ExcitationResult) -> tuple[ControllerProposal, list[PlantRun], int | None, TuningScenario, dict[str, float]]:
    """F1: the cautious PI on ``J_sigma`` with the highest crossover that keeps the margins on the
    worst cases of the class the test run allows; one run on the drive, delivered when it stays
    bounded (not stopped, not diverging: a slow loop that does not settle within the experiment is
    slow, not unstable; its margins hold on every model of its set)."""
    cfg, config = run.cfg, run.config
    J = min(float(result.parameters.J_sigma), _test_J(ex))
    bands = f1_bands(_accepted(ex), J, config, cfg.spec.class_V_J, cfg.spec.class_f_e, min_osc_quanta=cfg.rules.min_osc_quanta,
                     osc_visible_ratio=cfg.osc_visible_ratio)
    p = _model_params(result)
    if _positive(p["f_e"]) and _positive(p["V_J"]):  # the identified resonance too (+-50 %), trusted or not
        widen(bands, p["V_J"], p["f_e"] / 1.5, p["f_e"] * 1.5)
    prop = propose_cautious(J, config, cfg.spec, bands=bands)
    if J < float(result.parameters.J_sigma):
        prop = replace(prop, rules=prop.rules + (f"F1 J_sigma from the test run's acceleration (M* / accel = {J:.4g} kg m^2), "
                                                 f"below the identified {float(result.parameters.J_sigma):.4g} kg m^2",))
    sc, prediction = plan_scenario(prop, [], config, run.limits, limit_use=cfg.fallback_limit_use, max_samples=cfg.max_samples)
    run.known.update(fallback=prop, scenario=sc, prediction=prediction)
    runs = _run_candidates(run, prop, [(prop.Kp, prop.Ti, prop.T_f)], sc, "fallback F1")
    run.lap("fallback")
    return prop, runs, (0 if runs[0].bounded else None), sc, prediction


def _truth_checks(drive: Any, delivered: ControllerProposal | None, config: sim.DriveConfig, M_star: float) -> dict[str, Any] | None:
    """Simulation only: the true parameters and class, and the delivered loop's margins on the true
    linear model (with the drive's own ``current_loop_damping`` / ``extra_delay`` where its truth
    names them). None for a drive without ``truth()``."""
    if not callable(getattr(drive, "truth", None)):
        return None
    t = dict(drive.truth())
    p = sim.TwoMassParams.from_dicts({k: t[k] for k in sim.PARAM_NAMES})
    row = p.truth(config, M_star)[0]
    out: dict[str, Any] = {"parameters": {k: row[k] for k in (*sim.PARAM_NAMES, "C_F", "s_N", "r_osc")},
                           "structure": row["structure"]}
    if delivered is not None:
        plant = linear_plant({k: t[k] for k in sim.PARAM_NAMES}, config, current_loop_damping=t.get("current_loop_damping"),
                             extra_delay=int(t.get("extra_delay", 0)))
        m = margins(plant, delivered.Kp, delivered.Ti, delivered.T_f, delivered.notch)
        out.update(stable=m.stable, phase_margin=m.phase_margin, gain_margin_dB=m.gain_margin_dB, w_c=m.w_c)
    return out


def commission(
    drive: Any,
    limits: sim.DriveLimits,
    *,
    identifier: Any,
    config: CommissioningConfig | None = None,
    writer: Any = None,
    progress: Callable[[str], None] | None = None,
    name: str = "plant",
    tag: str | None = None,
) -> CommissioningReport:
    """Run the whole chain on one drive (SPEC 8, 8.1).

    Args:
        drive: a SPEC 8.1 drive: ``config`` (``T_s``, ``K_M``, ``T_Ei``, ``encoder_counts``,
            ``M_N``, ``M_max``), ``run_test(M_star, w_max, limits) -> sim.Record``,
            ``run_closed_loop(law, scenario, limits) -> sim.Record`` (e.g. :class:`sim.SimulatedDrive`).
        limits: the user's limits (:class:`sim.DriveLimits`), handed to every experiment.
        identifier: object with ``identify(record)`` returning an identification result
            (``training.Identifier``); an error it raises (ValueError, RuntimeError) is rule V1.
        config: the chain's settings (:class:`CommissioningConfig`).
        writer: optional TensorBoard ``SummaryWriter``; progress: optional one-line callback.
        name, tag: report name and TensorBoard tag prefix (default: the name).

    Returns :class:`CommissioningReport`. A refusal is a normal outcome (the report says why); so
    is a record that shows one of the user's limits passed: the experiments end there, nothing is
    delivered and the report's ``breach`` says which limit, by how much, in which experiment
    (SPEC 8.2). The drive is handed ``limits`` with ``M_max`` the torque cap
    (:meth:`sim.DriveLimits.for_drive`), or less where a run needs headroom. A drive that breaks the
    interface (a call that raises or passes ``config.drive_timeout``, a malformed record, one that
    contradicts the drive's config, a closed-loop record cut short) raises
    :class:`training.errors.CommissioningError`.
    """
    cfg = CommissioningConfig() if config is None else config
    if not isinstance(limits, sim.DriveLimits):
        raise TypeError(f"limits: expected sim.DriveLimits, received {type(limits).__name__}")
    if not callable(getattr(identifier, "identify", None)):
        raise TypeError(f"identifier: expected an object with identify(record), received {type(identifier).__name__}")
    if not isinstance(cfg, CommissioningConfig):
        raise TypeError(f"config: expected CommissioningConfig or None, received {type(cfg).__name__}")
    conf = drive_config(drive)
    limits = limits.for_drive(conf)
    check_resolution(limits, conf)
    run = _Run(CheckedDrive(drive, conf, limits, cfg.drive_timeout), conf, limits, cfg, progress or (lambda msg: None), writer,
               name, tag or name)
    try:
        return _chain(run, drive, identifier)
    except LimitPassed:
        if run.drive.breach is None:  # not one of ours: the drive raised it
            raise
        return _stopped(run, drive)


def _chain(run: _Run, drive: Any, identifier: Any) -> CommissioningReport:
    """The stages on ``run`` (:func:`commission`); each stage's outputs also in ``run.known``."""
    cfg, conf, limits, name = run.cfg, run.config, run.limits, run.name
    run.say(f"{name}: adapting the test signal")
    ex = adapt_test_signal(run.drive, limits, cfg.rules, log=run.test_log)
    run.known["excitation"] = ex
    if any(e["aborted"] for e in ex.log):
        run.warn("run_stopped", "the drive stopped a test run at a limit")
    run.lap("excitation")
    if ex.code == "speed_against_torque":  # E10: nothing to identify; the maps would blame the units
        run.warn("speed_against_torque", ex.reason)
        result: Any = IdentificationFailed(f"not identified: {ex.reason}")
    else:
        run.say(f"{name}: identifying")
        result = _identify(identifier, ex.record)
    validation, vwarn = _validate(result, conf, ex.record, cfg)
    run.warnings.extend(vwarn)
    if not ex.informative:
        run.warn("test_not_informative", f"test response not informative: {ex.reason}")
    run.lap("identification_validation")
    run.known.update(identification=result, validation=validation)
    J_loop = min(_test_J(ex), float(result.parameters.J_sigma) if result.ok and _positive(result.parameters.J_sigma) else math.inf)
    cap = limits.torque_cap(conf)
    run.loop_limits = guarded_limits(limits, stop_headroom(cap / J_loop, conf, cfg.rules) if math.isfinite(J_loop) else
                                     cfg.rules.first_headroom * limits.w_max, conf, cfg.rules)
    perm = may_propose_controller(result, validation, warnings=tuple(run.warnings), max_validation_error=cfg.max_validation_error,
                                  max_map_distance_ratio=cfg.max_map_distance_ratio)
    run.known.update(permission=perm, outside_training=outside_training(result, cfg.max_map_distance_ratio) if result.ok else None)
    outcome = None
    if perm.allowed:
        outcome = _model_based(run, result, ex)
    proposal = tuning = None
    runs: list[PlantRun] = []
    chosen = sc = prediction = None
    fallback: str | None = None
    if outcome is not None:
        proposal, tuning, runs, chosen, sc, prediction = outcome
        run.known["runs"] = runs
        if chosen is None:
            run.warn("loop_not_settled", "no candidate loop settled on the drive")
            fallback = "loop_not_settled"
    else:
        fallback = "refused" if not perm.allowed else "margins_not_reached"
    J = result.parameters.J_sigma if result.ok else None
    f1, f1_runs, delivered, delivered_run = None, [], None, None
    if fallback and cfg.fallback and _positive(J):
        run.say(f"{name}: fallback F1 ({fallback})")
        run.known["fallback_reason"] = fallback
        f1, f1_runs, f1_chosen, sc, prediction = _fallback(run, result, ex)
        if f1_chosen is not None:
            delivered, delivered_run = f1, f1_runs[f1_chosen]
        else:
            run.warn("loop_not_settled", f"the fallback F1 did not settle on the drive either ({f1_runs[0].verdict_text}): "
                                         f"no controller delivered")
    elif chosen is not None:
        delivered_run = runs[chosen]
        if chosen == 0:
            delivered = proposal
        elif chosen == 1:
            delivered = tuning.controller
        else:
            g = runs[chosen].gains
            delivered = proposal.with_gains(conf, *g, rule=(
                f"T2 on the drive: the geometric mean of the proposal's and the tuned gains: Kp {g[0]:.4g}, Ti {g[1]:.4g} s, "
                f"T_f {g[2]:.3g} s"))
    if delivered_run is not None and sc is not None and delivered_run.cost > sc.model_warn_factor * delivered_run.model_cost:
        run.warn("loop_unlike_model", f"the delivered loop costs {delivered_run.cost / delivered_run.model_cost:.3g} x what "
                                      "the identified model predicts for its gains: the margins guaranteed on the model "
                                      "may not hold on this drive (a torque scale or K_M off? a plant unlike the model?)")
    if prediction:
        prediction = {**prediction, "stop_at": run.loop_limits.w_max}
    checks = limit_checks(run.drive.experiments, limits, conf)
    run.timings["total"] = time.perf_counter() - run._start
    return CommissioningReport(
        config=conf, limits=limits, excitation=ex, identification=result, validation=validation, permission=perm,
        warnings=tuple(run.warnings), max_map_distance_ratio=cfg.max_map_distance_ratio,
        outside_training=run.known["outside_training"],
        proposal=proposal, tuning=tuning, fallback=f1, fallback_reason=fallback, runs=runs, fallback_runs=f1_runs,
        delivered=delivered, delivered_run=delivered_run, scenario=sc, prediction=prediction or {}, checks=checks,
        truth=_truth_checks(drive, delivered, conf, float(ex.log[-1]["M_star"])), timings=run.timings, name=name)


def _stopped(run: _Run, drive: Any) -> CommissioningReport:
    """The report of a chain that a record ended at a passed limit (``run.drive.breach``): what the
    stages had produced, the test runs up to the one that passed it (its log entry says so), every
    experiment's limit check; nothing delivered."""
    breach, known, conf = run.drive.breach, run.known, run.config
    tests = [(rec, req) for (kind, rec), req in zip(run.drive.experiments, run.drive.requests) if kind == "test"]
    ex = known.get("excitation")
    if ex is None:  # a test run passed it: the adaptation's log so far, and that run
        rec, req = tests[-1]
        entry = {"iteration": len(run.test_log), "M_star": req["M_star"], "w_max": req["w_max"], "stop_at": req["stop_at"],
                 **measure_response(rec, conf), "decision": "stop", "reason": breach.text()}
        kept = [r for r, _ in tests if not r.meta.get("aborted", False)]
        ex = ExcitationResult(record=kept[-1] if kept else rec, records=[r for r, _ in tests], log=[*run.test_log, entry],
                              informative=False, reason=breach.text(), code="limit_passed")
    prediction = known.get("prediction")
    if prediction and run.loop_limits is not None:
        prediction = {**prediction, "stop_at": run.loop_limits.w_max}
    run.timings["total"] = time.perf_counter() - run._start
    return CommissioningReport(
        config=conf, limits=run.limits, excitation=ex, identification=known.get("identification"),
        validation=known.get("validation"), permission=known.get("permission"), warnings=tuple(run.warnings),
        max_map_distance_ratio=run.cfg.max_map_distance_ratio, outside_training=known.get("outside_training"),
        proposal=known.get("proposal"), tuning=known.get("tuning"), fallback=known.get("fallback"),
        fallback_reason=known.get("fallback_reason"), runs=known.get("runs", []), scenario=known.get("scenario"),
        prediction=prediction or {}, checks=limit_checks(run.drive.experiments, run.limits, conf),
        truth=_truth_checks(drive, None, conf, float(tests[-1][1]["M_star"])), timings=run.timings, name=run.name,
        breach=breach)
