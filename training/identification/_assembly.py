"""One record's result, assembled once from the maps' answer, the refinement's and, where the
angle showed a gap the speed hides, that gap: a draft (:class:`Draft`) that starts as the maps'
answer and passes the adjust-or-warn steps of :data:`ADJUSTMENTS` in order, then becomes the
typed :class:`IdentificationResult`.

The steps, in order (each adjusts the draft's answer or adds warnings, never both undone later):

1. :func:`warn_maps`: a map's recall unlike its training data; an oscillation below one quantum;
2. :func:`take_angle_or_refinement`: the angle's gap, else the refinement's answer where it stands
   (:func:`._policy.refinement_stands`; else ``class_undecided``), else the maps' one;
3. :func:`warn_below_quantum`: an elastic answer the refinement found in a stiff-looking record;
4. :func:`check_envelope`: the drive and the identified mechanics against the envelope;
5. :func:`drop_impossible`: values no mechanic can have are not reported;
6. :func:`warn_implausible`: values the record cannot support;
7. :func:`bound_backlash`: a backlash the record cannot show becomes an upper bound;
8. :func:`warn_near_threshold`: a class quantity near a threshold of the class rule;
9. :func:`state_confidence`: with a calibration (SPEC 4.1), the 90 % intervals, the class
   probabilities and the probability that the answer is right; the remarks of
   :data:`._result.NOTE_CODES` become notes, and ``likely_wrong`` warns where that probability is low.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace

from sim import CLASS_THRESHOLDS, gap_width, normalized_backlash, two_mass_derived
from training.identification._analysis import Analysis
from training.identification._confidence import (Calibration, ConfidenceInputs, class_margins, confidence_inputs,
                                                 share_rest, stand_in_points)
from training.identification._envelope import Envelope, Finding, envelope_warnings
from training.identification._limits import (backlash_negligible, backlash_resolution, implausible, impossible,
                                             travel)
from training.identification._policy import (BACKLASH_CLASSES, ClassModel, IdentificationPolicy, MapsAnswer,
                                             class_quantities, load_torque_threshold, refinement_stands, spec_class)
from training.identification._refine import HiddenGap, Refined
from training.identification._result import (NOTE_CODES, IdentificationResult, IdentWarning, Intervals, Parameters,
                                              Quality)

#: The label of the maps' model in a warning where another model's answer stands.
_MAPS_ESTIMATE = " (the maps' estimate)"


@dataclass(frozen=True)
class RecordEvidence:
    """What one record's result is assembled from: its analysis, the maps' answer, the
    refinement's (``None``: not refined), the gap the angle showed (``None``: none), the
    envelope's findings on its drive, and its name (the result's ``record``)."""

    analysis: Analysis
    maps: MapsAnswer
    refined: Refined | None
    drive_findings: Sequence[Finding]
    name: str | None
    gap: HiddenGap | None = None


@dataclass(frozen=True)
class Draft:
    """The answer as the steps leave it: ``structure``, ``parameters``, the ``models`` of which the
    class rule speaks (the answer's first), the ``warnings`` so far, the envelope's ``findings``
    and the backlash's upper bound where the record cannot show one."""

    structure: str
    parameters: Parameters
    models: tuple[ClassModel, ...]
    warnings: tuple[IdentWarning, ...]
    findings: tuple[Finding, ...] = ()
    backlash_bound: float | None = None
    notes: tuple[IdentWarning, ...] = ()
    confidence: ConfidenceInputs | None = None
    intervals: Intervals | None = None
    probabilities: dict[str, float] | None = None
    answer_probability: float | None = None

    def warned(self, *warnings: IdentWarning) -> "Draft":
        return replace(self, warnings=self.warnings + warnings)


@dataclass(frozen=True)
class Judge:
    """What the steps consult besides the record: the drive ``envelope``, the ``policy`` and the
    ``calibration`` of the answers' confidence (``None``: none; the answers carry no intervals)."""

    envelope: Envelope
    policy: IdentificationPolicy
    calibration: Calibration | None = None


#: One adjust-or-warn step over a record's draft.
Step = Callable[[RecordEvidence, Draft, Judge], Draft]


def assemble(evidence: RecordEvidence, judge: Judge) -> IdentificationResult:
    """The result of one record: the maps' answer through :data:`ADJUSTMENTS`."""
    draft = _maps_draft(evidence)
    for step in ADJUSTMENTS:
        draft = step(evidence, draft, judge)
    return IdentificationResult(draft.structure, draft.parameters, _quality(evidence, draft, judge.policy),
                                draft.warnings, evidence.name, draft.intervals, draft.notes, draft.confidence)


def _maps_draft(evidence: RecordEvidence) -> Draft:
    analysis, answer = evidence.analysis, evidence.maps
    maps_model = ClassModel(analysis.fit.J_sigma, answer.V_J, answer.f_e, answer.d, answer.s_N)
    return Draft(answer.structure, maps_parameters(analysis, answer), (maps_model,), tuple(analysis.warnings))


# -- the steps ---------------------------------------------------------------------------------
def warn_maps(evidence: RecordEvidence, draft: Draft, judge: Judge) -> Draft:
    """A map whose recall lies beyond its training 99 % quantile; an elastic maps' answer whose
    oscillation lies below one speed quantum."""
    answer, analysis = evidence.maps, evidence.analysis
    unlike = tuple(IdentWarning("unlike_training_data", f"record unlike the training data of the {name} map "
                                                        f"(distance {answer.distance_ratio[name]:.2f} x its 99 % "
                                                        "quantile)")
                   for name in answer.used if answer.distance_ratio[name] > 1.0)
    draft = draft.warned(*unlike)
    if analysis.osc_quanta < judge.policy.visible_quanta and answer.structure != "stiff":
        draft = draft.warned(_below_quantum(analysis))
    return draft


def take_angle_or_refinement(evidence: RecordEvidence, draft: Draft, judge: Judge) -> Draft:
    """The gap the angle showed decides the answer; else the refinement's answer where it stands
    (warned where its fit is partial or STEP 2's values were replaced), or ``class_undecided``."""
    analysis, answer, gap, refined = evidence.analysis, evidence.maps, evidence.gap, evidence.refined
    maps_model = replace(draft.models[0], label=_MAPS_ESTIMATE)
    if gap is not None:
        structure, parameters = refined_parameters(analysis, gap)
        angle_model = ClassModel(parameters.J_sigma, gap.V_J, gap.f_e, gap.d, gap.s_N)
        return replace(draft, structure=structure, parameters=parameters,
                       models=(angle_model, maps_model)).warned(_from_angle(gap))
    if refined is None:
        return draft
    structure, parameters = refined_parameters(analysis, refined)
    if not refinement_stands(answer.structure, structure, refined, judge.policy):
        return draft.warned(_undecided(answer.structure, structure, refined.evidence, judge.policy))
    refined_model = ClassModel(parameters.J_sigma, refined.V_J, refined.f_e, refined.d, refined.s_N)
    return replace(draft, structure=structure, parameters=parameters,
                   models=(refined_model, maps_model)).warned(*refine_warnings(refined, structure, judge.policy))


def warn_below_quantum(evidence: RecordEvidence, draft: Draft, judge: Judge) -> Draft:
    """An elastic answer where the maps said stiff on an oscillation below one speed quantum."""
    if (draft.structure != "stiff" and evidence.maps.structure == "stiff"
            and evidence.analysis.osc_quanta < judge.policy.visible_quanta):
        return draft.warned(_below_quantum(evidence.analysis))
    return draft


def check_envelope(evidence: RecordEvidence, draft: Draft, judge: Judge) -> Draft:
    """The drive's and the identified mechanics' findings against the envelope, each warned (the
    latter as ``answer_outside_envelope``)."""
    answer_findings = judge.envelope.check(mechanics_quantities(evidence.analysis, draft.parameters))
    return replace(draft, findings=tuple(evidence.drive_findings) + tuple(answer_findings)).warned(
        *envelope_warnings(list(evidence.drive_findings)), *envelope_warnings(list(answer_findings), answer=True))


def drop_impossible(evidence: RecordEvidence, draft: Draft, judge: Judge) -> Draft:
    """Values no mechanic can have are not reported (:func:`._limits.impossible`)."""
    parameters, warnings = impossible(draft.parameters)
    return replace(draft, parameters=parameters).warned(*warnings)


def warn_implausible(evidence: RecordEvidence, draft: Draft, judge: Judge) -> Draft:
    """Values the record cannot support (:func:`._limits.implausible`)."""
    analysis = evidence.analysis
    return draft.warned(*implausible(draft.parameters, T_s=analysis.T_s, T_Ei=analysis.T_Ei,
                                     travel=travel(analysis.fit.speed, analysis.T_s),
                                     J_sigma_one_mass=analysis.fit.J_sigma))


def bound_backlash(evidence: RecordEvidence, draft: Draft, judge: Judge) -> Draft:
    """Where the record cannot show a backlash of the width that matters (:mod:`._limits`): the
    upper bound and a warning; the answer without a width (``None`` instead of 0 or a width the
    class calls negligible), unless its class has a backlash: its width stands, with the warning
    that it is uncertain (of 28 such widths on the drive matrix and 40 envelope drives, 23 came out
    within 30 %)."""
    analysis, parameters = evidence.analysis, draft.parameters
    if parameters.J_sigma is None:
        return draft
    bound = backlash_resolution(analysis.q_w, analysis.drive.q_phi, parameters.J_sigma, analysis.M_star,
                                parameters.V_J)
    shown = parameters.backlash is not None and parameters.backlash >= bound
    if shown or bound <= backlash_negligible(analysis.M_N, analysis.T_Ei, parameters.J_sigma, parameters.C_F):
        return draft
    where = f"in this record (encoder {analysis.encoder_counts} counts, T_s {analysis.T_s:.3g} s)"
    if draft.structure in BACKLASH_CLASSES and parameters.backlash:
        width = parameters.backlash
        return replace(draft, backlash_bound=bound).warned(IdentWarning(
            "backlash_below_resolution", f"the backlash of {width:.3g} rad ({math.degrees(width):.3g} deg) "
                                         f"is narrower than what shows reliably {where}, {bound:.3g} rad "
                                         f"({math.degrees(bound):.3g} deg): its width is uncertain"))
    return replace(draft, parameters=replace(parameters, backlash=None), backlash_bound=bound).warned(IdentWarning(
        "backlash_below_resolution", f"a backlash up to {bound:.3g} rad ({math.degrees(bound):.3g} deg) would not show "
                                     f"{where}: backlash not identified, at most that wide"))


def warn_near_threshold(evidence: RecordEvidence, draft: Draft, judge: Judge) -> Draft:
    """``class_near_threshold`` where the answer's class quantities lie within the policy's
    ``class_margin`` of a threshold of the class rule: there the neighbouring class is about as
    likely (the evaluation scores the class beyond 20 % only)."""
    margin = judge.policy.class_margin
    near: dict[tuple[str, float], str] = {}
    for quantities, label in _threshold_sources(evidence.analysis, draft):
        for name, value in quantities.items():
            for threshold in CLASS_THRESHOLDS[name]:
                if math.isfinite(value) and abs(value - threshold) < margin * threshold:
                    near.setdefault((name, threshold), f"{name} = {value:.3g}{label}")
    return draft.warned(*(IdentWarning("class_near_threshold", f"{what} lies within {margin:.0%} of the class "
                                                               f"threshold {threshold:g}: the neighbouring class is "
                                                               "about as likely")
                          for (name, threshold), what in near.items()))


def state_confidence(evidence: RecordEvidence, draft: Draft, judge: Judge) -> Draft:
    """The answer's confidence inputs (:mod:`._confidence`); with a calibration its intervals, class
    probabilities and answer probability, the uncertainty remarks as notes, and ``likely_wrong``
    where the answer probability lies below the calibration's ``warn_below``."""
    inputs = answer_confidence(evidence, draft)
    calibration, raw = judge.calibration, evidence.maps.probabilities
    if calibration is None:  # the structure map's weights, normalized, the answer's class their largest
        total = sum(max(p, 0.0) for p in raw.values())
        p = max(raw[draft.structure], 0.0) / total if total > 0 else 0.0
        return replace(draft, confidence=inputs, probabilities=share_rest(draft.structure, max(p, 0.25), raw))
    probabilities = calibration.probabilities(inputs, raw)
    p_right = min(calibration.answer_probability(inputs), probabilities[draft.structure])  # right needs the class
    notes = tuple(w for w in draft.warnings if w.code in NOTE_CODES)
    warnings = tuple(w for w in draft.warnings if w.code not in NOTE_CODES)
    if p_right < calibration.warn_below:
        why = "; ".join(w.text for w in notes[:2])
        warnings += (IdentWarning("likely_wrong", f"this answer is wrong with probability {1.0 - p_right:.1%} (answers "
                                                  f"are warned from {1.0 - calibration.warn_below:.1%}): check it, or "
                                                  "test again with a larger M* or a finer encoder"
                                                  + (f" ({why})" if why else "")),)
    intervals = calibration.intervals(inputs)
    if not draft.parameters.M_L0:  # not detected: as wide as the detection's threshold at least
        floor = load_torque_threshold(evidence.analysis, judge.policy)
        intervals = replace(intervals, M_L0=(min(intervals.M_L0[0], -floor), max(intervals.M_L0[1], floor)))
    return replace(draft, warnings=warnings, notes=notes, confidence=inputs, intervals=intervals,
                   probabilities=probabilities, answer_probability=p_right)


def answer_confidence(evidence: RecordEvidence, draft: Draft) -> ConfidenceInputs:
    """The :class:`._confidence.ConfidenceInputs` of the draft's answer."""
    analysis, answer, refined = evidence.analysis, evidence.maps, evidence.refined
    fit = analysis.fit
    points = stand_in_points(draft.parameters, (answer.f_e, answer.V_J, answer.d), fit.J_sigma, (fit.M_FC, fit.mu_F))
    maps_quantities = class_quantities(analysis, fit.J_sigma, answer.V_J, answer.f_e, answer.d, answer.s_N)
    return confidence_inputs(
        analysis, draft.structure, draft.parameters, points, maps_structure=answer.structure,
        maps_probabilities=answer.probabilities,
        map_distance=max((answer.distance_ratio[n] for n in answer.used), default=1.0),
        margins=(class_margins(_threshold_sources(analysis, draft)[0][0]), class_margins(maps_quantities)),
        maps_elastic=(answer.f_e, answer.V_J, answer.d),
        refine=None if refined is None else (refined.residual, refined.evidence, refined.start_residual),
        backlash_bound=draft.backlash_bound,
        remarks=[w.code for w in draft.warnings])


#: The adjust-or-warn steps, in the order they run over a record's draft.
ADJUSTMENTS: tuple[Step, ...] = (warn_maps, take_angle_or_refinement, warn_below_quantum, check_envelope,
                                 drop_impossible, warn_implausible, bound_backlash, warn_near_threshold,
                                 state_confidence)


# -- the answers' parameters -------------------------------------------------------------------
def maps_parameters(analysis: Analysis, answer: MapsAnswer) -> Parameters:
    """The maps' elastic parameters (none for ``stiff``) on STEP 2's one-mass values."""
    fit = analysis.fit
    one_mass = dict(J_sigma=fit.J_sigma, M_FC=max(fit.M_FC, 0.0), mu_F=max(fit.mu_F, 0.0), M_L0=analysis.M_L0,
                    backlash=0.0)
    if answer.structure == "stiff":
        return Parameters(**one_mass)
    derived = two_mass_derived(fit.J_sigma, answer.V_J, answer.f_e, answer.d)
    if answer.structure in BACKLASH_CLASSES:  # s_N = s C_F / M_N, backlash = 2 s
        one_mass["backlash"] = gap_width(answer.s_N_backlash, analysis.M_N, derived.C_F)
    return Parameters(**one_mass, f_e=answer.f_e, V_J=answer.V_J, d=answer.d, J_M=derived.J_M, J_L=derived.J_L,
                      C_F=derived.C_F)


def refined_parameters(analysis: Analysis, refined: Refined | HiddenGap) -> tuple[str, Parameters]:
    """The refined elastic parameters and backlash width; the structure follows SPEC's class
    rule on the refined values (the maps' class and estimate stay in ``quality``). A ``stiff``
    result keeps the one-mass answer. ``J_sigma``, ``M_FC``, ``mu_F``: the whole-record fit's
    where STEP 2's was not trusted; ``M_FC``, ``M_FCM``: STEP 2's Coulomb friction split between
    the load and the motor where the refinement split it (``M_FCM`` 0 where it found no motor share);
    ``mu_F``, ``mu_FM``: its viscous friction so split where the restart split it (``mu_FM`` None
    elsewhere: not estimated);
    ``M_L0``: the load torque the refined model carried (the analysis's where none was refined)."""
    fit = analysis.fit
    J_sigma, M_FC, mu_F = ((fit.J_sigma, max(fit.M_FC, 0.0), max(fit.mu_F, 0.0)) if refined.J_sigma is None
                           else (refined.J_sigma, refined.M_FC, refined.mu_F))
    if refined.M_FCM is not None and refined.J_sigma is None:  # the split's load share
        M_FC = refined.M_FC
        mu_F = mu_F if refined.mu_FM is None else refined.mu_F
    derived = two_mass_derived(J_sigma, refined.V_J, refined.f_e, refined.d)
    structure = spec_class(analysis, J_sigma, refined.V_J, refined.f_e, refined.d,
                           normalized_backlash(refined.backlash, analysis.M_N, derived.C_F))
    M_L0 = analysis.M_L0 if refined.M_L0 is None else refined.M_L0
    one_mass = dict(J_sigma=J_sigma, M_FC=M_FC, mu_F=mu_F, M_L0=M_L0, M_FCM=refined.M_FCM or 0.0, mu_FM=refined.mu_FM)
    if structure == "stiff":
        return structure, Parameters(**one_mass, backlash=0.0)
    # the backlash is measured even where the class calls it negligible (elastic)
    return structure, Parameters(**one_mass, f_e=refined.f_e, V_J=refined.V_J, d=refined.d, J_M=derived.J_M,
                                 J_L=derived.J_L, C_F=derived.C_F, backlash=refined.backlash)


# -- what the envelope checks ------------------------------------------------------------------
def drive_quantities(analysis: Analysis) -> dict[str, float | None]:
    """The record's drive and test values the envelope (:mod:`training.identification._envelope`) checks."""
    drive = analysis.drive
    from_record = drive.sources["M_N"] == "record"
    return {"T_s": drive.T_s, "encoder_counts": float(drive.encoder_counts), "T_Ei": drive.T_Ei,
            "M_N": drive.M_N if from_record else None,
            "M_max_over_M_N": drive.M_max / drive.M_N if drive.M_max is not None and from_record else None,
            "M_star_over_M_max": drive.M_star / drive.M_max if drive.M_max is not None else None,
            "time_scale": drive.time_scale(analysis.fit.J_sigma), "current_noise": drive.current_noise / drive.M_star}


def mechanics_quantities(analysis: Analysis, parameters: Parameters) -> dict[str, float | None]:
    """The identified mechanics the envelope checks (``d``, the least certain, with a slack:
    :meth:`._envelope.EnvelopeTolerances.slack`)."""
    s_N = (normalized_backlash(parameters.backlash, analysis.M_N, parameters.C_F)
           if parameters.backlash is not None and parameters.C_F is not None else None)
    return {"f_e": parameters.f_e, "V_J": parameters.V_J, "d": parameters.d, "s_N": s_N,
            "M_FC_over_M_star": None if parameters.M_FC is None else parameters.M_FC / analysis.M_star}


# -- the pieces of the steps -------------------------------------------------------------------
def _threshold_sources(analysis: Analysis, draft: Draft) -> list[tuple[dict[str, float], str]]:
    """The class quantities to check near a threshold, each with its label: the final parameters'
    where they are elastic; else those of each of the draft's models (a ``stiff`` answer's own
    model, and the maps' estimate where the refinement's stands; a record that shows little leaves
    both uncertain)."""
    p = draft.parameters
    if p.f_e is not None and p.V_J is not None and p.d is not None and p.J_sigma is not None:
        bounded = p.backlash is None or p.C_F is None  # a backlash bounded, not measured: its s_N unknown
        s_N = 0.0 if bounded else normalized_backlash(p.backlash, analysis.M_N, p.C_F)
        quantities = class_quantities(analysis, p.J_sigma, p.V_J, p.f_e, p.d, s_N)
        if bounded:
            del quantities["s_N"]
        return [(quantities, "")]
    return [(class_quantities(analysis, model.J_sigma, model.V_J, model.f_e, model.d, model.s_N), model.label)
            for model in draft.models]


def refine_warnings(refined: Refined, structure: str, policy: IdentificationPolicy) -> list[IdentWarning]:
    """Where the refinement's answer stands: STEP 2's values replaced; a partial fit of an elastic answer."""
    out = []
    if refined.J_sigma is not None:
        out.append(IdentWarning("one_mass_fit_replaced", "J_sigma, M_FC and mu_F from the two-mass fit of the whole "
                                                         "record (the one-mass fit of STEP 2 was not trusted)"))
    if refined.residual > policy.partial_fit_residual and structure != "stiff":
        out.append(IdentWarning("refine_partial_fit", f"the refined model reproduces only part of the measured "
                                                      f"oscillation (residual {refined.residual:.2f} of its rms)"))
    return out


def _undecided(maps: str, refined: str, evidence: float, policy: IdentificationPolicy) -> IdentWarning:
    return IdentWarning("class_undecided", f"the record does not decide between {maps} (the maps' answer, kept) and "
                                           f"{refined} (the refinement's: the evidence of its better fit is "
                                           f"{evidence:.3g}, below {policy.class_evidence:g})")


def _from_angle(gap: HiddenGap) -> IdentWarning:
    return IdentWarning("backlash_from_angle", f"the backlash shows in the motor's angle (its angle error is "
                                               f"{gap.angle_ratio:.2f} x that of the best model without a gap), not "
                                               "in the fit of its speed: structure and width rest on the angle")


def _below_quantum(analysis: Analysis) -> IdentWarning:
    return IdentWarning("oscillation_below_quantum", f"oscillation only {analysis.osc_quanta:.2f} speed quanta "
                                                     "rms: elastic parameters uncertain")


def _quality(evidence: RecordEvidence, draft: Draft, policy: IdentificationPolicy) -> Quality:
    """The result's quality figures (the refinement's and the angle's only where they ran; the mode
    a stiff answer's record shows only where it shows one)."""
    analysis, answer, refined, gap = evidence.analysis, evidence.maps, evidence.refined, evidence.gap
    refinement = ({} if refined is None else dict(maps_structure=answer.structure, refine_residual=refined.residual,
                                                  refine_start_residual=refined.start_residual,
                                                  refined_s_N=refined.s_N))
    angle = {} if gap is None else dict(angle_ratio=gap.angle_ratio)  # only refined records are checked in the angle
    return Quality(
        structure_probabilities=draft.probabilities if draft.probabilities is not None else answer.probabilities,
        map_distance_ratio=answer.distance_ratio,
        osc_quanta=analysis.osc_quanta, oscillation_fit_r2=analysis.feature("r2_fit"),
        one_mass_rel_residual=analysis.fit.rel_residual,
        outside_training=answer.outside_training or any("trained" in f.outside for f in evidence.drive_findings),
        section_flags=analysis.section_flags,
        maps_estimate={"f_e": answer.f_e, "V_J": answer.V_J, "d": answer.d, "s_N": answer.s_N},
        outside_envelope={f.quantity: f.to_dict() for f in draft.findings}, backlash_upper_bound=draft.backlash_bound,
        answer_probability=draft.answer_probability, **refinement, **angle,
        **_stiff_mode(analysis, draft.structure, policy))


def _stiff_mode(analysis: Analysis, structure: str, policy: IdentificationPolicy) -> dict[str, float | str]:
    """A stiff answer whose record still shows a mode (the oscillation fit explains at least
    ``policy.mode_fit_r2`` of ``w_osc``): that mode, and why the class rule leaves it out: above the
    current loop's bandwidth (``w T_Ei >= 1``: the speed loop cannot act on it), else too small for
    the encoder to resolve its elastic values."""
    if structure not in ("stiff", "stiff_backlash") or analysis.feature("r2_fit") < policy.mode_fit_r2:
        return {}
    f_mode = 10.0 ** analysis.feature("log10_f_fit")
    if 2.0 * math.pi * f_mode * analysis.T_Ei >= CLASS_THRESHOLDS["w_e_T_Ei"][0]:
        why = "above the current loop's bandwidth: the speed loop cannot act on it"
    else:
        why = (f"only {analysis.osc_quanta:.2g} speed quanta rms: too small for the encoder to resolve "
               "its elastic values")
    return {"stiff_mode_Hz": f_mode, "stiff_mode_note": f"a mode near {f_mode:.3g} Hz, {why}"}
