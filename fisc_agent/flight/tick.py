"""One tick of the agent as the runner keeps it (``TickRecord``), and the telemetry flags of a
mission state (pure): ``failsafe`` (a failsafe holds or returns the vehicle) and ``outside_map``
(outside the CVs where the mission belongs inside)."""

from __future__ import annotations

from dataclasses import dataclass

from fisc_agent.flight.control import Vec
from fisc_agent.flight.health import VehicleHealth
from fisc_agent.flight.mission_types import Cause, HoldCause, MissionOutput, Reason, State
from fisc_agent.map.codec import CommandMap
from fisc_agent.mavlink.adapters import ModeClass


@dataclass(frozen=True, slots=True)
class TickRecord:
    """What one tick saw and did (replaced whole every tick, so reading it is atomic); ``snapshot()``
    turns it into the telemetry snapshot on demand."""

    now_s: float
    """Monotonic time of the tick [s]."""
    wall_time_s: float
    """UNIX time of the tick [s]."""
    out: MissionOutput
    """The mission's output this tick."""
    position_map_m: Vec | None
    """Gated position, map frame [m]."""
    velocity_map_m_s: Vec | None
    """Measured velocity, map frame [m/s]."""
    setpoint_map_m_s: Vec | None
    """Clamped setpoint sent, map frame [m/s] (None: none sent)."""
    cmap: CommandMap | None
    """Map in use."""
    link_ok: bool
    """Autopilot HEARTBEATs are arriving."""
    heartbeat_age_s: float
    """Age of the newest HEARTBEAT [s]."""
    position_age_s: float
    """Age of the newest accepted fix [s]."""
    autopilot: str | None
    """Adapter in use (``px4`` / ``ardupilot``)."""
    armed: bool
    """Armed flag from the HEARTBEAT."""
    mode: ModeClass
    """Autopilot mode class."""
    laps: int
    """Completed passes."""
    parcel_map_m: Vec | None
    """Streamline-tracking parcel in FLOW, map frame [m]."""
    health: VehicleHealth
    """The autopilot's health report."""




FAILSAFE_HOLD_CAUSES = frozenset({HoldCause.LINK_LOST, HoldCause.POSITION_STALE, HoldCause.GEOFENCE,
                                  HoldCause.PILOT_OVERRIDE, HoldCause.POSITION_JUMP, HoldCause.AGENT_FAULT})
"""Hold causes that are failsafes (a fleet or exit hold is not)."""


def failsafe_active(state: State, reason: Reason) -> bool:
    """True while a failsafe holds or returns the vehicle: a HOLD for a lost link, a stale or
    lost position, the geofence or a mode taken from the agent, or the geofence's RETURN."""
    if state == State.HOLD:
        return reason.cause in FAILSAFE_HOLD_CAUSES
    return state == State.RETURN and reason.cause == Cause.GEOFENCE_RETURN


def outside_map(state: State, reason: Reason, cv_id: int, position_known: bool) -> bool:
    """True when the vehicle is outside the map's CVs (``cv_id`` -1 at a known position) in a
    state that belongs inside: FLOW, the geofence's RETURN, or a geofence HOLD (joining from
    the staging area and leaving past the outlet are outside by design)."""
    if not position_known or cv_id >= 0:
        return False
    return state in (State.FLOW, State.RETURN) or (state == State.HOLD and reason.cause == HoldCause.GEOFENCE)


