"""The emulated vehicle's state machine on a simulated clock (no sockets, no wall time)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from sim.autopilot.personalities import ARDUPILOT, PX4, FlightMode
from sim.autopilot.vehicle import Setpoint, Vehicle, VehicleConfig
from sim.plant.fit import plant_preset
from sim.plant.model import VelocityPlant
from sim.plant.px4_loop import Px4LoopParams

ACCEPTED = mavlink.MAV_RESULT_ACCEPTED
REJECTED = mavlink.MAV_RESULT_TEMPORARILY_REJECTED


class Clock:
    """Simulated time driving a vehicle, with a setpoint stream helper."""

    def __init__(self, vehicle: Vehicle) -> None:
        self.v = vehicle
        self.t = 0.0

    def run(self, seconds: float, setpoint: Setpoint | None = None, rate_hz: float = 20.0) -> None:
        end = self.t + seconds
        while self.t < end - 1e-9:
            self.t = min(self.t + 1.0 / rate_hz, end)
            if setpoint is not None:
                self.v.set_setpoint(setpoint, self.t)
            else:
                self.v.step(self.t)


def vel(n: float, e: float, d: float) -> Setpoint:
    return Setpoint(velocity_ned_m_s=(n, e, d))


def px4_offboard(start=(0.0, 0.0, 0.0)) -> tuple[Vehicle, Clock]:
    v = Vehicle(PX4, VehicleConfig(start_ned_m=start))
    c = Clock(v)
    assert v.arm(c.t).ok
    c.run(0.5, vel(0, 0, 0))
    assert v.set_mode(FlightMode.OFFBOARD, c.t).ok
    return v, c


def test_uses_the_papers_velocity_plant():
    v = Vehicle(PX4)
    assert isinstance(v._plant, VelocityPlant)


def test_px4_boots_disarmed_on_the_ground_in_hold():
    s = Vehicle(PX4).snapshot()
    assert not s.armed and s.mode == FlightMode.LOITER
    assert s.custom_mode == (4 << 16) | (3 << 24)
    assert s.landed_state == mavlink.MAV_LANDED_STATE_ON_GROUND
    assert s.position_ned_m == (0.0, 0.0, 0.0)


def test_arming_needs_a_position_estimate():
    v = Vehicle(PX4)
    v.set_position_valid(False, 0.1)
    out = v.arm(0.2)
    assert out.result == REJECTED and "position" in out.text
    v.set_position_valid(True, 0.3)
    assert v.arm(0.4).ok and v.snapshot().armed


def test_offboard_refused_without_a_setpoint_stream():
    v = Vehicle(PX4)
    assert v.arm(0.0).ok
    out = v.set_mode(FlightMode.OFFBOARD, 0.1)
    assert out.result == REJECTED
    assert v.snapshot().mode == FlightMode.LOITER


def test_offboard_refused_when_the_stream_went_stale():
    v = Vehicle(PX4)
    c = Clock(v)
    c.run(1.0, vel(0, 0, 0))
    c.run(0.8)  # silence longer than the 0.5 s window
    assert v.set_mode(FlightMode.OFFBOARD, c.t).result == REJECTED
    c.run(0.3, vel(0, 0, 0))
    assert v.set_mode(FlightMode.OFFBOARD, c.t).ok


def test_offboard_velocity_moves_the_vehicle_in_the_commanded_direction():
    v, c = px4_offboard()
    c.run(4.0, vel(1.0, -0.5, -1.0))
    s = v.snapshot()
    n, e, d = s.position_ned_m
    assert n > 2.0 and e < -1.0 and d < -2.0
    np.testing.assert_allclose(s.velocity_ned_m_s, (1.0, -0.5, -1.0), atol=0.1)
    assert s.landed_state == mavlink.MAV_LANDED_STATE_IN_AIR


def test_horizontal_command_on_the_ground_does_not_slide():
    v, c = px4_offboard()
    c.run(1.0, vel(1.0, 0.0, 0.0))
    s = v.snapshot()
    assert s.position_ned_m == (0.0, 0.0, 0.0) and s.landed_state == mavlink.MAV_LANDED_STATE_ON_GROUND


def test_position_and_position_velocity_setpoints_converge():
    v, c = px4_offboard(start=(0.0, 0.0, -5.0))
    c.run(8.0, Setpoint(position_ned_m=(3.0, 2.0, -6.0)))
    np.testing.assert_allclose(v.snapshot().position_ned_m, (3.0, 2.0, -6.0), atol=0.15)
    c.run(3.0, Setpoint(position_ned_m=(3.0, 2.0, -6.0), velocity_ned_m_s=(0.0, 0.0, 0.0)))
    np.testing.assert_allclose(v.snapshot().position_ned_m, (3.0, 2.0, -6.0), atol=0.05)


def test_offboard_loss_failsafe_switches_to_hold_after_com_of_loss_t():
    v, c = px4_offboard(start=(0.0, 0.0, -5.0))
    c.run(2.0, vel(2.0, 0.0, 0.0))
    c.run(0.9)
    assert v.snapshot().mode == FlightMode.OFFBOARD  # 0.9 s < COM_OF_LOSS_T = 1.0 s
    c.run(0.2)
    s = v.snapshot()
    assert s.mode == FlightMode.LOITER and s.armed
    c.run(3.0)
    assert np.linalg.norm(v.snapshot().velocity_ned_m_s) < 0.1  # decelerated to a hover
    assert any("offboard" in e.text for e in v.drain_events())


def test_offboard_loss_action_follows_com_obl_rc_act_and_com_of_loss_t():
    v, c = px4_offboard(start=(0.0, 0.0, -5.0))
    v.set_param("COM_OBL_RC_ACT", 4)  # Land
    v.set_param("COM_OF_LOSS_T", 0.3)
    c.run(1.0, vel(0, 0, 0))
    c.run(0.4)
    assert v.snapshot().mode == FlightMode.LAND


def test_land_descends_touches_down_and_px4_disarms_after_com_disarm_land():
    v, c = px4_offboard(start=(0.0, 0.0, -2.0))
    assert v.land(c.t).ok
    c.run(2.0)
    s = v.snapshot()
    assert s.mode == FlightMode.LAND and s.landed_state == mavlink.MAV_LANDED_STATE_LANDING
    assert s.velocity_ned_m_s[2] == pytest.approx(0.7, abs=0.05)  # MPC_LAND_SPEED
    c.run(1.5)
    s = v.snapshot()
    assert s.position_ned_m[2] == 0.0 and s.armed and s.landed_state == mavlink.MAV_LANDED_STATE_ON_GROUND
    c.run(2.1)  # COM_DISARM_LAND = 2 s
    assert not v.snapshot().armed


def test_never_below_ground_and_force_disarm_in_air_falls():
    v, c = px4_offboard(start=(0.0, 0.0, -3.0))
    c.run(3.0, vel(0, 0, 1.5))
    assert v.snapshot().position_ned_m[2] <= 0.0
    v2, c2 = px4_offboard(start=(0.0, 0.0, -3.0))
    assert v2.disarm(c2.t).result == REJECTED  # in the air, not forced
    assert v2.disarm(c2.t, force=True).ok
    c2.run(1.0)
    s = v2.snapshot()
    assert s.position_ned_m[2] == 0.0 and not s.armed and s.landed_state == mavlink.MAV_LANDED_STATE_ON_GROUND


def test_px4_disarms_when_armed_but_never_taken_off():
    v = Vehicle(PX4)
    c = Clock(v)
    assert v.arm(c.t).ok
    c.run(9.5)
    assert v.snapshot().armed
    c.run(1.0)  # COM_DISARM_PRFLT = 10 s
    assert not v.snapshot().armed


def test_px4_takeoff_climbs_to_mis_takeoff_alt_then_holds():
    v = Vehicle(PX4)
    c = Clock(v)
    assert v.takeoff(c.t).result == REJECTED  # disarmed
    assert v.arm(c.t).ok
    assert v.takeoff(c.t, altitude_m=math.nan).ok
    assert v.snapshot().mode == FlightMode.TAKEOFF
    c.run(6.0)
    s = v.snapshot()
    assert s.mode == FlightMode.LOITER
    assert s.position_ned_m[2] == pytest.approx(-2.5, abs=0.2)


def test_px4_manual_modes_refused_without_rc():
    v = Vehicle(PX4)
    assert v.set_mode(FlightMode.POSCTL, 0.0).result == REJECTED
    assert v.set_mode(FlightMode.GUIDED, 0.0).result == mavlink.MAV_RESULT_UNSUPPORTED


def test_ardupilot_guided_takeoff_climbs_at_1_5_m_s_then_flies_velocity():
    v = Vehicle(ARDUPILOT)
    c = Clock(v)
    assert v.snapshot().mode == FlightMode.STABILIZED
    assert v.set_mode(FlightMode.GUIDED, c.t).ok
    assert v.takeoff(c.t, 5.0).result == mavlink.MAV_RESULT_FAILED  # disarmed
    assert v.arm(c.t).ok
    assert v.takeoff(c.t, 5.0).ok
    c.run(2.0)
    s = v.snapshot()
    assert s.velocity_ned_m_s[2] == pytest.approx(-1.5, abs=0.1)
    assert s.landed_state == mavlink.MAV_LANDED_STATE_TAKEOFF
    c.run(4.0)
    assert v.snapshot().position_ned_m[2] == pytest.approx(-5.0, abs=0.2)
    c.run(3.0, vel(0.0, 1.0, 0.0))
    s = v.snapshot()
    assert s.mode == FlightMode.GUIDED and s.position_ned_m[1] > 1.5


def test_ardupilot_arms_in_stabilize_like_sitl_and_sits_still():
    v = Vehicle(ARDUPILOT)
    c = Clock(v)
    assert v.arm(c.t).ok
    assert v.takeoff(c.t, 2.0).result == mavlink.MAV_RESULT_FAILED  # takeoff needs GUIDED
    c.run(5.0)
    s = v.snapshot()
    assert s.armed and s.position_ned_m == (0.0, 0.0, 0.0)
    c.run(5.5)  # DISARM_DELAY = 10 s
    assert not v.snapshot().armed


def test_ardupilot_refuses_arming_in_land_and_rtl():
    v = Vehicle(ARDUPILOT)
    assert v.set_mode(FlightMode.LAND, 0.0).ok
    assert v.arm(0.1).result == mavlink.MAV_RESULT_FAILED
    assert v.set_mode(FlightMode.RTL, 0.2).ok
    assert v.arm(0.3).result == mavlink.MAV_RESULT_FAILED


def test_ardupilot_target_during_takeoff_climb_ends_the_takeoff():
    v = Vehicle(ARDUPILOT)
    c = Clock(v)
    v.set_mode(FlightMode.GUIDED, c.t)
    v.arm(c.t)
    assert v.takeoff(c.t, 10.0).ok
    c.run(1.0)
    c.run(2.0, vel(0.0, 0.0, 0.0))
    s = v.snapshot()
    assert -2.5 < s.position_ned_m[2] < -0.5 and abs(s.velocity_ned_m_s[2]) < 0.1
    assert s.landed_state == mavlink.MAV_LANDED_STATE_IN_AIR


def test_ardupilot_guid_timeout_stops_the_vehicle_but_stays_guided():
    v = Vehicle(ARDUPILOT, VehicleConfig(start_ned_m=(0.0, 0.0, -5.0)))
    c = Clock(v)
    assert v.set_mode(FlightMode.GUIDED, c.t).ok
    c.run(2.0, vel(2.0, 0.0, 0.0))
    c.run(2.5)  # < GUID_TIMEOUT = 3 s: keeps flying the old target
    assert v.snapshot().velocity_ned_m_s[0] == pytest.approx(2.0, abs=0.1)
    c.run(3.0)
    s = v.snapshot()
    assert s.mode == FlightMode.GUIDED and abs(s.velocity_ned_m_s[0]) < 0.1


def test_ardupilot_land_disarms_on_touchdown():
    v = Vehicle(ARDUPILOT, VehicleConfig(start_ned_m=(0.0, 0.0, -1.0)))
    c = Clock(v)
    assert v.land(c.t).ok and v.snapshot().mode == FlightMode.LAND
    c.run(2.5)  # LAND_SPEED 50 cm/s
    s = v.snapshot()
    assert s.position_ned_m[2] == 0.0 and not s.armed


def test_ardupilot_gcs_failsafe_rtl_when_enabled():
    v = Vehicle(ARDUPILOT, VehicleConfig(start_ned_m=(10.0, 0.0, -5.0)))
    c = Clock(v)
    v.set_mode(FlightMode.GUIDED, c.t)
    v.gcs_heartbeat(c.t)
    c.run(6.0)
    assert v.snapshot().mode == FlightMode.GUIDED  # FS_GCS_ENABLE = 0 by default
    v.set_param("FS_GCS_ENABLE", 1)
    v.gcs_heartbeat(c.t)
    c.run(5.5)
    assert v.snapshot().mode == FlightMode.RTL


def test_rtl_returns_home_and_lands():
    v, c = px4_offboard(start=(0.0, 0.0, -3.0))
    v.set_param("RTL_RETURN_ALT", 4.0)
    c.run(3.0, vel(2.0, 0.0, 0.0))
    assert v.snapshot().position_ned_m[0] > 4.0
    assert v.return_to_launch(c.t).ok
    c.run(4.0)
    assert v.snapshot().position_ned_m[2] == pytest.approx(-4.0, abs=0.3)  # climbed to RTL_RETURN_ALT
    c.run(16.0)
    s = v.snapshot()
    assert abs(s.position_ned_m[0]) < 0.6 and s.position_ned_m[2] == 0.0 and not s.armed


def test_airborne_start_is_armed_and_holding():
    s = Vehicle(ARDUPILOT, VehicleConfig(start_ned_m=(1.0, 2.0, -4.0))).snapshot()
    assert s.armed and s.mode == FlightMode.BRAKE and s.in_air   # ArduPilot's pilot-free hold


def test_ardupilot_throttle_stick_modes_sink_without_rc_and_brake_holds():
    """Real ArduCopter SITL: LOITER with no RC descended and hit the ground at 2.47 m/s; BRAKE held."""
    for mode, sinks in ((FlightMode.LOITER, True), (FlightMode.ALTCTL, True), (FlightMode.BRAKE, False)):
        v = Vehicle(ARDUPILOT, VehicleConfig(start_ned_m=(0.0, 0.0, -10.0)))
        assert v.set_mode(mode, 0.0).result == 0
        v.step(2.0)
        d = v.snapshot().position_ned_m[2]
        assert (d > -8.5) if sinks else (abs(d + 10.0) < 0.1), (mode, d)   # sank > 1.5 m in 2 s
    px4 = Vehicle(PX4, VehicleConfig(start_ned_m=(0.0, 0.0, -10.0)))
    px4.step(2.0)
    assert px4.snapshot().mode == FlightMode.LOITER and abs(px4.snapshot().position_ned_m[2] + 10.0) < 0.1


def test_start_below_ground_is_an_error():
    with pytest.raises(ValueError, match="below the ground"):
        Vehicle(PX4, VehicleConfig(start_ned_m=(0.0, 0.0, 1.0)))


def test_body_frame_yaw_setpoint_turns_the_vehicle():
    v, c = px4_offboard(start=(0.0, 0.0, -5.0))
    c.run(3.0, Setpoint(velocity_ned_m_s=(0.0, 0.0, 0.0), yaw_rad=math.pi / 2))
    assert v.snapshot().yaw_rad == pytest.approx(math.pi / 2, abs=1e-6)


def test_time_must_not_go_backwards():
    v = Vehicle(PX4)
    v.step(1.0)
    with pytest.raises(ValueError, match="backwards"):
        v.step(0.5)


def _steady_north(personality, accel_n_m_s2: float, seconds: float = 25.0) -> Vehicle:
    """A vehicle on the stock PX4 SIH plant (quadratic drag, no feed-forward of its own) flying 1.5 m/s north
    in OFFBOARD / GUIDED with ``accel_n_m_s2`` as the setpoint's acceleration."""
    v = Vehicle(personality, VehicleConfig(start_ned_m=(0.0, 0.0, -5.0), plant_params=plant_preset("px4-sih")))
    c = Clock(v)
    sp = Setpoint(velocity_ned_m_s=(1.5, 0.0, 0.0), accel_ned_m_s2=(accel_n_m_s2, 0.0, 0.0))
    c.run(0.5, sp)
    assert v.set_mode(FlightMode.OFFBOARD if personality is PX4 else FlightMode.GUIDED, c.t).ok
    c.run(seconds, sp)
    return v


