"""How a 90 % interval (SPEC 4.1) reads in text: one formatter for the demo, the identify page and
the commissioning report, so that the three say the same thing the same way."""

from __future__ import annotations

import math

from ._result import INTERVAL_NAMES

#: The parameters that may be 0 (no backlash, no friction, no load torque): their interval always
#: reads ``[low .. high]``, never relative to a value that may be 0 or below the resolution.
MAY_BE_ZERO: frozenset[str] = frozenset({"backlash", "M_FC", "mu_F", "M_L0", "M_FCM", "mu_FM"})

#: The relative form is used while the interval's upper side lies within this share of the value
#: (above it, e.g. a damping of 0.02 in [0.004, 0.13], ``[low .. high]`` reads better than +500 %).
RELATIVE_UP_TO = 1.0


def _percent(x: float) -> str:
    """A share as a percentage with two significant digits (at least one decimal below 10 %)."""
    p = 100.0 * x
    return f"{p:.2g}" if p < 10.0 else f"{p:.0f}"


def interval_text(name: str, value: float | None, interval: tuple[float, float], *, scale: float = 1.0,
                  digits: int = 4) -> str:
    """The 90 % interval ``interval`` = ``(low, high)`` [SI] of parameter ``name`` around its
    reported ``value`` [SI; None: not identified] in words: ``+-x %`` where both sides lie within
    ``x %`` of the value and are about equal (within a factor 1.25; ``x`` the larger side, so the
    text covers the interval), ``-a/+b %`` where they differ, else ``[low .. high]`` in the unit
    ``scale`` x SI with ``digits`` significant digits (a parameter of :data:`MAY_BE_ZERO`, a value
    of 0, None or outside the interval, or an upper side above :data:`RELATIVE_UP_TO`)."""
    if name not in INTERVAL_NAMES:
        raise ValueError(f"name: expected one of {list(INTERVAL_NAMES)}, received {name!r}")
    low, high = (float(x) for x in interval)
    if not (math.isfinite(low) and math.isfinite(high)) or low > high:
        raise ValueError(f"interval of {name}: expected finite (low, high) with low <= high, received {interval!r}")
    if (name not in MAY_BE_ZERO and value is not None and value > 0.0 and 0.0 < low <= value <= high
            and high - value <= RELATIVE_UP_TO * value):
        down, up = (value - low) / value, (high - value) / value
        if max(down, up) <= 1.25 * min(down, up) or _percent(down) == _percent(up):
            return f"+-{_percent(max(down, up))} %"
        return f"-{_percent(down)}/+{_percent(up)} %"
    return f"[{low * scale:.{digits}g} .. {high * scale:.{digits}g}]"
