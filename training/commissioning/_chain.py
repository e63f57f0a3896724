"""The self-commissioning chain (the paper's section 2) through a drive of docs/contract.md
section 4: named stages applied in order (:data:`STAGES`), each reading what the earlier ones left
in the run's :class:`ChainState` and adding its own.

    hold      the rest check (SPEC 1.1, :mod:`._rest`): does the drive hold the axis? (else ``AxisNotHeld``)
    excite    adapt the test signal on the drive (E0-E13, ``drive.run_test``)
    identify  what the shipped maps say of the accepted test record (V1 when the identifier fails)
    validate  re-simulate the identified model (with ``M_L0``, from rest held) under the record's test signal
    guard     the limits handed to the drive for the closed-loop runs (E9: less the stop headroom)
    permit    may a model-based controller be proposed? (V1-V6)
    design    optimize the law over the uncertainty set (R6, R7, R4, R5), tune on the identified model, plan the experiment
    try       run the candidates on the drive (``drive.run_closed_loop``) and choose the cheapest usable one
    measure   the plant's frequency response on the chosen loop (a multisine ``M_dist``, :mod:`._frf`)
    redesign  the design again with the measurement; its candidates on the drive, kept where not worse
    fallback  the cautious F1 where no model-based loop can be delivered
    deliver   the controller delivered, and whether its run on the drive looks like its model

The chain reaches the plant only through the drive (:class:`sim.Drive`: ``config``, ``run_test``,
``run_closed_loop``); everything it decides comes from the records these return. Every call goes
through :class:`training.commissioning._guard.CheckedDrive`: bounded in time, each record checked
as it comes and held against the user's limits; the first passed limit ends the experiments (the
report's ``breach``, nothing delivered, the stages' results so far). A drive that offers
``truth()`` (a simulator) gets truth-based figures in the report, apart, marked "simulation only";
they are never used for a decision.
"""

from __future__ import annotations

import functools
import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from typing import Any, Protocol

import numpy as np

import sim
from training._settings import (AT_LEAST_ONE, FLAG, NON_NEGATIVE, NON_NEGATIVE_OR_INF, POSITIVE, POSITIVE_OR_INF, SHARE, InstanceOf,
                                Interval, OneOf, OrNone, check_settings)
from training.errors import CommissioningError, LimitPassed, one_line

from ._bands import f1_bands, hidden_bands, narrowed, widen
from ._excitation import (ExcitationResult, ExcitationRules, adapt_test_signal, check_limits, guarded_limits, measure_response,
                          stop_headroom, trusted_inertia)
from ._frf import FRF_SETTINGS, FRFSettings, MeasuredResponse
from ._measure import measured_response, plan_frf
from ._guard import CONFIG_KEYS, CheckedDrive, passed_limits, record_peaks
from ._loop import linear_plant, margins
from ._permission import (CommissioningWarning, IdentificationFailed, IdentificationOutcome, Permission, may_propose_controller,
                          outside_training)
from ._report import CommissioningReport, PlantRun
from ._rest import REST_SETTINGS, RestCheck, RestSettings, check_rest
from ._design import MechanicsBounds, elastic_doubts
from ._rules import BACKLASH_CLASSES, ControllerProposal, ControllerSpec, propose_cautious, propose_controller, uncertainty_set
from ._tuning import (BOUNDED_VERDICTS, applied_torque_gain, Gains, TuningResult, TuningScenario, closed_loop_cost, loop_verdict,
                      model_response, plan_scenario, response_figures, tune_controller)
from ._validation import OSC_METRICS, VALIDATION_MODES, ValidationResult, validate_model

__all__ = ["CommissioningConfig", "commission", "limit_checks", "drive_config", "check_resolution", "MIN_LIMIT_QUANTA",
           "RecordIdentifier", "ScalarWriter", "ChainRun", "ChainState", "LoopPlan", "LoopTrial", "STAGES"]

#: Identification warning codes that make the elastic parameters uncertain, for an identification
#: without calibrated intervals (rule R7c widens the interim set; ``outside_envelope`` and
#: ``drive_outside_training`` only where a finding concerns more than friction and torque levels:
#: :func:`training.commissioning._design.elastic_doubts`).
UNCERTAIN_CODES: frozenset[str] = frozenset({"unlike_training_data", "oscillation_below_quantum", "refine_partial_fit",
                                             "implausible_output", "drive_outside_training", "outside_envelope",
                                             "answer_outside_envelope", "class_undecided", "backlash_from_angle",
                                             "likely_wrong"})
