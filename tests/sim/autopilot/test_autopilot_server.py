"""The emulator over real sockets on 127.0.0.1, flown by an unmodified pymavlink client."""

from __future__ import annotations

import math
import time

import pytest
from pymavlink import mavutil
from pymavlink.dialects.v20 import ardupilotmega as ML2

from autopilot_testkit import POS_ONLY_MASK, POS_VEL_MASK, Client

from ...ports import free_tcp_port
from fisc_agent.flight.drag import thrust_accel_ne
from fisc_agent.flight.frames import GeodeticAnchor
from sim.autopilot.server import AutopilotEmulator
from sim.autopilot.setpoints import resolve_local_setpoint
from sim.autopilot.transport import parse_emulator_endpoint as parse_endpoint

ML = mavutil.mavlink
PX4_OFFBOARD = 6 << 16
PX4_LOITER = (4 << 16) | (3 << 24)


# ---------------------------------------------------------------- pure helpers
@pytest.mark.parametrize(
    ("url", "kind", "host", "port"),
    [
        ("udpin:0.0.0.0:14540", "udpin", "0.0.0.0", 14540),
        ("udp::14540", "udpin", "0.0.0.0", 14540),
        ("udpout:127.0.0.1:14550", "udpout", "127.0.0.1", 14550),
        ("udpin://0.0.0.0:14540", "udpin", "0.0.0.0", 14540),
        ("tcpin:0.0.0.0:5760", "tcpin", "0.0.0.0", 5760),
        ("tcp:localhost:5760", "tcp", "localhost", 5760),
        ("tcpout:localhost:5760", "tcp", "localhost", 5760),
    ],
)
def test_parse_endpoint(url, kind, host, port):
    ep = parse_endpoint(url)
    assert (ep.kind, ep.host, ep.port) == (kind, host, port)


@pytest.mark.parametrize(
    "url", ["serial:/dev/ttyUSB0", "udpin:0.0.0.0", "udpout:host:x", "udpout:127.0.0.1:0", "/dev/ttyACM0:57600",
            "udpbcast:255.255.255.255:14550"],
)
def test_parse_endpoint_errors(url):
    with pytest.raises(ValueError, match="endpoint"):
        parse_endpoint(url)


def test_emulator_geodesy_is_the_agents_wgs84_anchor():
    em = AutopilotEmulator("udpin:127.0.0.1:0", home_lla=(47.397742, 8.545594, 488.0))
    assert em.anchor == GeodeticAnchor(47.397742, 8.545594, 488.0, 0.0)
    lat, lon, alt = em.anchor.ned_to_geodetic(100.0, -50.0, -10.0)
    assert lat > 47.397742 and lon < 8.545594 and alt == pytest.approx(498.0)
    # one degree of latitude at 47.4 deg N is 111,180 m on WGS-84 (the old sphere said 111,319 m)
    assert (lat - 47.397742) * 111_180.0 == pytest.approx(100.0, rel=2e-4)


