"""The agent's drag identification and feed-forward closed around the emulated PX4, on a simulated clock:
ODOMETRY's attitude (from the plant's realised thrust) in, the setpoint's acceleration out.  What
``fisc-sim emulate --plant px4-sih`` flies when it predicts a stock PX4 fleet with the feed-forward on."""

from __future__ import annotations

import pytest

from pymavlink.dialects.v20 import ardupilotmega as mavlink

from fisc_agent.flight.drag import DragEstimator, thrust_accel_ne
from fisc_agent.flight.frames import GeodeticAnchor
from sim.autopilot.personalities import PX4, FlightMode
from sim.autopilot.telemetry import TelemetryBuilder
from sim.autopilot.vehicle import Setpoint, Vehicle, VehicleConfig
from sim.plant.fit import plant_preset
from sim.plant.px4_loop import Px4LoopParams

DT_S = 0.05
K_DRAG = 1.225 * 0.39 / 2.0  # the px4-sih preset's quadratic drag rho S / 2m [1/m] (Cd 1, 1 kg)


def _fly(pattern, accel_of=lambda v_ne: (0.0, 0.0), loop: Px4LoopParams | None = None):
    """A stock-PX4-plant vehicle (``loop``: the PX4 loop model) flying ``pattern`` ((seconds, (vn, ve)), ...) in
    OFFBOARD at 20 Hz; yields (t, velocity NE, the thrust's NE acceleration as the agent reads it from ODOMETRY,
    the setpoint NE)."""
    veh = Vehicle(PX4, VehicleConfig(start_ned_m=(0.0, 0.0, -5.0), plant_params=plant_preset("px4-sih"),
                                     px4_loop=loop))
    tel = TelemetryBuilder(mavlink.MAVLink(None), PX4, GeodeticAnchor(47.4, 8.5, 500.0, 0.0), 1, lambda: 0.0)
    t = 0.0
    for k in range(10):
        t += DT_S
        veh.set_setpoint(Setpoint(velocity_ned_m_s=(0.0, 0.0, 0.0)), t)
    assert veh.set_mode(FlightMode.OFFBOARD, t).ok
    for seconds, sp in pattern:
        for _ in range(round(seconds / DT_S)):
            t += DT_S
            a = accel_of(sp)
            veh.set_setpoint(Setpoint(velocity_ned_m_s=(sp[0], sp[1], 0.0), accel_ned_m_s2=(a[0], a[1], 0.0)), t)
            st = veh.snapshot()
            yield t, st.velocity_ned_m_s[:2], thrust_accel_ne(tuple(tel.odometry(st).q)), sp


PATTERN = [(8.0, (1.5, 0.0)), (8.0, (-1.0, 0.0)), (8.0, (0.0, 1.2)), (8.0, (0.6, -0.6)), (8.0, (0.0, 0.0))]


def test_the_agent_identifies_the_emulated_drag_from_odometry():
    est = DragEstimator()
    for t, v, acc, _ in _fly(PATTERN):
        est.observe(t, v, acc)
    assert est.drag_1_s is not None
    # quadratic drag k v |v| seen as linear c v over these speeds (0-1.5 m/s): c about k times the typical speed
    assert 0.6 * K_DRAG < est.drag_1_s < 1.5 * K_DRAG, est.drag_1_s


def test_fed_forward_the_identified_drag_brings_the_emulated_speed_to_the_setpoint():
    est = DragEstimator()
    for t, v, acc, _ in _fly(PATTERN):
        est.observe(t, v, acc)
    c = est.drag_1_s
    cruise = [(15.0, (1.2, 0.0))]
    *_, (_, unfed, _, _) = _fly(cruise)
    *_, (_, fed, _, _) = _fly(cruise, accel_of=lambda sp: (c * sp[0], c * sp[1]))
    assert 1.2 - unfed[0] > 0.15  # the stock plant falls short of a cruise setpoint without it
    assert abs(1.2 - fed[0]) < 0.5 * (1.2 - unfed[0]), (fed, unfed, c)


@pytest.mark.parametrize("drag", [0.6, 1.0, 1.4])
def test_on_the_px4_loop_model_the_agent_identifies_sihs_linear_drag(drag):
    """SIH's drag is linear: on the PX4 loop model the agent's fit finds it (on real SIH: 0.78-1.00 /s for 1.00)."""
    est = DragEstimator()
    for t, v, acc, _ in _fly(PATTERN, loop=Px4LoopParams(drag_1_s=drag)):
        est.observe(t, v, acc)
    assert est.drag_1_s == pytest.approx(drag, rel=0.05)


def test_on_the_px4_loop_model_the_setpoints_acceleration_reaches_its_pid():
    """Fed forward ``c v_sp``, a step to 1.2 m/s is flown 3 s later within a third of the shortfall the integrator
    alone leaves then."""
    loop = Px4LoopParams()
    step = [(3.0, (1.2, 0.0))]
    *_, (_, unfed, _, _) = _fly(step, loop=loop)
    *_, (_, fed, _, _) = _fly(step, accel_of=lambda sp: (loop.drag_1_s * sp[0], 0.0), loop=loop)
    assert 1.2 - unfed[0] > 0.2 and abs(1.2 - fed[0]) < 0.3 * (1.2 - unfed[0]), (unfed, fed)
