"""Issue 36 items 2-4, link side: one vehicle per link, acks matched to their command, health and
position integrity, all through a real ``MavlinkLink`` fed real MAVLink frames over loopback UDP."""

from __future__ import annotations

import select
import socket
import time

import pytest
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from fisc_agent.flight.health import LandedState
from fisc_agent.flight.integrity import DisruptionReason
from fisc_agent.mavlink.framing import AutopilotTracker, HeartbeatVerdict
from fisc_agent.mavlink.link import MavlinkLink

PX4, ARDUPILOT, ARMED = 12, 3, 128 | 1


class SimClock:
    """A settable monotonic clock."""

    def __init__(self, t: float = 100.0) -> None:
        self.t = t

    def __call__(self) -> float:
        return self.t


class Vehicle:
    """A UDP socket speaking as MAVLink system ``system`` component 1."""

    def __init__(self, system: int, component: int = 1) -> None:
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.bind(("127.0.0.1", 0))
        self.mav = mavlink.MAVLink(None, srcSystem=system, srcComponent=component)
        self.decoder = mavlink.MAVLink(None)

    def send(self, link: MavlinkLink, *msgs) -> None:
        for m in msgs:
            self.sock.sendto(m.pack(self.mav), link.udp.local_address)
        while select.select([link.udp.sock], [], [], 0.05)[0]:
            link.poll()

    def heartbeat(self, autopilot=PX4, base_mode=1, system_status=3):
        return mavlink.MAVLink_heartbeat_message(2, autopilot, base_mode, 0, system_status, 3)

    def received(self, seconds: float = 0.1) -> list:
        """Messages the link sent to this vehicle."""
        out, end = [], time.monotonic() + seconds
        while time.monotonic() < end:
            if not select.select([self.sock], [], [], 0.02)[0]:
                continue
            data, _ = self.sock.recvfrom(65535)
            out += self.decoder.parse_buffer(data) or []
        return out

    def close(self) -> None:
        self.sock.close()


@pytest.fixture()
def clock():
    return SimClock()


@pytest.fixture()
def vehicles():
    made = []

    def make(system, component=1):
        made.append(Vehicle(system, component))
        return made[-1]
    yield make
    for v in made:
        v.close()


@pytest.fixture()
def link_factory(clock):
    links = []

    def make(**kw):
        links.append(MavlinkLink("udpin:127.0.0.1:0", clock=clock, **kw))
        return links[-1]
    yield make
    for link in links:
        link.close()


def local_position(x, vx=0.0, boot_ms=1000):
    return mavlink.MAVLink_local_position_ned_message(boot_ms, x, 0.0, -5.0, vx, 0.0, 0.0)


def odometry(reset_counter):
    return mavlink.MAVLink_odometry_message(1, 1, 1, 0, 0, 0, [1, 0, 0, 0], 0, 0, 0, 0, 0, 0, [0] * 21, [0] * 21,
                                            reset_counter)


# ------------------------------------------------------------------------------ one vehicle per link
def test_the_first_autopilot_is_pinned_and_a_second_one_on_the_same_port_never_takes_over(link_factory, vehicles,
                                                                                           clock):
    link, ap, other = link_factory(), vehicles(1), vehicles(2)
    ap.send(link, ap.heartbeat(), ap.heartbeat())
    assert link.target_system == 1 and link.tracker.pinned_system == 1
    clock.t += 60.0                                   # the autopilot is silent and disarmed for a minute
    other.send(link, other.heartbeat(), local_position(3.0), other.heartbeat())
    assert link.target_system == 1 and link.latest_position() is None
    assert link.other_system_messages == 3 and link.rlog.count("mavlink:other_system") == 3
    ap.send(link, local_position(1.0))
    assert link.latest_position().pos_ned_m[0] == pytest.approx(1.0)