def test_setpoint_type_mask_and_frames():
    vel_only = 0b0000_1101_1100_0111
    sp = resolve_local_setpoint(ML.MAV_FRAME_LOCAL_NED, vel_only, (9, 9, 9), (1, 2, 3), 0, 0, (0, 0, 0), 0)
    assert all(math.isnan(x) for x in sp.position_ned_m) and sp.velocity_ned_m_s == (1, 2, 3)
    assert math.isnan(sp.yaw_rad)
    sp = resolve_local_setpoint(ML.MAV_FRAME_LOCAL_NED, POS_ONLY_MASK, (1, 2, -3), (9, 9, 9), 0, 0, (0, 0, 0), 0)
    assert sp.position_ned_m == (1, 2, -3) and all(math.isnan(x) for x in sp.velocity_ned_m_s)
    sp = resolve_local_setpoint(ML.MAV_FRAME_LOCAL_NED, POS_VEL_MASK, (1, 2, -3), (4, 5, 6), 0, 0, (0, 0, 0), 0)
    assert sp.position_ned_m == (1, 2, -3) and sp.velocity_ned_m_s == (4, 5, 6)
    sp = resolve_local_setpoint(ML.MAV_FRAME_LOCAL_OFFSET_NED, POS_ONLY_MASK, (1, 0, 0), (0, 0, 0), 0, 0, (5, 5, -5), 0)
    assert sp.position_ned_m == (6, 5, -5)
    sp = resolve_local_setpoint(ML.MAV_FRAME_BODY_NED, vel_only, (0, 0, 0), (1, 0, 0), 0, 0, (0, 0, 0), math.pi / 2)
    assert sp.velocity_ned_m_s == pytest.approx((0, 1, 0))  # forward while facing east
    sp = resolve_local_setpoint(ML.MAV_FRAME_BODY_OFFSET_NED, POS_ONLY_MASK, (2, 0, 0), (0, 0, 0), 0, 0, (1, 1, -1), math.pi)
    assert sp.position_ned_m == pytest.approx((-1, 1, -1))
    assert resolve_local_setpoint(ML.MAV_FRAME_GLOBAL, vel_only, (0, 0, 0), (1, 0, 0), 0, 0, (0, 0, 0), 0) is None


def test_setpoint_acceleration_kept_by_its_mask_bits_and_dropped_as_a_force():
    vel_acc = 0b0000_1100_0000_0111  # 3079: the agent's velocity with the drag's acceleration (PX4)
    sp = resolve_local_setpoint(ML.MAV_FRAME_LOCAL_NED, vel_acc, (9, 9, 9), (1, 2, 0), 0, 0, (0, 0, 0), 0, (0.5, -0.25, 0))
    assert sp.velocity_ned_m_s == (1, 2, 0) and sp.accel_ned_m_s2 == (0.5, -0.25, 0)
    ay_ignored = vel_acc | ML.POSITION_TARGET_TYPEMASK_AY_IGNORE
    sp = resolve_local_setpoint(ML.MAV_FRAME_LOCAL_NED, ay_ignored, (9, 9, 9), (1, 2, 0), 0, 0, (0, 0, 0), 0, (0.5, -0.25, 0))
    assert sp.accel_ned_m_s2[0] == 0.5 and math.isnan(sp.accel_ned_m_s2[1]) and sp.accel_ned_m_s2[2] == 0
    as_force = vel_acc | ML.POSITION_TARGET_TYPEMASK_FORCE_SET
    sp = resolve_local_setpoint(ML.MAV_FRAME_LOCAL_NED, as_force, (9, 9, 9), (1, 2, 0), 0, 0, (0, 0, 0), 0, (0.5, -0.25, 0))
    assert all(math.isnan(a) for a in sp.accel_ned_m_s2) and sp.velocity_ned_m_s == (1, 2, 0)
    sp = resolve_local_setpoint(ML.MAV_FRAME_LOCAL_NED, 0b0000_1101_1100_0111, (9, 9, 9), (1, 2, 0), 0, 0, (0, 0, 0), 0,
                                (0.5, -0.25, 0))  # the velocity-only mask
    assert all(math.isnan(a) for a in sp.accel_ned_m_s2)
    sp = resolve_local_setpoint(ML.MAV_FRAME_BODY_NED, vel_acc, (0, 0, 0), (1, 0, 0), 0, 0, (0, 0, 0), math.pi / 2, (0.5, 0, 0))
    assert sp.accel_ned_m_s2 == pytest.approx((0, 0.5, 0))  # forward while facing east, as the velocity
    nan = (math.nan, math.nan, math.nan)
    sp = resolve_local_setpoint(ML.MAV_FRAME_LOCAL_NED, vel_acc, (9, 9, 9), (1, 2, 0), 0, 0, (0, 0, 0), 0, nan)
    assert all(math.isnan(a) for a in sp.accel_ned_m_s2)  # NaN fields: none, whatever the mask


