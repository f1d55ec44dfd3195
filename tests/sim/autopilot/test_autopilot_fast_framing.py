"""The emulator's fast MAVLink paths (issue 40) give pymavlink's bytes and messages:

* ``TelemetryBuilder.payloads`` framed by ``Encoder.frame_payload`` == the builder's message framed by
  ``Encoder.frame`` (``MAVLink.send``), byte for byte, with the same sequence numbers;
* ``framing.parse`` == ``parser.parse_buffer`` for single frames, split frames, two frames in one
  datagram, garbage and MAVLink 1;
* an emulator over real UDP answers and streams as before (its frames decode with pymavlink).
"""

from __future__ import annotations

import math
import socket
import time

import pytest
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from fisc_agent.flight.frames import GeodeticAnchor
from sim.autopilot.framing import Encoder, new_parser, parse
from sim.autopilot.personalities import ARDUPILOT, PX4, FlightMode
from sim.autopilot.server import DEFAULT_HOME_LLA, AutopilotEmulator
from sim.autopilot.telemetry import TelemetryBuilder
from sim.autopilot.vehicle_types import VehicleState

F32_MAX = 3.4028234663852886e38


def _state(pos, vel, t_s=1.234, armed=True, mode=FlightMode.OFFBOARD, custom=393216) -> VehicleState:
    return VehicleState(t_s=t_s, armed=armed, mode=mode, custom_mode=custom, position_ned_m=pos, velocity_ned_m_s=vel,
                        roll_rad=0.0, pitch_rad=0.0, yaw_rad=0.0, yaw_rate_rad_s=0.0, landed_state=2,
                        home_ned_m=(0.0, 0.0, 0.0), position_valid=True, last_setpoint_t_s=0.0,
                        velocity_command_ned_m_s=(0.0, 0.0, 0.0))


STATES = [
    _state((0.0, 0.0, 0.0), (0.0, 0.0, 0.0), t_s=0.0, armed=False, mode=FlightMode.LOITER, custom=0),
    _state((-0.0, 1e-45, -3.5), (F32_MAX, -F32_MAX, 0.25)),
    _state((123.456, -78.9, -10.0), (math.inf, -math.inf, 1e-3), t_s=4294967.295),  # boot ms at 2**32 - 1
    _state((1.0, 2.0, 3.0), (4.0, 5.0, 6.0), t_s=4294967.296, custom=0xFFFFFFFF),  # boot ms wraps to 0
]


@pytest.mark.parametrize("personality", [PX4, ARDUPILOT], ids=["px4", "ardupilot"])
@pytest.mark.parametrize("st", STATES)
def test_fast_payloads_frame_as_the_messages_do(personality, st):
    ref, fast = Encoder(42, 1), Encoder(42, 1)
    anchor = GeodeticAnchor(*DEFAULT_HOME_LLA, heading_deg=0.0)
    tb_ref = TelemetryBuilder(ref.mav, personality, anchor, 42, lambda: 0.0)
    tb_fast = TelemetryBuilder(fast.mav, personality, anchor, 42, lambda: 0.0)
    assert set(tb_fast.payloads) == {mavlink.MAVLINK_MSG_ID_HEARTBEAT, mavlink.MAVLINK_MSG_ID_LOCAL_POSITION_NED}
    for _ in range(300):  # through the sequence number's wrap at 256
        for msg_id, (crc_extra, payload) in tb_fast.payloads.items():
            want = ref.frame(tb_ref.builders[msg_id](st))
            assert fast.frame_payload(msg_id, crc_extra, payload(st)) == want
    assert (fast.mav.seq, fast.mav.total_packets_sent, fast.mav.total_bytes_sent) == \
        (ref.mav.seq, ref.mav.total_packets_sent, ref.mav.total_bytes_sent)


def _frames() -> list[bytes]:
    enc = Encoder(9, 190)
    return [enc.frame(enc.mav.set_position_target_local_ned_encode(17, 1, 1, 1, 3527, 0, 0, 0, 1.5, -2.0, 0.0,
                                                                    0, 0, 0, 0, 0)),
            enc.frame(enc.mav.command_long_encode(1, 1, 511, 0, 33.0, -1.0, 0, 0, 0, 0, 0)),
            enc.frame(enc.mav.heartbeat_encode(18, 8, 0, 0, 4, 3)),
            enc.frame(enc.mav.statustext_encode(4, b"hi"))]


def _same_messages(a: list, b: list) -> None:
    assert [m.get_type() for m in a] == [m.get_type() for m in b]
    for x, y in zip(a, b):
        assert x.get_msgbuf() == y.get_msgbuf()
        assert x.to_dict() == y.to_dict()
        assert vars(x.get_header()) == vars(y.get_header())


@pytest.mark.parametrize("chunks", [
    pytest.param(lambda fr: [fr[0]], id="one frame"),
    pytest.param(lambda fr: [fr[0], fr[1], fr[2], fr[3]], id="one frame per datagram"),
    pytest.param(lambda fr: [fr[0] + fr[1]], id="two frames in a datagram"),
    pytest.param(lambda fr: [fr[0][:7], fr[0][7:], fr[1]], id="a frame split over two datagrams"),
    pytest.param(lambda fr: [fr[0][:-1], fr[1]], id="a frame cut short, then a whole one"),
    pytest.param(lambda fr: [b"\x00\x01garbage", fr[2]], id="garbage then a frame"),
    pytest.param(lambda fr: [fr[0][:-1] + bytes(((fr[0][-1] + 1) % 256,)), fr[1]], id="a bad CRC then a frame"),
])
def test_parse_is_parse_buffer(chunks):
    frames = _frames()
    ref, fast = new_parser(), new_parser()
    for data in chunks(frames):
        _same_messages(parse(fast, data), ref.parse_buffer(data) or [])


def test_parse_of_mavlink1_is_parse_buffer():
    v1 = mavlink.MAVLink(None, srcSystem=3, srcComponent=1)
    data = v1.heartbeat_encode(6, 8, 0, 0, 4, 3).pack(v1, force_mavlink1=True)
    _same_messages(parse(new_parser(), data), new_parser().parse_buffer(data) or [])


def test_emulator_over_udp_streams_decodable_positions():
    emu = AutopilotEmulator("udpin:127.0.0.1:0", "px4", (1.0, 2.0, -3.0), sysid=7, rate_position_hz=50.0).start()
    try:
        sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        sock.settimeout(0.2)
        enc = Encoder(255, 190)
        sock.sendto(enc.frame(enc.mav.heartbeat_encode(6, 8, 0, 0, 4, 3)), emu.local_address)
        parser, seen, t_end = new_parser(), {}, time.monotonic() + 5.0
        while time.monotonic() < t_end and not {"HEARTBEAT", "LOCAL_POSITION_NED"} <= set(seen):
            try:
                data = sock.recv(65535)
            except socket.timeout:
                continue
            for m in parser.parse_buffer(data) or []:
                seen[m.get_type()] = m
        lp = seen["LOCAL_POSITION_NED"]
        assert (lp.x, lp.y, lp.z) == pytest.approx((1.0, 2.0, -3.0), abs=0.05)
        assert seen["HEARTBEAT"].get_srcSystem() == 7 and seen["HEARTBEAT"].autopilot == mavlink.MAV_AUTOPILOT_PX4
    finally:
        emu.stop()
        sock.close()
