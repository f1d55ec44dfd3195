"""The vehicle's health as the autopilot reports it (pure types; the MAVLink link fills them).

``VehicleHealth`` is what the mission and telemetry read of HEARTBEAT.system_status, SYS_STATUS /
BATTERY_STATUS, EXTENDED_SYS_STATE, ESTIMATOR_STATUS / EKF_STATUS_REPORT, ODOMETRY, SYSTEM_TIME and
HOME_POSITION.  A field the autopilot does not stream stays at its "unknown" value (None or
``UNKNOWN``), and nothing is decided on an unknown: a check that needs it passes with a logged
"not reported".
"""

from __future__ import annotations

from dataclasses import dataclass
from enum import StrEnum

Vec = tuple[float, float, float]


class LandedState(StrEnum):
    """EXTENDED_SYS_STATE.landed_state (MAV_LANDED_STATE)."""

    UNKNOWN = "unknown"
    ON_GROUND = "on-ground"
    IN_AIR = "in-air"
    TAKEOFF = "takeoff"
    LANDING = "landing"


class SystemState(StrEnum):
    """HEARTBEAT.system_status (MAV_STATE)."""

    UNKNOWN = "unknown"
    BOOT = "boot"
    CALIBRATING = "calibrating"
    STANDBY = "standby"
    ACTIVE = "active"
    CRITICAL = "critical"
    EMERGENCY = "emergency"
    POWEROFF = "poweroff"
    FLIGHT_TERMINATION = "termination"


@dataclass(frozen=True)
class VehicleHealth:
    """The autopilot's own view of its health, newest values (immutable: replaced whole)."""

    system_state: SystemState = SystemState.UNKNOWN
    """HEARTBEAT.system_status."""
    battery_pct: float | None = None
    """Remaining battery [%] (BATTERY_STATUS.battery_remaining, else SYS_STATUS); None: not reported."""
    landed: LandedState = LandedState.UNKNOWN
    """EXTENDED_SYS_STATE.landed_state."""
    estimator_ok: bool | None = None
    """The estimator's horizontal/vertical position solution is good (PX4 ESTIMATOR_STATUS flags,
    ArduPilot EKF_STATUS_REPORT flags); None: not reported."""
    estimator_detail: str = ""
    """What is wrong with the estimator, in words ("" when fine or unknown)."""
    position_resets: int = 0
    """Estimator position resets seen so far (PX4 ODOMETRY.reset_counter steps, ArduPilot
    EKF_STATUS_REPORT reset flags); a step of this counter means the local frame jumped."""
    gps_unix_s: float | None = None
    """The autopilot's UNIX time from its GNSS (SYSTEM_TIME.time_unix_usec) at ``gps_rx_s``; None: not
    reported (or 0: the autopilot has no time yet)."""
    gps_rx_s: float | None = None
    """Monotonic time at which ``gps_unix_s`` was received [s]."""
    home_ned_m: Vec | None = None
    """HOME_POSITION in the vehicle's local NED frame [m]; None: not reported."""
    autopilot_reboots: int = 0
    """Autopilot reboots seen on the link (its boot time went backwards); streams are re-requested after each."""

    def unix_time_at(self, now_s: float) -> float | None:
        """The autopilot's GNSS UNIX time extrapolated to monotonic ``now_s``; None when it gives none."""
        if self.gps_unix_s is None or self.gps_rx_s is None:
            return None
        return self.gps_unix_s + (now_s - self.gps_rx_s)
