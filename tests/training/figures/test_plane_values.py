"""The maps page names each value of a quantity with what it is, and which one is reported."""

from __future__ import annotations

from types import SimpleNamespace

from training.figures._identify import plane_values


def _result(f_e=42.0, refined_s_N=None, maps=None):
    quality = SimpleNamespace(maps_estimate={"f_e": 40.0, "V_J": 1.2, "s_N": 0.3} if maps is None else maps,
                              refined_s_N=refined_s_N)
    return SimpleNamespace(quality=quality, parameters=SimpleNamespace(f_e=f_e, backlash=0.01))


def test_each_value_is_labelled_and_the_reported_one_named():
    assert plane_values("f_e", 41.0, _result(), member=1) == [("best unit (member 2)", 41.0), ("maps", 40.0),
                                                               ("reported", 42.0)]
    # the maps do not estimate the backlash: the unit's value and the reported one
    assert plane_values("backlash", 0.02, _result()) == [("best unit (member 1)", 0.02), ("reported", 0.01)]


def test_s_N_reported_is_the_refined_value_else_the_maps():
    assert plane_values("s_N", 0.2, _result(refined_s_N=0.25))[-1] == ("reported", 0.25)
    assert plane_values("s_N", 0.2, _result())[-2:] == [("maps", 0.3), ("reported", 0.3)]


def test_without_a_result_only_the_unit():
    assert plane_values("f_e", 41.0, None) == [("best unit (member 1)", 41.0)]