# ---------------------------------------------------------------- PX4 over UDP
def test_heartbeat_identifies_a_px4_quadrotor_in_hold(make_emulator, connect):
    em = make_emulator(personality="px4", sysid=1)
    c = connect(em)
    hb = c.wait("HEARTBEAT")
    assert hb.autopilot == ML.MAV_AUTOPILOT_PX4 and hb.type == ML.MAV_TYPE_QUADROTOR
    assert hb.base_mode & ML.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED
    assert not hb.base_mode & ML.MAV_MODE_FLAG_SAFETY_ARMED
    assert hb.custom_mode == PX4_LOITER
    assert c.wait("EXTENDED_SYS_STATE", past=True).landed_state == ML.MAV_LANDED_STATE_ON_GROUND
    gp = c.wait("GLOBAL_POSITION_INT", past=True)
    assert gp.lat == round(47.397742e7) and gp.relative_alt == 0
    sys_status = c.wait("SYS_STATUS", past=True)
    assert sys_status.onboard_control_sensors_health & ML.MAV_SYS_STATUS_SENSOR_GPS


def test_px4_arm_stream_offboard_and_fly_north(make_emulator, connect):
    em = make_emulator(personality="px4")
    c = connect(em)
    c.wait("HEARTBEAT")
    assert c.arm().result == ML.MAV_RESULT_ACCEPTED
    c.wait("HEARTBEAT", lambda m: m.base_mode & ML.MAV_MODE_FLAG_SAFETY_ARMED)
    climb = c.streamer(0.0, 0.0, -2.0)
    c.run_for(0.5, climb)
    assert c.set_mode_px4(6, tick=climb).result == ML.MAV_RESULT_ACCEPTED
    c.wait("HEARTBEAT", lambda m: m.custom_mode == PX4_OFFBOARD, tick=climb)
    c.run_for(0.7, climb)
    north = c.streamer(2.0, 0.0, 0.0)
    c.run_for(1.5, north)
    lp = c.wait("LOCAL_POSITION_NED", tick=north)
    assert lp.x > 1.0 and lp.vx > 1.5 and abs(lp.y) < 0.1 and lp.z < -0.5
    assert em.state.position_ned_m[0] > 1.0
    assert em.stats["setpoints"] > 40 and em.stats["errors"] == 0


def test_px4_offboard_refused_without_setpoint_stream(make_emulator, connect):
    em = make_emulator(personality="px4")
    c = connect(em)
    c.arm()
    ack = c.set_mode_px4(6)
    assert ack.result == ML.MAV_RESULT_TEMPORARILY_REJECTED
    assert c.wait("HEARTBEAT").custom_mode == PX4_LOITER
    assert "setpoint" in c.wait("STATUSTEXT", lambda m: "Offboard" in m.text, past=True).text


def test_px4_offboard_loss_failsafe_holds_after_com_of_loss_t(make_emulator, connect):
    em = make_emulator(personality="px4", start_ned=(0.0, 0.0, -5.0))
    c = connect(em)
    fly = c.streamer(1.5, 0.0, 0.0)
    c.run_for(0.3, fly)
    assert c.set_mode_px4(6, tick=fly).result == ML.MAV_RESULT_ACCEPTED
    c.run_for(0.5, fly)
    t_stop = time.monotonic()
    hb = c.wait("HEARTBEAT", lambda m: m.custom_mode == PX4_LOITER, timeout=4.0)
    assert time.monotonic() - t_stop > 0.9  # not before COM_OF_LOSS_T = 1 s
    assert hb.base_mode & ML.MAV_MODE_FLAG_SAFETY_ARMED
    c.wait("STATUSTEXT", lambda m: "offboard" in m.text.lower(), past=True)
    c.run_for(1.0)
    lp = c.wait("LOCAL_POSITION_NED")
    assert math.hypot(lp.vx, lp.vy) < 0.5  # decelerating to a hover