#: With calibrated intervals (SPEC 4.1) the intervals carry the uncertainty (the other codes are the
#: answer's notes); these warnings still widen the set (R7c): the intervals hold for records like the
#: calibration's, inside the envelope and the maps' training. So does an answer more likely wrong
#: than right (:data:`DOUBTFUL_ANSWER`), named ``likely_wrong``.
CALIBRATED_UNCERTAIN_CODES: frozenset[str] = frozenset({"drive_outside_training", "outside_envelope"})
#: The calibrated answer probability below which the design treats the answer as doubtful (R7c and
#: R7b): the identification warns ``likely_wrong`` from a much higher level (so that nearly every
#: wrong answer is warned), where the answer is still far more often right than wrong and its
#: intervals already hold it.
DOUBTFUL_ANSWER: float = 0.5
#: Identification codes (warnings or notes) that say the oscillation is not determined at all, or
#: the answer likely wrong (rule R7b as for ``stiff``: the set covers what the test cannot exclude).
UNDETERMINED_CODES: frozenset[str] = frozenset({"refine_partial_fit", "oscillation_below_quantum", "likely_wrong"})
#: The fewest samples a closed-loop experiment may be given: six segments of at least 100 samples.
MIN_EXPERIMENT_SAMPLES: int = 600


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
            code of :data:`UNCERTAIN_CODES`, or a map beyond its training).
        uncertain_damping: rule R7c: the set's lowest damping is the identified ``d`` times this
            share (a lighter damped resonance).
        hidden_resonances: rule R7b: the guarantee of a ``stiff`` answer, or of one whose
            oscillation is not determined (:data:`UNDETERMINED_CODES`), also covers the resonances
            the test could not show (:func:`training.commissioning._bands.hidden_bands`).
        fallback_resonance_factor: F1 also covers the identified resonance, trusted or not, from
            ``f_e / factor`` to ``f_e * factor``.
        min_scenario_quanta: a closed-loop speed step of fewer speed quanta warns ``scenario_small``
            (the figures on the drive are coarse).
        drive_timeout: the longest a drive call may take [s] (a test run of six sections of up to
            10 s each on a real drive, with its upload, fits the default); past it the drive is a
            fault (:func:`training.commissioning._guard.call_drive`). None: no bound, the drive is
            called in the calling thread.
        measure_response: run the frequency-response experiment on the chosen model-based loop
            and the design again with it (stages ``measure``, ``redesign``); False: skip both (faster).
        redesign_tolerance: the redesign counts as worse on the drive only where its settling time
            or its disturbance dip per Nm exceeds the first design's by more than this share
            (:func:`_not_worse`): each figure is read from one run, the two differ in size, the
            drive adds friction and encoder quantization, and a settling time moves in steps of
            half a period of any residual oscillation (docs/commissioning.md, section 3b).
        frf: the frequency-response experiment's settings (:class:`FRFSettings`).
        rest: the rest check before the first test run (:class:`RestSettings`).
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
    uncertain_damping: float = 0.5
    hidden_resonances: bool = True
    fallback_resonance_factor: float = 1.5
    min_scenario_quanta: float = 20.0
    drive_timeout: float | None = 600.0
    measure_response: bool = True
    redesign_tolerance: float = 0.1
    frf: FRFSettings = FRF_SETTINGS
    rest: RestSettings = REST_SETTINGS

    def __post_init__(self) -> None:
        check_settings(self, {
            "spec": InstanceOf(ControllerSpec), "rules": InstanceOf(ExcitationRules), "tune": FLAG,
            "validation_mode": OneOf(VALIDATION_MODES), "osc_metric": OneOf(OSC_METRICS),
            "max_validation_error": POSITIVE_OR_INF, "max_map_distance_ratio": OrNone(POSITIVE_OR_INF),
            "tune_evaluations": AT_LEAST_ONE, "fallback": FLAG, "limit_use": SHARE, "fallback_limit_use": SHARE,
            "max_samples": Interval(MIN_EXPERIMENT_SAMPLES, integer=True), "osc_visible_ratio": NON_NEGATIVE_OR_INF,
            "uncertain_spread": Interval(0.0, 1.0, open_high=True), "uncertain_damping": SHARE, "hidden_resonances": FLAG,
            "fallback_resonance_factor": Interval(1.0, finite=False), "min_scenario_quanta": NON_NEGATIVE_OR_INF,
            "drive_timeout": OrNone(POSITIVE), "measure_response": FLAG, "redesign_tolerance": NON_NEGATIVE, "frf": InstanceOf(FRFSettings),
            "rest": InstanceOf(RestSettings)})


class RecordIdentifier(Protocol):
    """What the chain asks of an identifier (``training.Identifier``): the answer to one test record
    (a result with ``ok``, ``structure``, ``parameters``, ``quality``, ``warnings``); an error it
    raises (ValueError, RuntimeError) is refusal rule V1."""

    def identify(self, record: sim.Record) -> IdentificationOutcome: ...


class ScalarWriter(Protocol):
    """A TensorBoard ``SummaryWriter``, as far as the chain writes to it."""

    def add_scalar(self, tag: str, scalar_value: float, global_step: int) -> None: ...


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


# --------------------------------------------------------------------------- the run and its state


@dataclass(frozen=True)
class LoopPlan:
    """A controller ready for the drive: the ``proposal``, its candidate ``gains`` (the proposal's
    first, then the tuned ones), the ``tuning`` that found them (None: not tuned), the closed-loop
    experiment ``scenario`` planned for them and the model's predicted peaks (``prediction``)."""

    proposal: ControllerProposal
    gains: tuple[Gains, ...]
    scenario: TuningScenario
    prediction: dict[str, float]
    tuning: TuningResult | None = None


@dataclass(frozen=True)
class LoopTrial:
    """A plan's candidates on the drive (``runs``, in the plan's order) and the index of the one
    chosen for delivery (None: none may be delivered)."""

    runs: list[PlantRun]
    chosen: int | None


@dataclass
class ChainState:
    """What the stages have produced so far: the report's fields. A chain that a passed limit ends
    reports what its state holds then."""

    rest: RestCheck | None = None
    """The rest check before the first test run (None: not run yet)."""
    excitation: ExcitationResult | None = None
    identification: IdentificationOutcome | None = None
    validation: ValidationResult | None = None
    permission: Permission | None = None
    outside_training: bool | None = None
    design: LoopPlan | None = None
    """The model-based plan (None: refused, or no design keeps the margins)."""
    design_trial: LoopTrial | None = None
    measured: MeasuredResponse | None = None
    """The plant's frequency response measured on the drive (None: not measured)."""
    redesign: LoopPlan | None = None
    """The design made again with the measured response (None: not measured, or the same design)."""
    redesign_trial: LoopTrial | None = None
    redesign_kept: bool = False
    """The redesigned loop settled on the drive, not worse than the first: it is delivered."""
    measured_unlike: float | None = None
    """The measured response's gain near the crossover over the identified model's, where it lies
    outside :attr:`FRFSettings.model_gain_factor` (``loop_unlike_model``; None: alike or not
    measured): the model is not redesigned on."""
    gap_open_cycled: bool = False
    """A model-based candidate limit-cycled on the drive while the design held the decoupled motor
    only to the gap-open margins: every later design holds it to the guarantee's (R6)."""
    redesign_reason: str = ""
    """Why the redesign is or is not delivered, or why nothing was measured (one line; empty where
    the experiment did not apply)."""
    fallback_reason: str | None = None
    """Why no model-based loop is delivered (``refused``, ``margins_not_reached``, ``loop_not_settled``)."""
    fallback: LoopPlan | None = None
    """The fallback F1's plan (None: it did not run)."""
    fallback_trial: LoopTrial | None = None
    delivered: ControllerProposal | None = None
    delivered_run: PlantRun | None = None

    @property
    def model_plan(self) -> LoopPlan | None:
        """The model-based plan delivered or to deliver: the redesign where it is kept, else the design."""
        return self.redesign if self.redesign_kept else self.design

    @property
    def model_trial(self) -> LoopTrial | None:
        """The trial of :attr:`model_plan`."""
        return self.redesign_trial if self.redesign_kept else self.design_trial

    @property
    def last_plan(self) -> LoopPlan | None:
        """The plan whose experiment is delivered or ran last (F1's over the model-based one): the report's scenario."""
        return self.fallback if self.fallback is not None else self.model_plan


