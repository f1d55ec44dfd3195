"""The interfaces the runner depends on: ``PositionSample``, ``PositionSource``, ``SetpointSink``, ``VehicleLink``.

``link.MavlinkLink`` (pymavlink) and ``mavsdk_backend.MavsdkLink`` implement ``VehicleLink``; the
tests' in-memory vehicles do too.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol, runtime_checkable

from fisc_agent.flight.health import VehicleHealth
from fisc_agent.flight.integrity import IntegrityVerdict
from fisc_agent.mavlink.adapters import Adapter, CommandResult, ModeClass, VehicleCommands


@dataclass(frozen=True)
class PositionSample:
    """One position fix in local NED (or anchor NED in geodetic mode)."""

    t_s: float
    """Local monotonic receive time [s]."""
    pos_ned_m: tuple[float, float, float]
    """Position [m]."""
    vel_ned_m_s: tuple[float, float, float]
    """Velocity [m/s]."""
    autopilot_t_s: float | None = None
    """The autopilot's own time of the fix (the message's ``time_boot_ms``) [s]; None when the source
    gives none (MAVSDK's callbacks)."""


@dataclass(frozen=True)
class GnssVelocity:
    """The GNSS receiver's own horizontal velocity (MAVLink GPS_RAW_INT ``vel`` and ``cog``), NED."""

    t_s: float
    """Local monotonic receive time [s]."""
    vel_ne_m_s: tuple[float, float]
    """(north, east) velocity over ground [m/s]."""


@dataclass(frozen=True)
class ThrustAccel:
    """The horizontal acceleration the vehicle's thrust asks for, from its reported attitude
    (``fisc_agent.flight.drag.thrust_accel_ne``)."""

    t_s: float
    """Local monotonic receive time [s]."""
    acc_ne_m_s2: tuple[float, float]
    """(north, east) [m/s^2]."""


@runtime_checkable
class PositionSource(Protocol):
    """Where the runner reads the vehicle's position from."""
    def latest_position(self) -> PositionSample | None:
        """The newest fix, or None if none arrived yet."""

    def latest_gnss_velocity(self) -> GnssVelocity | None:
        """The GNSS receiver's newest velocity with a 3D fix, or None (none yet, or a source without it)."""

    def latest_thrust_accel(self) -> ThrustAccel | None:
        """The thrust's horizontal acceleration from the newest attitude, or None (none yet, or a source
        without it)."""


@runtime_checkable
class SetpointSink(Protocol):
    """Where the runner streams its velocity setpoints to."""
    def send_velocity_ned(self, vn: float, ve: float, vd: float) -> None:
        """Send one velocity-only setpoint in MAV_FRAME_LOCAL_NED [m/s]."""

    def send_velocity_accel_ned(self, vn: float, ve: float, vd: float, an: float, ae: float, ad: float) -> None:
        """Send one velocity setpoint [m/s] with its acceleration feed-forward [m/s^2], MAV_FRAME_LOCAL_NED."""


class VehicleLink(PositionSource, SetpointSink, VehicleCommands, Protocol):
    """Everything the runner needs from a link to one autopilot."""

    autopilot: str | None
    """``px4`` / ``ardupilot`` as the autopilot announces itself; None while unknown."""
    armed: bool
    """Armed flag of the vehicle."""
    last_heartbeat_t: float | None
    """Local monotonic time of the newest sign of life [s]; None: never."""

    @property
    def mode_t_s(self) -> float | None:
        """Local monotonic time [s] of the newest report of the mode, the autopilot's HEARTBEAT (1 Hz on PX4 and
        ArduPilot); None: never.  The ``Commander`` judges whether a request is made on a fresh view by it."""

    @property
    def mode(self) -> ModeClass:
        """The vehicle's mode class (``UNKNOWN`` before the first HEARTBEAT or ``use_adapter``)."""

    @property
    def health(self) -> VehicleHealth:
        """The autopilot's own view of its health (unknown fields where it reports none)."""

    @property
    def integrity(self) -> IntegrityVerdict:
        """Whether the position may be flown on (``fisc_agent.flight.integrity``); ok while nothing is known."""

    def use_adapter(self, adapter: Adapter) -> None:
        """The autopilot flavour to encode intents and decode modes with (chosen by the runner)."""

    def poll(self) -> int:
        """Handle whatever arrived (non-blocking); returns how many messages."""

    def pop_results(self) -> list[CommandResult]:
        """The autopilot's answers to commands since the last call, oldest first."""

    def send_heartbeat(self) -> None:
        """Our own HEARTBEAT (a no-op where the library sends its own)."""

    def discard_backlog(self) -> int:
        """Drop, unread, whatever queued up while the agent was not reading (after the agent itself
        stalled: that backlog is an old view of the vehicle, which a fresh stamp would pass off as
        current); returns how many datagrams (0 where the library keeps no backlog)."""

    def close(self) -> None:
        """Release the connection."""
