"""The one check of the settings objects (frozen dataclasses of thresholds), after scikit-learn's
parameter constraints: each settings class declares one constraint per field, in one mapping, and
its ``__post_init__`` calls :func:`check_settings`, whose error names ``Class.field``, what was
expected and what was received. A field without a declared constraint is a programming error."""

from __future__ import annotations

import math
import numbers
from collections.abc import Mapping
from dataclasses import dataclass, fields
from typing import Any, Protocol

__all__ = ["Constraint", "Interval", "Values", "Rows", "Pair", "OneOf", "OrNone", "InstanceOf", "POSITIVE",
           "NON_NEGATIVE", "SHARE", "REAL", "NON_NEGATIVE_OR_INF", "POSITIVE_OR_INF", "REAL_OR_INF", "INTEGER", "COUNT",
           "AT_LEAST_ONE", "FLAG", "check_settings"]


class Constraint(Protocol):
    """What one field may hold."""

    def holds(self, value: Any) -> bool:
        """Whether ``value`` keeps the constraint."""

    def text(self) -> str:
        """What is expected, as the error says it (``a finite number > 0``)."""


#: An end of an :class:`Interval`: a number, or the name of another field of the same settings.
Bound = float | str


@dataclass(frozen=True)
class Interval:
    """The values ``low .. high`` a setting may take (finite ones: ``open_low``/``open_high`` exclude the
    ends; ``integer``: whole numbers only; ``finite``: False lets ``inf`` in too, a threshold that
    switches its rule off). An end may name another field of the settings (its value there is the
    bound, :meth:`on`)."""

    low: Bound = -math.inf
    high: Bound = math.inf
    open_low: bool = False
    open_high: bool = False
    integer: bool = False
    finite: bool = True

    def on(self, settings: Any) -> Interval:
        """This interval with the ends that name a field of ``settings`` replaced by its value there."""
        low, high = (getattr(settings, end) if isinstance(end, str) else end for end in (self.low, self.high))
        return Interval(low, high, self.open_low, self.open_high, self.integer, self.finite)

    def holds(self, value: Any) -> bool:
        """Whether ``value`` is a real number, finite where asked (an integer where asked; never a
        bool; never NaN), inside."""
        if isinstance(value, bool) or not isinstance(value, numbers.Integral if self.integer else numbers.Real):
            return False
        number = float(value)
        if math.isnan(number) or (self.finite and math.isinf(number)):
            return False
        above = number > self.low if self.open_low else number >= self.low
        below = number < self.high if self.open_high else number <= self.high
        return bool(above and below)

    def text(self) -> str:
        """``a finite number in (0, 1]``, ``an integer >= elites``, ``a number >= 0 or inf``, ..."""
        kind = "an integer" if self.integer else "a finite number" if self.finite else "a number"
        return f"{kind}{self._range()}{'' if self.finite else ' or inf'}"

    def _range(self) -> str:
        """`` in (0, 1]``, `` >= 1``, ... (empty where both ends are open-ended)."""
        low, high = (end if isinstance(end, str) else f"{end:g}" for end in (self.low, self.high))
        if self.high == math.inf:
            return "" if self.low == -math.inf else f" {'>' if self.open_low else '>='} {low}"
        if self.low == -math.inf:
            return f" {'<' if self.open_high else '<='} {high}"
        return f" in {'(' if self.open_low else '['}{low}, {high}{')' if self.open_high else ']'}"


#: ``> 0``.
POSITIVE = Interval(0.0, open_low=True)
#: ``>= 0``.
NON_NEGATIVE = Interval(0.0)
#: A share of something: ``(0, 1]``.
SHARE = Interval(0.0, 1.0, open_low=True)
#: Any finite number.
REAL = Interval()
#: ``>= 0`` or ``inf`` (a threshold that switches its rule off).
NON_NEGATIVE_OR_INF = Interval(0.0, finite=False)
#: ``> 0`` or ``inf``.
POSITIVE_OR_INF = Interval(0.0, open_low=True, finite=False)
#: Any number but NaN.
REAL_OR_INF = Interval(finite=False)
#: Any integer.
INTEGER = Interval(integer=True)
#: A count: an integer ``>= 0``.
COUNT = Interval(0, integer=True)
#: An integer ``>= 1``.
AT_LEAST_ONE = Interval(1, integer=True)


@dataclass(frozen=True)
class Values:
    """A tuple of values, each inside ``each``: ``size`` of them (``what``: what they stand for),
    or any number where ``size`` is None (``empty``: none at all too)."""

    each: Interval = REAL
    size: int | None = None
    what: str = ""
    empty: bool = True

    def holds(self, value: Any) -> bool:
        if not isinstance(value, tuple) or (self.size is not None and len(value) != self.size):
            return False
        return (self.empty or bool(value)) and all(self.each.holds(item) for item in value)

    def text(self) -> str:
        count = (f"a tuple of {self.size} values" if self.size is not None
                 else "a tuple" if self.empty else "a non-empty tuple")
        return f"{count}{f' ({self.what})' if self.what else ''}, each {self.each.text()}"


@dataclass(frozen=True)
class Rows:
    """A non-empty tuple of rows, each a tuple that keeps ``row`` (a :class:`Values`)."""

    row: Values

    def holds(self, value: Any) -> bool:
        return isinstance(value, tuple) and bool(value) and all(self.row.holds(item) for item in value)

    def text(self) -> str:
        return f"a non-empty tuple of rows, each {self.row.text()}"


@dataclass(frozen=True)
class Pair:
    """A range ``(low, high)``: two values inside ``each``, the first below the second."""

    each: Interval = POSITIVE

    def holds(self, value: Any) -> bool:
        return Values(self.each, 2).holds(value) and value[0] < value[1]

    def text(self) -> str:
        return f"a pair (low, high), low < high, each {self.each.text()}"


@dataclass(frozen=True)
class OneOf:
    """One of ``options``."""

    options: tuple[Any, ...]

    def holds(self, value: Any) -> bool:
        return value in self.options

    def text(self) -> str:
        return f"one of {self.options}"


@dataclass(frozen=True)
class OrNone:
    """None, or a value that keeps ``constraint``."""

    constraint: Constraint

    def holds(self, value: Any) -> bool:
        return value is None or self.constraint.holds(value)

    def text(self) -> str:
        return f"{self.constraint.text()} or None"


@dataclass(frozen=True)
class InstanceOf:
    """An instance of ``kind`` (a nested settings object, a flag)."""

    kind: type

    def holds(self, value: Any) -> bool:
        return isinstance(value, self.kind)

    def text(self) -> str:
        return self.kind.__name__


#: A flag: True or False.
FLAG = InstanceOf(bool)


def check_settings(settings: Any, constraints: Mapping[str, Constraint], error: type[Exception] = ValueError) -> None:
    """Raise ``error`` naming ``Class.field``, what it expects and what it received, for the first
    field of the dataclass ``settings`` (in the order of ``constraints``) outside its constraint;
    a TypeError where a field has no declared constraint or a constraint names no field."""
    owner = type(settings).__name__
    names = {field.name for field in fields(settings)}
    if names != set(constraints):
        raise TypeError(f"{owner}: constraints declared for {sorted(set(constraints) - names)} (no such field), "
                        f"missing for {sorted(names - set(constraints))}")
    for name, constraint in constraints.items():
        value = getattr(settings, name)
        bound = constraint.on(settings) if isinstance(constraint, Interval) else constraint
        if not bound.holds(value):
            raise error(f"{owner}.{name}: expected {constraint.text()}, received {value!r}")