@dataclass
class ChainRun:
    """One run of the chain: the checked drive, the identifier, the drive's config, the user's
    limits, the settings, where progress goes, the warnings, the stage timings [s] and the stages'
    :class:`ChainState`."""

    drive: CheckedDrive
    identifier: RecordIdentifier
    config: sim.DriveConfig
    limits: sim.DriveLimits
    settings: CommissioningConfig
    say: Callable[[str], None]
    writer: ScalarWriter | None
    name: str
    tag: str
    warnings: list[CommissioningWarning] = field(default_factory=list)
    timings: dict[str, float] = field(default_factory=dict)
    loop_limits: sim.DriveLimits | None = None
    """The limits handed to the drive for the closed-loop runs (E9: less the headroom after a stop)."""
    test_log: list[dict[str, Any]] = field(default_factory=list)
    """The test runs' log entries as they are decided (kept when a run passes a limit)."""
    state: ChainState = field(default_factory=ChainState)
    started: float = field(default_factory=time.perf_counter)
    """When the run started (``time.perf_counter``)."""
    last_lap: float = 0.0

    def elapsed(self) -> float:
        """Seconds since the run started."""
        return time.perf_counter() - self.started

    def lap(self, stage: str) -> None:
        """Time ``stage`` took, from the previous lap (or the start)."""
        now = time.perf_counter()
        self.timings[stage] = now - (self.last_lap or self.started)
        self.last_lap = now

    def warn(self, code: str, text: str) -> None:
        self.warnings.append(CommissioningWarning(code, text))

    @property
    def result(self) -> Any:
        """The identification result (its ``parameters`` read where ``ok``)."""
        return self.state.identification

    @property
    def excitation(self) -> ExcitationResult:
        excitation = self.state.excitation
        if excitation is None:
            raise RuntimeError("the chain's stages ran out of order: no excitation yet")
        return excitation


# --------------------------------------------------------------------------- helpers of the stages


def _identify(identifier: RecordIdentifier, record: sim.Record) -> IdentificationOutcome:
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


def _simulated_model(result: Any) -> dict[str, float | None]:
    """The model the chain simulates against a record: the seven parameters (:func:`_model_params`)
    and the real axis's ``M_L0``, ``M_FCM``, ``mu_FM`` (SPEC 1.1; 0 where not identified), so
    that it starts at rest held by its ``M_L0`` as the drive holds the axis."""
    real = {k: getattr(result.parameters, k) for k in sim.REAL_AXIS_NAMES}
    return {**_model_params(result), **{k: 0.0 if v is None else float(v) for k, v in real.items()}}


def _holding_torque(result: Any) -> float:
    """The torque [Nm] that holds the axis, where the delivered law's integrator starts (SPEC 1.1):
    the identified constant load torque ``M_L0``, 0 where the identification gives none."""
    M_L0 = result.parameters.M_L0
    return 0.0 if M_L0 is None else float(M_L0)


def _accepted(excitation: ExcitationResult) -> dict[str, Any]:
    """The log entry of the test record the identification used (the last one the drive did not stop)."""
    kept = [e for e in excitation.log if not e["aborted"]]
    return kept[-1] if kept else excitation.log[-1]


def _informative_entries(excitation: ExcitationResult) -> list[dict[str, Any]]:
    """The log entries of the informative test runs: the accepted one and, where an E12/E13 probe
    replaced a run (:attr:`ExcitationResult.replaced`), the run before it (the last kept one before)."""
    kept = [e for e in excitation.log if not e["aborted"]]
    return kept[-2:] if excitation.replaced is not None and len(kept) > 1 else [_accepted(excitation)]


def _test_J(excitation: ExcitationResult) -> float:
    """The one-mass inertia the accepted test run's mean acceleration gives, ``M* / accel`` [kg m^2]
    (friction makes it larger, never smaller; inf when the run had no acceleration to measure):
    the bound of the stop headroom (E9), never a design's inertia (F1 takes :func:`trusted_inertia`)."""
    entry = _accepted(excitation)
    if not entry.get("accel", 0.0) > 0:
        return math.inf
    return entry["M_star"] / entry["accel"]


def _positive(x: Any) -> bool:
    return isinstance(x, (int, float)) and math.isfinite(x) and x > 0


def _intervals(result: Any) -> Any:
    """The identification's calibrated intervals (None: its maps carry no calibration, or the
    identifier reports none)."""
    return getattr(result, "intervals", None)


def _uncertain(result: Any) -> list[str]:
    """Why the identified elastic values are more uncertain than the set shows (warning codes of
    :data:`UNCERTAIN_CODES`, or of :data:`CALIBRATED_UNCERTAIN_CODES` where the result has
    calibrated intervals, that concern them; ``outside_training``: :func:`elastic_doubts`); empty
    when nothing says so."""
    if _intervals(result) is None:
        return elastic_doubts(result, UNCERTAIN_CODES)
    return sorted({*elastic_doubts(result, CALIBRATED_UNCERTAIN_CODES), *(["likely_wrong"] if _doubtful(result) else [])})


def _gap_probability(result: Any) -> float:
    """The identification's calibrated probability that the plant has a gap (its backlash classes'
    share of ``quality.structure_probabilities``; 1 where it gives none: nothing says there is none)."""
    probabilities = getattr(result.quality, "structure_probabilities", None)
    if not probabilities:
        return 1.0
    return float(sum(p for c, p in probabilities.items() if c in BACKLASH_CLASSES))


def _doubtful(result: Any) -> bool:
    """A calibrated answer more likely wrong than right (:data:`DOUBTFUL_ANSWER`; where the result
    gives no answer probability: its ``likely_wrong`` warning)."""
    p = getattr(result.quality, "answer_probability", None)
    if p is None:
        return any(w.code == "likely_wrong" for w in result.warnings)
    return p < DOUBTFUL_ANSWER


def _undetermined(result: Any) -> list[str]:
    """The codes of :data:`UNDETERMINED_CODES` among the result's warnings or notes (with a
    calibration the oscillation's codes arrive as notes: what the test cannot show stays so), with
    ``likely_wrong`` only where the answer is doubtful (:func:`_doubtful`)."""
    remarks = {w.code for w in (*result.warnings, *getattr(result, "notes", ()))} - {"likely_wrong"}
    return sorted(UNDETERMINED_CODES & (remarks | ({"likely_wrong"} if _doubtful(result) else set())))


def _run_candidates(run: ChainRun, plan: LoopPlan, kind: str) -> list[PlantRun]:
    """Each gain set of ``plan`` on the drive over its scenario (one experiment each), scored from its
    record and judged (:func:`loop_verdict`) against what the identified model predicts for the same
    gains."""
    out = []
    proposal, scenario = plan.proposal, plan.scenario
    mech = proposal.mechanics
    cap = run.limits.torque_cap(run.config)
    model_costs = closed_loop_cost(model_response(mech, run.config, list(plan.gains), proposal.notch, scenario), scenario,
                                   mech)[0]
    for i, gains in enumerate(plan.gains):
        law = proposal.law(run.config, Kp=gains[0], Ti=gains[1], T_f=gains[2])
        rec = run.drive.run_closed_loop(law, scenario.scenario(), run.loop_limits, f"{kind} {i}")
        stopped = bool(rec.meta.get("aborted", False))
        speed = np.asarray(rec.speed, dtype=np.float64)
        cost, terms = closed_loop_cost(speed, scenario, mech, stopped)
        model_cost = float(model_costs[i])
        verdict, why = loop_verdict(speed, rec.torque_ref, scenario, cap, float(cost), model_cost, stopped)
        out.append(PlantRun(gains=gains, cost=float(cost), motor=float(terms["motor"]), load=float(terms["load"]),
                            aborted=stopped, figures=response_figures(speed, scenario, mech), speed=speed, verdict=verdict,
                            verdict_text=why, model_cost=model_cost))
        _check_applied_law(run, law, rec, scenario)
        if stopped:
            run.warn("run_stopped", f"the drive stopped the closed-loop run {kind} {i} at a limit")
        elif verdict not in BOUNDED_VERDICTS:
            run.warn("loop_rejected", f"{kind} {i} not delivered [{verdict}]: {why}")
    return out


