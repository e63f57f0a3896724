"""Records that are well formed but not the test their metadata describe get a coded warning
(training.identification._consistency); clean records get none. The runs come from the
stand-alone reference simulator of test_sections.py."""

from __future__ import annotations

import copy

import numpy as np
import pytest
from test_sections import simulate_switching

from training.errors import IdentificationError
from training.identification import analyze, detect_sections

NEW_CODES = {"test_law_mismatch", "torque_scale_mismatch", "record_starts_late", "run_aborted"}


@pytest.fixture(scope="module")
def run():
    return simulate_switching(seed=3)


def _codes(record) -> set[str]:
    return {w.code for w in analyze(record).warnings} & NEW_CODES


def _variant(record, *, keep_ref: bool = True, **meta):
    r = copy.deepcopy(record)
    if not keep_ref:
        r.torque_ref = r.section = None
    r.meta.update(meta)
    return r


@pytest.mark.parametrize("keep_ref", [True, False])
def test_clean_record_gets_none_of_these_warnings(run, keep_ref):
    assert _codes(_variant(run, keep_ref=keep_ref)) == set()


@pytest.mark.parametrize("keep_ref", [True, False])
def test_speed_clipped_below_w_max_breaks_the_switching_law(run, keep_ref):
    r = _variant(run, keep_ref=keep_ref)
    r.speed = np.clip(r.speed, -99.0, 99.0)  # a scope's full scale just below w_max = 100
    assert "test_law_mismatch" in _codes(r)


@pytest.mark.parametrize("keep_ref", [True, False])
def test_speed_clipped_exactly_at_w_max_is_named(keep_ref):
    # a = M*/J_sigma = 500 rad/s^2: 5 speed quanta a sample at the switch, and on for T_Ei after it
    r = _variant(simulate_switching(J_sigma=0.02, seed=4), keep_ref=keep_ref)
    assert _codes(r) == set()
    r.speed = np.clip(r.speed, -100.0, 100.0)  # the scope's full scale = w_max: the law's ends still hold
    assert "test_law_mismatch" in _codes(r)


@pytest.mark.parametrize("w_max", [50.0, 200.0])
def test_wrong_w_max_breaks_the_switching_law(run, w_max):
    assert "test_law_mismatch" in _codes(_variant(run, w_max=w_max))


@pytest.mark.parametrize("factor", [2.0, 0.5, 2 ** 0.5])
def test_wrong_K_M_is_named(run, factor):
    assert "torque_scale_mismatch" in _codes(_variant(run, K_M=run.meta["K_M"] * factor))


def test_wrong_K_M_without_torque_ref_names_K_M_when_no_sections_show(run):
    r = _variant(run, keep_ref=False, K_M=run.meta["K_M"] * 2.0)
    with pytest.raises(IdentificationError, match=r"reaches 2 x metadata M_star = 10 Nm: K_M"):
        analyze(r)


def test_torque_ref_in_percent_names_its_units_when_no_sections_show(run):
    r = _variant(run)
    r.torque_ref = r.torque_ref * 10.0  # % of M_N = 10 Nm instead of Nm
    with pytest.raises(IdentificationError, match=r"torque_ref reaches 10 x metadata M_star = 10 Nm: its units"):
        analyze(r)


@pytest.mark.parametrize("keep_ref", [True, False])
def test_recording_that_starts_inside_section_I_is_named(run, keep_ref):
    r = _variant(run, keep_ref=keep_ref)
    k = 400  # about half way up to w_max
    for name in ("t", "speed", "current", "torque_ref", "section"):
        if getattr(r, name) is not None:
            setattr(r, name, getattr(r, name)[k:])
    r.t = r.t - r.t[0]
    assert "record_starts_late" in _codes(r)


def test_aborted_run_is_named(run):
    assert _codes(_variant(run, aborted=True)) == {"run_aborted"}


def test_section_I_of_a_slow_current_loop_starts_at_the_first_sample():
    # T_Ei of 3.4 samples: the torque rises through the 0.7 M* level for a few samples, which is
    # no run before section I (it was taken for one: I started 4 samples late)
    r = simulate_switching(J_sigma=0.004, M_star=6.0, w_max=130.0, T_s=6.4e-4, T_Ei=2.2e-3, f_e=40.0)
    split = detect_sections(_variant(r, keep_ref=False))
    assert split.bounds[0, 0] == int(np.flatnonzero(r.section == 1)[0]) == 0
    assert not any("before section I" in f for f in split.flags)