def test_land_lands_and_disarms(make_emulator, connect):
    em = make_emulator(personality="px4", start_ned=(0.0, 0.0, -0.6))
    c = connect(em)
    c.mav.param_set_send(1, 1, b"COM_DISARM_LAND", 0.5, ML.MAV_PARAM_TYPE_REAL32)
    c.wait("PARAM_VALUE", lambda m: m.param_id == "COM_DISARM_LAND")
    assert c.command(ML.MAV_CMD_NAV_LAND).result == ML.MAV_RESULT_ACCEPTED
    c.wait("EXTENDED_SYS_STATE", lambda m: m.landed_state == ML.MAV_LANDED_STATE_LANDING)
    c.wait("EXTENDED_SYS_STATE", lambda m: m.landed_state == ML.MAV_LANDED_STATE_ON_GROUND, timeout=4.0)
    c.wait("HEARTBEAT", lambda m: not m.base_mode & ML.MAV_MODE_FLAG_SAFETY_ARMED, timeout=2.0)
    assert em.state.position_ned_m[2] == 0.0 and not em.state.armed


def test_ardupilot_guided_takeoff_and_velocity(make_emulator, connect):
    em = make_emulator(personality="ardupilot")
    c = connect(em)
    hb = c.wait("HEARTBEAT")
    assert hb.autopilot == ML.MAV_AUTOPILOT_ARDUPILOTMEGA and hb.custom_mode == 0  # STABILIZE
    c.mav.set_mode_send(1, ML.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, 4)  # SET_MODE message -> GUIDED
    assert c.wait("COMMAND_ACK", lambda m: m.command == ML.MAVLINK_MSG_ID_SET_MODE).result == ML.MAV_RESULT_ACCEPTED
    c.wait("HEARTBEAT", lambda m: m.custom_mode == 4)
    assert c.arm().result == ML.MAV_RESULT_ACCEPTED
    assert c.command(ML.MAV_CMD_NAV_TAKEOFF, 0, 0, 0, 0, 0, 0, 1.5).result == ML.MAV_RESULT_ACCEPTED
    c.wait("EXTENDED_SYS_STATE", lambda m: m.landed_state == ML.MAV_LANDED_STATE_TAKEOFF)
    c.wait("GLOBAL_POSITION_INT", lambda m: m.relative_alt > 1300, timeout=4.0)
    east = c.streamer(0.0, 1.5, 0.0)
    c.run_for(1.2, east)
    lp = c.wait("LOCAL_POSITION_NED", tick=east)
    assert lp.y > 0.5 and lp.vy > 1.0 and lp.z == pytest.approx(-1.5, abs=0.3)


def test_ardupilot_land_mode_disarms_on_the_ground(make_emulator, connect):
    em = make_emulator(personality="ardupilot", start_ned=(0.0, 0.0, -0.5))
    c = connect(em)
    c.mav.set_mode_send(1, ML.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, 9)
    c.wait("HEARTBEAT", lambda m: m.custom_mode == 9)
    c.wait("HEARTBEAT", lambda m: not m.base_mode & ML.MAV_MODE_FLAG_SAFETY_ARMED, timeout=4.0)
    assert em.state.position_ned_m[2] == 0.0


def test_params_list_read_set(make_emulator, connect):
    em = make_emulator(personality="px4")
    c = connect(em)
    c.mav.param_request_list_send(1, 1)
    first = c.wait("PARAM_VALUE")
    names = {first.param_id}
    for _ in range(first.param_count - 1):
        names.add(c.wait("PARAM_VALUE").param_id)
    assert {"COM_OF_LOSS_T", "COM_OBL_RC_ACT"} <= names
    c.mav.param_set_send(1, 1, b"COM_OF_LOSS_T", 0.4, ML.MAV_PARAM_TYPE_REAL32)
    assert c.wait("PARAM_VALUE", lambda m: m.param_id == "COM_OF_LOSS_T").param_value == pytest.approx(0.4)
    assert em.vehicle.params["COM_OF_LOSS_T"] == pytest.approx(0.4)
    c.mav.param_request_read_send(1, 1, b"COM_OBL_RC_ACT", -1)
    pv = c.wait("PARAM_VALUE", lambda m: m.param_id == "COM_OBL_RC_ACT")
    assert pv.param_type == ML.MAV_PARAM_TYPE_INT32


