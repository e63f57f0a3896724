"""The checks of the stages' settings: each names the settings class and the field that fails."""

from __future__ import annotations

from typing import Any


def _fail(settings: object, field: str, expected: str) -> None:
    raise ValueError(f"{type(settings).__name__}.{field}: expected {expected}, "
                     f"received {getattr(settings, field)!r}")


def at_least(settings: object, bound: float, *fields: str) -> None:
    """Each of ``fields`` of ``settings`` is a number ``>= bound`` (NaN fails)."""
    for field in fields:
        if not getattr(settings, field) >= bound:
            _fail(settings, field, f">= {bound:g}")


def above(settings: object, bound: float, *fields: str) -> None:
    """Each of ``fields`` of ``settings`` is a number ``> bound`` (NaN fails)."""
    for field in fields:
        if not getattr(settings, field) > bound:
            _fail(settings, field, f"> {bound:g}")


def within(settings: object, field: str, low: float, high: float) -> None:
    """``settings.field`` lies in ``(low, high]``."""
    if not low < getattr(settings, field) <= high:
        _fail(settings, field, f"{low:g} < {field} <= {high:g}")


def not_below_field(settings: object, field: str, other: str) -> None:
    """``settings.field >= settings.other``."""
    if not getattr(settings, field) >= getattr(settings, other):
        _fail(settings, field, f">= {other} ({getattr(settings, other)!r})")


def sized(settings: object, field: str, size: int, what: str) -> None:
    """``settings.field`` holds ``size`` values (``what``: what they stand for)."""
    if len(getattr(settings, field)) != size:
        _fail(settings, field, f"{size} values ({what})")


def each_above(settings: object, field: str, bound: float) -> None:
    """Every value of ``settings.field`` is ``> bound``."""
    values: Any = getattr(settings, field)
    if any(not v > bound for v in values):
        _fail(settings, field, f"every value above {bound:g}")