def test_a_single_stray_heartbeat_is_not_pinned():
    """Issue 12 finding 6 still holds: one forged HEARTBEAT before the autopilot starts cannot hold the agent."""
    t = AutopilotTracker(relock_after_s=3.0)
    assert t.on_heartbeat(42, 1, "x", 2, PX4, armed=False, now_s=0.0) == HeartbeatVerdict.LOCKED
    assert t.pinned_system is None
    assert t.on_heartbeat(1, 1, "ap", 2, PX4, armed=False, now_s=3.5) == HeartbeatVerdict.LOCKED
    assert t.on_heartbeat(1, 1, "ap", 2, PX4, armed=False, now_s=4.5) == HeartbeatVerdict.AUTOPILOT
    assert t.pinned_system == 1
    assert t.on_heartbeat(42, 1, "x", 2, PX4, armed=False, now_s=60.0) == HeartbeatVerdict.FOREIGN


def test_the_same_system_may_come_back_from_a_new_address_but_an_unknown_type_is_not_pinned():
    t = AutopilotTracker(relock_after_s=3.0)
    t.on_heartbeat(1, 1, "a", 2, PX4, armed=False, now_s=0.0)
    t.on_heartbeat(1, 1, "a", 2, PX4, armed=False, now_s=1.0)
    assert t.on_heartbeat(1, 1, "b", 2, PX4, armed=False, now_s=4.0) == HeartbeatVerdict.FOREIGN   # 3.0 s: not yet
    assert t.on_heartbeat(1, 1, "b", 2, PX4, armed=False, now_s=4.01) == HeartbeatVerdict.LOCKED   # a reconnect
    assert t.pinned_system == 1 and t.relocks == 1
    t = AutopilotTracker()
    t.on_heartbeat(5, 1, "g", 2, 0, armed=False, now_s=0.0)                      # MAV_AUTOPILOT_GENERIC
    t.on_heartbeat(5, 1, "g", 2, 0, armed=False, now_s=1.0)
    assert t.pinned_system is None
    assert t.on_heartbeat(1, 1, "a", 2, PX4, armed=False, now_s=1.1) == HeartbeatVerdict.LOCKED


def test_a_given_target_system_is_the_only_one(link_factory, vehicles):
    link, one, two = link_factory(target_system=2), vehicles(1), vehicles(2)
    one.send(link, one.heartbeat(), local_position(1.0))
    assert link.target_system is None and link.other_system_messages == 2
    two.send(link, two.heartbeat(ARDUPILOT))
    assert link.target_system == 2 and link.autopilot == "ardupilot"


@pytest.mark.parametrize("system, ok", [(0, False), (1, True), (255, True), (256, False), (-1, False)])
def test_target_system_bounds(system, ok):
    if ok:
        assert AutopilotTracker(target_system=system).pinned_system == system
    else:
        with pytest.raises(ValueError, match="target_system"):
            AutopilotTracker(target_system=system)


def test_system_id_0_is_never_a_vehicle_and_255_is_another_system(link_factory, vehicles):
    link, zero = link_factory(), vehicles(0)
    zero.send(link, zero.heartbeat(), zero.heartbeat(), local_position(1.0))
    assert link.target_system is None and link.rlog.count("mavlink:system_0") == 3
    link, ap, gcs = link_factory(target_system=1), vehicles(1), vehicles(255)
    gcs.send(link, gcs.heartbeat(), gcs.heartbeat(ARDUPILOT, ARMED))
    assert link.target_system is None
    ap.send(link, ap.heartbeat())
    assert link.target_system == 1 and link.other_system_messages == 2


# ------------------------------------------------------------------------------ acks matched to their command
def ack(link, command, result=0, target_system=None, target_component=None):
    return mavlink.MAVLink_command_ack_message(command, result, 0, 0,
                                              link.mav.srcSystem if target_system is None else target_system,
                                              link.mav.srcComponent if target_component is None else target_component)


