"""Identification of a record with the shipped maps (SPEC sections 4 and 9).

An app needs three lines::

    from training import Identifier
    ident = Identifier.load()                   # shipped maps, checked against the manifest
    result = ident.identify_file("run.csv")     # or ident.identify(record) / identify_records([...])

Each record gets one :class:`IdentificationResult` (``structure``, ``parameters``, ``quality``,
coded ``warnings``; ``to_dict()`` is the JSON object of SPEC 9), or an
:class:`IdentificationFailure` with the one-line reason, built once after the maps' recall and
the refinement.
"""

from __future__ import annotations

import math
import os
from collections.abc import Callable, Iterable, Iterator, Sequence
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

import som_torch as st
from sim import (CLASS_THRESHOLDS, STRUCTURE_CLASSES, Record, class_index, gap_width, normalized_backlash,
                 two_mass_derived)
from training.config import blas_threads, checkpoints_folder
from training.errors import one_line
from training.identification._analysis import FEATURE_NAMES, Analysis, analyze
from training.identification._batch import analysis_outcome, answered_files
from training.identification._envelope import Envelope, Finding, envelope_warnings, trained_envelope
from training.identification._limits import (backlash_negligible, backlash_resolution, implausible, impossible,
                                             speed_resolution, travel)
from training.identification._maps import (CHECKPOINT_FILES, MAP_SPECS, TrainedMap, from_correction, load_map,
                                            recall_targets)
from training.identification._refine import (HiddenGap, RefineConfig, RefineProblem, Refined, find_hidden_gap,
                                             refine, torque_reference)
from training.identification._result import (IdentificationFailure, IdentificationResult, IdentWarning, Outcome,
                                             Parameters, Quality)

_BACKLASH_CLASSES = ("elastic_backlash", "stiff_backlash")
#: Relative distance to a class threshold within which an answer gets ``class_near_threshold``.
CLASS_MARGIN = 0.25
#: The structure map's probability of ``stiff`` below which a stiff answer is refined too.
STIFF_SURE = 0.6
#: The refinement's :attr:`Refined.evidence` below which its class does not replace the maps' one.
CLASS_EVIDENCE = 15.0


@dataclass(frozen=True)
class _MapsAnswer:
    """What the maps say about one record, before the refinement: the structure and its
    probabilities, ``f_e`` [Hz], ``V_J``, ``d``, the structure map's and the backlash map's
    ``s_N`` (on the record's own ``M_N``: :func:`_s_N`), and each map's recall
    distance over its training 99 % quantile."""

    structure: str
    probabilities: dict[str, float]
    f_e: float
    V_J: float
    d: float
    s_N: float
    s_N_backlash: float
    distance_ratio: dict[str, float]

    @property
    def used(self) -> tuple[str, ...]:
        """The maps whose recall this answer rests on."""
        return (("structure",) + (("f_e", "V_J") if self.structure != "stiff" else ())
                + (("backlash",) if self.structure in _BACKLASH_CLASSES else ()))

    @property
    def outside_training(self) -> bool:
        return any(self.distance_ratio[n] > 1.0 for n in self.used)


