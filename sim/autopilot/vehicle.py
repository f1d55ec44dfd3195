"""Emulated multicopter: flight-mode state machine, arming, takeoff/land, failsafes, physics.

Pure: no sockets, no wall clock.  Every public method takes the simulated time ``t_s``
(seconds, non-decreasing) and first advances the physics to it, so a unit test drives the
vehicle with a fake clock exactly as the MAVLink server drives it with ``time.monotonic``.

Physics: a point mass in local NED.  The realised velocity comes from the paper's
:class:`sim.plant.model.VelocityPlant` (velocity command in, velocity out, speed/tilt/thrust limits
inside the plant), or from stock PX4's velocity loop (``VehicleConfig.px4_loop``); position integrates
velocity.  Flat ground at ``D = 0``: the vehicle cannot go below it; while on the ground and not
commanded to climb it sits still (landed).  A vehicle disarmed in the air falls.  Fixed physics step
(``VehicleConfig.physics_dt_s``, zero-order hold of the command over it).  With an estimate error
(``VehicleConfig.estimate_error``) the velocity loop holds the estimate at the command and the snapshot
carries the estimate beside the truth.

Rules (see docs/autopilot_emulator.md for the full list):

* arming needs a position estimate and an armable mode; disarming in the air needs force;
* PX4 OFFBOARD can only be entered while setpoints stream (last one younger than
  ``offboard_stream_window_s``); in OFFBOARD, no setpoint for ``COM_OF_LOSS_T`` triggers the
  ``COM_OBL_RC_ACT`` action (default: Hold = AUTO.LOITER, zero velocity);
* ArduPilot GUIDED: NAV_TAKEOFF climbs to the altitude at ``WPNAV_SPEED_UP``; velocity targets
  older than ``GUID_TIMEOUT`` are replaced by zero velocity (the vehicle stops);
* LAND descends and disarms on the ground; auto-disarm after landing / when armed but never
  taken off; GCS heartbeat-loss failsafe (PX4 ``NAV_DLL_ACT``, ArduPilot ``FS_GCS_ENABLE``).

Many vehicles: each :class:`Vehicle` owns a 1-agent plant (a batched stepper could gather them).
"""

from __future__ import annotations

import logging
import math
from typing import Callable

import numpy as np
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from sim.autopilot.attitude import attitude_from_thrust
from sim.autopilot.estimate_error import EstimateError
from sim.autopilot.personalities import FlightMode, Personality
from sim.autopilot.rules import FailsafeAction, PersonalityRules
from sim.autopilot.vehicle_types import (ACCEPTED, FAILED, NAN3, TEMPORARILY_REJECTED, UNSUPPORTED, Outcome,
                                         Setpoint, StatusEvent, VehicleConfig, VehicleState)
from sim.plant.model import PlantParams, VelocityPlant
from sim.plant.px4_loop import Px4LoopPlant

__all__ = ["Outcome", "Setpoint", "VehicleConfig", "VehicleState", "Vehicle", "StatusEvent"]

_log = logging.getLogger(__name__)
_NOT_ARMABLE = frozenset({FlightMode.LAND, FlightMode.RTL, FlightMode.BRAKE})  # PX4 and ArduPilot refuse LAND/RTL
_EXTERNAL = frozenset({FlightMode.OFFBOARD, FlightMode.GUIDED})  # the modes flying external setpoints
PlantFactory = Callable[[PlantParams], VelocityPlant]


