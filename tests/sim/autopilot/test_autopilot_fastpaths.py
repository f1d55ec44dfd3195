"""The emulator's per-vehicle fast paths give exactly what the general code gives.

* the plant's prepared fixed-length step (``VelocityPlant.fixed_step``) == ``VelocityPlant.step``, bit for bit;
* a Vehicle on the prepared step == the same Vehicle on ``VelocityPlant.step`` (``plant_factory``);
* MAVLink framing (``framing.Encoder``, pymavlink's public ``MAVLink.send``) gives valid MAVLink 2
  frames, checked field by field from the raw bytes, over a real UDP socket too;
* the lazily built ``AutopilotEmulator.state`` follows commands and physics.
"""

from __future__ import annotations

import math
import socket

import numpy as np
import pytest
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from sim.autopilot.personalities import ARDUPILOT, PX4, FlightMode
from sim.autopilot.framing import Encoder, new_parser
from sim.autopilot.server import AutopilotEmulator
from sim.autopilot.vehicle import Setpoint, Vehicle, VehicleConfig
from sim.plant.model import PlantParams, VelocityPlant, numba_available
from ...optional import needs

BACKENDS = ["numpy", pytest.param("numba", marks=needs(numba_available(), "numba", extra="jit"))]


@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize(("n", "dt_s"), [(1, 0.02), (1, 0.05), (1, 0.013), (3, 0.02)])
def test_fixed_step_is_bit_identical_to_velocity_plant_step(backend, n, dt_s):
    params = PlantParams()
    ref, fast = VelocityPlant(params, n, backend=backend), VelocityPlant(params, n, backend=backend)
    step = fast.fixed_step(dt_s)
    rng = np.random.default_rng(3)
    for k in range(300):
        cmd = rng.uniform(-12.0, 12.0, size=(n, 3)) if k % 7 else np.zeros((1, 3))
        ref.step(cmd, dt_s)
        assert step(cmd) is fast.velocity
        assert np.array_equal(fast.velocity, ref.velocity)
        assert np.array_equal(fast.thrust_accel, ref.thrust_accel)
    ref.step(cmd[0], dt_s)  # a (3,) command takes the checked path, with the same numbers
    step(cmd[0])
    assert np.array_equal(fast.velocity, ref.velocity)


