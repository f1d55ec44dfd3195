"""The MAVSDK backend dates its position fixes on the autopilot's clock (``autopilot_time``)."""

import pytest

from fisc_agent.mavlink.mavsdk_backend import ODOMETRY_STAMP_MAX_AGE_S, autopilot_time


def test_a_fix_is_dated_by_the_newest_odometry_stamp_plus_the_gap_since_it():
    assert autopilot_time((100.0, 42.0), 100.02) == pytest.approx(42.02)
    assert autopilot_time((100.0, 42.0), 100.0) == 42.0


def test_no_stamp_or_a_stale_one_leaves_the_fix_on_receive_time():
    assert autopilot_time(None, 5.0) is None
    assert autopilot_time((100.0, 42.0), 100.0 + ODOMETRY_STAMP_MAX_AGE_S + 0.01) is None
    assert autopilot_time((100.0, 42.0), 99.9) is None  # a stamp from the future: clocks disagree


def test_a_slow_simulator_is_seen_on_the_autopilot_clock():
    # PX4 SITL at 0.75 x real time: odometry stamps 0.0375 s apart arrive 0.05 s apart; fixes dated by
    # them advance at the autopilot's rate, so a position's rate of change is not read 25 % low
    stamps = [(100.0 + 0.05 * k, 10.0 + 0.0375 * k) for k in range(5)]
    times = [autopilot_time(st, st[0] + 0.01) for st in stamps]
    steps = [b - a for a, b in zip(times, times[1:])]
    assert steps == pytest.approx([0.0375] * 4)
