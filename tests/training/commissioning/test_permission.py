"""The refusal rules V1-V6: each refusal carries its rule code; decisions key on codes, never on text."""

from __future__ import annotations

import pytest

from training.commissioning import CommissioningWarning, Permission, may_propose_controller
from training.identification import IdentificationFailure

ELASTIC = {"J_sigma": 0.05, "V_J": 1.0, "f_e": 30.0, "d": 0.03}
NOTE = ("refine_partial_fit", "the refined model reproduces only part of the measured oscillation")


def test_good_result_may_get_a_controller(make_result, make_validation):
    perm = may_propose_controller(make_result("elastic", ELASTIC, warnings=(NOTE,)), make_validation())
    assert perm and perm.allowed and perm.rule is None and perm.notes == (NOTE[1],)


@pytest.mark.parametrize(
    "case, rule",
    [
        (dict(structure="wobbly"), "V1"),
        (dict(failure="no sections found"), "V1"),
        (dict(params={"J_sigma": 0.05, "V_J": 1.0, "f_e": None}), "V2"),
        (dict(params={"J_sigma": -0.05}), "V2"),
        (dict(validation=dict(nrmse=0.4, passed=False, reason="speed error 0.4 > 0.1")), "V3"),
        (dict(validation=dict(nrmse=0.08)), "V3"),  # passed its own 0.1 threshold, above the rule's 0.05 bound
        (dict(validation=dict(nrmse=float("nan"))), "V3"),
        (dict(validation=None), "V3"),
        (dict(outside_training=True), "V4"),
        (dict(ratios={"structure": 0.5, "f_e": 4.0}, bound=3.0), "V4"),
        (dict(warnings=(CommissioningWarning("test_not_informative", "test response not informative"),)), "V6"),
    ],
)
def test_each_refusal_carries_its_rule_code(make_result, make_validation, case, rule):
    result = (IdentificationFailure(case["failure"]) if "failure" in case else
              make_result(case.get("structure", "elastic"), case.get("params", ELASTIC),
                          outside_training=case.get("outside_training", False), ratios=case.get("ratios")))
    v = case.get("validation", {})
    perm = may_propose_controller(result, None if v is None else make_validation(**v), warnings=case.get("warnings", ()),
                                  max_validation_error=0.05, max_map_distance_ratio=case.get("bound"))
    assert not perm and perm.rule == rule and perm.reason.startswith(rule)


def test_map_distance_bound_reads_only_the_maps_the_structure_uses(make_result, make_validation):
    """With a bound, the commissioning's reading replaces the identifier's flag: a far map that an
    elastic result does not use (backlash) does not refuse, even with the identifier's flag set."""
    result = make_result("elastic", ELASTIC, outside_training=True, ratios={"structure": 0.5, "f_e": 2.0, "backlash": 9.0})
    assert may_propose_controller(result, make_validation(), max_map_distance_ratio=3.0).allowed
    assert may_propose_controller(result, make_validation()).rule == "V4"


def test_warning_codes_block_not_words(make_result, make_validation):
    """A warning whose text says 'timeout' but whose code is harmless passes; the same code
    declared blocking refuses (V6)."""
    harmless = make_result("elastic", ELASTIC, warnings=(("oscillation_below_quantum", "section IV timeout: timed out"),))
    assert may_propose_controller(harmless, make_validation()).allowed
    perm = may_propose_controller(harmless, make_validation(), blocking_codes={"oscillation_below_quantum"})
    assert perm.rule == "V6" and "timeout" in perm.reason


def test_stiff_needs_only_J_sigma_and_input_checks(make_result, make_validation):
    assert may_propose_controller(make_result("stiff", {"J_sigma": 0.05}), make_validation()).allowed
    with pytest.raises(TypeError):
        may_propose_controller({"structure": "stiff", "parameters": {"J_sigma": 0.05}}, make_validation())
    with pytest.raises(ValueError):
        Permission(False, "V9 no such rule", rule="V9")
    with pytest.raises(ValueError):
        Permission(True, "fine", rule="V1")
    with pytest.raises(ValueError):
        CommissioningWarning("timeout", "words are no codes")
