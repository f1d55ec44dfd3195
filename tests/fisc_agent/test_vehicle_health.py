"""Vehicle health (issue 36 item 2): the pure decoders of fisc_agent.flight.health and the
HealthReader, fed with real MAVLink frames (packed and decoded by pymavlink's dialect)."""

from __future__ import annotations

import pytest
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from fisc_agent.flight.health import (LandedState, SystemState, VehicleHealth, battery_pct_of, estimator_health,
                                      landed_state_of, system_state_of)
from fisc_agent.mavlink.health_reader import HealthReader, stream_requests

AP = mavlink.MAVLink(None, srcSystem=1, srcComponent=1)
DECODER = mavlink.MAVLink(None)

PX4_FLAGS_AT_REST = 1023
"""ESTIMATOR_STATUS.flags of PX4 SITL landed and disarmed (measured; includes CONST_POS_MODE)."""
AP_FLAGS_READY = 831
"""EKF_STATUS_REPORT.flags of ArduCopter SITL ready to arm (measured)."""


def wire(msg):
    """``msg`` packed to bytes and decoded again, as the link receives it."""
    return DECODER.decode(bytearray(msg.pack(AP)))


def sys_status(battery_remaining):
    return wire(mavlink.MAVLink_sys_status_message(0, 0, 0, 100, 12600, -1, battery_remaining, 0, 0, 0, 0, 0, 0))


def battery_status(remaining, battery_id=0):
    return wire(mavlink.MAVLink_battery_status_message(battery_id, 0, 0, 32767, [12600] + [65535] * 9, -1, -1, -1,
                                                       remaining))


def odometry(reset_counter):
    return wire(mavlink.MAVLink_odometry_message(1, 1, 1, 0, 0, 0, [1, 0, 0, 0], 0, 0, 0, 0, 0, 0, [0] * 21, [0] * 21,
                                                 reset_counter))


def system_time(unix_us, boot_ms):
    return wire(mavlink.MAVLink_system_time_message(unix_us, boot_ms))


# --------------------------------------------------------------------------------- pure decoders
@pytest.mark.parametrize("raw, state", [(0, SystemState.UNKNOWN), (3, SystemState.STANDBY), (4, SystemState.ACTIVE),
                                        (5, SystemState.CRITICAL), (8, SystemState.FLIGHT_TERMINATION),
                                        (9, SystemState.UNKNOWN), (255, SystemState.UNKNOWN)])
def test_system_state_of(raw, state):
    assert system_state_of(raw) == state


@pytest.mark.parametrize("raw, state", [(0, LandedState.UNKNOWN), (1, LandedState.ON_GROUND), (2, LandedState.IN_AIR),
                                        (3, LandedState.TAKEOFF), (4, LandedState.LANDING), (5, LandedState.UNKNOWN)])
def test_landed_state_of(raw, state):
    assert landed_state_of(raw) == state


@pytest.mark.parametrize("raw, pct", [(-1, None), (0, 0.0), (1, 1.0), (100, 100.0), (101, None), (-2, None)])
def test_battery_pct_bounds(raw, pct):
    assert battery_pct_of(raw) == pct


def test_estimator_flags_as_measured_on_both_autopilots_are_healthy():
    assert estimator_health(PX4_FLAGS_AT_REST, ardupilot=False) == (True, "")
    assert estimator_health(AP_FLAGS_READY, ardupilot=True) == (True, "")


@pytest.mark.parametrize("bit, text", [(1, "no attitude"), (2, "no horizontal velocity"), (4, "no vertical velocity"),
                                       (8, "no horizontal position"), (32, "no vertical position")])
def test_each_required_estimator_flag_missing_is_named(bit, text):
    for ardupilot, flags in ((False, PX4_FLAGS_AT_REST), (True, AP_FLAGS_READY)):
        ok, detail = estimator_health(flags & ~bit, ardupilot)
        assert not ok and detail == text


def test_bad_estimator_flags_differ_between_autopilots():
    assert estimator_health(PX4_FLAGS_AT_REST | 1024, False) == (False, "GNSS glitch")
    assert estimator_health(PX4_FLAGS_AT_REST | 2048, False) == (False, "accelerometer error")
    assert estimator_health(AP_FLAGS_READY | 1024, True) == (False, "uninitialised")
    assert estimator_health(AP_FLAGS_READY | 32768, True) == (False, "GNSS glitch")
    assert estimator_health(AP_FLAGS_READY | 128, True) == (False, "constant-position mode")
    assert estimator_health(0, True)[0] is False


