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


BAD_SYSTEM_STATES = frozenset({SystemState.CRITICAL, SystemState.EMERGENCY, SystemState.POWEROFF,
                               SystemState.FLIGHT_TERMINATION})
"""HEARTBEAT.system_status values that are a health problem in themselves."""

_SYSTEM_STATE_OF = {1: SystemState.BOOT, 2: SystemState.CALIBRATING, 3: SystemState.STANDBY, 4: SystemState.ACTIVE,
                    5: SystemState.CRITICAL, 6: SystemState.EMERGENCY, 7: SystemState.POWEROFF,
                    8: SystemState.FLIGHT_TERMINATION}
_LANDED_STATE_OF = {1: LandedState.ON_GROUND, 2: LandedState.IN_AIR, 3: LandedState.TAKEOFF, 4: LandedState.LANDING}


def system_state_of(mav_state: int) -> SystemState:
    """HEARTBEAT.system_status (MAV_STATE) as a ``SystemState`` (UNINIT and unknown values: ``UNKNOWN``)."""
    return _SYSTEM_STATE_OF.get(int(mav_state), SystemState.UNKNOWN)


def landed_state_of(mav_landed_state: int) -> LandedState:
    """EXTENDED_SYS_STATE.landed_state (MAV_LANDED_STATE) as a ``LandedState`` (UNDEFINED: ``UNKNOWN``)."""
    return _LANDED_STATE_OF.get(int(mav_landed_state), LandedState.UNKNOWN)


def battery_pct_of(battery_remaining: int) -> float | None:
    """SYS_STATUS / BATTERY_STATUS.battery_remaining [%] (-1 or outside 0..100: not reported -> None)."""
    value = int(battery_remaining)
    return float(value) if 0 <= value <= 100 else None


# ESTIMATOR_STATUS_FLAGS (PX4) and EKF_STATUS_FLAGS (ArduPilot) share bits 0..9.
FLAG_ATTITUDE = 1
FLAG_VELOCITY_HORIZ = 2
FLAG_VELOCITY_VERT = 4
FLAG_POS_HORIZ_REL = 8
FLAG_POS_VERT_ABS = 32
FLAG_CONST_POS_MODE = 128
PX4_GPS_GLITCH = 1024
"""ESTIMATOR_GPS_GLITCH (PX4)."""
PX4_ACCEL_ERROR = 2048
"""ESTIMATOR_ACCEL_ERROR (PX4)."""
AP_UNINITIALIZED = 1024
"""EKF_UNINITIALIZED (ArduPilot; the same bit as PX4's GPS glitch)."""
AP_GPS_GLITCHING = 32768
"""EKF_GPS_GLITCHING (ArduPilot)."""

_REQUIRED = ((FLAG_ATTITUDE, "no attitude"), (FLAG_VELOCITY_HORIZ, "no horizontal velocity"),
             (FLAG_VELOCITY_VERT, "no vertical velocity"), (FLAG_POS_HORIZ_REL, "no horizontal position"),
             (FLAG_POS_VERT_ABS, "no vertical position"))


def estimator_health(flags: int, ardupilot: bool) -> tuple[bool, str]:
    """(ok, what is wrong) from PX4 ESTIMATOR_STATUS.flags (``ardupilot=False``) or ArduPilot
    EKF_STATUS_REPORT.flags (``ardupilot=True``).  Ok needs attitude, horizontal and vertical
    velocity, a relative horizontal and an absolute vertical position, and no constant-position mode,
    GNSS glitch, accelerometer error (PX4) or uninitialised filter (ArduPilot).

    The constant-position flag is a problem on ArduPilot only: PX4 also sets it for a vehicle at rest
    (measured on PX4 SITL, landed and disarmed: flags 1023)."""
    flags = int(flags)
    wrong = [text for bit, text in _REQUIRED if not flags & bit]
    bad = ((FLAG_CONST_POS_MODE, "constant-position mode"), (AP_UNINITIALIZED, "uninitialised"),
           (AP_GPS_GLITCHING, "GNSS glitch")) if ardupilot else (
        (PX4_GPS_GLITCH, "GNSS glitch"), (PX4_ACCEL_ERROR, "accelerometer error"))
    wrong += [text for bit, text in bad if flags & bit]
    return not wrong, ", ".join(wrong)
