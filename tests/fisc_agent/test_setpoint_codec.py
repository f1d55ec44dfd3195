"""``fisc_agent.mavlink.setpoint_codec`` packs the velocity setpoint byte for byte as pymavlink does, and
``MavlinkLink.send_velocity_ned`` puts those bytes on the wire (a real UDP socket)."""

from __future__ import annotations

import os
import random
import socket

os.environ.setdefault("MAVLINK20", "1")

import pytest  # noqa: E402
from pymavlink.dialects.v20 import ardupilotmega as mavlink  # noqa: E402

from fisc_agent.mavlink.link import MAV_FRAME_LOCAL_NED, TYPEMASK_VELOCITY_ONLY, MavlinkLink  # noqa: E402
from fisc_agent.mavlink.setpoint_codec import TYPEMASK_VELOCITY_ACCEL  # noqa: E402
from fisc_agent.mavlink.setpoint_codec import pack_velocity_setpoint, send_velocity_setpoint  # noqa: E402


class Sink:
    """A pymavlink ``file``: keeps what is written."""

    def __init__(self) -> None:
        self.written: list[bytes] = []

    def write(self, buf: bytes) -> None:
        self.written.append(bytes(buf))


def _reference(mav, boot_ms, ts, tc, vn, ve, vd) -> bytes:
    return mav.set_position_target_local_ned_encode(boot_ms, ts, tc, MAV_FRAME_LOCAL_NED, TYPEMASK_VELOCITY_ONLY, 0.0,
                                                    0.0, 0.0, vn, ve, vd, 0.0, 0.0, 0.0, 0.0, 0.0).pack(mav)


VALUES = [0.0, -0.0, 1.0, -1.0, 1e-30, -3.25, 12.5, 1e30, float("inf"), -float("inf"), 0.1, 2.0 / 3.0]


@pytest.mark.parametrize("ts,tc", [(1, 1), (0, 0), (255, 191), (7, 0)])
def test_the_frame_is_pymavlinks_for_edge_and_random_values(ts, tc):
    rng = random.Random(1)
    mav = mavlink.MAVLink(None, srcSystem=3, srcComponent=191)
    cases = [(v, w, u) for v in VALUES for w in (0.0, -2.5) for u in VALUES]
    cases += [tuple(rng.uniform(-20, 20) for _ in range(3)) for _ in range(300)]
    for i, (vn, ve, vd) in enumerate(cases):
        mav.seq = i % 256
        boot_ms = (i * 7919) & 0xFFFFFFFF if i % 5 else 0xFFFFFFFF * (i % 2)
        assert pack_velocity_setpoint(mav, boot_ms, ts, tc, MAV_FRAME_LOCAL_NED, TYPEMASK_VELOCITY_ONLY, vn, ve,
                                      vd) == _reference(mav, boot_ms, ts, tc, vn, ve, vd), (i, vn, ve, vd)


def test_an_all_zero_payload_keeps_one_byte_as_pymavlink_does():
    mav = mavlink.MAVLink(None, srcSystem=1, srcComponent=1)
    got = pack_velocity_setpoint(mav, 0, 0, 0, 0, 0, 0.0, 0.0, 0.0)
    want = mav.set_position_target_local_ned_encode(0, 0, 0, 0, 0, *([0.0] * 11)).pack(mav)
    assert got == want and got[1] == 1


def test_send_counts_and_numbers_frames_as_mavlink_send_does():
    ours, ref = Sink(), Sink()
    a = mavlink.MAVLink(ours, srcSystem=2, srcComponent=191)
    b = mavlink.MAVLink(ref, srcSystem=2, srcComponent=191)
    a.seq = b.seq = 250
    for i in range(10):  # across the sequence number's wrap
        send_velocity_setpoint(a, i, 1, 1, MAV_FRAME_LOCAL_NED, TYPEMASK_VELOCITY_ONLY, 0.5 * i, -1.0, 0.25)
        b.send(b.set_position_target_local_ned_encode(i, 1, 1, MAV_FRAME_LOCAL_NED, TYPEMASK_VELOCITY_ONLY, 0.0, 0.0,
                                                      0.0, 0.5 * i, -1.0, 0.25, 0.0, 0.0, 0.0, 0.0, 0.0))
    assert ours.written == ref.written
    assert (a.seq, a.total_packets_sent, a.total_bytes_sent) == (b.seq, b.total_packets_sent, b.total_bytes_sent)


def test_a_signing_link_is_left_to_pymavlink():
    ours, ref = Sink(), Sink()
    a = mavlink.MAVLink(ours, srcSystem=2, srcComponent=191)
    b = mavlink.MAVLink(ref, srcSystem=2, srcComponent=191)
    for m in (a, b):
        m.signing.secret_key = bytes(range(32))
        m.signing.sign_outgoing = True
        m.signing.timestamp = 123456
    send_velocity_setpoint(a, 5, 1, 1, MAV_FRAME_LOCAL_NED, TYPEMASK_VELOCITY_ONLY, 1.0, 2.0, 3.0)
    b.send(b.set_position_target_local_ned_encode(5, 1, 1, MAV_FRAME_LOCAL_NED, TYPEMASK_VELOCITY_ONLY, 0.0, 0.0, 0.0,
                                                  1.0, 2.0, 3.0, 0.0, 0.0, 0.0, 0.0, 0.0))
    assert ours.written == ref.written and len(ours.written[0]) > 13 + 12


def _pymavlink_setpoint(link, mask, v, a=(0.0, 0.0, 0.0)) -> bytes:
    """pymavlink's own bytes of the setpoint ``link`` sends next."""
    boot_ms = int(link.clock() * 1000) & 0xFFFFFFFF
    return link.mav.set_position_target_local_ned_encode(boot_ms, 1, link.target_component, MAV_FRAME_LOCAL_NED, mask,
                                                         0.0, 0.0, 0.0, *v, *a, 0.0, 0.0).pack(link.mav)


def test_the_link_sends_the_messages_bytes_over_udp():
    rx = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    rx.bind(("127.0.0.1", 0))
    rx.settimeout(2.0)
    clock = [1234.5678]
    link = MavlinkLink(f"udpout:127.0.0.1:{rx.getsockname()[1]}", source_system=9, clock=lambda: clock[0])
    try:
        want = _pymavlink_setpoint(link, TYPEMASK_VELOCITY_ONLY, (1.5, -0.5, 0.125))
        link.send_velocity_ned(1.5, -0.5, 0.125)
        got, _ = rx.recvfrom(512)
        assert got == want and link.setpoints_sent == 1 and link.mav.seq == 1
        # with the drag's acceleration feed-forward: velocity and acceleration used (type mask 3079)
        want = _pymavlink_setpoint(link, TYPEMASK_VELOCITY_ACCEL, (1.5, -0.5, 0.125), (0.75, -0.25, 0.0))
        link.send_velocity_accel_ned(1.5, -0.5, 0.125, 0.75, -0.25, 0.0)
        got, _ = rx.recvfrom(512)
        assert got == want and link.setpoints_sent == 2 and TYPEMASK_VELOCITY_ACCEL == 3079
        msg = mavlink.MAVLink(None).decode(bytearray(got))
        assert (msg.afx, msg.afy, msg.afz, msg.type_mask) == (0.75, -0.25, 0.0, 3079)
    finally:
        link.close()
        rx.close()
