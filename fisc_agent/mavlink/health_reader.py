"""The autopilot's health messages -> ``VehicleHealth`` (pure: decoded messages and times come in).

``HealthReader.on_message`` reads HEARTBEAT.system_status, SYS_STATUS and BATTERY_STATUS (battery %),
EXTENDED_SYS_STATE (landed state), ESTIMATOR_STATUS (PX4) / EKF_STATUS_REPORT (ArduPilot), ODOMETRY
(PX4 reset_counter; its attitude is the link's, for the drag), SYSTEM_TIME (GNSS UNIX time, autopilot
reboots) and HOME_POSITION, and answers what changed that the link must act on (a reboot: re-request the
streams; a position reset or an estimator verdict: tell the integrity monitor).

``stream_requests`` is what the link asks the autopilot to stream (MAV_CMD_SET_MESSAGE_INTERVAL).
Measured on the SITL builds in ``../shared/sitl`` (API link, udp 14540):

- PX4 (onboard link) streams all of these by default: SYS_STATUS 5 Hz, BATTERY_STATUS 0.5 Hz,
  EXTENDED_SYS_STATE 5 Hz, ESTIMATOR_STATUS 1 Hz, ODOMETRY 30 Hz, SYSTEM_TIME 1 Hz, HOME_POSITION
  0.5 Hz, LOCAL_POSITION_NED 30 Hz, GLOBAL_POSITION_INT 50 Hz; EKF_STATUS_REPORT is UNSUPPORTED.
  The requests are still sent: a PX4 link in another MAVLink mode (a telemetry radio) streams less.
- ArduCopter (serial0, SR0_* = 0) streams only HEARTBEAT: every message must be requested.  It
  accepts all of these but ESTIMATOR_STATUS and ODOMETRY (DENIED).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from typing import Callable

from pymavlink.dialects.v20.ardupilotmega import (MAVLINK_MSG_ID_BATTERY_STATUS, MAVLINK_MSG_ID_EKF_STATUS_REPORT,
                                                  MAVLINK_MSG_ID_ESTIMATOR_STATUS,
                                                  MAVLINK_MSG_ID_EXTENDED_SYS_STATE,
                                                  MAVLINK_MSG_ID_GLOBAL_POSITION_INT, MAVLINK_MSG_ID_GPS_RAW_INT,
                                                  MAVLINK_MSG_ID_HOME_POSITION,
                                                  MAVLINK_MSG_ID_LOCAL_POSITION_NED, MAVLINK_MSG_ID_ODOMETRY,
                                                  MAVLINK_MSG_ID_SYS_STATUS, MAVLINK_MSG_ID_SYSTEM_TIME)

from fisc_agent.flight.health import (VehicleHealth, battery_pct_of, estimator_health, landed_state_of,
                                      system_state_of)

Vec = tuple[float, float, float]

ODOMETRY_RATE_HZ = 10.0
"""ODOMETRY is asked for its reset counter and its attitude (the drag's identification, ``fisc_agent.flight.drag``;
230 bytes a message: not at the position rate on a radio)."""
RESET_COUNTER_MODULO = 256
"""ODOMETRY.reset_counter is a uint8: it wraps from 255 to 0."""


GNSS_RATE_HZ = 10.0
"""Rate asked for GPS_RAW_INT [Hz] (the receiver's velocity corrects the estimator's: ``link.MavlinkLink.latest_gnss_velocity``;
an autopilot sends it at most at its receiver's rate, PX4 SIH's 8 Hz)."""


def stream_requests(autopilot: str | None, geodetic: bool, position_rate_hz: float) -> tuple[tuple[int, float], ...]:
    """(message id, rate [Hz]) pairs to request from ``autopilot`` (``px4``, ``ardupilot`` or None:
    both estimator messages); the position message first (GLOBAL_POSITION_INT when ``geodetic``)."""
    position = MAVLINK_MSG_ID_GLOBAL_POSITION_INT if geodetic else MAVLINK_MSG_ID_LOCAL_POSITION_NED
    out = [(position, position_rate_hz), (MAVLINK_MSG_ID_SYS_STATUS, 2.0), (MAVLINK_MSG_ID_BATTERY_STATUS, 1.0),
           (MAVLINK_MSG_ID_EXTENDED_SYS_STATE, 2.0), (MAVLINK_MSG_ID_SYSTEM_TIME, 1.0),
           (MAVLINK_MSG_ID_HOME_POSITION, 0.5), (MAVLINK_MSG_ID_GPS_RAW_INT, GNSS_RATE_HZ)]
    if autopilot != "ardupilot":
        out += [(MAVLINK_MSG_ID_ESTIMATOR_STATUS, 2.0), (MAVLINK_MSG_ID_ODOMETRY, ODOMETRY_RATE_HZ)]
    if autopilot != "px4":
        out.append((MAVLINK_MSG_ID_EKF_STATUS_REPORT, 2.0))
    return tuple(out)


@dataclass(frozen=True)
class HealthUpdate:
    """What one message changed that the link acts on."""

    rebooted: bool = False
    """The autopilot's boot time went backwards: it rebooted (re-request the streams)."""
    reset_steps: int = 0
    """Estimator position resets reported by this message (ODOMETRY.reset_counter steps)."""
    estimator: tuple[bool, str] | None = None
    """(ok, detail) when this message carried an estimator status."""


