"""A record is one whole test run whose units the metadata can check (SPEC 2, 3): what the
identification refuses or says of a record that is not (more than one run, a run cut short, a
``K_M`` beyond the float range, units nothing in the record can check)."""

from __future__ import annotations

import copy
import math

import numpy as np
import pytest

from sim import DriveConfig, Record, TestSignalConfig, TwoMassParams, responses_to_records, simulate_test
from training.errors import IdentificationError
from training.identification import analyze, detect_sections

from test_plausibility import variant

RPM = 60.0 / (2.0 * math.pi)


def _copy(rec: Record, *, drop: tuple[str, ...] = (), keep_ref: bool = False, **changes) -> Record:
    """``rec`` without its ``section`` column (and ``torque_ref`` unless ``keep_ref``), metadata
    ``drop`` removed, then ``changes`` to metadata or columns (:func:`test_plausibility.variant`)."""
    return variant(rec, drop_meta=drop, section=None, **({} if keep_ref else {"torque_ref": None}), **changes)


def _rows(rec: Record, rows: np.ndarray) -> Record:
    """``rec`` with the rows ``rows`` of every column, ``t`` on its uniform grid from ``rec``'s start."""
    new = copy.deepcopy(rec)
    for c in ("speed", "current", "torque", "torque_ref", "section"):
        if getattr(rec, c) is not None:
            setattr(new, c, np.asarray(getattr(rec, c))[rows])
    new.t = rec.t[0] + np.arange(rows.size) * rec.T_s
    return new


def _repeated(rec: Record, k: int, upto: int | None = None) -> Record:
    """``k`` copies of ``rec``'s first ``upto`` rows (all by default), one after the other, ``t`` continuing."""
    n = len(rec.t) if upto is None else upto
    return _rows(rec, np.tile(np.arange(n), k))


def _cut(rec: Record, n: int) -> Record:
    return _rows(rec, np.arange(n))


def _end_of(rec: Record, section: int) -> int:
    return int(np.flatnonzero(np.asarray(rec.section) == section)[-1]) + 1


@pytest.fixture(scope="module")
def noisy() -> Record:
    """A run whose current noise (5 % of M*) sends the section detection to the switching law."""
    drive, signal = DriveConfig(current_noise_std=0.5 / DriveConfig().K_M), TestSignalConfig()
    params = TwoMassParams(J_sigma=0.05, V_J=1.0, f_e=30.0, d=0.02, backlash=0.0, M_FC=0.2, mu_F=0.001)
    return responses_to_records(simulate_test(params, drive, signal, seed=0), params.reshape(1), drive, signal,
                                names=["noisy"])[0]


def _error(rec: Record) -> str:
    with pytest.raises(IdentificationError) as err:
        analyze(rec)
    text = str(err.value)
    assert "\n" not in text
    return text


# -- one test run: more than one is refused ----------------------------------------------------------

@pytest.mark.parametrize("keep_ref", [False, True])
def test_one_run_is_answered_as_before(good, keep_ref):
    a = analyze(_copy(good, keep_ref=keep_ref))
    truth = np.array([[np.flatnonzero(good.section == k)[0], _end_of(good, k)] for k in range(1, 7)])
    assert np.abs(a.sections.bounds - truth).max() <= 2
    assert not any("further" in f for f in a.section_flags)


@pytest.mark.parametrize("keep_ref", [False, True])
@pytest.mark.parametrize("k", [2, 3])
def test_repeated_runs_are_refused_as_such(good, k, keep_ref):
    rec = _copy(_repeated(good, k), keep_ref=keep_ref)
    text = _error(rec)
    assert text.startswith(f"the record holds {k} test runs (section I starts again from rest at t = ")
    assert "cut the record to one run" in text
    second = float(text.split("t = ")[1].split(",")[0].split(" ")[0])
    assert abs(second - float(rec.t[len(good.t)])) < 0.01  # where the second copy's torque rises


def test_many_runs_are_refused_naming_the_first_restarts(good):
    text = _error(_copy(_repeated(good, 12)))
    assert text.startswith("the record holds 12 test runs") and ", ..." in text


def test_runs_without_a_tail_between_them_are_refused(good):
    text = _error(_copy(_repeated(good, 2, upto=_end_of(good, 6))))
    assert text.startswith("the record holds 2 test runs")


def test_repeated_noisy_runs_are_refused(noisy):
    assert _error(_copy(_repeated(noisy, 2))).startswith("the record holds 2 test runs")