def test_px4_adds_the_setpoints_acceleration_to_its_velocity_loop():
    """Analytic: the plant's shaping ``(v_cmd - v) / tau_v + a - k v^2 = 0`` holds ``v = v_cmd`` when the setpoint
    carries the drag's acceleration ``a = k v_cmd^2``, and settles short of it without."""
    k = 1.225 * 0.39 / 2.0  # rho S / 2m of the px4-sih preset (Cd 1, 1 kg)
    fed = _steady_north(PX4, k * 1.5**2)
    unfed = _steady_north(PX4, 0.0)
    assert fed.vel[0] == pytest.approx(1.5, abs=1e-3)
    assert unfed.vel[0] < 1.5 - 0.2
    assert fed.snapshot().velocity_command_ned_m_s == pytest.approx((1.5, 0.0, 0.0))  # the velocity, not the sum
    over = _steady_north(PX4, 2.0 * k * 1.5**2)  # twice the drag: it overshoots (sign and scale of the term)
    assert over.vel[0] > 1.5 + 0.1


def test_ardupilot_guided_does_not_fly_the_acceleration_field():
    fed = _steady_north(ARDUPILOT, 0.5)
    unfed = _steady_north(ARDUPILOT, 0.0)
    assert fed.vel[0] == pytest.approx(unfed.vel[0], abs=1e-12)


