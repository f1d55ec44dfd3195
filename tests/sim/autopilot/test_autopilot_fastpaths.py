"""The emulator's per-vehicle fast paths give exactly what the general code gives.

* one-vehicle plant step (``vehicle._fast_plant_step``) == ``VelocityPlant.step``, bit for bit;
* a Vehicle on the fast path == the same Vehicle on the general plant path (``plant_factory``);
* MAVLink framing (``server._pack``) == pymavlink's ``msg.pack``, byte for byte;
* the lazily built ``AutopilotEmulator.state`` follows commands and physics.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from sim.autopilot.personalities import ARDUPILOT, PX4, FlightMode
from sim.autopilot.server import AutopilotEmulator, _pack
from sim.autopilot.vehicle import Setpoint, Vehicle, VehicleConfig, _fast_plant_step
from sim.plant import PlantParams, VelocityPlant, numba_available

needs_numba = pytest.mark.skipif(not numba_available(), reason="the fast plant path uses the numba kernel")


@needs_numba
@pytest.mark.parametrize("dt_s", [0.02, 0.05, 0.013])
def test_fast_plant_step_is_bit_identical_to_velocity_plant_step(dt_s):
    params = PlantParams()
    ref, fast = VelocityPlant(params, 1), VelocityPlant(params, 1)
    step = _fast_plant_step(fast, dt_s)
    assert step is not None
    rng = np.random.default_rng(3)
    for k in range(300):
        cmd = rng.uniform(-12.0, 12.0, size=(1, 3)) if k % 7 else np.zeros((1, 3))
        ref.step(cmd, dt_s)
        step(fast.velocity, fast.thrust_accel, cmd)
        assert np.array_equal(fast.velocity, ref.velocity)
        assert np.array_equal(fast.thrust_accel, ref.thrust_accel)


def test_fast_plant_step_declines_what_it_does_not_cover():
    assert _fast_plant_step(VelocityPlant(PlantParams(), 2), 0.02) is None  # not one vehicle
    assert _fast_plant_step(VelocityPlant(PlantParams(), 1, backend="numpy"), 0.02) is None


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


@needs_numba
@pytest.mark.parametrize("personality", [PX4, ARDUPILOT], ids=["px4", "ardupilot"])
def test_vehicle_on_the_fast_path_flies_exactly_like_the_general_plant_path(personality):
    fast = Vehicle(personality, VehicleConfig())
    general = Vehicle(personality, VehicleConfig(), plant_factory=lambda p: VelocityPlant(p, 1))
    assert fast._fast_step is not None and general._fast_step is None
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


def test_pack_gives_pymavlinks_bytes():
    ours, theirs = mavlink.MAVLink(None, srcSystem=7, srcComponent=1), mavlink.MAVLink(None, srcSystem=7, srcComponent=1)
    for i in range(300):  # sequence numbers wrap
        ours.seq = theirs.seq = i % 256
        for a, b in zip(_messages(ours, i), _messages(theirs, i)):
            assert _pack(a, ours) == b.pack(theirs)
    parser = mavlink.MAVLink(None)
    msgs = parser.parse_buffer(_pack(_messages(ours, 5)[1], ours))
    assert [m.get_type() for m in msgs] == ["LOCAL_POSITION_NED"] and msgs[0].x == 7.5


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