def test_ardupilot_params(make_emulator, connect):
    em = make_emulator(personality="ardupilot")
    c = connect(em)
    c.mav.param_request_read_send(1, 1, b"GUID_TIMEOUT", -1)
    assert c.wait("PARAM_VALUE", lambda m: m.param_id == "GUID_TIMEOUT").param_value == pytest.approx(3.0)
    c.mav.param_set_send(1, 1, b"FS_GCS_ENABLE", 1.0, ML.MAV_PARAM_TYPE_INT8)
    assert c.wait("PARAM_VALUE", lambda m: m.param_id == "FS_GCS_ENABLE").param_value == 1.0


def test_requests_version_intervals_missions_timesync(make_emulator, connect):
    em = make_emulator(personality="px4", rate_position_hz=2.0)
    c = connect(em)
    ack = c.command(ML.MAV_CMD_REQUEST_MESSAGE, ML.MAVLINK_MSG_ID_AUTOPILOT_VERSION)
    assert ack.result == ML.MAV_RESULT_ACCEPTED
    av = c.wait("AUTOPILOT_VERSION")
    assert av.capabilities & ML.MAV_PROTOCOL_CAPABILITY_MAVLINK2
    assert av.capabilities & ML.MAV_PROTOCOL_CAPABILITY_PARAM_ENCODE_BYTEWISE
    assert c.command(ML.MAV_CMD_REQUEST_AUTOPILOT_CAPABILITIES, 1).result == ML.MAV_RESULT_ACCEPTED
    c.wait("AUTOPILOT_VERSION")
    assert c.command(ML.MAV_CMD_REQUEST_MESSAGE, ML.MAVLINK_MSG_ID_HOME_POSITION).result == ML.MAV_RESULT_ACCEPTED
    c.wait("HOME_POSITION")
    assert c.command(ML.MAV_CMD_SET_MESSAGE_INTERVAL, ML.MAVLINK_MSG_ID_LOCAL_POSITION_NED, 20_000).result == 0
    first = c.wait("LOCAL_POSITION_NED")
    for _ in range(10):
        last = c.wait("LOCAL_POSITION_NED")
    assert last.time_boot_ms - first.time_boot_ms < 1000  # ~50 Hz now, not 2 Hz
    assert c.command(ML.MAV_CMD_DO_WINCH).result == ML.MAV_RESULT_UNSUPPORTED
    c.mav.mission_request_list_send(1, 1)
    assert c.wait("MISSION_COUNT").count == 0
    c.mav.timesync_send(0, 12345)
    assert c.wait("TIMESYNC", lambda m: m.ts1 == 12345).tc1 > 0


def _mavlink2(c: Client) -> Client:
    """The client reading MAVLink 2's own messages (ODOMETRY: id 331), not mavutil's MAVLink 1 default."""
    c.conn.mav = c.mav = ML2.MAVLink(c.conn, srcSystem=255, srcComponent=190)
    return c