class Identifier:
    """Trained maps, loaded once; identifies records (one at a time or many in one batch).

    ``refine``: the model-based refinement of the maps' answer (:mod:`training.identification._refine`); ``None``
    gives the maps' answer alone (the paper's method). ``envelope``: the drive envelope and what
    the maps were trained on (:mod:`training.identification._envelope`; default: from the maps'
    metadata). The work runs with one BLAS thread (:func:`training.config.blas_threads`) whoever
    calls it.

    Every drive value comes from the record (:mod:`training.identification._drive`), never from
    the maps: the maps' features and targets are dimensionless (the maps' normalized backlash
    ``s* = s C_F / M*`` is turned into the record's ``s_N = s C_F / M_N`` by the record's own ``M*``
    and ``M_N``)."""

    def __init__(self, maps: dict[str, TrainedMap], refine: RefineConfig | None = RefineConfig(),
                 envelope: Envelope | None = None) -> None:
        missing = [n for n in MAP_SPECS if n not in maps]
        if missing:
            raise ValueError(f"Identifier: maps missing: {missing}; expected {list(MAP_SPECS)}")
        if refine is not None and not isinstance(refine, RefineConfig):
            raise TypeError(f"refine: expected a RefineConfig or None, received {type(refine).__name__}")
        self.maps = maps
        self.refine = refine
        self.envelope = envelope if envelope is not None else trained_envelope(maps["structure"].metadata)

    @classmethod
    def load(cls, folder: str | os.PathLike[str] | None = None, *,
             refine: RefineConfig | None = RefineConfig()) -> "Identifier":
        """Load every map of ``folder`` (default: :func:`training.config.checkpoints_folder`, the
        shipped maps unless ``$TWOMASS_CHECKPOINTS`` names others) after checking the manifest's
        SHA-256 of each file; the manifest must list every file read (:data:`CHECKPOINT_FILES`)."""
        folder = Path(folder) if folder is not None else checkpoints_folder()
        st.verify_manifest(folder, required=CHECKPOINT_FILES)
        maps = {name: load_map(folder / f"{name}.pt") for name in MAP_SPECS}
        return cls(maps, refine, Envelope.load(folder))

    # -- public entries ---------------------------------------------------------------------
    def identify(self, record: Record) -> IdentificationResult:
        """Identify one record.

        Raises:
            IdentificationError: one line, when the record cannot be analysed.
        """
        with blas_threads():
            return self._identify_batch([analyze(record)], [None])[0]

    def identify_records(self, records: Sequence[Record]) -> list[Outcome]:
        """One outcome per record, in order; a record that cannot be analysed or recalled gets an
        :class:`IdentificationFailure` with the reason."""
        with blas_threads():
            return self._recall_isolated([analysis_outcome(r) for r in records], [None] * len(records))

    def identify_file(self, path: str | os.PathLike[str]) -> Outcome:
        """Read and identify one record file (``record`` = the path as given)."""
        return self.identify_files([path])[0]

    def identify_files(self, paths: Iterable[str | os.PathLike[str]], *, jobs: int | None = 1,
                       progress: Callable[[int], object] | None = None) -> list[Outcome]:
        """:meth:`iter_files` as a list."""
        return list(self.iter_files(paths, jobs=jobs, progress=progress))

    def iter_files(self, paths: Iterable[str | os.PathLike[str]], *, jobs: int | None = 1,
                   progress: Callable[[int], object] | None = None) -> Iterator[Outcome]:
        """One outcome per path, in the order given (``record`` = the path as given), as they are
        done: records are read and analysed, then recalled and refined in batches of
        :data:`CHUNK`; with ``jobs > 1`` whole batches run in ``jobs`` forked worker processes
        (``None``: 1 for fewer than two batches, else one per CPU, at most one per batch), with the
        same outcomes.
        ``progress`` is called with the number of records done as they are.

        A record that cannot be read, analysed or recalled gets an :class:`IdentificationFailure`
        (an unexpected exception is named as such: ``"unexpected TypeError in the analysis: ..."``);
        the others are still answered."""
        if isinstance(paths, (str, bytes, os.PathLike)):  # its characters are no paths
            raise TypeError(f"paths: expected a list of record paths, received one {type(paths).__name__} "
                            "(identify_file(path) answers one)")
        return answered_files([str(p) for p in paths], jobs, self._recall_chunk, progress)

    def identify_analyses(self, analyses: Sequence[Analysis]) -> list[IdentificationResult]:
        """Recall all maps for a batch of analysed records (one tensor computation per map), then
        refine; one result per analysis, in order (an exception ends the whole batch)."""
        with blas_threads():
            return self._identify_batch(analyses, [None] * len(analyses))

    # -- batches with per-record isolation ----------------------------------------------------
    def _recall_chunk(self, chunk: list[tuple[str, Analysis | IdentificationFailure]]) -> list[Outcome]:
        with blas_threads():
            return self._recall_isolated([item for _, item in chunk], [name for name, _ in chunk])

    def _recall_isolated(self, items: Sequence[Analysis | IdentificationFailure],
                         names: Sequence[str | None]) -> list[Outcome]:
        """Outcomes of ``items`` in order (``names``: their ``record``): the failures as they are,
        the analyses recalled in one batch; when the batch fails, each alone, so that a failing
        record costs only its own answer."""
        todo = [i for i, item in enumerate(items) if isinstance(item, Analysis)]
        try:
            done: list[Outcome] = list(self._identify_batch([items[i] for i in todo], [names[i] for i in todo]))
        except Exception:  # noqa: BLE001 - isolate the record that breaks the batch
            done = [self._recall_one(items[i], names[i]) for i in todo]
        answered = dict(zip(todo, done))
        return [answered[i] if isinstance(item, Analysis) else item for i, item in enumerate(items)]

    def _recall_one(self, a: Analysis, name: str | None) -> Outcome:
        try:
            return self._identify_batch([a], [name])[0]
        except ValueError as err:
            return IdentificationFailure(f"recall failed: {one_line(err)}", name)
        except Exception as err:  # noqa: BLE001 - a bug must not cost the other records their answer
            return IdentificationFailure(f"unexpected {type(err).__name__} in the recall: {one_line(err)}", name)

    # -- the identification of a batch ------------------------------------------------------------
    def _identify_batch(self, analyses: Sequence[Analysis], names: Sequence[str | None]) -> list[IdentificationResult]:
        if not analyses:
            return []
        answers = self._recall(analyses)
        drive_findings = [self.envelope.check(_drive_quantities(a)) for a in analyses]
        refined: list[Refined | None] = [None] * len(analyses)
        problems: dict[int, RefineProblem] = {}  # the refined records' problems, by index
        if self.refine is not None:
            # stiff answers are refined too where the oscillation shows above the quantization
            # (near the w_e T_Ei = 1 threshold the maps' f_e decides the class), where the drive
            # lies outside the maps' training (their stiff verdict is then unproven), where the
            # drive's speed could hide a backlash from the features (the replay still sees
            # the gap crossings), and where the structure map itself is unsure of stiff
            todo = [i for i, (a, m, f) in enumerate(zip(analyses, answers, drive_findings))
                    if m.structure != "stiff" or a.osc_quanta >= 1.0 or f or _hides_backlash(a)
                    or m.probabilities["stiff"] < STIFF_SURE]
            problems = {i: self._problem(analyses[i], answers[i]) for i in todo}
            for i, r in zip(problems, refine(list(problems.values()), self.refine)):
                refined[i] = r
        results = [self._result(a, m, r, f, name)
                   for a, m, r, f, name in zip(analyses, answers, refined, drive_findings, names)]
        if self.refine is not None:
            # a stiff answer on a record whose speed could hide a backlash (so it was refined), or
            # whose refinement dropped the maps' gap: the angle may show it
            hidden = [i for i in problems
                      if results[i].structure == "stiff" and not analyses[i].fit.warnings
                      and (_hides_backlash(analyses[i]) or answers[i].structure in _BACKLASH_CLASSES)]
            for i in hidden:
                gap = find_hidden_gap(problems[i], self.refine)
                if gap is not None:
                    results[i] = self._result(analyses[i], answers[i], refined[i], drive_findings[i], names[i], gap)
        return results

    def _recall(self, analyses: Sequence[Analysis]) -> list[_MapsAnswer]:
        """The maps' answer per analysis (one batched recall per map)."""
        F = np.stack([a.features for a in analyses])  # M x F
        recalled = {}
        for name, m in self.maps.items():
            cols = [FEATURE_NAMES.index(f) for f in m.spec.features]
            recalled[name] = recall_targets(m, F[:, cols], int(m.metadata["train_config"]["interpolate"]))
        return [self._maps_answer(a, {n: {k: float(v[i]) for k, v in r.items()} for n, r in recalled.items()})
                for i, a in enumerate(analyses)]

    def _maps_answer(self, a: Analysis, r: dict[str, dict[str, float]]) -> _MapsAnswer:
        # the maps store corrections to the eq.-1 fit (training.identification._maps.TARGETS)
        f_e, V_J = (from_correction(p, lambda k, p=p: r[p][k] if k in r[p] else a.feature(k)) for p in ("f_e", "V_J"))
        d = min(max(r["f_e"]["d"], 0.0), 0.9)
        s_N = _s_N(a, r["structure"]["log10_s_star"])
        probs = {c: r["structure"][f"p_{c}"] for c in STRUCTURE_CLASSES}
        # SPEC's stiff rule on the identified values; otherwise the structure map's most likely other class
        if _spec_class(a, a.fit.J_sigma, V_J, f_e, d, s_N) == "stiff":
            structure = "stiff"
        else:
            structure = max((c for c in STRUCTURE_CLASSES if c != "stiff"), key=probs.get)
        ratio = {}
        for name, m in self.maps.items():  # recall distance over the training 99 % quantile
            q99 = m.metadata["distance_quantiles"]["0.99"]
            ratio[name] = r[name]["distance"] / q99 if q99 > 0 else float("inf")
        return _MapsAnswer(structure, probs, f_e, V_J, d, s_N, _s_N(a, r["backlash"]["log10_s_star"]), ratio)

    def _problem(self, a: Analysis, m: _MapsAnswer) -> RefineProblem:
        """The refinement of one maps' answer: the record's replayed test signal, STEP 2's
        one-mass values, and the maps' ``f_e``, ``V_J``, ``d``, ``s_N`` as the start."""
        b = a.sections.bounds
        start, level = torque_reference(b, a.M_star)
        segments = np.concatenate([b, [[b[5, 1], len(a.fit.speed)]]])  # the six sections and the tail
        segments = segments[segments[:, 1] > segments[:, 0]]  # a record that ends with VI has no tail
        return RefineProblem(speed=a.fit.speed, start=start, level=level, segments=segments, J_sigma=a.fit.J_sigma,
                             M_FC=max(a.fit.M_FC, 0.0), mu_F=max(a.fit.mu_F, 0.0), T_s=a.T_s, T_Ei=a.T_Ei,
                             encoder_counts=a.encoder_counts, M_N=a.M_N, free_one_mass=bool(a.fit.warnings),
                             theta=np.array([math.log10(m.f_e), math.log10(m.V_J), m.d,
                                             math.log10(max(m.s_N, 1e-3))]))

    # -- the result, assembled once ---------------------------------------------------------------
    def _result(self, a: Analysis, m: _MapsAnswer, r: Refined | None, drive_findings: list[Finding],
                name: str | None, gap: HiddenGap | None = None) -> IdentificationResult:
        """The result of one record from the maps' answer ``m``, the refinement's ``r`` and, where
        the angle showed a gap the speed hides, that ``gap`` (it decides the answer)."""
        warnings = list(a.warnings) + self._maps_warnings(a, m)
        structure, parameters = m.structure, self._maps_parameters(a, m)
        maps_model = (a.fit.J_sigma, m.V_J, m.f_e, m.d, m.s_N)  # of which the class rule speaks
        models = [(maps_model, "")]
        if gap is not None:
            structure, parameters = self._refined_parameters(a, gap)
            angle_model = (parameters.J_sigma, gap.V_J, gap.f_e, gap.d, gap.s_N)
            models = [(angle_model, ""), (maps_model, " (the maps' estimate)")]
            warnings.append(_from_angle(gap))
        elif r is not None:
            refined_structure, refined_parameters = self._refined_parameters(a, r)
            if refined_structure == m.structure or r.evidence >= CLASS_EVIDENCE or r.J_sigma is not None:
                structure, parameters = refined_structure, refined_parameters
                refined_model = (refined_parameters.J_sigma, r.V_J, r.f_e, r.d, r.s_N)
                models = [(refined_model, ""), (maps_model, " (the maps' estimate)")]
                warnings += _refine_warnings(r, structure)
            else:
                warnings.append(_undecided(m.structure, refined_structure, r.evidence))
        if structure != "stiff" and m.structure == "stiff" and a.osc_quanta < 1.0:
            warnings.append(_below_quantum(a))
        findings = drive_findings + self.envelope.check(_mechanics_quantities(a, parameters))
        warnings += envelope_warnings(findings)
        parameters, impossible_warnings = impossible(parameters)
        warnings += impossible_warnings + implausible(parameters, T_s=a.T_s, T_Ei=a.T_Ei, travel=travel(a.fit.speed, a.T_s),
                                                      J_sigma_one_mass=a.fit.J_sigma)
        parameters, bound, bound_warnings = _backlash_bound(a, parameters, structure)
        warnings += bound_warnings + _near_threshold(a, models, parameters)
        quality = Quality(
            structure_probabilities=m.probabilities, map_distance_ratio=m.distance_ratio, osc_quanta=a.osc_quanta,
            oscillation_fit_r2=a.feature("r2_fit"), one_mass_rel_residual=a.fit.rel_residual,
            outside_training=m.outside_training or any("trained" in f.outside for f in drive_findings),
            section_flags=a.section_flags, maps_estimate={"f_e": m.f_e, "V_J": m.V_J, "d": m.d, "s_N": m.s_N},
            outside_envelope={f.quantity: f.to_dict() for f in findings}, backlash_upper_bound=bound,
            **({} if r is None else dict(maps_structure=m.structure, refine_residual=r.residual,
                                         refine_start_residual=r.start_residual, refined_s_N=r.s_N)),
            **({} if gap is None else dict(angle_ratio=gap.angle_ratio)))  # only refined records are checked in the angle
        return IdentificationResult(structure, parameters, quality, tuple(warnings), name)

    def _maps_parameters(self, a: Analysis, m: _MapsAnswer) -> Parameters:
        """The maps' elastic parameters (none for ``stiff``) on STEP 2's one-mass values."""
        fit = a.fit
        one_mass = dict(J_sigma=fit.J_sigma, M_FC=max(fit.M_FC, 0.0), mu_F=max(fit.mu_F, 0.0), backlash=0.0)
        if m.structure == "stiff":
            return Parameters(**one_mass)
        dv = two_mass_derived(fit.J_sigma, m.V_J, m.f_e, m.d)
        if m.structure in _BACKLASH_CLASSES:  # s_N = s C_F / M_N, backlash = 2 s
            one_mass["backlash"] = gap_width(m.s_N_backlash, a.M_N, dv.C_F)
        return Parameters(**one_mass, f_e=m.f_e, V_J=m.V_J, d=m.d, J_M=dv.J_M, J_L=dv.J_L, C_F=dv.C_F)

    def _refined_parameters(self, a: Analysis, r: Refined | HiddenGap) -> tuple[str, Parameters]:
        """The refined elastic parameters and backlash width; the structure follows SPEC's class
        rule on the refined values (the maps' class and estimate stay in ``quality``). A ``stiff``
        result keeps the one-mass answer. ``J_sigma``, ``M_FC``, ``mu_F``: the whole-record fit's
        where STEP 2's was not trusted."""
        fit = a.fit
        J_sigma, M_FC, mu_F = ((fit.J_sigma, max(fit.M_FC, 0.0), max(fit.mu_F, 0.0)) if r.J_sigma is None
                               else (r.J_sigma, r.M_FC, r.mu_F))
        dv = two_mass_derived(J_sigma, r.V_J, r.f_e, r.d)
        structure = _spec_class(a, J_sigma, r.V_J, r.f_e, r.d, normalized_backlash(r.backlash, a.M_N, dv.C_F))
        one_mass = dict(J_sigma=J_sigma, M_FC=M_FC, mu_F=mu_F)
        if structure == "stiff":
            return structure, Parameters(**one_mass, backlash=0.0)
        # the backlash is measured even where the class calls it negligible (elastic)
        return structure, Parameters(**one_mass, f_e=r.f_e, V_J=r.V_J, d=r.d, J_M=dv.J_M, J_L=dv.J_L, C_F=dv.C_F,
                                     backlash=r.backlash)

    @staticmethod
    def _maps_warnings(a: Analysis, m: _MapsAnswer) -> list[IdentWarning]:
        out = [IdentWarning("unlike_training_data", f"record unlike the training data of the {name} map "
                                                    f"(distance {m.distance_ratio[name]:.2f} x its 99 % quantile)")
               for name in m.used if m.distance_ratio[name] > 1.0]
        if a.osc_quanta < 1.0 and m.structure != "stiff":
            out.append(_below_quantum(a))
        return out