def _check_applied_law(run: ChainRun, law: Any, record: sim.Record, scenario: TuningScenario) -> None:
    """Warn (once) where the drive did not apply the law as given: its recorded torque is far from
    the law replayed (reset) on the record (:func:`applied_torque_gain`); the margins rest on that law."""
    if "loop_unlike_model" in {w.code for w in run.warnings}:
        return
    held = float(record.meta.get("M_hold", 0.0))  # the drive's holding torque on the law's output (SPEC 1.1)
    torque = None if record.torque_ref is None else np.asarray(record.torque_ref, dtype=np.float64) - held
    gain = applied_torque_gain(law, np.asarray(record.speed, dtype=np.float64), torque, scenario.scenario(),
                               run.loop_limits.torque_cap(run.config))
    tolerance = scenario.torque_gain_tolerance
    if gain is not None and not 1 / tolerance <= gain <= tolerance:
        run.warn("loop_unlike_model", f"the drive applied {gain:.3g} x the law's torque in a closed-loop run: the margins "
                                      "guaranteed on the model do not hold for what it runs (a torque scale or K_M off?)")


def _choose(runs: list[PlantRun]) -> int | None:
    """The delivered candidate: the lowest cost (motor and estimated load together) among the usable
    runs (:attr:`PlantRun.usable`: settled, or near the reference and only slow); the proposal's
    (index 0) on a tie; None when none is usable. A tuned candidate may trade the motor against the
    load: its load peak was bounded on the model (:func:`tune_controller`)."""
    settled = [i for i, r in enumerate(runs) if r.usable]
    if not settled:
        return None
    return min(settled, key=lambda i: (runs[i].cost, i))


def _design_spec(run: ChainRun) -> ControllerSpec:
    """The guarantee's spec of a model-based design: ``settings.spec`` (an uncertain identification
    widens the design's set, R7c in :func:`_propose`, not the margins); once a candidate limit-cycled
    on the drive (:attr:`ChainState.gap_open_cycled`), the decoupled motor held to the guarantee's
    margins (R6)."""
    spec = run.settings.spec
    if not run.state.gap_open_cycled:
        return spec
    return replace(spec, gap_open_phase_margin=max(spec.gap_open_phase_margin, spec.min_phase_margin),
                   gap_open_gain_margin_dB=max(spec.gap_open_gain_margin_dB, spec.min_gain_margin_dB))


def _propose(run: ChainRun) -> ControllerProposal:
    """The optimized design (R4-R7) on the uncertainty set of the identified model: spanning the
    identification's calibrated intervals (:class:`MechanicsBounds`), or the interim spread where it
    has none (the R7 rule line says which); R7b covers the resonances the test could not show
    unless the frequency response was measured (then the measurement stands in for them), R7c an
    identification whose elastic values are uncertain beyond what the set shows (wider spread,
    lighter damping)."""
    settings, result = run.settings, run.result
    params, why = _model_params(result), _uncertain(result)
    spec = _design_spec(run)
    intervals = _intervals(result)
    bounds = None if intervals is None else MechanicsBounds.from_intervals(intervals)
    hidden = notch_at = None
    if settings.hidden_resonances and (params["f_e"] is None or _undetermined(result)):
        hidden, notch_at = hidden_bands(_accepted(run.excitation), float(params["J_sigma"]), run.config, spec.class_V_J,
                                        f_lo=spec.class_f_e[0], min_osc_quanta=settings.rules.min_osc_quanta)
    r7c = bool(why) and params["f_e"] is not None
    uncertainty = uncertainty_set(params, spec, structure=result.structure, hidden=hidden, measured=run.state.measured,
                                  spread=settings.uncertain_spread if r7c else None,
                                  damping=settings.uncertain_damping if r7c else None, doubts=tuple(why), bounds=bounds,
                                  drive=run.config, gap_probability=_gap_probability(result))
    proposal = propose_controller(result.structure, params, run.config, spec, notch_at=notch_at, uncertainty=uncertainty)
    proposal = replace(proposal, M_hold=_holding_torque(result))
    if run.state.gap_open_cycled:
        proposal = replace(proposal, rules=("R6 a loop with the decoupled motor at the gap-open margins limit-cycled on the drive: "
                                            "designed again with the guarantee's margins there",) + proposal.rules)
    if r7c:
        f_es, V_Js, (d_lo, _) = uncertainty.spans()
        proposal = replace(proposal, rules=(f"R7c identification uncertain ({', '.join(why)}): the set's f_e "
                                            f"{f_es[0]:.4g}..{f_es[-1]:.4g} Hz (+-{uncertainty.f_e_spread:.0%} at least), "
                                            f"V_J {V_Js[0]:.3g}..{V_Js[-1]:.3g} (+-{uncertainty.V_J_spread:.0%} at least), "
                                            f"d from {d_lo:.3g}",) + proposal.rules)
    return proposal


def _tune(run: ChainRun, proposal: ControllerProposal) -> tuple[TuningResult | None, list[Gains]]:
    """The tuning on the identified model and the candidate gain sets: the proposal's, the tuned
    ones where the search found better, and their geometric mean where it keeps the margins."""
    settings, config = run.settings, run.config
    gains: list[Gains] = [(proposal.Kp, proposal.Ti, proposal.T_f)]
    if not settings.tune:
        return None, gains
    scenario, _ = plan_scenario(proposal, [], config, run.limits, limit_use=settings.limit_use,
                                max_samples=settings.max_samples)
    run.say(f"{run.name}: tuning on the identified model ({settings.tune_evaluations} evaluations)")
    tuning = tune_controller(proposal, config, scenario, _design_spec(run),
                             max_evaluations=settings.tune_evaluations)
    tuned = tuning.controller
    if tuned is not proposal:
        gains.append((tuned.Kp, tuned.Ti, tuned.T_f))
        mid = tuple(math.sqrt(a * b) for a, b in zip(gains[0], gains[1]))
        if proposal.models.margins(*mid, proposal.notch).meets(settings.spec.min_phase_margin, settings.spec.min_gain_margin_dB):
            gains.append(mid)
    if run.writer is not None:
        for i, step in enumerate(tuning.history):
            run.writer.add_scalar(f"{run.tag}/tune/cost", step["cost"], i)
            run.writer.add_scalar(f"{run.tag}/tune/Kp", step["Kp"], i)
    return tuning, gains