def test_px4_streams_odometry_on_request_with_the_attitude_of_its_thrust(make_emulator, connect):
    em = make_emulator(personality="px4")
    c = _mavlink2(connect(em))
    c.wait("HEARTBEAT")
    assert c.arm().result == ML.MAV_RESULT_ACCEPTED
    climb = c.streamer(0.0, 0.0, -2.0)
    c.run_for(0.5, climb)
    assert c.set_mode_px4(6, tick=climb).result == ML.MAV_RESULT_ACCEPTED
    c.wait("HEARTBEAT", lambda m: m.custom_mode == PX4_OFFBOARD, tick=climb)
    c.run_for(0.7, climb)
    assert c.command(ML.MAV_CMD_SET_MESSAGE_INTERVAL, ML2.MAVLINK_MSG_ID_ODOMETRY, 50_000).result == 0
    level = c.wait("ODOMETRY", tick=climb)
    assert thrust_accel_ne(tuple(level.q)) == pytest.approx((0.0, 0.0), abs=0.05)
    east = c.streamer(0.0, 2.0, 0.0)
    c.run_for(0.3, east)  # accelerating east: the thrust leans east, a roll to the right at heading north
    od = c.wait("ODOMETRY", tick=east)
    assert (od.frame_id, od.child_frame_id, od.reset_counter) == (ML.MAV_FRAME_LOCAL_NED, ML2.MAV_FRAME_BODY_FRD, 0)
    assert sum(x * x for x in od.q) == pytest.approx(1.0, abs=1e-6)
    acc = thrust_accel_ne(tuple(od.q))
    assert acc is not None and acc[1] > 0.5 and abs(acc[0]) < 0.1
    assert od.vy > 0.1 and abs(od.vx) < 0.1  # body FRD: right is east at heading north
    assert od.time_usec > 0 and math.isnan(od.pose_covariance[0])


def test_ardupilot_refuses_odometry_as_the_real_one_does(make_emulator, connect):
    c = _mavlink2(connect(make_emulator(personality="ardupilot")))
    c.wait("HEARTBEAT")
    assert c.command(ML.MAV_CMD_SET_MESSAGE_INTERVAL, ML2.MAVLINK_MSG_ID_ODOMETRY, 100_000).result != 0


def test_packet_loss_is_observable(make_emulator, connect):
    em = make_emulator(personality="px4", loss=0.5, seed=1)
    c = connect(em)
    for _ in range(20):
        c.wait("LOCAL_POSITION_NED", timeout=10)
    assert em.stats["tx_dropped"] > 0 and em.stats["tx"] > 0
    assert c.conn.mav_loss > 0  # sequence gaps seen by the client
    clean = make_emulator(personality="px4")
    c2 = connect(clean)
    for _ in range(10):
        c2.wait("LOCAL_POSITION_NED")
    assert c2.conn.mav_loss == 0


def test_latency_delays_replies(make_emulator, connect):
    em = make_emulator(personality="px4", latency_s=0.4)
    c = connect(em)
    c.wait("HEARTBEAT")
    t0 = time.monotonic()
    c.command(ML.MAV_CMD_REQUEST_MESSAGE, ML.MAVLINK_MSG_ID_AUTOPILOT_VERSION)
    assert time.monotonic() - t0 >= 0.35


def test_position_dropout_window(make_emulator, connect):
    em = make_emulator(personality="px4", position_dropouts=((0.6, 0.8),))
    c = connect(em)
    seen = []
    arm_results = {}  # "during" / "after" the dropout -> (emulator time sent, time answered, result)
    end = time.monotonic() + 3.0
    while time.monotonic() < end and "after" not in arm_results:
        m = c.conn.recv_match(type=["LOCAL_POSITION_NED", "GLOBAL_POSITION_INT"], blocking=True, timeout=0.1)
        if m is not None:
            seen.append(m.time_boot_ms)
        phase = "during" if 0.8 < em.time_s < 1.2 else "after" if em.time_s > 1.6 else None
        if phase is not None and phase not in arm_results:
            t_sent = em.time_s
            result = c.arm().result
            arm_results[phase] = (t_sent, em.time_s, result)
    # both attempts happened (no assertion hidden behind a timing branch), the first one wholly
    # inside the dropout: refused for want of a position; the positive control after it: armed
    assert set(arm_results) == {"during", "after"}, arm_results
    t_sent, t_done, result = arm_results["during"]
    assert 0.6 <= t_sent and t_done < 1.4, f"the machine was too slow to probe inside the dropout: {arm_results}"
    assert result == ML.MAV_RESULT_TEMPORARILY_REJECTED  # no position estimate
    assert arm_results["after"][2] == ML.MAV_RESULT_ACCEPTED
    assert any(t < 600 for t in seen) and any(t >= 1400 for t in seen)
    assert not any(600 <= t < 1400 for t in seen)
    assert em.stats["position_suppressed"] > 0