def _undecided(maps: str, refined: str, evidence: float) -> IdentWarning:
    return IdentWarning("class_undecided", f"the record does not decide between {maps} (the maps' answer, kept) and "
                                           f"{refined} (the refinement's: the evidence of its better fit is "
                                           f"{evidence:.3g}, below {CLASS_EVIDENCE:g})")


def _from_angle(gap: HiddenGap) -> IdentWarning:
    return IdentWarning("backlash_from_angle", f"the backlash shows in the motor's angle (its angle error is "
                                               f"{gap.angle_ratio:.2f} x that of the best model without a gap), not "
                                               "in the fit of its speed: structure and width rest on the angle")


def _below_quantum(a: Analysis) -> IdentWarning:
    return IdentWarning("oscillation_below_quantum", f"oscillation only {a.osc_quanta:.2f} speed quanta "
                                                     "rms: elastic parameters uncertain")


def _s_N(a: Analysis, log10_s_star: float) -> float:
    """The record's ``s_N = s C_F / M_N`` from a map's ``log10_s_star``, ``s* = s C_F / M*`` (the
    gap's torque over the test's torque: what the speed shows), by the record's ``M*`` and ``M_N``."""
    return 10.0 ** log10_s_star * a.M_star / a.M_N


def _hides_backlash(a: Analysis) -> bool:
    """Whether the record's speed could hide a backlash that matters on a stiff shaft
    (:func:`._limits.speed_resolution`, :func:`._limits.backlash_negligible`): the angle may still
    show it."""
    J_sigma = abs(a.fit.J_sigma)
    return speed_resolution(a.q_w, J_sigma, a.M_star) > backlash_negligible(a.M_N, a.T_Ei, J_sigma)


