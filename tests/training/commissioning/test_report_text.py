"""The commissioning report's text: each warning printed in the section it belongs to (by code),
and a summary with nothing to summarize says so."""

from __future__ import annotations

import sys
from dataclasses import replace
from pathlib import Path

import pytest

sim = pytest.importorskip("sim")

from training.commissioning import commission, summarize, summary_text  # noqa: E402
from training.commissioning._permission import COMMISSIONING_WARNING_CODES, CommissioningWarning  # noqa: E402
from training.commissioning._report import _WARNING_SECTION  # noqa: E402

sys.path.insert(0, str(Path(__file__).parent))
from setups import FAST, LIMITS, ONE_MASS, STIFF  # noqa: E402


def _line(lines: list[str], start: str) -> int:
    return next(i for i, ln in enumerate(lines) if ln.startswith(start))


def test_warnings_are_printed_where_they_belong(stub):
    rep = commission(sim.SimulatedDrive(STIFF), LIMITS, identifier=stub("stiff", ONE_MASS), config=FAST)
    assert rep.runs and rep.delivered is not None
    warns = tuple(CommissioningWarning(code, f"text of {code}") for code in
                  ("speed_against_torque", "validation_not_run", "loop_rejected", "run_stopped", "loop_unlike_model"))
    lines = replace(rep, warnings=warns).to_text().splitlines()
    at = {w.code: _line(lines, f"   warning [{w.code}]") for w in warns}
    assert at["speed_against_torque"] < _line(lines, "2 identification")
    assert _line(lines, "4 permission") < at["validation_not_run"] < _line(lines, "5 proposal")
    for code in ("loop_rejected", "run_stopped", "loop_unlike_model"):  # after the runs on the drive
        assert _line(lines, "7 on the drive") < at[code] < _line(lines, "8 delivered"), code


def test_every_placed_code_is_a_commissioning_code():
    assert set(_WARNING_SECTION) <= set(COMMISSIONING_WARNING_CODES)


def test_a_summary_without_a_model_based_delivery_says_so():
    class Failing:
        def identify(self, record):
            raise ValueError("no test run found")

    rep = commission(sim.SimulatedDrive(STIFF), LIMITS, identifier=Failing(), config=FAST)
    text = summary_text(summarize([rep, rep], 2.5))
    assert "none to summarize" in text and "(None)" not in text and "median -" not in text
    assert "chain time 2.5 s" in text and "start-up" in text and "wall time" not in text


def test_the_identification_section_names_the_intervals_of_f_e_V_J_J_sigma(stub):
    from training.identification import INTERVAL_NAMES, Intervals

    rep = commission(sim.SimulatedDrive(STIFF), LIMITS, identifier=stub("stiff", ONE_MASS), config=FAST)
    lines = rep.to_text().splitlines()
    assert lines[_line(lines, "2 identification") + 1:].count(
        "   90 % intervals: none (the maps carry no calibration): the design's set is the interim spread") == 1
    bounds = {n: (1.0, 2.0) for n in INTERVAL_NAMES} | {"f_e": (37.31, 41.6), "V_J": (0.6381, 0.9612),
                                                         "J_sigma": (0.04992, 0.0501)}
    ident = replace(rep.identification, intervals=Intervals(**bounds))
    lines = replace(rep, identification=ident).to_text().splitlines()
    (row,) = [ln for ln in lines if ln.startswith("   90 % intervals")]
    assert row == "   90 % intervals: f_e 37.31 .. 41.6 Hz, V_J 0.6381 .. 0.9612, J_sigma 0.04992 .. 0.0501 kg m^2"
    assert _line(lines, "2 identification") < lines.index(row) < _line(lines, "3 ")
