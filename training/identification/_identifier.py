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
from sim import STRUCTURE_CLASSES, Record
from training.config import blas_threads, checkpoints_folder
from training.errors import one_line
from training.identification._analysis import Analysis, analyze, feature_columns
from training.identification._assembly import Judge, RecordEvidence, assemble, drive_quantities
from training.identification._confidence import FILE_NAME as CONFIDENCE_FILE
from training.identification._confidence import Calibration, check_calibrated_for
from training.identification._batch import ReadRecord, analysis_outcome, answered_files
from training.identification._envelope import Envelope, trained_envelope
from training.identification._maps import (CHECKPOINT_FILES, MAP_SPECS, MapMetadata, TrainedMap, from_correction,
                                            load_map, recall_targets)
from training.identification._policy import (IdentificationPolicy, MapsAnswer, angle_checked_when, held_torque, refined_when,
                                             s_N_on_record, second_f_e_start, spec_class)
from training.identification._refine import (RefineConfig, RefineProblem, Refined, find_hidden_gap, refine,
                                             torque_reference)
from training.identification._result import IdentificationFailure, IdentificationResult, Outcome


@dataclass(frozen=True)
class _Refinement:
    """One record's refinement: its ``problem`` (which the angle's check reuses) and the ``refined`` answer."""

    problem: RefineProblem
    refined: Refined