def _drive_quantities(a: Analysis) -> dict[str, float | None]:
    """The record's drive and test values the envelope (:mod:`training.identification._envelope`) checks."""
    d = a.drive
    return {"T_s": d.T_s, "encoder_counts": float(d.encoder_counts), "T_Ei": d.T_Ei,
            "M_N": d.M_N if d.sources["M_N"] == "record" else None,
            "M_max_over_M_N": d.M_max / d.M_N if d.M_max is not None and d.sources["M_N"] == "record" else None,
            "M_star_over_M_max": d.M_star / d.M_max if d.M_max is not None else None,
            "time_scale": d.time_scale(a.fit.J_sigma), "current_noise": d.current_noise / d.M_star}


def _mechanics_quantities(a: Analysis, p: Parameters) -> dict[str, float | None]:
    """The identified mechanics the envelope checks (``d``, the least certain, with a slack:
    :data:`._envelope.SLACK`)."""
    s_N = normalized_backlash(p.backlash, a.M_N, p.C_F) if p.backlash is not None and p.C_F is not None else None
    return {"f_e": p.f_e, "V_J": p.V_J, "d": p.d, "s_N": s_N,
            "M_FC_over_M_star": None if p.M_FC is None else p.M_FC / a.M_star}


def _backlash_bound(a: Analysis, p: Parameters, structure: str) -> tuple[Parameters, float | None, list[IdentWarning]]:
    """Where the record cannot show a backlash of the width that matters (:mod:`._limits`): the
    upper bound and a warning; ``p`` without a width (``None`` instead of 0 or a width the class
    calls negligible), unless ``structure`` has a backlash: its width stands, with the warning that
    it is uncertain (of 28 such widths on the drive matrix and 40 envelope drives, 23 came out
    within 30 %)."""
    if p.J_sigma is None:
        return p, None, []
    bound = backlash_resolution(a.q_w, a.drive.q_phi, p.J_sigma, a.M_star, p.V_J)
    shown = p.backlash is not None and p.backlash >= bound
    if shown or bound <= backlash_negligible(a.M_N, a.T_Ei, p.J_sigma, p.C_F):
        return p, None, []
    where = f"in this record (encoder {a.encoder_counts} counts, T_s {a.T_s:.3g} s)"
    if structure in _BACKLASH_CLASSES and p.backlash:
        return p, bound, [IdentWarning(
            "backlash_below_resolution", f"the backlash of {p.backlash:.3g} rad ({math.degrees(p.backlash):.3g} deg) "
                                         f"is narrower than what shows reliably {where}, {bound:.3g} rad "
                                         f"({math.degrees(bound):.3g} deg): its width is uncertain")]
    return replace(p, backlash=None), bound, [IdentWarning(
        "backlash_below_resolution", f"a backlash up to {bound:.3g} rad ({math.degrees(bound):.3g} deg) would not show "
                                     f"{where}: backlash not identified, at most that wide")]


