"""The identifier's typed result (SPEC 9), its coded warnings and its per-record error isolation."""

from __future__ import annotations

import copy
import json
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

from sim import STRUCTURE_CLASSES, two_mass_derived, write_record
from training.errors import IdentificationError
from training.identification import (PARAMETER_NAMES, WARNING_CODES, IdentificationFailure, IdentificationResult,
                                     Identifier, IdentWarning, Parameters, Quality, fit_one_mass)
from training.identification import IdentificationPolicy, _assembly, _batch, analyze
from training.identification._assembly import Draft, Judge, RecordEvidence
from training.identification._maps import MAP_SPECS
from training.identification._policy import MapsAnswer
from training.identification._refine import Refined

#: The keys of SPEC section 9's object and of its ``quality`` (the refinement's last four).
SPEC9_KEYS = ["structure", "parameters", "intervals", "quality", "warnings", "notes"]  # the shipped maps are calibrated
QUALITY_KEYS = ["structure_probabilities", "map_distance_ratio", "osc_quanta", "oscillation_fit_r2",
                "one_mass_rel_residual", "outside_training", "section_flags", "maps_estimate", "outside_envelope"]
REFINE_KEYS = ["maps_structure", "refine_residual", "refine_start_residual", "refined_s_N"]


@pytest.fixture(scope="module")
def ident() -> Identifier:
    return Identifier.load()


@pytest.fixture(scope="module")
def files(good, tmp_path_factory) -> Path:
    d = tmp_path_factory.mktemp("records")
    write_record(d / "good", good)
    constant = copy.deepcopy(good)
    constant.speed = np.zeros(len(good))
    write_record(d / "constant", constant)
    return d


def _quality(**kw) -> Quality:
    base = dict(structure_probabilities={"stiff": 1.0}, map_distance_ratio={"structure": 0.5}, osc_quanta=2.0,
                oscillation_fit_r2=0.9, one_mass_rel_residual=0.01, outside_training=False, section_flags=("x",),
                maps_estimate={"f_e": 30.0}, outside_envelope={})
    return Quality(**{**base, **kw})


def test_to_dict_gives_the_spec9_keys_in_order(ident, good):
    res = ident.identify(good)
    assert isinstance(res, IdentificationResult) and res.ok and res.record is None
    d = res.to_dict()
    assert list(d) == SPEC9_KEYS
    assert res.structure in STRUCTURE_CLASSES
    assert list(d["parameters"]) == list(PARAMETER_NAMES)
    assert list(d["quality"]) == QUALITY_KEYS + REFINE_KEYS + ["answer_probability"]
    assert d["warnings"] == [w.text for w in res.warnings]
    json.dumps(d)  # plain JSON types only


def test_without_refinement_the_refine_figures_are_absent(good):
    res = Identifier.load(refine=None).identify(good)
    assert list(res.to_dict()["quality"]) == QUALITY_KEYS + ["answer_probability"]
    assert res.quality.maps_structure is None


def test_warnings_carry_codes():
    res = IdentificationResult("elastic", Parameters(J_sigma=1.0), _quality(),
                               (IdentWarning("oscillation_below_quantum", "oscillation only 0.5 speed quanta"),))
    assert res.has_warning("oscillation_below_quantum") and not res.has_warning("refine_partial_fit")
    assert res.to_dict()["warnings"] == ["oscillation only 0.5 speed quanta"]
    with pytest.raises(ValueError, match="expected one of"):
        res.has_warning("oscillation")  # a code, not a piece of text
    with pytest.raises(ValueError, match="IdentWarning.code"):
        IdentWarning("made_up", "text")


def test_the_identifier_codes_its_own_warnings():
    analysis = SimpleNamespace(osc_quanta=0.5)
    answer = SimpleNamespace(structure="elastic", used=("structure", "f_e", "V_J"),
                             distance_ratio={"structure": 0.5, "f_e": 1.5, "V_J": 0.9, "backlash": 3.0})
    draft = Draft("elastic", Parameters(J_sigma=1.0), (), ())
    judge = Judge(envelope=None, policy=IdentificationPolicy())
    warns = _assembly.warn_maps(RecordEvidence(analysis, answer, None, (), None), draft, judge).warnings
    assert [w.code for w in warns] == ["unlike_training_data", "oscillation_below_quantum"]
    assert "f_e map (distance 1.50" in warns[0].text
    refined = SimpleNamespace(J_sigma=0.1, residual=0.9)
    policy = IdentificationPolicy()
    assert [w.code for w in _assembly.refine_warnings(refined, "elastic", policy)] == ["one_mass_fit_replaced",
                                                                                      "refine_partial_fit"]
    assert [w.code for w in _assembly.refine_warnings(refined, "stiff", policy)] == ["one_mass_fit_replaced"]


@pytest.mark.parametrize("field, value", [("stiff_sure", 1.5), ("class_evidence", 0.0), ("damping_cap", float("nan")),
                                          ("class_margin", True)])