def _fallback_reason(state: ChainState) -> str | None:
    """Why no model-based loop is delivered; None when one is."""
    if state.design_trial is not None:
        return "loop_not_settled" if state.design_trial.chosen is None else None
    return "refused" if not state.permission.allowed else "margins_not_reached"


def _fallback_plan(run: ChainRun) -> LoopPlan:
    """F1: the cautious law on ``J_sigma`` optimized over the worst cases of the class the test run
    allows (and the identified resonance), planned on the one-mass model, stating the lowest
    crossover over that set; ``J_sigma`` the smaller of the identified and the test run's
    rigid-body fit where the run accelerated the load (:func:`trusted_inertia`; a run that moved the
    motor alone shows ``J_M``, and a loop designed on it is slower than it states)."""
    settings, config, result, excitation = run.settings, run.config, run.result, run.excitation
    spec, identified_J = settings.spec, float(result.parameters.J_sigma)
    trusted = trusted_inertia(excitation, settings.rules)
    J = identified_J if trusted is None else min(identified_J, trusted)
    bands = functools.reduce(narrowed, (f1_bands(entry, J, config, spec.class_V_J, spec.class_f_e,
                                                 min_osc_quanta=settings.rules.min_osc_quanta,
                                                 osc_visible_ratio=settings.osc_visible_ratio)
                                        for entry in _informative_entries(excitation)))
    params = _model_params(result)
    if _positive(params["f_e"]) and _positive(params["V_J"]):  # the identified resonance too, trusted or not
        factor = settings.fallback_resonance_factor
        widen(bands, params["V_J"], params["f_e"] / factor, params["f_e"] * factor)
    proposal = replace(propose_cautious(J, config, spec, bands=bands), M_hold=_holding_torque(result))
    if J < identified_J:
        proposal = replace(proposal, rules=proposal.rules + (
            f"F1 J_sigma from the test run's rigid-body fit ({J:.4g} kg m^2), "
            f"below the identified {identified_J:.4g} kg m^2",))
    scenario, prediction = plan_scenario(proposal, [], config, run.limits, limit_use=settings.fallback_limit_use,
                                         max_samples=settings.max_samples)
    return LoopPlan(proposal, ((proposal.Kp, proposal.Ti, proposal.T_f),), scenario, prediction)


def _model_based_delivery(run: ChainRun, design: LoopPlan, trial: LoopTrial) -> ControllerProposal:
    """The controller of the chosen model-based candidate of ``design``: the proposal, the tuned
    one, or their geometric mean (T2)."""
    if trial.chosen == 0:
        return design.proposal
    if trial.chosen == 1:
        return design.tuning.controller
    gains = trial.runs[trial.chosen].gains
    return design.proposal.with_gains(run.config, *gains, rule=(
        f"T2 on the drive: the geometric mean of the proposal's and the tuned gains: Kp {gains[0]:.4g}, Ti {gains[1]:.4g} s, "
        f"T_f {gains[2]:.3g} s"))


# --------------------------------------------------------------------------- the stages, in order


def _check_hold(run: ChainRun) -> None:
    """SPEC 1.1: before any test, the limits' E0 check (where the rules refuse uninformative limits),
    then the rest check (:func:`check_rest`): a drive that does not hold the axis raises
    :class:`training.errors.AxisNotHeld` and nothing is excited."""
    rules = run.settings.rules
    if rules.refuse_uninformative_limits:
        check_limits(run.limits, run.config, rules)
    run.say(f"{run.name}: checking that the drive holds the axis at rest")
    run.state.rest = check_rest(run.drive, run.config, run.limits, run.settings.rest)
    run.lap("rest_check")


def _excite(run: ChainRun) -> None:
    """E0-E13: the test signal adapted on the drive until its response is informative."""
    run.say(f"{run.name}: adapting the test signal")
    excitation = adapt_test_signal(run.drive, run.limits, run.settings.rules, log=run.test_log)
    run.state.excitation = excitation
    if any(e["aborted"] for e in excitation.log):
        run.warn("run_stopped", "the drive stopped a test run at a limit")
    run.lap("excitation")


def _identify_record(run: ChainRun) -> None:
    """The identifier's answer to the accepted test record; none where the speed moved against the
    torque (E10: the maps would blame the units)."""
    excitation = run.excitation
    if excitation.code == "speed_against_torque":
        run.warn("speed_against_torque", excitation.reason)
        run.state.identification = IdentificationFailed(f"not identified: {excitation.reason}")
    else:
        run.say(f"{run.name}: identifying")
        run.state.identification = _identify(run.identifier, excitation.record)
    if excitation.replaced is None or not run.state.identification.ok:
        return
    before = _identify(run.identifier, excitation.replaced)  # the run the E12/E13 probe replaced
    p_probe, p_before = _answer_probability(run.state.identification), _answer_probability(before)
    if p_probe is not None and p_before is not None and p_before > p_probe:
        run.state.identification = before
        run.state.excitation = replace(excitation, record=excitation.replaced, reason=(
            f"{excitation.reason}; its answer is right with probability {p_probe:.1%}, the run before it's with "
            f"{p_before:.1%}: the run before it is identified"))


def _answer_probability(result: Any) -> float | None:
    """The calibrated probability that an identification answer is right (None: no answer, or an
    identifier without a calibration)."""
    p = getattr(getattr(result, "quality", None), "answer_probability", None) if result.ok else None
    return None if p is None else float(p)


def _validate(run: ChainRun) -> None:
    """Does the identified model reproduce the record? (None: no result, or the re-simulation could
    not run, with a warning saying why.)"""
    result, excitation, settings = run.result, run.excitation, run.settings
    validation = None
    if result.ok:
        try:
            validation = validate_model(_simulated_model(result), run.config, excitation.record, mode=settings.validation_mode,
                                        osc_metric=settings.osc_metric)
        except ValueError as err:
            run.warn("validation_not_run", f"validation failed: {one_line(err)}")
    if not excitation.informative:
        run.warn("test_not_informative", f"test response not informative: {excitation.reason}")
    run.lap("identification_validation")
    run.state.validation = validation