def _refine_warnings(r: Refined, structure: str) -> list[IdentWarning]:
    out = []
    if r.J_sigma is not None:
        out.append(IdentWarning("one_mass_fit_replaced", "J_sigma, M_FC and mu_F from the two-mass fit of the whole "
                                                         "record (the one-mass fit of STEP 2 was not trusted)"))
    if r.residual > 0.7 and structure != "stiff":
        out.append(IdentWarning("refine_partial_fit", f"the refined model reproduces only part of the measured "
                                                      f"oscillation (residual {r.residual:.2f} of its rms)"))
    return out


def _class_quantities(a: Analysis, J_sigma: float, V_J: float, f_e: float, d: float, s_N: float) -> dict[str, float]:
    """The quantities of SPEC's class rule (:data:`sim.CLASS_THRESHOLDS`) of a two-mass model on the
    record's drive: ``s_N``, ``w_e T_Ei`` and ``r_osc = V_J M* / (J_sigma w_0 q_w)``."""
    dv = two_mass_derived(J_sigma, V_J, f_e, d)
    return {"s_N": s_N, "w_e_T_Ei": dv.w_e * a.T_Ei, "r_osc": V_J * a.M_star / (J_sigma * dv.w_0 * a.q_w)}


def _spec_class(a: Analysis, J_sigma: float, V_J: float, f_e: float, d: float, s_N: float) -> str:
    """SPEC's class (:func:`sim.class_index`) of a two-mass model on the record's drive."""
    return STRUCTURE_CLASSES[int(class_index(**_class_quantities(a, J_sigma, V_J, f_e, d, s_N)))]