class Identifier:
    """Trained maps, loaded once; identifies records (one at a time or many in one batch).

    ``refine``: the model-based refinement of the maps' answer (:mod:`training.identification._refine`); ``None``
    gives the maps' answer alone (the paper's method). ``policy``: the thresholds of the
    identifier's own decisions (:class:`IdentificationPolicy`: what is refined, whether the
    refinement's class stands, which warnings fire). ``envelope``: the drive envelope and what
    the maps were trained on (:mod:`training.identification._envelope`; default: from the maps'
    metadata). The work runs with one BLAS thread (:func:`training.config.blas_threads`) whoever
    calls it.

    Every drive value comes from the record (:mod:`training.identification._drive`), never from
    the maps: the maps' features and targets are dimensionless (the maps' normalized backlash
    ``s* = s C_F / M*`` is turned into the record's ``s_N = s C_F / M_N`` by the record's own ``M*``
    and ``M_N``)."""

    def __init__(self, maps: dict[str, TrainedMap], refine: RefineConfig | None = RefineConfig(),
                 envelope: Envelope | None = None, *, policy: IdentificationPolicy = IdentificationPolicy(),
                 calibration: Calibration | None = None) -> None:
        missing = [n for n in MAP_SPECS if n not in maps]
        if missing:
            raise ValueError(f"Identifier: maps missing: {missing}; expected {list(MAP_SPECS)}")
        if refine is not None and not isinstance(refine, RefineConfig):
            raise TypeError(f"refine: expected a RefineConfig or None, received {type(refine).__name__}")
        if not isinstance(policy, IdentificationPolicy):
            raise TypeError(f"policy: expected an IdentificationPolicy, received {type(policy).__name__}")
        if calibration is not None and not isinstance(calibration, Calibration):
            raise TypeError(f"calibration: expected a Calibration or None, received {type(calibration).__name__}")
        self.maps = maps
        self.refine = refine
        self.policy = policy
        #: the answers' confidence calibration (SPEC 4.1; ``None``: answers without intervals)
        self.calibration = calibration
        #: each map's metadata, checked once (:class:`MapMetadata`): what the recall reads of it
        self.map_metadata = {name: MapMetadata.from_dict(trained.metadata, name, trained.som.grid.n_units)
                             for name, trained in maps.items()}
        self.envelope = envelope if envelope is not None else trained_envelope(maps["structure"].metadata)

    @classmethod
    def load(cls, folder: str | os.PathLike[str] | None = None, *,
             refine: RefineConfig | None = RefineConfig(), calibrated: bool = True) -> "Identifier":
        """Load every map of ``folder`` (default: :func:`training.config.checkpoints_folder`, the
        shipped maps unless ``$TWOMASS_CHECKPOINTS`` names others) after checking the manifest's
        SHA-256 of each file; the manifest must list every file read (:data:`CHECKPOINT_FILES`, and
        the confidence calibration ``confidence.json`` where the folder has one: made for these
        maps, else an error). ``calibrated=False``: the maps alone, whatever calibration the folder
        holds (what ``twomass calibrate`` calibrates)."""
        folder = Path(folder) if folder is not None else checkpoints_folder()
        calibrated = calibrated and (folder / CONFIDENCE_FILE).exists()
        digests = st.verify_manifest(folder, required=CHECKPOINT_FILES)
        if calibrated and CONFIDENCE_FILE not in digests:  # e.g. maps trained anew into a calibrated folder
            raise ValueError(f"{folder}: {CONFIDENCE_FILE} is not listed in the manifest (made for earlier maps?): "
                             f"rerun `twomass calibrate --checkpoints {folder} --overwrite`, or remove it")
        maps = {name: load_map(folder / f"{name}.pt") for name in MAP_SPECS}
        calibration = Calibration.load(folder / CONFIDENCE_FILE) if calibrated else None
        if calibration is not None:
            check_calibrated_for(calibration, digests, folder)
        return cls(maps, refine, Envelope.load(folder), calibration=calibration)

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
            return self._recall_isolated([analysis_outcome(record) for record in records], [None] * len(records))

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
        return answered_files([str(p) for p in paths], jobs, self, progress)

    def identify_analyses(self, analyses: Sequence[Analysis]) -> list[IdentificationResult]:
        """Recall all maps for a batch of analysed records (one tensor computation per map), then
        refine; one result per analysis, in order (an exception ends the whole batch)."""
        with blas_threads():
            return self._identify_batch(analyses, [None] * len(analyses))

    def identify_read(self, chunk: Sequence[ReadRecord]) -> list[Outcome]:
        """The outcomes of records already read and analysed (:func:`._batch.file_outcome`), in
        order (``record``: each one's name): the failures as they are, the analyses recalled and
        refined in one batch (each alone when the batch fails). :func:`._batch.answered_files`
        hands it each chunk of files."""
        with blas_threads():
            return self._recall_isolated([item.outcome for item in chunk], [item.name for item in chunk])

    # -- batches with per-record isolation ----------------------------------------------------
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

    def _recall_one(self, analysis: Analysis, name: str | None) -> Outcome:
        try:
            return self._identify_batch([analysis], [name])[0]
        except ValueError as err:
            return IdentificationFailure(f"recall failed: {one_line(err)}", name)
        except Exception as err:  # noqa: BLE001 - a bug must not cost the other records their answer
            return IdentificationFailure(f"unexpected {type(err).__name__} in the recall: {one_line(err)}", name)

    # -- the identification of a batch ------------------------------------------------------------
    def _identify_batch(self, analyses: Sequence[Analysis], names: Sequence[str | None]) -> list[IdentificationResult]:
        """Recall the maps for the batch, refine the answers :func:`._policy.refined_when` names,
        assemble each result (:func:`._assembly.assemble`), then check the stiff results
        :func:`._policy.angle_checked_when` names for a gap in the motor's angle."""
        if not analyses:
            return []
        answers = self._recall(analyses)
        evidence = [RecordEvidence(analysis, answer, None, self.envelope.check(drive_quantities(analysis)), name)
                    for analysis, answer, name in zip(analyses, answers, names)]
        refinements = self._refinements(evidence)
        judge = Judge(self.envelope, self.policy, self.calibration)
        evidence = [replace(record, refined=refinements[i].refined) if i in refinements else record
                    for i, record in enumerate(evidence)]
        results = [assemble(record, judge) for record in evidence]
        checked = [i for i in refinements
                   if angle_checked_when(evidence[i].analysis, evidence[i].maps, results[i].structure)]
        for i in checked:
            gap = find_hidden_gap(refinements[i].problem, self.refine)
            if gap is not None:
                results[i] = assemble(replace(evidence[i], gap=gap), judge)
        return results

    def _refinements(self, evidence: Sequence[RecordEvidence]) -> dict[int, _Refinement]:
        """The refinement of each record it sees (:func:`._policy.refined_when`), by index; none
        without a refinement."""
        if self.refine is None:
            return {}
        todo = [i for i, record in enumerate(evidence)
                if refined_when(record.analysis, record.maps, record.drive_findings, self.policy)]
        problems = [self._problem(evidence[i].analysis, evidence[i].maps) for i in todo]
        return {i: _Refinement(problem.with_friction_of(refined), refined)
                for i, problem, refined in zip(todo, problems, refine(problems, self.refine))}

    def _recall(self, analyses: Sequence[Analysis]) -> list[MapsAnswer]:
        """The maps' answer per analysis (one batched recall per map)."""
        features = np.stack([analysis.features for analysis in analyses])  # M x F
        recalled = {name: recall_targets(trained, features[:, feature_columns(trained.spec.features)],
                                         self.map_metadata[name].interpolate)
                    for name, trained in self.maps.items()}
        f_e_map = self.maps["f_e"]
        if f_e_map.som.local is not None:  # the units' own weights too: the refinement explores around both
            recalled["f_e_flat"] = recall_targets(f_e_map, features[:, feature_columns(f_e_map.spec.features)],
                                                  self.map_metadata["f_e"].interpolate, local=False)
        return [self._maps_answer(analysis, {name: {target: float(values[i]) for target, values in targets.items()}
                                             for name, targets in recalled.items()})
                for i, analysis in enumerate(analyses)]

    def _maps_answer(self, analysis: Analysis, recalled: dict[str, dict[str, float]]) -> MapsAnswer:
        """One record's :class:`MapsAnswer` from each map's read-out ``recalled[map][target]``
        (``"f_e_flat"``: the ``f_e`` map's units' own weights, where it has a local read-out)."""
        # the maps store corrections to the eq.-1 fit (training.identification._maps.TARGETS)
        def read(param: str, source: str) -> float:
            return from_correction(param, lambda component: recalled[source][component]
                                   if component in recalled[source] else analysis.feature(component))

        f_e, V_J = read("f_e", "f_e"), read("V_J", "V_J")
        f_e_flat = read("f_e", "f_e_flat") if "f_e_flat" in recalled else None
        d = min(max(recalled["f_e"]["d"], 0.0), self.policy.damping_cap)
        s_N = s_N_on_record(analysis, recalled["structure"]["log10_s_star"])
        probabilities = {c: recalled["structure"][f"p_{c}"] for c in STRUCTURE_CLASSES}
        # SPEC's stiff rule on the identified values; otherwise the structure map's most likely other class
        if spec_class(analysis, analysis.fit.J_sigma, V_J, f_e, d, s_N) == "stiff":
            structure = "stiff"
        else:
            structure = max((c for c in STRUCTURE_CLASSES if c != "stiff"), key=probabilities.get)
        ratio = {name: recalled[name]["distance"] / self.map_metadata[name].distance_unit for name in self.maps}
        return MapsAnswer(structure, probabilities, f_e, V_J, d, s_N,
                          s_N_on_record(analysis, recalled["backlash"]["log10_s_star"]), ratio, f_e_flat)

    def _problem(self, analysis: Analysis, answer: MapsAnswer) -> RefineProblem:
        """The refinement of one maps' answer: the record's replayed test signal, STEP 2's
        one-mass values, and the maps' ``f_e``, ``V_J``, ``d``, ``s_N`` as the start (and
        :func:`._policy.second_f_e_start`)."""
        bounds, fit = analysis.sections.bounds, analysis.fit
        start, level = torque_reference(bounds, analysis.M_star, analysis.drive.M_hold)
        segments = np.concatenate([bounds, [[bounds[5, 1], len(fit.speed)]]])  # the six sections and the tail
        segments = segments[segments[:, 1] > segments[:, 0]]  # a record that ends with VI has no tail
        return RefineProblem(speed=fit.speed, start=start, level=level, segments=segments, J_sigma=fit.J_sigma,
                             M_FC=max(fit.M_FC, 0.0), mu_F=max(fit.mu_F, 0.0), T_s=analysis.T_s, T_Ei=analysis.T_Ei,
                             encoder_counts=analysis.encoder_counts, M_N=analysis.M_N, free_one_mass=bool(fit.warnings),
                             M_L0=held_torque(analysis, self.policy), f_e_other=second_f_e_start(answer),
                             theta=np.array([math.log10(answer.f_e), math.log10(answer.V_J), answer.d,
                                             math.log10(max(answer.s_N, self.policy.start_s_N_floor))]))
