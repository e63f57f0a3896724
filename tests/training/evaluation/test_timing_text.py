"""The evaluation report says what its wall time covers."""

from training.evaluation._report import timing_lines


def test_the_wall_time_says_the_start_up_is_not_counted():
    first = timing_lines({"total_s": 12.4, "sets": {}}, 2)[0]
    assert first.startswith("Wall time of this run's study (the command's start-up not counted): 12 s")