def test_acks_count_only_when_addressed_to_us_and_answering_a_command_we_sent(link_factory, vehicles, clock):
    link, ap, other = link_factory(), vehicles(1), vehicles(2)
    ap.send(link, ap.heartbeat(), ap.heartbeat())
    link.pop_results()
    link.arm()
    arm = mavlink.MAV_CMD_COMPONENT_ARM_DISARM
    ap.send(link, ack(link, arm, target_component=link.mav.srcComponent + 1),     # another component's
            ack(link, arm, target_system=link.mav.srcSystem + 1),                  # another system's
            ack(link, mavlink.MAV_CMD_NAV_TAKEOFF))                                # never sent
    other.send(link, ack(link, arm))                                               # another vehicle
    assert link.pop_results() == [] and link.rlog.count("mavlink:unmatched_ack") == 3
    ap.send(link, ack(link, arm))
    results = link.pop_results()
    assert len(results) == 1 and results[0].accepted
    clock.t += 30.0                                   # ACK_WINDOW_S after the send: still ours
    ap.send(link, ack(link, arm, result=4))
    assert len(link.pop_results()) == 1
    clock.t += 0.001                                  # just outside the window
    ap.send(link, ack(link, arm))
    assert link.pop_results() == []


def test_stream_requests_are_sent_on_lock_and_again_after_a_reboot_and_their_acks_stay_inside(
        link_factory, vehicles):
    link, ap = link_factory(), vehicles(1)
    ap.send(link, ap.heartbeat())
    asked = {int(m.param1) for m in ap.received() if m.get_type() == "COMMAND_LONG"
             and m.command == mavlink.MAV_CMD_SET_MESSAGE_INTERVAL}
    assert {mavlink.MAVLINK_MSG_ID_LOCAL_POSITION_NED, mavlink.MAVLINK_MSG_ID_SYS_STATUS,
            mavlink.MAVLINK_MSG_ID_ESTIMATOR_STATUS, mavlink.MAVLINK_MSG_ID_ODOMETRY,
            mavlink.MAVLINK_MSG_ID_SYSTEM_TIME} <= asked
    ap.send(link, ack(link, mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, result=4))
    assert link.pop_results() == [] and link.stream_requests_refused == 1
    ap.send(link, mavlink.MAVLink_system_time_message(0, 60_000), mavlink.MAVLink_system_time_message(0, 60_000))
    assert not [m for m in ap.received() if m.get_type() == "COMMAND_LONG"]      # same boot: nothing asked
    ap.send(link, mavlink.MAVLink_system_time_message(0, 1_500))                  # boot time went backwards
    again = [m for m in ap.received() if m.get_type() == "COMMAND_LONG"]
    assert len(again) >= 5 and link.health.autopilot_reboots == 1


# ------------------------------------------------------------------------------ health and integrity
def test_health_comes_from_the_autopilot_only(link_factory, vehicles):
    link, ap, other = link_factory(), vehicles(1), vehicles(2)
    ap.send(link, ap.heartbeat(system_status=4), ap.heartbeat(system_status=4),
            mavlink.MAVLink_extended_sys_state_message(0, 2),
            mavlink.MAVLink_battery_status_message(0, 0, 0, 32767, [12600] + [65535] * 9, -1, -1, -1, 64))
    other.send(link, mavlink.MAVLink_battery_status_message(0, 0, 0, 32767, [1] * 10, -1, -1, -1, 3),
               mavlink.MAVLink_extended_sys_state_message(0, 1))
    h = link.health
    assert (h.battery_pct, h.landed, h.system_state.value) == (64.0, LandedState.IN_AIR, "active")


def test_an_odometry_reset_step_disrupts_the_integrity_until_a_consistent_track(link_factory, vehicles, clock):
    link, ap = link_factory(), vehicles(1)
    ap.send(link, ap.heartbeat(), ap.heartbeat(), odometry(15))
    for i in range(5):
        clock.t += 0.1
        ap.send(link, local_position(0.1 * i, vx=1.0, boot_ms=1000 + 100 * i))
    assert link.integrity.ok
    ap.send(link, odometry(16))
    v = link.integrity
    assert not v.ok and v.reason == DisruptionReason.RESET_COUNTER and v.since_s == clock.t
    assert link.health.position_resets == 1
    for i in range(5, 26):                            # 2.1 s of consistent track
        clock.t += 0.1
        ap.send(link, local_position(0.1 * i, vx=1.0, boot_ms=1000 + 100 * i))
    assert link.integrity.ok


