"""The one check of the identification's settings objects (frozen dataclasses of thresholds)."""

from __future__ import annotations

import math
from dataclasses import fields
from typing import Any


def _positive(value: Any) -> bool:
    return (not isinstance(value, bool) and isinstance(value, (int, float)) and math.isfinite(value)
            and value > 0)


def check_positive(settings: Any, at_most_one: tuple[str, ...] = ()) -> None:
    """Raise ValueError naming the first field of the frozen dataclass ``settings`` that is no
    finite number > 0 (a pair: two such numbers, the first below the second); the fields
    ``at_most_one`` (shares, probabilities) must not exceed 1 either."""
    owner = type(settings).__name__
    for field in fields(settings):
        value = getattr(settings, field.name)
        if isinstance(value, tuple):
            if len(value) != 2 or not all(_positive(v) for v in value) or not value[0] < value[1]:
                raise ValueError(f"{owner}.{field.name}: expected a pair of finite numbers 0 < low < high, "
                                 f"received {value!r}")
        elif not _positive(value) or (field.name in at_most_one and value > 1.0):
            bound = "a number in (0, 1]" if field.name in at_most_one else "a finite number > 0"
            raise ValueError(f"{owner}.{field.name}: expected {bound}, received {value!r}")