def test_every_estimator_problem_is_named_in_one_comma_separated_detail():
    assert estimator_health(0, ardupilot=False) == (False, "no attitude, no horizontal velocity, no vertical velocity, "
                                                           "no horizontal position, no vertical position")
    assert estimator_health(PX4_FLAGS_AT_REST | 1024 | 2048, False) == (False, "GNSS glitch, accelerometer error")


def test_gps_time_needs_both_the_time_and_when_it_was_received():
    """``unix_time_at`` extrapolates to the second (a drift of seconds would misdate a fleet command), and is
    None unless both the GNSS time and its reception time are known."""
    h = VehicleHealth(gps_unix_s=1_000_000.0, gps_rx_s=10.0)
    assert h.unix_time_at(10.0) == 1_000_000.0
    assert h.unix_time_at(12.5) == 1_000_002.5 and h.unix_time_at(9.0) == 999_999.0  # before reception: earlier
    assert VehicleHealth(gps_unix_s=1_000_000.0).unix_time_at(12.5) is None
    assert VehicleHealth(gps_rx_s=10.0).unix_time_at(12.5) is None


def test_problems_at_the_battery_boundary_and_unknowns():
    from fisc_agent.flight.readiness import health_problems

    def texts(h, limit=None):
        return tuple(p.text for p in health_problems(h, limit))

    assert texts(VehicleHealth(), 25.0) == ()                          # nothing known: nothing wrong
    assert texts(VehicleHealth(battery_pct=25.0), 25.0) == ()          # equal: fine
    assert texts(VehicleHealth(battery_pct=24.9), 25.0) == ("battery 24.9 % < 25 %",)
    assert texts(VehicleHealth(battery_pct=5.0), None) == ()           # no limit given
    h = VehicleHealth(system_state=SystemState.CRITICAL, estimator_ok=False, estimator_detail="GNSS glitch")
    assert texts(h) == ("estimator: GNSS glitch", "autopilot state critical")
    assert texts(VehicleHealth(system_state=SystemState.STANDBY, estimator_ok=True)) == ()


# --------------------------------------------------------------------------------- HealthReader
def test_reader_folds_the_health_messages():
    r = HealthReader()
    r.on_message(wire(mavlink.MAVLink_heartbeat_message(2, 12, 29, 0, 4, 3)), 1.0)
    r.on_message(wire(mavlink.MAVLink_extended_sys_state_message(0, 2)), 1.0)
    r.on_message(sys_status(80), 1.0)
    assert r.health.battery_pct == 80.0
    r.on_message(battery_status(77), 1.1)
    r.on_message(sys_status(80), 1.2)          # BATTERY_STATUS is the better source once it reported
    r.on_message(battery_status(50, battery_id=1), 1.2)    # a second battery: not ours to judge here
    up = r.on_message(wire(mavlink.MAVLink_estimator_status_message(0, PX4_FLAGS_AT_REST | 1024, 0, 0, 0, 0, 0, 0,
                                                                    0, 0)), 1.3)
    home = wire(mavlink.MAVLink_home_position_message(473977429, 85455931, 489627, 1.5, -2.0, 0.25, [1, 0, 0, 0],
                                                      0, 0, 0))
    r.on_message(home, 1.4)
    h = r.health
    assert (h.system_state, h.landed, h.battery_pct) == (SystemState.ACTIVE, LandedState.IN_AIR, 77.0)
    assert up.estimator == (False, "GNSS glitch") and h.estimator_ok is False and h.estimator_detail == "GNSS glitch"
    assert h.home_ned_m == pytest.approx((1.5, -2.0, 0.25))
    ekf = wire(mavlink.MAVLink_ekf_status_report_message(AP_FLAGS_READY, 0, 0, 0, 0, 0))
    assert r.on_message(ekf, 1.5).estimator == (True, "") and r.health.estimator_ok