def test_a_small_jump_the_gate_accepts_is_a_disruption(link_factory, vehicles, clock):
    link, ap = link_factory(), vehicles(1)
    ap.send(link, ap.heartbeat(), ap.heartbeat(), local_position(0.0, boot_ms=1000))
    clock.t += 0.1
    ap.send(link, local_position(3.0, boot_ms=1100))   # 3 m in 0.1 s: beyond the gate's 15 m/s * 0.1 s + 1 m
    assert link.latest_position().pos_ned_m[0] == 0.0 and link.integrity.ok
    clock.t += 0.1
    ap.send(link, local_position(2.2, boot_ms=1200))   # 2.2 m in 0.2 s: the gate allows 4 m, at rest
    v = link.integrity
    assert link.latest_position().pos_ned_m[0] == pytest.approx(2.2)            # the gate let it through
    assert not v.ok and v.reason == DisruptionReason.JUMP


def test_a_ground_station_on_the_link_is_not_counted_as_another_system(link_factory, vehicles):
    link, ap, gcs = link_factory(), vehicles(1), vehicles(255, 190)
    ap.send(link, ap.heartbeat(), ap.heartbeat())
    gcs.send(link, mavlink.MAVLink_heartbeat_message(6, 8, 0, 0, 4, 3))      # MAV_TYPE_GCS, MAV_AUTOPILOT_INVALID
    assert link.other_system_messages == 0 and link.target_system == 1


def test_an_autopilot_reboot_disrupts_the_integrity(link_factory, vehicles, clock):
    link, ap = link_factory(), vehicles(1)
    ap.send(link, ap.heartbeat(), ap.heartbeat(), mavlink.MAVLink_system_time_message(0, 60_000))
    assert link.integrity.ok
    ap.send(link, mavlink.MAVLink_system_time_message(0, 59_999))
    assert link.integrity.reason == DisruptionReason.AUTOPILOT_REBOOT and not link.integrity.ok


def test_discard_backlog_drops_what_queued_up_unread(link_factory, vehicles):
    """After the agent stalled, the datagrams queued meanwhile are dropped unread: the vehicle's mode
    stays what it was before the stall (not the backlog's), and the next one is read as usual."""
    link, v = link_factory(), vehicles(1)
    v.send(link, v.heartbeat(), v.heartbeat())
    seen = link.heartbeats
    for _ in range(20):                      # the backlog: queued while nobody reads
        v.sock.sendto(v.heartbeat(base_mode=1 | 128).pack(v.mav), link.udp.local_address)
    time.sleep(0.1)
    assert link.discard_backlog() == 20
    assert link.discard_backlog() == 0       # empty: nothing more to drop
    assert link.heartbeats == seen and not link.armed   # none of the armed heartbeats was read
    v.send(link, v.heartbeat(base_mode=1 | 128))
    assert link.heartbeats == seen + 1 and link.armed


def test_odometrys_attitude_gives_the_thrusts_horizontal_acceleration(link_factory, vehicles, clock):
    """PX4's ODOMETRY carries the attitude: 10 degrees nose down reads as g tan(10 deg) north; a quaternion
    that is no rotation (all zero: PX4 without an attitude yet) leaves the last one in place."""
    import math

    link, ap = link_factory(), vehicles(1)
    assert link.latest_thrust_accel() is None
    a = math.radians(10.0)
    pitched = mavlink.MAVLink_odometry_message(1, 1, 1, 0, 0, 0, [math.cos(a / 2), 0, -math.sin(a / 2), 0], 0, 0, 0, 0,
                                               0, 0, [0] * 21, [0] * 21, 0, 0, 0)
    ap.send(link, ap.heartbeat(), pitched)
    got = link.latest_thrust_accel()
    assert got is not None and got.t_s == clock.t
    assert got.acc_ne_m_s2[0] == pytest.approx(9.80665 * math.tan(a), rel=1e-6)
    assert got.acc_ne_m_s2[1] == pytest.approx(0.0, abs=1e-6)
    clock.t += 1.0
    zero = mavlink.MAVLink_odometry_message(1, 1, 1, 0, 0, 0, [0, 0, 0, 0], 0, 0, 0, 0, 0, 0, [0] * 21, [0] * 21, 0, 0, 0)
    ap.send(link, zero)
    assert link.latest_thrust_accel() is got