def test_the_policy_names_its_failing_setting(field, value):
    with pytest.raises(ValueError, match=rf"^IdentificationPolicy\.{field}: expected"):
        IdentificationPolicy(**{field: value})


def test_one_mass_fit_warnings_carry_codes():
    """A plant whose test sections hold less than two periods of its oscillation: STEP 2 says so."""
    from test_sections import simulate_switching

    from training.identification import detect_sections

    rec = simulate_switching(J_sigma=0.05, V_J=4.0, f_e=6.0, d=0.02, M_star=10.0, w_max=30.0, seed=2)
    fit = fit_one_mass(rec.current, rec.speed, rec.meta["T_s"], sections=detect_sections(rec))
    assert fit.warnings and all(w.code in WARNING_CODES for w in fit.warnings)
    assert "one_mass_fit_short_sections" in [w.code for w in fit.warnings]


def test_failure_to_dict():
    assert IdentificationFailure("no sections", "a.csv").to_dict() == {"record": "a.csv", "error": "no sections"}
    assert not IdentificationFailure("x").ok


def test_identify_raises_on_a_record_without_a_test_run(ident, good):
    ramp = copy.deepcopy(good)
    ramp.speed = np.linspace(0.0, 100.0, len(good))
    ramp.current = np.full(len(good), 10.0)
    ramp.torque_ref = ramp.section = None
    ramp.meta = {k: v for k, v in good.meta.items() if k not in ("M_star", "w_max")}
    with pytest.raises(IdentificationError, match="no recognisable test-signal sections") as err:
        ident.identify(ramp)
    assert "\n" not in str(err.value)


def test_identify_files_isolates_a_bad_file(ident, files):
    paths = [str(files / "good.csv"), str(files / "missing"), files / "constant"]
    out = ident.identify_files(paths)
    assert [r.record for r in out] == [str(p) for p in paths]
    assert [r.ok for r in out] == [True, False, False]
    assert "file not found" in out[1].error and "constant speed" in out[2].error
    assert all("\n" not in r.error for r in out[1:])
    assert out[0].to_dict() | {"record": None} == ident.identify_file(files / "good").to_dict() | {"record": None}


def test_identify_records_isolates_a_bad_record(ident, good):
    ramp = copy.deepcopy(good)
    ramp.speed = np.zeros(len(good))
    res = ident.identify_records([ramp, good])
    assert [r.ok for r in res] == [False, True] and "constant speed" in res[0].error


def test_an_unexpected_exception_is_named_and_costs_only_its_record(ident, files, monkeypatch):
    real = _batch.analyze

    def analyze(record):
        if record.name == "constant":
            raise TypeError("a bug\nwith two lines")
        return real(record)

    monkeypatch.setattr(_batch, "analyze", analyze)
    out = ident.identify_files([files / "constant", files / "good"])
    assert out[0].error == "unexpected TypeError in the analysis: a bug"
    assert out[1].ok


def test_a_failing_recall_costs_only_its_record(ident, files, monkeypatch):
    real = Identifier._identify_batch
    calls = []

    def batch(self, analyses, names):
        calls.append(list(names))
        if len(analyses) > 1 or len(calls) == 3:  # the batch fails, then the second record alone
            raise RuntimeError("boom\nsecond line")
        return real(self, analyses, names)

    monkeypatch.setattr(Identifier, "_identify_batch", batch)
    paths = [str(files / "good.csv"), str(files / "good"), str(files / "constant.csv")]
    out = ident.identify_files(paths)
    assert [r.record for r in out] == paths
    assert out[0].ok
    assert out[1].error == "unexpected RuntimeError in the recall: boom"
    assert "constant speed" in out[2].error


def test_iter_files_streams_with_progress_and_checks_jobs(ident, files):
    ticks = []
    it = ident.iter_files([files / "constant"] * 3, progress=ticks.append)
    assert [r.ok for r in it] == [False] * 3 and ticks == [1, 1, 1]
    with pytest.raises(ValueError, match=r"jobs: expected an integer >= 1 or None, received 0"):
        ident.identify_files([files / "good"], jobs=0)


def test_load_defaults_to_the_checkpoints_folder_at_call_time(monkeypatch, tmp_path):
    monkeypatch.setenv("TWOMASS_CHECKPOINTS", str(tmp_path / "elsewhere"))
    with pytest.raises((ValueError, OSError), match="elsewhere"):
        Identifier.load()


