"""The one check of the settings objects (:mod:`training._settings`): its constraints, its message
(``Class.field``, what was expected, what was received), and every settings class that uses it
declaring a constraint for each of its fields."""

from __future__ import annotations

import ast
import dataclasses
import importlib
import math
import re
from pathlib import Path

import pytest

from training._settings import (AT_LEAST_ONE, FLAG, NON_NEGATIVE_OR_INF, POSITIVE, SHARE, Interval, OneOf, OrNone, Pair,
                                Values, check_settings)
from training.errors import CommissioningError

REPO = Path(__file__).resolve().parents[2]


@dataclasses.dataclass(frozen=True)
class _Example:
    low: float = 1.0
    high: int = 3
    share: float = 0.5
    band: tuple[float, float] = (1.0, 2.0)
    mode: str = "a"
    limit: float | None = None
    flag: bool = True

    def __post_init__(self) -> None:
        check_settings(self, {"low": POSITIVE, "high": Interval("low", integer=True), "share": SHARE,
                              "band": Pair(POSITIVE), "mode": OneOf(("a", "b")), "limit": OrNone(POSITIVE),
                              "flag": FLAG})


@pytest.mark.parametrize("field, value, expected", [
    ("low", 0.0, "a finite number > 0"), ("low", math.inf, "a finite number > 0"), ("low", True, "a finite number > 0"),
    ("high", 0, "an integer >= low"), ("high", 2.0, "an integer >= low"), ("share", math.nan, "a finite number in (0, 1]"),
    ("band", (2.0, 1.0), "a pair (low, high), low < high, each a finite number > 0"),
    ("band", (1.0,), "a pair (low, high), low < high, each a finite number > 0"), ("mode", "c", "one of ('a', 'b')"),
    ("limit", -1.0, "a finite number > 0 or None"), ("flag", 1, "bool"),
])
def test_the_error_names_the_field_what_it_expects_and_what_it_received(field, value, expected):
    with pytest.raises(ValueError, match="^" + re.escape(f"_Example.{field}: expected {expected}, received {value!r}") + "$"):
        _Example(**{field: value})


def test_valid_settings_pass_and_the_error_class_is_the_callers():
    assert _Example(low=2.0, high=2, limit=5.0).high == 2
    with pytest.raises(CommissioningError, match=r"^_Example\.low: expected"):
        check_settings(_Example(low=2.0, high=2), {**_constraints(), "low": Interval(3.0)}, CommissioningError)


def _constraints() -> dict:
    return {"low": POSITIVE, "high": AT_LEAST_ONE, "share": SHARE, "band": Pair(), "mode": OneOf(("a",)),
            "limit": OrNone(POSITIVE), "flag": FLAG}


def test_every_field_needs_its_constraint():
    constraints = _constraints()
    del constraints["flag"]
    with pytest.raises(TypeError, match=r"_Example: .*missing for \['flag'\]"):
        check_settings(_Example(), constraints)
    with pytest.raises(TypeError, match=r"_Example: constraints declared for \['other'\]"):
        check_settings(_Example(), {**_constraints(), "other": POSITIVE})


def test_a_threshold_may_switch_its_rule_off_with_inf_but_never_be_nan():
    assert NON_NEGATIVE_OR_INF.holds(math.inf) and not NON_NEGATIVE_OR_INF.holds(math.nan)
    assert not NON_NEGATIVE_OR_INF.holds(-1.0) and NON_NEGATIVE_OR_INF.text() == "a number >= 0 or inf"
    assert Values(POSITIVE, empty=False).text() == "a non-empty tuple, each a finite number > 0"
    assert not Values(POSITIVE, empty=False).holds(()) and Values(POSITIVE).holds(())
    assert not Values(POSITIVE, 2).holds([1.0, 2.0])  # a tuple, as the frozen settings hold


def _settings_classes() -> list[type]:
    """The classes under training/ whose ``__post_init__`` calls :func:`check_settings`."""
    found = []
    for path in sorted((REPO / "training").rglob("*.py")):
        module = ".".join(path.relative_to(REPO).with_suffix("").parts)
        for node in ast.parse(path.read_text()).body:
            if isinstance(node, ast.ClassDef) and any(
                    isinstance(item, ast.FunctionDef) and item.name == "__post_init__"
                    and "check_settings" in ast.unparse(item) for item in node.body):
                found.append(getattr(importlib.import_module(module), node.name))
    return found


def test_every_settings_class_is_a_frozen_dataclass_that_checks_every_field():
    classes = _settings_classes()
    assert len(classes) >= 25, [c.__name__ for c in classes]
    for settings in classes:  # the defaults pass, every field declared (check_settings refuses a missing one)
        assert dataclasses.is_dataclass(settings) and settings.__dataclass_params__.frozen, settings.__name__
        settings()