def test_home_in_a_geodetic_anchor_frame():
    r = HealthReader(home_to_ned=lambda lat, lon, alt: (lat, lon, alt))
    r.on_message(wire(mavlink.MAVLink_home_position_message(473977429, 85455931, 489627, 1, 2, 3, [1, 0, 0, 0],
                                                            0, 0, 0)), 0.0)
    assert r.health.home_ned_m == pytest.approx((47.3977429, 8.5455931, 489.627))


def test_reset_counter_first_value_is_a_baseline_and_wraps():
    r = HealthReader()
    assert r.on_message(odometry(15), 0.0).reset_steps == 0       # PX4 SITL boots with 15 (measured)
    assert r.on_message(odometry(15), 0.1).reset_steps == 0
    assert r.on_message(odometry(16), 0.2).reset_steps == 1
    assert r.on_message(odometry(255), 0.3).reset_steps == 239
    assert r.on_message(odometry(0), 0.4).reset_steps == 1        # uint8 wrap: 255 -> 0 is one reset
    assert r.on_message(odometry(2), 0.5).reset_steps == 2
    assert r.health.position_resets == 1 + 239 + 1 + 2


def test_system_time_gives_gps_time_and_detects_reboots():
    r = HealthReader()
    assert not r.on_message(system_time(0, 5000), 10.0).rebooted
    assert r.health.gps_unix_s is None and r.health.unix_time_at(11.0) is None   # 0: the autopilot has no time
    assert not r.on_message(system_time(1_796_459_816_339_252, 6000), 11.0).rebooted
    assert r.health.gps_unix_s == pytest.approx(1_796_459_816.339252) and r.health.gps_rx_s == 11.0
    assert r.health.unix_time_at(13.5) == pytest.approx(1_796_459_818.839252, abs=1e-6)  # 2.5 s later, to the us
    assert not r.on_message(system_time(1, 6000), 12.0).rebooted                   # equal boot time: no reboot
    r.on_message(odometry(7), 12.0)
    up = r.on_message(system_time(1, 5999), 13.0)                                  # 1 ms backwards: reboot
    assert up.rebooted and r.health.autopilot_reboots == 1
    assert r.on_message(odometry(0), 13.1).reset_steps == 0       # a new boot: its counter is a new baseline


def test_unknown_messages_change_nothing():
    r = HealthReader()
    before = r.health
    assert r.on_message(wire(mavlink.MAVLink_attitude_message(0, 0, 0, 0, 0, 0, 0)), 0.0).estimator is None
    assert r.health is before


def test_stream_requests_per_autopilot():
    ids = lambda ap, geo=False: {m for m, _ in stream_requests(ap, geo, 50.0)}
    assert mavlink.MAVLINK_MSG_ID_ESTIMATOR_STATUS in ids("px4") and mavlink.MAVLINK_MSG_ID_ODOMETRY in ids("px4")
    assert dict(stream_requests("px4", False, 50.0))[mavlink.MAVLINK_MSG_ID_ODOMETRY] == 10.0   # not at 50 Hz
    assert mavlink.MAVLINK_MSG_ID_EKF_STATUS_REPORT not in ids("px4")            # PX4: UNSUPPORTED (measured)
    assert mavlink.MAVLINK_MSG_ID_EKF_STATUS_REPORT in ids("ardupilot")
    assert not {mavlink.MAVLINK_MSG_ID_ESTIMATOR_STATUS, mavlink.MAVLINK_MSG_ID_ODOMETRY} & ids("ardupilot")  # DENIED
    assert {mavlink.MAVLINK_MSG_ID_ESTIMATOR_STATUS, mavlink.MAVLINK_MSG_ID_EKF_STATUS_REPORT} <= ids(None)
    assert stream_requests("px4", False, 50.0)[0] == (mavlink.MAVLINK_MSG_ID_LOCAL_POSITION_NED, 50.0)
    assert stream_requests("px4", True, 50.0)[0] == (mavlink.MAVLINK_MSG_ID_GLOBAL_POSITION_INT, 50.0)
    common = {mavlink.MAVLINK_MSG_ID_SYS_STATUS, mavlink.MAVLINK_MSG_ID_BATTERY_STATUS,
              mavlink.MAVLINK_MSG_ID_EXTENDED_SYS_STATE, mavlink.MAVLINK_MSG_ID_SYSTEM_TIME,
              mavlink.MAVLINK_MSG_ID_HOME_POSITION}
    assert common <= ids("px4") and common <= ids("ardupilot")
