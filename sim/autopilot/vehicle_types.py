"""Value types of the emulated vehicle: command outcomes, setpoints, status events, settings, snapshots.

Pure data (frozen dataclasses) shared by the state machine (:mod:`sim.autopilot.vehicle`), the
MAVLink front end (:mod:`sim.autopilot.server`) and the setpoint resolution
(:mod:`sim.autopilot.setpoints`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

from pymavlink.dialects.v20 import ardupilotmega as mavlink

from sim.autopilot.estimate_error import EstimateErrorParams
from sim.autopilot.personalities import FlightMode
from sim.plant.model import PlantParams
from sim.plant.px4_loop import Px4LoopParams

__all__ = [
    "ACCEPTED", "DENIED", "FAILED", "TEMPORARILY_REJECTED", "UNSUPPORTED",
    "Outcome", "Setpoint", "StatusEvent", "VehicleConfig", "VehicleState",
]

ACCEPTED = mavlink.MAV_RESULT_ACCEPTED
TEMPORARILY_REJECTED = mavlink.MAV_RESULT_TEMPORARILY_REJECTED
DENIED = mavlink.MAV_RESULT_DENIED
UNSUPPORTED = mavlink.MAV_RESULT_UNSUPPORTED
FAILED = mavlink.MAV_RESULT_FAILED

NAN3 = (math.nan, math.nan, math.nan)
"""A 3-vector not given (NaN per axis)."""


@dataclass(frozen=True)
class Outcome:
    """Result of a command: a MAV_RESULT code and a short human-readable reason."""

    result: int
    """MAV_RESULT_* value for COMMAND_ACK."""
    text: str = ""
    """Why (empty when accepted)."""

    @property
    def ok(self) -> bool:
        """True when the command was accepted."""
        return self.result == ACCEPTED


@dataclass(frozen=True)
class Setpoint:
    """An external position/velocity target already resolved to local NED (NaN = not given)."""

    position_ned_m: tuple[float, float, float] = NAN3
    """Target position [m] local NED; NaN per axis where the type mask ignores it."""
    velocity_ned_m_s: tuple[float, float, float] = NAN3
    """Target (feed-forward) velocity [m/s] NED; NaN per axis where ignored."""
    yaw_rad: float = math.nan
    """Target heading [rad] (NaN: keep)."""
    yaw_rate_rad_s: float = math.nan
    """Target yaw rate [rad/s] (NaN: none); used only when ``yaw_rad`` is NaN."""
    accel_ned_m_s2: tuple[float, float, float] = NAN3
    """Acceleration feed-forward [m/s^2] NED (NaN per axis: none).  The PX4 personality adds it to its
    velocity loop's output (PX4's ``PositionControl``: ``_acc_sp`` plus the PID's); ArduPilot's guided mode
    reads it as the rate of its velocity target, which the emulator does not fly."""

    @property
    def has_velocity(self) -> bool:
        """True if any velocity axis is given."""
        return any(math.isfinite(v) for v in self.velocity_ned_m_s)


@dataclass(frozen=True)
class StatusEvent:
    """Something a real autopilot would announce with STATUSTEXT."""

    t_s: float
    """Simulated time [s]."""
    severity: int
    """MAV_SEVERITY_*."""
    text: str
    """Message (<= 50 characters is what STATUSTEXT carries in one chunk)."""


@dataclass(frozen=True)
class VehicleConfig:
    """Emulator-side settings that are not autopilot parameters."""

    start_ned_m: tuple[float, float, float] = (0.0, 0.0, 0.0)
    """Initial position [m] local NED; D < 0 starts airborne, armed, in the hold mode."""
    start_yaw_rad: float = 0.0
    """Initial heading [rad]."""
    physics_dt_s: float = 0.02
    """Fixed physics step [s]."""
    position_gain_1_s: float = 1.0
    """Proportional gain of position hold / position setpoints [1/s] (PX4 MPC_XY_P ~ 0.95)."""
    yaw_rate_max_rad_s: float = math.radians(90.0)
    """Yaw slew limit [rad/s]."""
    offboard_stream_window_s: float = 0.5
    """PX4: OFFBOARD may be entered only if the last setpoint is at most this old (>= 2 Hz)."""
    takeoff_tolerance_m: float = 0.15
    """Takeoff counts as complete within this distance of the target altitude [m]."""
    rtl_arrival_radius_m: float = 0.5
    """RTL starts descending within this horizontal distance of home [m]."""
    plant_params: PlantParams = field(default_factory=PlantParams)
    """Parameters of the velocity plant (paper nominal quadrotor)."""
    px4_loop: Px4LoopParams | None = None
    """Fly stock PX4's velocity loop on SIH's quadrotor (:mod:`sim.plant.px4_loop`) instead of the velocity
    plant ``plant_params`` (the emulator's ``--plant px4-sih-loop``); None: the velocity plant."""
    estimate_error: EstimateErrorParams | None = None
    """The error of the autopilot's state estimate (:mod:`sim.autopilot.estimate_error`): its velocity loop holds
    the estimate at the command and it reports the estimate, its GNSS receiver (GPS_RAW_INT) the truth; None:
    the estimate is the truth."""


@dataclass(frozen=True)
class VehicleState:
    """Immutable snapshot of the vehicle (what telemetry reports)."""

    t_s: float
    """Simulated time [s]."""
    armed: bool
    """Motors armed."""
    mode: FlightMode
    """Current flight mode."""
    custom_mode: int
    """``custom_mode`` word of the mode in the personality's encoding."""
    position_ned_m: tuple[float, float, float]
    """Position [m] local NED."""
    velocity_ned_m_s: tuple[float, float, float]
    """Velocity [m/s] NED."""
    roll_rad: float
    """Roll [rad] (from the realised thrust direction)."""
    pitch_rad: float
    """Pitch [rad]."""
    yaw_rad: float
    """Heading [rad]."""
    yaw_rate_rad_s: float
    """Yaw rate [rad/s]."""
    landed_state: int
    """MAV_LANDED_STATE_*."""
    home_ned_m: tuple[float, float, float]
    """Home position [m] local NED (set at start and on arming)."""
    position_valid: bool
    """Whether the vehicle has a position estimate."""
    last_setpoint_t_s: float
    """Time of the last external setpoint [s] (-inf if none)."""
    velocity_command_ned_m_s: tuple[float, float, float]
    """Velocity command given to the plant in the last physics step [m/s]."""
    estimate_position_ned_m: tuple[float, float, float] | None = None
    """The autopilot's position estimate [m] local NED; None: the truth (``VehicleConfig.estimate_error``)."""
    estimate_velocity_ned_m_s: tuple[float, float, float] | None = None
    """The autopilot's velocity estimate [m/s] NED; None: the truth."""

    @property
    def reported_position_ned_m(self) -> tuple[float, float, float]:
        """The position the autopilot reports: its estimate."""
        return self.position_ned_m if self.estimate_position_ned_m is None else self.estimate_position_ned_m

    @property
    def reported_velocity_ned_m_s(self) -> tuple[float, float, float]:
        """The velocity the autopilot reports: its estimate."""
        return self.velocity_ned_m_s if self.estimate_velocity_ned_m_s is None else self.estimate_velocity_ned_m_s

    @property
    def in_air(self) -> bool:
        """True unless on the ground."""
        return self.landed_state not in (mavlink.MAV_LANDED_STATE_ON_GROUND, mavlink.MAV_LANDED_STATE_UNDEFINED)