def test_fixed_step_follows_a_changed_population_and_rejects_bad_input():
    plant = VelocityPlant(PlantParams(), 1)
    step = plant.fixed_step(0.02)
    plant.append(np.array([[1.0, 0.0, 0.0]]))
    ref = VelocityPlant(PlantParams(), 2, velocity_ned_m_s=plant.velocity.copy(), thrust_accel_ned_m_s2=plant.thrust_accel.copy())
    cmd = np.array([[2.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
    assert np.array_equal(step(cmd), ref.step(cmd, 0.02))
    with pytest.raises(ValueError, match="cmd_ned_m_s"):
        step(np.zeros((5, 3)))
    with pytest.raises(ValueError, match="dt_s"):
        plant.fixed_step(0.0)


class _CheckedStepPlant(VelocityPlant):
    """A plant whose fixed step is plain ``step`` (the general path)."""

    def fixed_step(self, dt_s):
        return lambda cmd: self.step(cmd, dt_s)


def _fly(vehicle: Vehicle, personality_is_px4: bool) -> list:
    """A flight through takeoff, setpoints (position, velocity, yaw), failsafe, RTL/LAND."""
    out: list = []
    t = 0.0

    def run(seconds: float, sp=None) -> None:
        nonlocal t
        for _ in range(round(seconds / 0.05)):
            t += 0.05
            if sp is not None:
                vehicle.set_setpoint(sp(t), t)
            vehicle.step(t)
            out.append(vehicle.snapshot())

    wavy = lambda t: Setpoint((math.nan, math.nan, -6.0), (3 * math.cos(t), 20 * math.sin(t), math.nan), 1.0)
    if personality_is_px4:
        out += [vehicle.arm(0.0), vehicle.takeoff(0.0, 5.0)]
        run(8.0)
        run(0.3, wavy)
        out.append(vehicle.set_mode(FlightMode.OFFBOARD, t))
        run(8.0, wavy)
        run(6.0, lambda t: Setpoint((10.0, -5.0, -3.0), yaw_rate_rad_s=0.5))
        run(3.0)  # setpoints lost: failsafe
        out.append(vehicle.set_mode(FlightMode.RTL, t))
        run(20.0)
    else:
        out += [vehicle.set_mode(FlightMode.GUIDED, 0.0), vehicle.arm(0.0), vehicle.takeoff(0.0, 4.0)]
        run(8.0)
        run(6.0, lambda t: Setpoint(velocity_ned_m_s=(2.0, -1.0, 0.3 * math.sin(t)), yaw_rate_rad_s=0.3))
        run(5.0)  # stale velocity target: stops
        out.append(vehicle.land(t))
        run(15.0)
    out.append([e.text for e in vehicle.drain_events()])
    return out


@pytest.mark.parametrize("personality", [PX4, ARDUPILOT], ids=["px4", "ardupilot"])
def test_vehicle_on_the_fixed_step_flies_exactly_like_the_general_plant_path(personality):
    fast = Vehicle(personality, VehicleConfig())
    general = Vehicle(personality, VehicleConfig(), plant_factory=lambda p: _CheckedStepPlant(p, 1))
    a, b = _fly(fast, personality is PX4), _fly(general, personality is PX4)
    assert a == b
    assert any(s.velocity_ned_m_s != (0.0, 0.0, 0.0) for s in a[:-1] if hasattr(s, "velocity_ned_m_s"))


def _messages(m: mavlink.MAVLink, i: int) -> list:
    return [
        m.heartbeat_encode(mavlink.MAV_TYPE_QUADROTOR, mavlink.MAV_AUTOPILOT_PX4, 0, 0, 0, 3),
        m.local_position_ned_encode(i * 20, 1.5 * i, -2.0, 0.0, 0.0, 0.0, 0.0),
        m.local_position_ned_encode(0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0),  # all-zero payload: one byte stays
        m.global_position_int_encode(i, 473977420, 85455940, 488000, -10, 3, -4, 0, 36000),
        m.statustext_encode(mavlink.MAV_SEVERITY_INFO, b"Mode %d" % i),
        m.autopilot_version_encode(1, 2, 0, 0, 0, [0] * 8, [0] * 8, [0] * 8, 0, 0, 0x46495343_0000 + 3),
        m.home_position_encode(1, 2, 3, 0.0, 0.0, 0.0, [1.0, 0.0, 0.0, 0.0], 0.0, 0.0, 0.0, i),
    ]


def _check_v2_frame(buf: bytes, seq: int, sysid: int, compid: int) -> int:
    """Check one raw MAVLink 2 frame field by field (header, length, CRC); returns its message id."""
    assert buf[0] == 0xFD  # MAVLink 2 start byte
    length = buf[1]
    assert len(buf) == 10 + length + 2  # header, payload, CRC (unsigned: no signature)
    assert buf[2] == 0 and buf[3] == 0  # incompat/compat flags: not signed
    assert (buf[4], buf[5], buf[6]) == (seq, sysid, compid)
    msg_id = buf[7] | buf[8] << 8 | buf[9] << 16
    payload = buf[10 : 10 + length]
    assert length == 1 or payload[-1] != 0  # MAVLink 2 truncates trailing zero bytes (keeps one)
    crc = mavlink.x25crc(buf[1 : 10 + length] + bytes([mavlink.mavlink_map[msg_id].crc_extra])).crc
    assert buf[-2:] == crc.to_bytes(2, "little")
    return msg_id


def _fields(msg) -> dict:
    return {k: list(v) if isinstance(v, (list, tuple)) else v for k, v in msg.to_dict().items()}


def test_encoder_gives_mavlink2_frames_that_decode_from_raw_bytes():
    enc = Encoder(7, 1)
    parser = new_parser()
    seq = 0
    for i in range(300):  # sequence numbers wrap
        for msg in _messages(enc.mav, i):
            buf = enc.frame(msg)
            assert _check_v2_frame(buf, seq % 256, 7, 1) == msg.get_msgId()
            seq += 1
            (back,) = parser.parse_buffer(buf)
            assert back.get_type() == msg.get_type() and back.get_srcSystem() == 7
            assert _fields(back) == _fields(msg)
    (lp,) = parser.parse_buffer(enc.frame(_messages(enc.mav, 5)[1]))
    assert lp.get_type() == "LOCAL_POSITION_NED" and lp.x == 7.5


def test_emulator_datagrams_are_mavlink2_frames_of_its_system():
    sink = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sink.bind(("127.0.0.1", 0))
    sink.settimeout(2.0)
    em = AutopilotEmulator(f"udpout:127.0.0.1:{sink.getsockname()[1]}", "px4", (0.0, 0.0, -5.0), sysid=42).start()
    try:
        seqs, ids = [], set()
        while len(seqs) < 40:
            buf = sink.recv(65535)
            seqs.append(buf[4])
            ids.add(_check_v2_frame(buf, buf[4], 42, mavlink.MAV_COMP_ID_AUTOPILOT1))
    finally:
        em.stop()
        sink.close()
    assert all((b - a) % 256 == 1 for a, b in zip(seqs, seqs[1:]))  # one frame per datagram, none skipped
    assert {mavlink.MAVLINK_MSG_ID_HEARTBEAT, mavlink.MAVLINK_MSG_ID_GLOBAL_POSITION_INT} <= ids


def test_emulator_state_follows_commands_and_physics():
    clock = [0.0]
    em = AutopilotEmulator("udpin:127.0.0.1:0", "px4", (0.0, 0.0, -10.0), clock=lambda: clock[0])
    try:
        em.open()
        first = em.state
        assert first.armed and first.position_ned_m == (0.0, 0.0, -10.0)
        assert em.state is first  # nothing happened: the same snapshot
        em.vehicle.set_setpoint(Setpoint(velocity_ned_m_s=(2.0, 0.0, 0.0)), 0.0)
        assert em.vehicle.set_mode(FlightMode.OFFBOARD, 0.0).ok
        for _ in range(50):
            clock[0] += 0.02
            em.vehicle.set_setpoint(Setpoint(velocity_ned_m_s=(2.0, 0.0, 0.0)), clock[0])
            em.poll()
        st = em.state
        assert st.mode == FlightMode.OFFBOARD and st.t_s == pytest.approx(1.0)
        assert st.position_ned_m[0] > 0.5 and st.velocity_ned_m_s[0] > 1.0
        assert st == em.vehicle.snapshot()
    finally:
        em.close()