def test_a_torque_dip_inside_section_one_is_still_one_run(good):
    rec = _copy(good)
    i1 = np.flatnonzero(good.section == 1)
    mid, n = int(i1[i1.size // 2]), int(round(4e-3 / good.T_s))
    rec.current[mid:mid + n] = 0.0  # the speed is moving: no rest, no new run
    detect_sections(rec)


# -- a run cut short is called incomplete, naming what is missing ------------------------------------

@pytest.mark.parametrize("keep_ref", [False, True])
@pytest.mark.parametrize("section, missing", [(3, "IV, V, VI"), (5, "VI"), (2, "III, IV, V, VI")])
def test_a_run_cut_short_is_called_incomplete(good, section, missing, keep_ref):
    end = _end_of(good, section)
    cut = end if section == 3 else end - 20  # II and V: cut while the speed still moves
    text = _error(_copy(_cut(good, cut), keep_ref=keep_ref))
    name = ["I", "II", "III", "IV", "V"][section - 1]
    assert text.startswith(f"incomplete test run: the record ends in section {name} ")
    assert f"sections {missing} and the 50 ms tail are missing" in text
    assert "units" not in text


def test_a_run_cut_in_section_one_is_incomplete_not_wrong_units(good):
    # the speed never reached 0.3 w_max: the speed-scale check called it wrong units
    rec = _copy(_cut(good, _end_of(good, 1) // 8))
    assert float(np.max(np.abs(rec.speed))) < 0.3 * rec.meta["w_max"]
    text = _error(rec)
    assert text.startswith("incomplete test run: the record ends in section I ") and "units" not in text


@pytest.mark.parametrize("section", [3, 6])
def test_a_speed_in_rev_per_s_is_still_wrong_units_where_the_run_passed_section_one(good, section):
    # past I the speed had reached w_max: a low peak is the units, whether or not the run is cut
    text = _error(_copy(_cut(good, _end_of(good, section)), speed=good.speed[:_end_of(good, section)] / (2 * math.pi)))
    assert text.startswith("speed looks like wrong units")


def test_a_noisy_run_cut_short_is_called_incomplete(noisy):
    text = _error(_copy(_cut(noisy, _end_of(noisy, 3))))
    assert text.startswith("incomplete test run: the record ends in section III ")


def test_an_aborted_run_says_so(good):
    rec = _copy(_cut(good, _end_of(good, 3)))
    rec.meta["aborted"] = True
    text = _error(rec)
    assert "the drive aborted it at a limit" in text


def test_a_run_cut_in_section_six_is_still_answered(good):
    a = analyze(_copy(_cut(good, _end_of(good, 6) - 5)))
    assert "record ends in section VI (no tail)" in a.section_flags


# -- K_M beyond the float range ---------------------------------------------------------------------

@pytest.mark.parametrize("drop", [(), ("M_star", "M_max", "M_N")])
def test_K_M_overflowing_the_torque_is_named(good, drop):
    with np.errstate(over="raise"):  # and no overflow warning on the way
        text = _error(_copy(good, drop=drop, K_M=1e308))
    assert text.startswith("metadata K_M looks implausible (K_M = 1e+308 Nm/A") and "overflows" in text
    assert "zero torque" not in text


def test_K_M_underflowing_the_torque_is_named(good):
    text = _error(_copy(good, K_M=5e-324, current=good.current * 0.01))
    assert text.startswith("metadata K_M looks implausible") and "underflows to a zero torque" in text


# -- units nothing in the record can check ------------------------------------------------------------

def _unchecked(rec: Record) -> list[str]:
    return [w.text for w in analyze(rec).warnings if w.code == "units_unchecked"]


def test_rpm_speed_without_w_max_or_encoder_counts_is_flagged(good):
    texts = _unchecked(_copy(good, drop=("w_max", "encoder_counts"), speed=good.speed * RPM))
    assert len(texts) == 1
    assert texts[0].startswith("the speed's units could not be checked: the record gives neither w_max nor "
                               "encoder_counts")


def test_a_filtered_speed_with_encoder_counts_but_no_w_max_is_flagged(good):
    smooth = np.convolve(good.speed, np.ones(3) / 3.0, mode="same")  # off the encoder's grid
    assert len(_unchecked(_copy(good, drop=("w_max",), speed=smooth))) == 1


@pytest.mark.parametrize("drop", [(), ("w_max",), ("encoder_counts",), ("M_star",), ("M_max", "M_N")])
def test_a_record_whose_units_are_checked_gets_no_such_warning(good, drop):
    assert _unchecked(_copy(good, drop=drop)) == []


def test_current_without_M_star_or_M_max_is_flagged(good):
    texts = _unchecked(_copy(good, drop=("M_star", "M_max")))
    assert len(texts) == 1 and texts[0].startswith("the current's units could not be checked")


def test_units_unchecked_is_a_known_code():
    from training.identification._result import WARNING_CODES

    assert "units_unchecked" in WARNING_CODES
