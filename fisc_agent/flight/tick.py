"""One tick of the agent as the runner keeps it (``TickRecord``), the telemetry snapshot made of it
(``AgentSnapshot``), and the telemetry flags of a mission state (pure): ``failsafe`` (a failsafe
holds or returns the vehicle) and ``outside_map`` (outside the CVs where the mission belongs inside)."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import NamedTuple

from fisc_agent.flight.control import Vec
from fisc_agent.flight.health import VehicleHealth
from fisc_agent.flight.readiness import HealthProblem
from fisc_agent.flight.safety_net import NetAction
from fisc_agent.flight.mission_types import HoldCause, MissionOutput, Reason, State
from fisc_agent.map.codec import CommandMap
from fisc_agent.mavlink.adapters import ModeClass


class TickRecord(NamedTuple):
    """What one tick saw and did (replaced whole every tick, so reading it is atomic); ``snapshot()``
    turns it into the telemetry snapshot on demand.  Immutable (a NamedTuple: built every tick, cheaper
    than a frozen dataclass)."""

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
    net: NetAction | None = None
    """What the separation safety net did this tick (None: it did not run)."""
    gnss_velocity_map_m_s: tuple[float, float] | None = None
    """The GNSS receiver's own horizontal velocity (a fresh GPS_RAW_INT), map x and y [m/s] (None: none fresh)."""


@dataclass(frozen=True)
class AgentSnapshot:
    """Telemetry of one agent at one tick."""

    time_s: float
    """Monotonic time of the tick [s]."""
    wall_time_s: float
    """UNIX time of the tick [s]."""
    agent_id: int
    """The agent's id."""
    state: str
    """Mission state name."""
    reason: str
    """Why the mission is in that state."""
    position_map_m: Vec | None
    """Position in the map frame [m] (None before the first fix)."""
    velocity_map_m_s: Vec | None
    """Measured velocity in the map frame [m/s]."""
    setpoint_map_m_s: Vec | None
    """Clamped velocity setpoint sent this tick, map frame [m/s] (None: none sent)."""
    cv_id: int
    """CV the vehicle is in, -1 outside the map."""
    map_sha256: str | None
    """sha256 of the map in use."""
    map_version: int | None
    """map_version of the map in use."""
    link_ok: bool
    """Autopilot HEARTBEATs are arriving."""
    heartbeat_age_s: float
    """Age of the newest autopilot HEARTBEAT [s] (inf: never)."""
    position_age_s: float
    """Age of the newest position fix [s] (inf: never)."""
    autopilot: str | None
    """``px4`` / ``ardupilot`` once known."""
    armed: bool
    """Armed flag from the HEARTBEAT."""
    mode: str
    """Autopilot mode class (``offboard``, ``hold``, ``land``, ``other``, ``unknown``)."""
    laps: int
    """Completed passes through the tunnel."""
    failsafe: bool
    """A failsafe holds the vehicle (``failsafe_active``: link lost, position stale or lost,
    geofence, mode taken by the pilot or an autopilot failsafe); telemetry flag ``failsafe``."""
    outside_map: bool
    """Outside the map's CVs where the mission expects to be inside (``outside_map``); telemetry
    flag ``outside_map``."""
    parcel_map_m: Vec | None = None
    """The streamline-tracking parcel, map frame [m] (None outside FLOW or flying open loop)."""
    authority: str = "waiting"
    """Who is in charge (``fisc_agent.flight.mission_types.Authority`` value)."""
    battery_pct: float | None = None
    """Remaining battery [%] as the autopilot reports it (None: not reported)."""
    landed: str = "unknown"
    """Landed state (``fisc_agent.flight.health.LandedState`` value)."""
    health_problems: tuple[HealthProblem, ...] = ()
    """What is wrong with the vehicle by its own report (kind and phrase); () healthy."""
    nearest_neighbour_m: float = math.inf
    """Distance to the nearest neighbour heard (safety net's view) [m] (inf: none heard or net off)."""
    net_ids: tuple[int, ...] = ()
    """Neighbours the safety net acted on this tick (closing too fast, or inside d_min); () none."""
    gnss_velocity_map_m_s: tuple[float, float] | None = None
    """The GNSS receiver's own horizontal velocity, map x and y [m/s] (None: none fresh): a measurement beside
    the autopilot's estimate (``velocity_map_m_s``), whose error PX4 SIH's EKF makes two to three times larger."""


NET_STATES = frozenset({State.JOIN, State.FLOW, State.RETURN, State.EXIT})
"""States in which the agent flies its own velocities in the air, where the safety net acts."""

FAILSAFE_HOLD_CAUSES = frozenset({HoldCause.LINK_LOST, HoldCause.POSITION_STALE, HoldCause.GEOFENCE,
                                  HoldCause.PILOT_OVERRIDE, HoldCause.POSITION_JUMP, HoldCause.AGENT_FAULT})
"""Hold causes that are failsafes (a fleet or exit hold is not)."""


def failsafe_active(state: State, reason: Reason) -> bool:
    """True while a failsafe holds or returns the vehicle: a HOLD for a lost link, a stale or
    lost position, the geofence or a mode taken from the agent, or a RETURN (flying back into the
    map from outside it, whatever began it: the geofence, or a hold that ended outside the map and
    resumed with "position fix back" or a fleet resume)."""
    if state == State.HOLD:
        return reason.cause in FAILSAFE_HOLD_CAUSES
    return state == State.RETURN


def outside_map(state: State, reason: Reason, cv_id: int, position_known: bool) -> bool:
    """True when the vehicle is outside the map's CVs (``cv_id`` -1 at a known position) in a
    state that belongs inside: FLOW, the geofence's RETURN, or a geofence HOLD (joining from
    the staging area and leaving past the outlet are outside by design)."""
    if not position_known or cv_id >= 0:
        return False
    return state in (State.FLOW, State.RETURN) or (state == State.HOLD and reason.cause == HoldCause.GEOFENCE)