NOTHING = HealthUpdate()


class HealthReader:
    """Folds the autopilot's health messages into a ``VehicleHealth``."""

    def __init__(self, home_to_ned: Callable[[float, float, float], Vec] | None = None) -> None:
        """``home_to_ned(lat_deg, lon_deg, alt_m)``: HOME_POSITION's geodetic position in the frame the
        link reports (a geodetic anchor); None: HOME_POSITION's own local x, y, z."""
        self.health = VehicleHealth()
        """The newest health."""
        self._home_to_ned = home_to_ned
        self._reset_counter: int | None = None
        self._boot_ms: int | None = None
        self._battery_from_status = False

    def on_message(self, msg, now_s: float) -> HealthUpdate:
        """Read one message from the autopilot (any type: the others change nothing)."""
        handler = _HANDLERS.get(msg.get_type())
        return NOTHING if handler is None else handler(self, msg, now_s)

    def _set(self, **changes) -> None:
        self.health = replace(self.health, **changes)

    def _heartbeat(self, msg, now_s: float) -> HealthUpdate:
        self._set(system_state=system_state_of(msg.system_status))
        return NOTHING

    def _sys_status(self, msg, now_s: float) -> HealthUpdate:
        if not self._battery_from_status:  # BATTERY_STATUS, when it comes, is the better source
            self._set(battery_pct=battery_pct_of(msg.battery_remaining))
        return NOTHING

    def _battery_status(self, msg, now_s: float) -> HealthUpdate:
        if int(msg.id) == 0:
            pct = battery_pct_of(msg.battery_remaining)
            self._battery_from_status = pct is not None
            if pct is not None:
                self._set(battery_pct=pct)
        return NOTHING

    def _extended_sys_state(self, msg, now_s: float) -> HealthUpdate:
        self._set(landed=landed_state_of(msg.landed_state))
        return NOTHING

    def _estimator(self, msg, now_s: float) -> HealthUpdate:
        ok, detail = estimator_health(msg.flags, ardupilot=msg.get_type() == "EKF_STATUS_REPORT")
        self._set(estimator_ok=ok, estimator_detail=detail)
        return HealthUpdate(estimator=(ok, detail))

    def _odometry(self, msg, now_s: float) -> HealthUpdate:
        counter, last = int(msg.reset_counter), self._reset_counter
        self._reset_counter = counter
        if last is None or counter == last:  # the first value is where the autopilot's count stands
            return NOTHING
        steps = (counter - last) % RESET_COUNTER_MODULO
        self._set(position_resets=self.health.position_resets + steps)
        return HealthUpdate(reset_steps=steps)

    def _system_time(self, msg, now_s: float) -> HealthUpdate:
        boot_ms, last = int(msg.time_boot_ms), self._boot_ms
        self._boot_ms = boot_ms
        unix_us = int(msg.time_unix_usec)
        self._set(gps_unix_s=unix_us * 1e-6 if unix_us > 0 else None, gps_rx_s=now_s if unix_us > 0 else None)
        if last is not None and boot_ms < last:
            self._reset_counter = None  # a new boot counts its resets afresh
            self._set(autopilot_reboots=self.health.autopilot_reboots + 1)
            return HealthUpdate(rebooted=True)
        return NOTHING

    def _home_position(self, msg, now_s: float) -> HealthUpdate:
        if self._home_to_ned is not None:
            home = self._home_to_ned(msg.latitude * 1e-7, msg.longitude * 1e-7, msg.altitude * 1e-3)
        else:
            home = (float(msg.x), float(msg.y), float(msg.z))
        if all(math.isfinite(v) for v in home):
            self._set(home_ned_m=tuple(float(v) for v in home))
        return NOTHING


_HANDLERS = {"HEARTBEAT": HealthReader._heartbeat, "SYS_STATUS": HealthReader._sys_status,
             "BATTERY_STATUS": HealthReader._battery_status, "EXTENDED_SYS_STATE": HealthReader._extended_sys_state,
             "ESTIMATOR_STATUS": HealthReader._estimator, "EKF_STATUS_REPORT": HealthReader._estimator,
             "ODOMETRY": HealthReader._odometry, "SYSTEM_TIME": HealthReader._system_time,
             "HOME_POSITION": HealthReader._home_position}