def _near_threshold(a: Analysis, models: list[tuple[tuple[float, float, float, float, float], str]],
                    p: Parameters) -> list[IdentWarning]:
    """``class_near_threshold`` where the answer's class quantities lie within :data:`CLASS_MARGIN`
    of a threshold of the class rule: there the neighbouring class is about as likely (the
    evaluation scores the class beyond 20 % only). The quantities: the final parameters' where
    they are elastic; else those of each of ``models`` (``J_sigma, V_J, f_e, d, s_N`` and a label
    for the text: a ``stiff`` answer's own model, and the maps' estimate where the refinement's
    stands; a record that shows little leaves both uncertain)."""
    if p.f_e is not None and p.V_J is not None and p.d is not None and p.J_sigma is not None:
        bounded = p.backlash is None or p.C_F is None  # a backlash bounded, not measured: its s_N unknown
        s_N = 0.0 if bounded else normalized_backlash(p.backlash, a.M_N, p.C_F)
        q = _class_quantities(a, p.J_sigma, p.V_J, p.f_e, p.d, s_N)
        if bounded:
            del q["s_N"]
        sources = [(q, "")]
    else:
        sources = [(_class_quantities(a, *model), label) for model, label in models]
    near: dict[tuple[str, float], str] = {}
    for q, label in sources:
        for name, v in q.items():
            for thr in CLASS_THRESHOLDS[name]:
                if math.isfinite(v) and abs(v - thr) < CLASS_MARGIN * thr:
                    near.setdefault((name, thr), f"{name} = {v:.3g}{label}")
    return [IdentWarning("class_near_threshold", f"{what} lies within {CLASS_MARGIN:.0%} of the class threshold "
                                                 f"{thr:g}: the neighbouring class is about as likely")
            for (name, thr), what in near.items()]