class Vehicle:
    """One emulated multicopter with a PX4 or ArduPilot Copter personality (pure state machine)."""

    def __init__(
        self,
        personality: Personality,
        config: VehicleConfig | None = None,
        sysid: int = 1,
        t0_s: float = 0.0,
        plant_factory: PlantFactory | None = None,
    ) -> None:
        self.personality = personality
        self.config = VehicleConfig() if config is None else config
        start = np.asarray(self.config.start_ned_m, dtype=float)
        if start.shape != (3,) or not np.all(np.isfinite(start)):
            raise ValueError(f"start_ned_m must be 3 finite numbers, got {self.config.start_ned_m!r}")
        if start[2] > 0.0:
            raise ValueError(f"start_ned_m down = {start[2]} m is below the ground (D must be <= 0)")
        if self.config.physics_dt_s <= 0:
            raise ValueError(f"physics_dt_s must be > 0, got {self.config.physics_dt_s}")
        self.params: dict[str, float] = personality.default_params(sysid)
        self._loop = None if self.config.px4_loop is None else Px4LoopPlant(self.config.px4_loop)
        self._plant = self._loop or (plant_factory or (lambda p: VelocityPlant(p, 1)))(self.config.plant_params)
        self._fixed_step = self._plant.fixed_step(self.config.physics_dt_s)
        self._tau_v_s = 0.0 if self._loop else 1.0 / float(self._plant.coefficients.inv_tau_v[0])
        self._px4 = personality.name == "px4"
        self._est = None if self.config.estimate_error is None else EstimateError(self.config.estimate_error)
        self._rules = PersonalityRules(self._px4, self.params)
        self.t_s = float(t0_s)
        self.pos = start.copy()
        self.vel = np.zeros(3)
        self.cmd = np.zeros(3)
        self.yaw = float(self.config.start_yaw_rad)
        self.yaw_rate = 0.0
        self.home = np.array([start[0], start[1], 0.0])
        self.position_valid = True
        self.mode = personality.boot_mode
        self.armed = False
        self.landed = start[2] >= 0.0
        self._ever_airborne = False
        self._landed_since = self.t_s
        self._setpoint: Setpoint | None = None
        self._setpoint_t = -math.inf
        self._guided_vel_t = -math.inf
        self._takeoff_target_d: float | None = None  # PX4 TAKEOFF and ArduPilot GUIDED takeoff
        self._rtl_phase = "climb"
        self._rtl_target_d = 0.0
        self._gcs_last_t: float | None = None
        self._gcs_failsafe_active = False
        self._events: list[StatusEvent] = []
        if not self.landed:  # airborne start: armed, hovering in the hold mode
            self.armed = True
            self._ever_airborne = True
            self.mode = personality.hold_mode
            self._plant.reset()

    def set_param(self, name: str, value: float) -> bool:
        """Set a known parameter (returns False for unknown names; system ids are read-only)."""
        if name not in self.params:
            return False
        if name not in ("MAV_SYS_ID", "SYSID_THISMAV"):
            self.params[name] = float(value)
        return True

    def drain_events(self) -> list[StatusEvent]:
        """Return and clear the pending status events."""
        ev, self._events = self._events, []
        return ev

    def _event(self, text: str, severity: int = mavlink.MAV_SEVERITY_INFO) -> None:
        self._events.append(StatusEvent(self.t_s, severity, text))
        _log.info("vehicle t=%.2f: %s", self.t_s, text)

    # ------------------------------------------------------------------ commands
    def set_position_valid(self, valid: bool, t_s: float) -> None:
        """Mark the position estimate (un)available (arming needs it)."""
        self.step(t_s)
        self.position_valid = bool(valid)

    def arm(self, t_s: float, force: bool = False) -> Outcome:
        """MAV_CMD_COMPONENT_ARM_DISARM param1 = 1."""
        self.step(t_s)
        if self.armed:
            return Outcome(ACCEPTED)
        if not force:
            if not self.position_valid:
                return Outcome(self._rules.reject_code, "Arming denied: no position estimate")
            if self.mode in _NOT_ARMABLE:
                return Outcome(self._rules.reject_code, f"Arming denied: not armable in {self.mode_name}")
            if self.mode.needs_pilot and self._px4:
                # (ArduPilot arms in pilot modes as SITL does with its idle simulated RC: the
                # vehicle then just sits / holds; PX4 never reaches them without RC)
                return Outcome(self._rules.reject_code, f"Arming denied: {self.mode_name} needs RC")
            if not self.landed:
                return Outcome(self._rules.reject_code, "Arming denied: not landed")
        self.armed = True
        self._ever_airborne = not self.landed
        self._landed_since = self.t_s
        if not self.landed:  # forced arming in the air: the plant picks up the current velocity
            self._plant.reset(self.vel)
        self.home = np.array([self.pos[0], self.pos[1], 0.0])
        self._event("Armed")
        return Outcome(ACCEPTED)

    def disarm(self, t_s: float, force: bool = False) -> Outcome:
        """MAV_CMD_COMPONENT_ARM_DISARM param1 = 0 (force: param2 = 21196)."""
        self.step(t_s)
        if not self.armed:
            return Outcome(ACCEPTED)
        if not self.landed and not force:
            return Outcome(self._rules.reject_code, "Disarming denied: not landed")
        self._disarm("Disarmed")
        return Outcome(ACCEPTED)

    def _disarm(self, why: str) -> None:
        self.armed = False
        self._takeoff_target_d = None
        self._event(why)

    @property
    def mode_name(self) -> str:
        """Current mode as the autopilot names it."""
        return self.personality.mode_name(self.mode)

    def set_mode(self, mode: FlightMode, t_s: float) -> Outcome:
        """Mode change request (SET_MODE / MAV_CMD_DO_SET_MODE), with the personality's rules."""
        self.step(t_s)
        if mode not in self.personality.modes:
            return Outcome(UNSUPPORTED, f"Mode {mode.value} not supported")
        if mode == self.mode:
            return Outcome(ACCEPTED)
        if self._px4:
            if mode.needs_pilot:
                return Outcome(TEMPORARILY_REJECTED, "Mode change denied: no RC")
            if mode == FlightMode.OFFBOARD and not self._offboard_stream_ok():
                return Outcome(TEMPORARILY_REJECTED, "Offboard denied: no setpoint stream")
        if mode in (FlightMode.OFFBOARD, FlightMode.GUIDED, FlightMode.TAKEOFF, FlightMode.LOITER,
                    FlightMode.RTL, FlightMode.MISSION, FlightMode.POSCTL) and not self.position_valid:
            return Outcome(self._rules.reject_code, "Mode change denied: no position estimate")
        self._enter_mode(mode)
        return Outcome(ACCEPTED)

    def _enter_mode(self, mode: FlightMode, takeoff_alt_m: float | None = None) -> None:
        self.mode = mode
        self._takeoff_target_d = None
        if mode == FlightMode.TAKEOFF:
            alt = self.params["MIS_TAKEOFF_ALT"] if takeoff_alt_m is None else takeoff_alt_m
            self._takeoff_target_d = self.home[2] - alt
        elif mode == FlightMode.GUIDED:
            self._setpoint = None
            self._guided_vel_t = -math.inf
        elif mode == FlightMode.RTL:
            self._rtl_phase = "climb"
            self._rtl_target_d = min(float(self.pos[2]), self.home[2] - self._rules.rtl_altitude_m())
        self._event(f"Mode {self.mode_name}")

    def takeoff(self, t_s: float, altitude_m: float | None = None) -> Outcome:
        """MAV_CMD_NAV_TAKEOFF; ``altitude_m`` above home (None: PX4 MIS_TAKEOFF_ALT)."""
        self.step(t_s)
        if altitude_m is not None and not (math.isfinite(altitude_m) and altitude_m > 0):
            altitude_m = None
        if not self.armed:
            return Outcome(self._rules.reject_code, "Takeoff denied: disarmed")
        if self._px4:
            if not self.position_valid:
                return Outcome(TEMPORARILY_REJECTED, "Takeoff denied: no position estimate")
            self._enter_mode(FlightMode.TAKEOFF, altitude_m)
            return Outcome(ACCEPTED)
        if self.mode != FlightMode.GUIDED:
            return Outcome(FAILED, "Takeoff denied: not in GUIDED")
        if not self.landed:
            return Outcome(FAILED, "Takeoff denied: already flying")
        if altitude_m is None:
            return Outcome(FAILED, "Takeoff denied: no altitude")
        self._takeoff_target_d = self.home[2] - altitude_m
        self._setpoint = None
        self._event(f"Takeoff to {altitude_m:.1f} m")
        return Outcome(ACCEPTED)

    def land(self, t_s: float) -> Outcome:
        """MAV_CMD_NAV_LAND: switch to LAND."""
        self.step(t_s)
        if self.mode != FlightMode.LAND:
            self._enter_mode(FlightMode.LAND)
        return Outcome(ACCEPTED)

    def return_to_launch(self, t_s: float) -> Outcome:
        """MAV_CMD_NAV_RETURN_TO_LAUNCH: switch to RTL."""
        return self.set_mode(FlightMode.RTL, t_s)

    def set_setpoint(self, setpoint: Setpoint, t_s: float) -> None:
        """An external SET_POSITION_TARGET_* (resolved to local NED); flown in OFFBOARD/GUIDED."""
        self.step(t_s)
        self._setpoint = setpoint
        self._setpoint_t = self.t_s
        if setpoint.has_velocity:
            self._guided_vel_t = self.t_s
        if self.mode == FlightMode.GUIDED and self._takeoff_target_d is not None and not self.landed:
            # ArduPilot: a new target during the takeoff climb ends the takeoff
            self._takeoff_target_d = None

    def gcs_heartbeat(self, t_s: float) -> None:
        """A HEARTBEAT from a ground station arrived (data-link-loss failsafe bookkeeping)."""
        self.step(t_s)
        self._gcs_last_t = self.t_s
        if self._gcs_failsafe_active:
            self._gcs_failsafe_active = False
            self._event("GCS link regained")

    def _offboard_stream_ok(self) -> bool:
        return self.t_s - self._setpoint_t <= self.config.offboard_stream_window_s

    # ------------------------------------------------------------------ failsafes
    def _check_failsafes(self) -> None:
        t = self.t_s
        rules = self._rules
        if self.mode == FlightMode.OFFBOARD and t - self._setpoint_t > rules.offboard_loss_timeout_s():
            self._failsafe("Failsafe: offboard setpoints lost", rules.offboard_loss_action())
        if self._gcs_last_t is not None and not self._gcs_failsafe_active and self.armed and not self.landed:
            action, timeout = rules.gcs_loss()
            if action != 0 and t - self._gcs_last_t > timeout:
                self._gcs_failsafe_active = True
                self._failsafe("Failsafe: GCS link lost", rules.gcs_loss_action(action))

    def _failsafe(self, why: str, action: FailsafeAction) -> None:
        self._event(why, mavlink.MAV_SEVERITY_WARNING)
        if action.mode is not None:
            self._enter_mode(action.mode)
        if action.disarm:
            self._disarm("Failsafe: disarmed")

    # ------------------------------------------------------------------ physics
    def step(self, t_s: float) -> None:
        """Advance the simulation to time ``t_s`` in fixed physics steps."""
        dt = self.config.physics_dt_s
        if t_s < self.t_s - 1e-9:
            raise ValueError(f"time went backwards: {t_s} < {self.t_s}")
        while self.t_s + dt <= t_s + 1e-9:
            self._substep(dt)

    def _velocity_command(self) -> list[float]:
        """Velocity command [m/s] NED of the current mode (motors assumed on), as 3 floats.

        Plain float arithmetic (one vehicle: numpy's per-call overhead would dominate)."""
        mode = self.mode
        k = self.config.position_gain_1_s
        if self._takeoff_target_d is not None and mode in (FlightMode.TAKEOFF, FlightMode.GUIDED):
            err = float(self.pos[2]) - self._takeoff_target_d  # > 0 below the target
            up = -min(max(k * err, -self._rules.land_speed_m_s()), self._rules.takeoff_speed_m_s())
            if abs(err) <= self.config.takeoff_tolerance_m:
                self._takeoff_target_d = None
                if mode == FlightMode.TAKEOFF:
                    self._event("Takeoff complete")
                    self._enter_mode(FlightMode.LOITER)
                else:
                    self._event("Takeoff complete")
            return [0.0, 0.0, up]
        if mode in _EXTERNAL:
            sp = self._setpoint
            if sp is None:
                return [0.0, 0.0, 0.0]
            v = sp.velocity_ned_m_s
            if mode == FlightMode.GUIDED and self.t_s - self._guided_vel_t > self.params["GUID_TIMEOUT"]:
                v = NAN3  # ArduPilot: stale velocity target -> stop
            isfinite = math.isfinite
            return [
                (vj if isfinite(vj) else 0.0) + (k * (pj - xj) if isfinite(pj) else 0.0)
                for vj, pj, xj in zip(v, sp.position_ned_m, self.pos.tolist())
            ]
        if mode == FlightMode.LAND:
            return [0.0, 0.0, self._rules.land_speed_m_s()]
        sink = self._rules.no_rc_descent_m_s(mode)
        if sink is not None:
            return [0.0, 0.0, sink]  # the throttle stick at zero: no RC, it sinks
        if mode == FlightMode.RTL:
            return self._rtl_command().tolist()
        return [0.0, 0.0, 0.0]  # hold modes (and TAKEOFF after completion): zero velocity

    def _rtl_command(self) -> np.ndarray:
        k = self.config.position_gain_1_s
        cmd = np.zeros(3)
        d_err = self.pos[2] - self._rtl_target_d
        if self._rtl_phase == "climb":
            cmd[2] = -min(self._rules.takeoff_speed_m_s(), k * d_err)
            if d_err <= self.config.takeoff_tolerance_m:
                self._rtl_phase = "return"
        elif self._rtl_phase == "return":
            delta = self.home[:2] - self.pos[:2]
            dist = float(np.hypot(*delta))
            speed = min(self._rules.cruise_speed_m_s(), k * dist)
            if dist > 1e-9:
                cmd[:2] = delta / dist * speed
            cmd[2] = -k * d_err
            if dist <= self.config.rtl_arrival_radius_m:
                self._rtl_phase = "land"
        else:
            cmd[:2] = k * (self.home[:2] - self.pos[:2])
            cmd[2] = self._rules.land_speed_m_s()
        return cmd

    def _with_accel_feedforward(self, cmd: list[float]) -> list[float]:
        """PX4 OFFBOARD adds a setpoint's acceleration to its velocity loop's output: the PX4 loop model takes it
        as such, the plant's shaping ``(v_cmd - v) / tau_v`` as ``tau_v a`` more command (ArduPilot: not flown)."""
        sp = self._setpoint
        on = sp is not None and self._px4 and self.mode == FlightMode.OFFBOARD
        if not on and self._loop is None:
            return cmd  # every physics step of a velocity plant without it: nothing to build
        acc = [a if math.isfinite(a) else 0.0 for a in (sp.accel_ned_m_s2 if on else NAN3)]
        if self._loop is not None:
            self._loop.accel_ff_ned_m_s2 = acc
            return cmd
        return [c + self._tau_v_s * a for c, a in zip(cmd, acc)]

    def _limit(self, cmd: list[float]) -> list[float]:
        """Clamp a 3-float command in place to the horizontal / climb / descent limits."""
        xy_max, up_max, dn_max = self._rules.command_limits_m_s()
        c0, c1 = cmd[0], cmd[1]
        if not c0 * c0 + c1 * c1 <= 0.98 * xy_max * xy_max:  # else clearly inside: skip np.hypot
            h = float(np.hypot(c0, c1))
            if h > xy_max:
                s = xy_max / h
                cmd[0] *= s
                cmd[1] *= s
        cmd[2] = min(max(cmd[2], -up_max), dn_max)
        return cmd

    def _substep(self, dt: float) -> None:
        self.t_s += dt
        self._check_failsafes()
        g = self.config.plant_params.g
        if not self.armed:
            self.cmd = np.zeros(3)
            if self.landed:
                self.vel[:] = 0.0
            else:  # motors off in the air: ballistic fall
                self.vel[2] += float(np.mean(g)) * dt
                self.pos += self.vel * dt
                self._ground_contact(falling=True)
            self._update_yaw(dt)
            return
        cmd = self._limit(self._velocity_command())
        self.cmd = np.array(cmd)
        cmd_row = np.array([self._with_accel_feedforward(cmd)])  # (1, 3), as the plant takes it
        if self._est is not None:  # under external setpoints its velocity loop holds the estimate, v + e, at them
            self._est.step(dt)
            if self.mode in _EXTERNAL:
                cmd_row -= self._est.velocity_ned_m_s
        if self.landed:
            if cmd[2] < -1e-6:  # commanded to climb: lift off from rest
                self.landed = False
                self._ever_airborne = True
                self._plant.reset()
                self._event("Takeoff detected")
            else:
                self.vel[:] = 0.0
                self._auto_disarm_check()
                self._update_yaw(dt)
                return
        if dt == self.config.physics_dt_s:
            self.vel = self._fixed_step(cmd_row)[0].copy()
        else:
            self.vel = np.array(self._plant.step(cmd_row, dt)[0], dtype=float)
        self.pos += self.vel * dt
        self._ground_contact(falling=False)
        self._update_yaw(dt)

    def _ground_contact(self, falling: bool) -> None:
        if self.pos[2] < 0.0:
            return
        self.pos[2] = 0.0
        if falling or self.cmd[2] >= 0.0:
            self.vel[:] = 0.0
            self.landed = True
            self._landed_since = self.t_s
            self._plant.reset()
            self._event("Landing detected")
            if self.armed and self.mode == FlightMode.LAND and not self._px4:
                self._disarm("Disarmed: landed")  # ArduPilot LAND disarms on touchdown
            elif self.armed and self.mode == FlightMode.RTL and not self._px4:
                self._disarm("Disarmed: landed")
        else:  # commanded to climb but the plant still sinks: rest on the ground
            self.vel[2] = min(self.vel[2], 0.0)
            self._plant.velocity[0, 2] = self.vel[2]

    def _auto_disarm_check(self) -> None:
        """Disarm a vehicle sitting on the ground (PX4 COM_DISARM_LAND / COM_DISARM_PRFLT,
        ArduPilot DISARM_DELAY; a negative / zero delay disables it)."""
        delay = self._rules.auto_disarm_delay_s(self._ever_airborne)
        if delay >= 0 and self.t_s - self._landed_since >= delay - 1e-9:
            self._disarm("Auto-disarmed: landed")

    def _update_yaw(self, dt: float) -> None:
        sp = self._setpoint
        rate = 0.0
        if self.armed and not self.landed and sp is not None and self.mode in _EXTERNAL:
            max_r = self.config.yaw_rate_max_rad_s
            if math.isfinite(sp.yaw_rad):
                err = (sp.yaw_rad - self.yaw + math.pi) % (2 * math.pi) - math.pi
                rate = min(max(err / dt, -max_r), max_r)
            elif math.isfinite(sp.yaw_rate_rad_s):
                rate = min(max(float(sp.yaw_rate_rad_s), -max_r), max_r)
        self.yaw = (self.yaw + rate * dt + math.pi) % (2 * math.pi) - math.pi
        self.yaw_rate = rate

    # ------------------------------------------------------------------ telemetry
    def _attitude(self) -> tuple[float, float]:
        """(roll, pitch) [rad] from the direction of the realised thrust."""
        if not self.armed or self.landed:
            return 0.0, 0.0
        return attitude_from_thrust(tuple(self._plant.thrust_accel[0].tolist()), self.yaw)

    def _landed_state(self) -> int:
        if self.landed or (not self.armed and self.pos[2] >= 0.0):
            return mavlink.MAV_LANDED_STATE_ON_GROUND
        if self._takeoff_target_d is not None:
            return mavlink.MAV_LANDED_STATE_TAKEOFF
        if self.mode == FlightMode.LAND or (self.mode == FlightMode.RTL and self._rtl_phase == "land"):
            return mavlink.MAV_LANDED_STATE_LANDING
        return mavlink.MAV_LANDED_STATE_IN_AIR

    def snapshot(self) -> VehicleState:
        """Immutable copy of the current state."""
        roll, pitch = self._attitude()
        pos, vel, e = self.pos.tolist(), self.vel.tolist(), self._est
        return VehicleState(
            t_s=self.t_s,
            armed=self.armed,
            mode=self.mode,
            custom_mode=self.personality.custom_mode(self.mode),
            position_ned_m=tuple(pos),
            velocity_ned_m_s=tuple(vel),
            roll_rad=roll,
            pitch_rad=pitch,
            yaw_rad=self.yaw,
            yaw_rate_rad_s=self.yaw_rate,
            landed_state=self._landed_state(),
            home_ned_m=tuple(self.home.tolist()),
            position_valid=self.position_valid,
            last_setpoint_t_s=self._setpoint_t,
            velocity_command_ned_m_s=tuple(self.cmd.tolist()),
            estimate_position_ned_m=None if e is None else tuple(p + d for p, d in zip(pos, e.position_ned_m)),
            estimate_velocity_ned_m_s=None if e is None else tuple(v + d for v, d in zip(vel, e.velocity_ned_m_s)),
        )

