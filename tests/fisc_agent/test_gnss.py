"""``fisc_agent.mavlink.gnss``: the receiver's velocity decoded from raw GPS_RAW_INT bytes, and the bias
the tracker learns from it."""

import math

import pytest
from pymavlink.dialects.v20 import ardupilotmega as mavlink2

from fisc_agent.flight.tracking import ParcelTracker, TrackingConfig
from fisc_agent.mavlink.gnss import UINT16_UNKNOWN, gnss_velocity, ground_velocity, mavsdk_ground_velocity


def _decoded(fix_type=3, vel=150, cog=9000):
    """A GPS_RAW_INT as an autopilot sends it: packed to bytes, then parsed back."""
    mav = mavlink2.MAVLink(None, srcSystem=1, srcComponent=1)
    raw = mav.gps_raw_int_encode(123456789, fix_type, 473977420, 85455940, 488000, 70, 100, vel, cog, 12).pack(mav)
    return mavlink2.MAVLink(None).decode(bytearray(raw))


@pytest.mark.parametrize("fix_type, vel, cog, expect", [
    (3, 150, 9000, (0.0, 1.5)),                  # 1.5 m/s on a course of 90 deg: east
    (3, 150, 0, (1.5, 0.0)),                     # north
    (3, 200, 22500, (-math.sqrt(2), -math.sqrt(2))),   # south-west
    (3, 0, 0, (0.0, 0.0)),                       # standing
    (6, 150, 18000, (-1.5, 0.0)),                # RTK fixed counts as 3D
    (2, 150, 9000, None),                        # a 2D fix: not used
    (0, 150, 9000, None),                        # no fix
    (3, UINT16_UNKNOWN, 9000, None),             # speed unknown
    (3, 150, UINT16_UNKNOWN, None),              # course unknown
])
def test_gnss_velocity_from_raw_bytes(fix_type, vel, cog, expect):
    got = gnss_velocity(_decoded(fix_type, vel, cog), 12.5)
    if expect is None:
        assert got is None
    else:
        assert got.t_s == 12.5 and got.vel_ne_m_s == pytest.approx(expect, abs=1e-9)


@pytest.mark.parametrize("fix_type, speed, course, expect", [
    (3, 1.5, 90.0, (0.0, 1.5)),
    (3, 1.5, 359.99, (1.5 * math.cos(math.radians(0.01)), -1.5 * math.sin(math.radians(0.01)))),  # just west of north
    (2, 1.5, 90.0, None),                                           # just below a 3D fix
    (3, 655.34, 90.0, (0.0, 655.34)),                               # the largest known speed
    (3, 655.35, 90.0, None),                                        # GPS_RAW_INT's unknown, as MAVSDK scales it
    (3, 1.5, 655.35, None),
    (3, math.nan, 90.0, None),                                      # or as NaN
    (3, 1.5, math.inf, None),
])
def test_mavsdks_raw_gps_velocity_at_its_boundaries(fix_type, speed, course, expect):
    got = mavsdk_ground_velocity(4.0, fix_type, speed, course)
    if expect is None:
        assert got is None
    else:
        assert got.t_s == 4.0 and got.vel_ne_m_s == pytest.approx(expect, abs=1e-9)
        assert ground_velocity(4.0, fix_type, speed, course) == got


def test_the_tracker_learns_the_horizontal_bias_from_the_gnss_velocity_and_the_vertical_from_the_position():
    # the estimate reports 1.0 m/s along x while the receiver says 1.3, 0.2; the position moves as
    # the estimate says (an EKF whose position follows its own velocity) and climbs at 0.1 m/s more
    cfg = TrackingConfig(bias_time_constant_s=1.0, gnss_bias_time_constant_s=0.5)
    with_gnss, without = ParcelTracker(cfg), ParcelTracker(cfg)
    for k in range(100):                         # 5 s at 20 Hz
        t = 0.05 * k
        pos, vel = (1.0 * t, 0.0, 0.1 * t), (1.0, 0.0, 0.0)
        with_gnss.observe(t, pos, vel, (1.3, 0.2))
        without.observe(t, pos, vel)
    assert with_gnss.bias_m_s == pytest.approx((0.3, 0.2, 0.1), abs=0.005)
    assert without.bias_m_s == pytest.approx((0.0, 0.0, 0.1), abs=0.005)
    # the horizontal time constant: after one of them, 1 - 1/e of a step
    fast = ParcelTracker(cfg)
    for k in range(11):                          # 0.5 s after the first fix
        fast.observe(0.05 * k, (0.0, 0.0, 0.0), (0.0, 0.0, 0.0), (1.0, 0.0))
    assert fast.bias_m_s[0] == pytest.approx(1 - (1 - 0.1) ** 10, abs=1e-9)
    # the correction switched off switches off the GNSS one too
    off = ParcelTracker(TrackingConfig(bias_time_constant_s=0.0))
    off.observe(0.0, (0.0, 0.0, 0.0), (0.0, 0.0, 0.0), (1.0, 0.0))
    off.observe(0.05, (0.0, 0.0, 0.0), (0.0, 0.0, 0.0), (1.0, 0.0))
    assert off.bias_m_s == (0.0, 0.0, 0.0)