def test_tcp_server_endpoint(make_emulator):
    port = free_tcp_port()
    em = make_emulator(f"tcpin:127.0.0.1:{port}", personality="ardupilot")
    c = Client(f"tcp:127.0.0.1:{port}")
    try:
        assert c.wait("HEARTBEAT").autopilot == ML.MAV_AUTOPILOT_ARDUPILOTMEGA
        c.mav.set_mode_send(1, ML.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, 4)
        c.wait("HEARTBEAT", lambda m: m.custom_mode == 4)
        assert em.state.mode.value == "guided"
    finally:
        c.close()


def test_many_emulators_in_one_process(make_emulator, connect):
    ems = [make_emulator(personality="px4", sysid=i + 1) for i in range(10)]
    clients = [connect(em) for em in ems]
    for em, c in zip(ems, clients):
        c.target = em.sysid
        assert c.wait("HEARTBEAT", past=True).get_srcSystem() == em.sysid


def test_commands_for_another_system_are_ignored(make_emulator, connect):
    em = make_emulator(personality="px4", sysid=3)
    c = connect(em)
    c.target = 3
    c.mav.command_long_send(9, 1, ML.MAV_CMD_COMPONENT_ARM_DISARM, 0, 1, 0, 0, 0, 0, 0, 0)
    with pytest.raises(AssertionError):
        c.wait("COMMAND_ACK", timeout=0.5)
    assert not em.state.armed


def test_emulator_rejects_bad_arguments():
    with pytest.raises(ValueError, match="endpoint"):
        AutopilotEmulator("bogus")
    with pytest.raises(ValueError, match="personality"):
        AutopilotEmulator("udpin:127.0.0.1:0", personality="inav")
    with pytest.raises(ValueError, match="sysid"):
        AutopilotEmulator("udpin:127.0.0.1:0", sysid=0)
    with pytest.raises(ValueError, match="home_lla"):
        AutopilotEmulator("udpin:127.0.0.1:0", home_lla=(95.0, 0.0, 0.0))


def test_global_int_position_target_and_nan_params(make_emulator, connect):
    em = make_emulator(personality="ardupilot", start_ned=(0.0, 0.0, -5.0))
    c = connect(em)
    nan = float("nan")
    ack = c.command(ML.MAV_CMD_DO_SET_MODE, ML.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, 4, nan, nan, nan, nan, nan)
    assert ack.result == ML.MAV_RESULT_ACCEPTED  # NaN for unused params, as MAVSDK sends
    lat, lon, _ = em.anchor.ned_to_geodetic(3.0, 0.0, 0.0)
    pos_only = 0b0000_1101_1111_1000
    for _ in range(3):
        c.mav.set_position_target_global_int_send(
            0, 1, 1, ML.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT, pos_only, round(lat * 1e7), round(lon * 1e7), 6.0,
            0, 0, 0, 0, 0, 0, 0, 0,
        )  # fmt: skip
    c.run_for(2.5)
    n, e, d = em.state.position_ned_m
    assert n > 2.0 and abs(e) < 0.1 and d < -5.5
    assert em.stats["errors"] == 0


def test_tcp_client_endpoint(make_emulator):
    port = free_tcp_port()
    c = Client(f"tcpin:127.0.0.1:{port}")
    try:
        em = make_emulator(f"tcp:127.0.0.1:{port}", personality="px4")
        c.wait("HEARTBEAT", timeout=5.0)
        c.heartbeat()
        assert c.arm().result == ML.MAV_RESULT_ACCEPTED
        assert em.state.armed
    finally:
        c.close()