def _guard_loop(run: ChainRun) -> None:
    """E9: the limits handed to the drive for the closed-loop runs, less the headroom a run gains
    after a stop (from the smaller of the test run's and the identified inertia)."""
    result, config, rules = run.result, run.config, run.settings.rules
    J_loop = min(_test_J(run.excitation), float(result.parameters.J_sigma) if result.ok and _positive(result.parameters.J_sigma)
                 else math.inf)
    cap = run.limits.torque_cap(config)
    headroom = stop_headroom(cap / J_loop, config, rules) if math.isfinite(J_loop) else rules.first_headroom * run.limits.w_max
    run.loop_limits = guarded_limits(run.limits, headroom, config, rules)


def _permit(run: ChainRun) -> None:
    """V1-V6: may a model-based controller be proposed?"""
    result, settings = run.result, run.settings
    run.state.permission = may_propose_controller(result, run.state.validation, warnings=tuple(run.warnings),
                                                  max_validation_error=settings.max_validation_error,
                                                  max_map_distance_ratio=settings.max_map_distance_ratio)
    run.state.outside_training = outside_training(result, settings.max_map_distance_ratio) if result.ok else None


def _design(run: ChainRun) -> None:
    """Where permitted: design (R6, R7, R4, R5), keep it only when it meets the guarantee (R7), tune it on
    the identified model and plan the closed-loop experiment for the candidates."""
    if not run.state.permission.allowed:
        return
    settings = run.settings
    proposal = _propose(run)
    if not proposal.meets(settings.spec):
        run.warn("margins_not_reached", f"R7: {proposal.warnings[-1]}")
        return
    run.lap("proposal")
    run.state.design = _plan_loop(run, proposal)


def _plan_loop(run: ChainRun, proposal: ControllerProposal) -> LoopPlan:
    """The proposal tuned on the identified model, its candidates and their experiment planned."""
    settings = run.settings
    tuning, gains = _tune(run, proposal)
    run.lap("tuning")
    scenario, prediction = plan_scenario(proposal, gains[1:], run.config, run.limits, limit_use=settings.limit_use,
                                         max_samples=settings.max_samples)
    if prediction["speed_quanta"] < settings.min_scenario_quanta:
        run.warn("scenario_small", f"the scenario's speed step is {prediction['speed_quanta']:.3g} speed quanta")
    run.say(f"{run.name}: running {len(gains)} gain set(s) on the drive")
    return LoopPlan(proposal, tuple(gains), scenario, prediction, tuning)


def _measure(run: ChainRun) -> None:
    """The plant's frequency response on the chosen model-based loop (:mod:`._frf`): a multisine
    disturbance torque planned on the identified model inside the limits handed to the drive; a run
    the drive stopped measures nothing (a warning says so; so does :attr:`ChainState.redesign_reason`)."""
    state, settings = run.state, run.settings
    trial = state.design_trial
    if not settings.measure_response or trial is None or trial.chosen is None:
        return
    proposal, gains = state.design.proposal, trial.runs[trial.chosen].gains
    try:
        plan = plan_frf(proposal.mechanics, run.config, gains, proposal.notch, run.loop_limits, settings.frf)
    except ValueError as err:
        state.redesign_reason = f"frequency response not measured: {one_line(err)}"
        return
    run.say(f"{run.name}: measuring the frequency response ({len(plan.scenario)} samples)")
    law = proposal.law(run.config, Kp=gains[0], Ti=gains[1], T_f=gains[2])
    rec = run.drive.run_closed_loop(law, plan.scenario, run.loop_limits, "frequency response")
    run.lap("frequency_response")
    if rec.meta.get("aborted", False):
        run.warn("run_stopped", "the drive stopped the frequency-response run at a limit: nothing measured")
        state.redesign_reason = "frequency response not measured: the drive stopped its run at a limit"
        return
    state.measured = measured = measured_response(rec, plan, proposal.mechanics, run.config, settings.frf)
    ratio = measured.model_gain_ratio(proposal.figures["w_c"], settings.frf.min_coherence)
    factor = settings.frf.model_gain_factor
    if ratio is not None and not 1 / factor <= ratio <= factor:
        state.measured_unlike = ratio
        run.warn("loop_unlike_model", f"the measured frequency response near the crossover is {ratio:.3g} x the identified "
                                      "model's: the margins guaranteed on the model may not hold on this drive (a torque "
                                      "scale or K_M off? a plant unlike the model?)")


def _same_law(a: ControllerProposal, b: ControllerProposal) -> bool:
    """The same law: gains, low-pass and notch."""
    return (a.Kp, a.Ti, a.T_f, a.notch) == (b.Kp, b.Ti, b.T_f, b.notch)


def _not_worse(new: PlantRun, new_plan: LoopPlan, old: PlantRun, old_plan: LoopPlan, tolerance: float = 0.0) -> str:
    """Why the redesigned run ``new`` is worse than the first design's ``old`` by more than the share
    ``tolerance`` (empty: it is not). The runs' scenarios differ in size; compared are what a linear
    loop does not scale: the first step's settling time and the disturbance's speed dip per Nm."""
    settle_new, settle_old = new.figures["settling_time"], old.figures["settling_time"]
    dip_new = new.figures["dist_peak"] / new_plan.scenario.M_dist
    dip_old = old.figures["dist_peak"] / old_plan.scenario.M_dist
    if settle_new > (1.0 + tolerance) * settle_old:
        return f"it settles in {settle_new:.3g} s, the first design in {settle_old:.3g} s"
    if dip_new > (1.0 + tolerance) * dip_old:
        return f"its disturbance dip is {dip_new:.3g} rad/s per Nm, the first design's {dip_old:.3g}"
    return ""


def _redesign(run: ChainRun) -> None:
    """With a measured response: the design again (:func:`_propose` reads it); a new law is tuned,
    planned and run on the drive, and kept for delivery where one of its candidates settled and is
    not worse than the first design's chosen run (:func:`_not_worse`). Not where the measurement
    says the plant does not follow the model near the crossover (:attr:`ChainState.measured_unlike`)."""
    state, settings = run.state, run.settings
    if state.measured is None:
        return
    if state.measured_unlike is not None:
        state.redesign_reason = (f"no redesign: the measured response near the crossover is {state.measured_unlike:.3g} x the "
                                 "identified model's, and a design on a model the plant does not follow keeps no margins")
        return
    proposal = _propose(run)
    if not proposal.meets(settings.spec):
        state.redesign_reason = f"the redesign misses the margins ({proposal.warnings[-1] if proposal.warnings else 'R7'})"
        return
    if _same_law(proposal, state.design.proposal):
        state.redesign_reason = "the measured response leaves the design as it is"
        return
    state.redesign = plan = _plan_loop(run, proposal)
    state.redesign_trial = trial = LoopTrial(_run_candidates(run, plan, "redesign"), None)
    chosen = _choose(trial.runs)
    run.lap("redesign")
    if chosen is None:
        state.redesign_reason = "no redesigned candidate settled on the drive: the first design is delivered"
        return
    first = state.design_trial
    worse = _not_worse(trial.runs[chosen], plan, first.runs[first.chosen], state.design, settings.redesign_tolerance)
    state.redesign_trial = LoopTrial(trial.runs, chosen)
    state.redesign_kept = not worse
    within = f"{settings.redesign_tolerance:.0%}"
    state.redesign_reason = (f"the redesign is worse on the drive by more than {within} ({worse}): the first design is delivered"
                             if worse else f"the redesign settled on the drive and is not worse (within {within}): it is delivered")


