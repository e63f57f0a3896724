"""How an interval reads (``interval_text``): relative where it is about the value, else its ends."""

from __future__ import annotations

import pytest

from training.identification import interval_text


@pytest.mark.parametrize("name, value, interval, text", [
    ("f_e", 30.0, (29.7, 30.3), "+-1 %"),
    ("f_e", 30.0, (29.7, 30.36), "+-1.2 %"),  # sides 1 % and 1.2 %: within a factor 1.25, the larger one
    ("V_J", 1.0, (0.8, 1.3), "-20/+30 %"),
    ("C_F", 400.0, (200.0, 800.0), "-50/+100 %"),  # the upper side exactly at the value: still relative
    ("C_F", 400.0, (200.0, 800.1), "[200 .. 800.1]"),  # above: the ends read better
    ("f_e", None, (500.0, 2000.0), "[500 .. 2000]"),  # not identified (a stiff answer)
    ("d", 0.0, (0.0, 0.01), "[0 .. 0.01]"),
    ("J_L", 0.025, (0.02, 0.024), "[0.02 .. 0.024]"),  # the value outside its interval
    ("M_FC", 0.2, (0.19, 0.21), "[0.19 .. 0.21]"),  # may be 0: never relative
    ("backlash", 0.0087266, (0.0, 0.0174533), "[0 .. 1]"),  # scale: rad -> deg
])
def test_interval_text(name, value, interval, text):
    assert interval_text(name, value, interval, scale=57.29577951308232 if name == "backlash" else 1.0) == text


def test_interval_text_rejects_what_is_no_interval():
    with pytest.raises(ValueError, match="name: expected one of"):
        interval_text("s_N", 1.0, (0.5, 2.0))
    with pytest.raises(ValueError, match="low <= high"):
        interval_text("f_e", 30.0, (31.0, 29.0))
    with pytest.raises(ValueError, match="finite"):
        interval_text("f_e", 30.0, (29.0, float("inf")))
