"""The one check of the commissioning's frozen settings: every numeric field inside its interval,
the error naming the failing field (:class:`training.errors.CommissioningError`)."""

from __future__ import annotations

import math
import numbers
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

from training.errors import CommissioningError

__all__ = ["Interval", "POSITIVE", "NON_NEGATIVE", "SHARE", "check_settings"]


@dataclass(frozen=True)
class Interval:
    """The finite values ``low .. high`` a setting may take; ``open_low``/``open_high`` exclude the
    ends; ``integer``: whole numbers only."""

    low: float = -math.inf
    high: float = math.inf
    open_low: bool = False
    open_high: bool = False
    integer: bool = False

    def holds(self, value: Any) -> bool:
        """Whether ``value`` is a finite real number (an integer where asked; never a bool) inside."""
        if isinstance(value, bool) or not isinstance(value, numbers.Integral if self.integer else numbers.Real):
            return False
        number = float(value)
        if not math.isfinite(number):
            return False
        above = number > self.low if self.open_low else number >= self.low
        below = number < self.high if self.open_high else number <= self.high
        return above and below

    def text(self) -> str:
        """``a finite number in (0, 1]``, ``an integer >= 1``, ..."""
        kind = "an integer" if self.integer else "a finite number"
        if math.isinf(self.high):
            return f"{kind} {'>' if self.open_low else '>='} {self.low:g}"
        return f"{kind} in {'(' if self.open_low else '['}{self.low:g}, {self.high:g}{')' if self.open_high else ']'}"


#: ``> 0``.
POSITIVE = Interval(0.0, open_low=True)
#: ``>= 0``.
NON_NEGATIVE = Interval(0.0)
#: A share of something: ``(0, 1]``.
SHARE = Interval(0.0, 1.0, open_low=True)


def check_settings(settings: Any, intervals: Mapping[str, Interval]) -> None:
    """Raise :class:`CommissioningError` naming the first field of ``settings`` outside its interval."""
    for name, interval in intervals.items():
        value = getattr(settings, name)
        if not interval.holds(value):
            raise CommissioningError(f"{type(settings).__name__}.{name}: expected {interval.text()}, received {value!r}")