def _try_design(run: ChainRun) -> None:
    """The design's candidates on the drive; the best one not worse than the proposal is chosen.
    Where none settled, one limit-cycled, and the design held the decoupled motor only to the
    gap-open margins (R6): designed again with the guarantee's margins there, and its candidates run."""
    state = run.state
    if state.design is None:
        return
    runs = _run_candidates(run, state.design, "closed loop")
    chosen = _choose(runs)
    if chosen is None and any(r.verdict == "limit_cycle" for r in runs) and _gap_open_relaxed(run, state.design.proposal):
        state.gap_open_cycled = True
        strict = _propose(run)
        if strict.meets(_design_spec(run)):
            run.say(f"{run.name}: a candidate limit-cycled: the design again with the guarantee's margins on the decoupled motor")
            state.design = _plan_loop(run, strict)
            runs = _run_candidates(run, state.design, "closed loop (gap open at the guarantee's margins)")
            chosen = _choose(runs)
    run.lap("drive_runs")
    state.design_trial = trial = LoopTrial(runs, chosen)
    if trial.chosen is None:
        run.warn("loop_not_settled", "no candidate loop settled on the drive")


def _gap_open_relaxed(run: ChainRun, proposal: ControllerProposal) -> bool:
    """Whether ``proposal``'s set holds a decoupled motor (R6) to less than the guarantee's margins."""
    spec = _design_spec(run)
    relaxed = spec.gap_open_phase_margin < spec.min_phase_margin or spec.gap_open_gain_margin_dB < spec.min_gain_margin_dB
    return relaxed and any(proposal.models.transient or ())


def _fall_back(run: ChainRun) -> None:
    """F1 where no model-based loop can be delivered (and the settings allow it, and the
    identification gave an inertia): one run on the drive, chosen when it stays bounded (not
    stopped, not diverging: a slow loop that does not settle within the experiment is slow, not
    unstable; its margins hold on every model of its set)."""
    state = run.state
    state.fallback_reason = reason = _fallback_reason(state)
    result = run.result
    if not (reason and run.settings.fallback and result.ok and _positive(result.parameters.J_sigma)):
        return
    run.say(f"{run.name}: fallback F1 ({reason})")
    state.fallback = plan = _fallback_plan(run)
    runs = _run_candidates(run, plan, "fallback F1")
    run.lap("fallback")
    state.fallback_trial = LoopTrial(runs, 0 if runs[0].bounded else None)


def _deliver(run: ChainRun) -> None:
    """The delivered controller and its run (F1's where it ran, else the chosen model-based one);
    a warning where that run costs far more than its model predicts."""
    state = run.state
    if state.fallback_trial is not None:
        trial = state.fallback_trial
        if trial.chosen is None:
            run.warn("loop_not_settled", f"the fallback F1 did not settle on the drive either ({trial.runs[0].verdict_text}): "
                                         f"no controller delivered")
            return
        state.delivered, state.delivered_run = state.fallback.proposal, trial.runs[trial.chosen]
    elif state.model_trial is not None and state.model_trial.chosen is not None:
        trial = state.model_trial
        state.delivered, state.delivered_run = _model_based_delivery(run, state.model_plan, trial), trial.runs[trial.chosen]
    else:
        return
    delivered_run, scenario = state.delivered_run, state.last_plan.scenario
    already = "loop_unlike_model" in {w.code for w in run.warnings}  # the measured response said so
    if not already and delivered_run.cost > scenario.model_warn_factor * delivered_run.model_cost:
        run.warn("loop_unlike_model", f"the delivered loop costs {delivered_run.cost / delivered_run.model_cost:.3g} x what "
                                      "the identified model predicts for its gains: the margins guaranteed on the model "
                                      "may not hold on this drive (a torque scale or K_M off? a plant unlike the model?)")


#: The chain, in order (module docstring): each stage reads the run's state and adds its own.
STAGES: tuple[tuple[str, Callable[[ChainRun], None]], ...] = (
    ("hold", _check_hold),
    ("excite", _excite),
    ("identify", _identify_record),
    ("validate", _validate),
    ("guard", _guard_loop),
    ("permit", _permit),
    ("design", _design),
    ("try", _try_design),
    ("measure", _measure),
    ("redesign", _redesign),
    ("fallback", _fall_back),
    ("deliver", _deliver),
)


# --------------------------------------------------------------------------- the chain and its report


def _truth_checks(drive: Any, delivered: ControllerProposal | None, config: sim.DriveConfig, M_star: float) -> dict[str, Any] | None:
    """Simulation only: the true parameters and class, and the delivered loop's margins on the true
    linear model (with the drive's own ``current_loop_damping`` / ``extra_delay`` where its truth
    names them). None for a drive without ``truth()``."""
    if not callable(getattr(drive, "truth", None)):
        return None
    truth = dict(drive.truth())
    params = sim.TwoMassParams.from_dicts({k: truth[k] for k in sim.PARAM_NAMES})
    row = params.truth(config, M_star)[0]
    out: dict[str, Any] = {"parameters": {k: row[k] for k in (*sim.PARAM_NAMES, "C_F", "s_N", "r_osc")},
                           "structure": row["structure"]}
    if delivered is not None:
        plant = linear_plant({k: truth[k] for k in sim.PARAM_NAMES}, config,
                             current_loop_damping=truth.get("current_loop_damping"), extra_delay=int(truth.get("extra_delay", 0)))
        found = margins(plant, delivered.Kp, delivered.Ti, delivered.T_f, delivered.notch)
        out.update(stable=found.stable, phase_margin=found.phase_margin, gain_margin_dB=found.gain_margin_dB, w_c=found.w_c)
    return out


def _open_run(drive: sim.Drive, limits: sim.DriveLimits, identifier: RecordIdentifier, settings: CommissioningConfig,
              writer: ScalarWriter | None, progress: Callable[[str], None] | None, name: str, tag: str | None) -> ChainRun:
    """The run of the chain on ``drive``: its config read, the user's limits with the torque cap,
    the speed limit checked against the encoder's resolution, every call guarded."""
    if not isinstance(limits, sim.DriveLimits):
        raise TypeError(f"limits: expected sim.DriveLimits, received {type(limits).__name__}")
    if not callable(getattr(identifier, "identify", None)):
        raise TypeError(f"identifier: expected an object with identify(record), received {type(identifier).__name__}")
    if not isinstance(settings, CommissioningConfig):
        raise TypeError(f"config: expected CommissioningConfig or None, received {type(settings).__name__}")
    config = drive_config(drive)
    limits = limits.for_drive(config)
    check_resolution(limits, config)
    return ChainRun(CheckedDrive(drive, config, limits, settings.drive_timeout), identifier, config, limits, settings,
                    progress or (lambda msg: None), writer, name, tag or name)