def test_the_px4_loop_model_takes_off_flies_offboard_and_lands_as_the_plant_does():
    """``VehicleConfig.px4_loop``: the same rules (take-off, OFFBOARD, land, the ground) over stock PX4's loop."""
    v = Vehicle(PX4, VehicleConfig(px4_loop=Px4LoopParams()))
    c = Clock(v)
    assert v.arm(c.t).ok and v.takeoff(c.t, altitude_m=math.nan).ok
    c.run(6.0)
    s = v.snapshot()
    assert s.mode == FlightMode.LOITER and s.position_ned_m[2] == pytest.approx(-2.5, abs=0.2)
    c.run(0.5, vel(1.0, 0, 0))
    assert v.set_mode(FlightMode.OFFBOARD, c.t).ok
    c.run(30.0, vel(1.0, 0, 0))
    s = v.snapshot()
    assert s.velocity_ned_m_s == pytest.approx((1.0, 0.0, 0.0), abs=0.02)  # the integrator holds SIH's drag
    assert s.pitch_rad == pytest.approx(-math.atan(1.0 / 9.81), abs=0.01)  # tilted against it: c v / g
    assert v.land(c.t).ok
    c.run(8.0)
    s = v.snapshot()
    assert s.position_ned_m[2] == 0.0 and s.landed_state == mavlink.MAV_LANDED_STATE_ON_GROUND
    c.run(2.1)  # COM_DISARM_LAND = 2 s
    assert not v.snapshot().armed