def test_refined_evidence_is_the_drop_of_the_squared_error_per_degree_of_freedom():
    """Hand-computed: residual 0.5 of the measured rms against the maps' 1.0 over 100 degrees of
    freedom drops the squared error by 0.75, 300 times the refined model's 0.0025 per degree."""
    def refined(residual: float, start: float) -> Refined:
        return Refined(f_e=30.0, V_J=1.0, d=0.02, s_N=0.5, backlash=1e-3, residual=residual, start_residual=start,
                       dof=100, n_sims=1)

    assert refined(0.5, 1.0).evidence == pytest.approx(300.0)
    assert refined(1.0, 0.9).evidence == 0.0  # no better than the maps' answer
    assert refined(0.0, 0.1).evidence == float("inf")


def _stiff_maps_answer(s_N: float = 1e-3) -> MapsAnswer:
    """The maps' answer ``stiff`` (a 3 kHz shaft) with the structure map's ``s_N``."""
    return MapsAnswer("stiff", {c: 0.25 for c in STRUCTURE_CLASSES}, f_e=3000.0, V_J=1.0, d=0.05,
                                   s_N=s_N, s_N_backlash=s_N, distance_ratio=dict.fromkeys(MAP_SPECS, 0.5))


def _refined_shaft(a, s_N: float, residual: float) -> Refined:
    """The refinement's model of the same shaft with a gap ``s_N`` (relative residual ``residual``
    against the maps' 1.0 over 4000 degrees of freedom)."""
    backlash = 2.0 * s_N * a.M_N / two_mass_derived(a.fit.J_sigma, 1.0, 3000.0, 0.05).C_F
    return Refined(f_e=3000.0, V_J=1.0, d=0.05, s_N=s_N, backlash=backlash, residual=residual, start_residual=1.0,
                   dof=4000, n_sims=1)


def _result(ident: Identifier, analysis, answer: MapsAnswer, refined: Refined) -> IdentificationResult:
    """The result the identifier assembles from these answers (no drive findings)."""
    return _assembly.assemble(RecordEvidence(analysis, answer, refined, (), "x"), Judge(ident.envelope, ident.policy))


@pytest.mark.parametrize("residual, kept", [(0.9999, "maps"), (0.9, "refined")])
def test_a_refined_class_stands_only_where_the_record_shows_it(ident, good, residual, kept):
    """The maps say stiff; the refinement's model adds a backlash (stiff_backlash). Fitting the
    record by 2e-4 of its rms better over 4000 degrees of freedom (evidence 0.8) does not show that
    backlash: the maps' answer stays, warned ``class_undecided``. 10 % better (evidence 940) does."""
    a = analyze(good)
    r = _refined_shaft(a, 1.0, residual)
    assert _assembly.refined_parameters(a, r)[0] == "stiff_backlash"
    res = _result(ident, a, _stiff_maps_answer(), r)
    if kept == "maps":
        assert res.structure == "stiff" and res.parameters.f_e is None
        assert res.has_warning("class_undecided")
        assert "between stiff (the maps' answer, kept) and stiff_backlash" in " ".join(w.text for w in res.warnings)
    else:
        assert res.structure == "stiff_backlash" and res.parameters.backlash == pytest.approx(r.backlash)
        assert not res.has_warning("class_undecided")


def test_a_refined_stiff_answer_near_the_backlash_threshold_says_so(ident, good):
    """The refinement's stiff model has s_N = 0.095, 5 % below the class threshold 0.1 (a large-axis
    shaft with s_N 0.102 came out so, unwarned): the answer is warned on the refined model's s_N,
    though the maps' estimate (0.001) lies far; and on the maps' estimate where only that lies near
    (a shaft with s_N 0.35 came out stiff at a refined 0.058)."""
    a = analyze(good)

    def near(maps_s_N: float, refined_s_N: float) -> list[str]:
        res = _result(ident, a, _stiff_maps_answer(maps_s_N), _refined_shaft(a, refined_s_N, 0.5))
        assert res.structure == "stiff"
        return [w.text.split(" lies")[0] for w in res.warnings if w.code == "class_near_threshold"]

    assert "s_N = 0.095" in near(1e-3, 0.095)
    assert "s_N = 0.09 (the maps' estimate)" in near(0.09, 0.01) and "s_N = 0.01" not in near(0.09, 0.01)


def test_the_refinement_stands_on_its_class_its_evidence_or_a_replaced_fit():
    """:func:`refinement_stands`: the maps' class kept, evidence at the policy's threshold, or
    STEP 2's values replaced; else the maps' answer stays."""
    from training.identification._policy import refinement_stands

    policy = IdentificationPolicy()
    weak = SimpleNamespace(evidence=policy.class_evidence / 2, J_sigma=None)
    assert refinement_stands("stiff", "stiff", weak, policy)
    assert not refinement_stands("stiff", "elastic", weak, policy)
    assert refinement_stands("stiff", "elastic", SimpleNamespace(evidence=policy.class_evidence, J_sigma=None), policy)
    assert refinement_stands("stiff", "elastic", SimpleNamespace(evidence=0.0, J_sigma=0.1), policy)
    assert not refinement_stands("stiff", "elastic", weak, IdentificationPolicy(class_evidence=1e9))