def commission(
    drive: sim.Drive,
    limits: sim.DriveLimits,
    *,
    identifier: RecordIdentifier,
    config: CommissioningConfig | None = None,
    writer: ScalarWriter | None = None,
    progress: Callable[[str], None] | None = None,
    name: str = "plant",
    tag: str | None = None,
) -> CommissioningReport:
    """Run the whole chain on one drive (:data:`STAGES`, in order).

    Args:
        drive: a drive of docs/contract.md section 4 (:class:`sim.Drive`: ``config`` with ``T_s``,
            ``K_M``, ``T_Ei``, ``encoder_counts``, ``M_N``, ``M_max``; ``run_test(M_star, w_max,
            limits)`` and ``run_closed_loop(law, scenario, limits)``, each returning a
            :class:`sim.Record`), e.g. :class:`sim.SimulatedDrive`.
        limits: the user's limits (:class:`sim.DriveLimits`), handed to every experiment.
        identifier: ``identify(record)`` returning an identification result
            (:class:`RecordIdentifier`, e.g. ``training.Identifier``); an error it raises
            (ValueError, RuntimeError) is rule V1.
        config: the chain's settings (:class:`CommissioningConfig`).
        writer: optional TensorBoard ``SummaryWriter``; progress: optional one-line callback.
        name, tag: report name and TensorBoard tag prefix (default: the name).

    Returns :class:`CommissioningReport`. A refusal is a normal outcome (the report says why); so
    is a record that shows one of the user's limits passed: the experiments end there, nothing is
    delivered and the report's ``breach`` says which limit, by how much, in which experiment. The
    drive is handed ``limits`` with ``M_max`` the torque cap (:meth:`sim.DriveLimits.for_drive`),
    or less where a run needs headroom. A drive that breaks the interface (a call that raises or
    passes ``config.drive_timeout``, a malformed record, one that contradicts the drive's config,
    a closed-loop record cut short) raises :class:`training.errors.CommissioningError`.
    """
    settings = CommissioningConfig() if config is None else config
    run = _open_run(drive, limits, identifier, settings, writer, progress, name, tag)
    try:
        for _, stage in STAGES:
            stage(run)
    except LimitPassed:
        if run.drive.breach is None:  # not one of ours: the drive raised it
            raise
        excitation, M_star = _excitation_so_far(run)
        return _report(run, excitation, M_star)
    return _report(run, run.excitation, float(run.excitation.log[-1]["M_star"]))


def _excitation_so_far(run: ChainRun) -> tuple[ExcitationResult, float]:
    """For a chain that a record ended at a passed limit: the excitation (where a test run passed
    it: the adaptation's log so far and that run, whose entry says so) and the last test run's
    ``M_star``."""
    breach = run.drive.breach
    tests = [(rec, req) for (kind, rec), req in zip(run.drive.experiments, run.drive.requests) if kind == "test"]
    excitation = run.state.excitation
    if excitation is None:
        rec, req = tests[-1]
        entry = {"iteration": len(run.test_log), "M_star": req["M_star"], "w_max": req["w_max"], "stop_at": req["stop_at"],
                 **measure_response(rec, run.config), "decision": "stop", "reason": breach.text()}
        kept = [r for r, _ in tests if not r.meta.get("aborted", False)]
        excitation = ExcitationResult(record=kept[-1] if kept else rec, records=[r for r, _ in tests], log=[*run.test_log, entry],
                                      informative=False, reason=breach.text(), code="limit_passed")
    return excitation, float(tests[-1][1]["M_star"])


def _report(run: ChainRun, excitation: ExcitationResult, M_star: float) -> CommissioningReport:
    """The report of the run: what its stages produced (a chain stopped at a passed limit: up to
    there, nothing delivered), every experiment's limit check, the simulation-only truth."""
    state, plan = run.state, run.state.last_plan
    prediction = plan.prediction if plan is not None else None
    if prediction and run.loop_limits is not None:
        prediction = {**prediction, "stop_at": run.loop_limits.w_max}
    design, trial = state.design, state.design_trial
    checks = limit_checks(run.drive.experiments, run.limits, run.config)
    run.timings["total"] = run.elapsed()
    return CommissioningReport(
        config=run.config, limits=run.limits, excitation=excitation, identification=state.identification,
        validation=state.validation, permission=state.permission, warnings=tuple(run.warnings),
        max_map_distance_ratio=run.settings.max_map_distance_ratio, outside_training=state.outside_training,
        proposal=None if design is None else design.proposal, tuning=None if design is None else design.tuning,
        fallback=None if state.fallback is None else state.fallback.proposal, fallback_reason=state.fallback_reason,
        runs=[] if trial is None else trial.runs, fallback_runs=[] if state.fallback_trial is None else state.fallback_trial.runs,
        delivered=state.delivered, delivered_run=state.delivered_run, scenario=None if plan is None else plan.scenario,
        prediction=prediction or {}, checks=checks, truth=_truth_checks(run.drive.drive, state.delivered, run.config, M_star),
        timings=run.timings, name=run.name, breach=run.drive.breach, measured=state.measured,
        redesign=None if state.redesign is None else state.redesign.proposal,
        redesign_runs=[] if state.redesign_trial is None else state.redesign_trial.runs, redesign_kept=state.redesign_kept,
        redesign_reason=state.redesign_reason, load_peak_dB=_load_peak(state.delivered), limited_by=_limited_by(state),
        rest=state.rest)


def _limited_by(state: ChainState) -> str:
    """Why the delivered loop is below what the identified model allows: the fallback F1 and its
    reason, else what bounds the design's crossover (:attr:`ControllerProposal.limited_by`); empty
    where nothing is delivered."""
    delivered = state.delivered
    if delivered is None:
        return ""
    if state.fallback is not None and delivered is state.fallback.proposal:
        return f"the cautious fallback F1 ({state.fallback_reason}): designed on the class's worst cases, not on the model"
    return delivered.limited_by


def _load_peak(delivered: ControllerProposal | None) -> float | None:
    """The delivered loop's worst reference-to-load-speed peak [dB] over its design set (None: none
    delivered, or not known)."""
    if delivered is None or not math.isfinite(delivered.load_peak_dB):
        return None
    return delivered.load_peak_dB
