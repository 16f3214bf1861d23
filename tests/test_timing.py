"""Phase timings and the time left of a progress line."""

from meshseg.timing import Timings, time_left


def test_time_left_at_the_pace_so_far():
    assert time_left(30.0, 3, 4) == "about 40 s left"
    assert time_left(600.0, 2, 3) == "about 15 min left"  # from 2 minutes on, in minutes
    assert time_left(0.0, 0, 5) == ""  # nothing done yet: no pace to go by
    assert time_left(12.0, 4, 0) == "about 0 s left"


def test_timings_add_up_per_phase():
    t = Timings()
    for _ in range(2):
        with t("train"):
            pass
    assert list(t) == ["train"] and t["train"] >= 0
