"""Failsafe decisions (pure): position health, link health, geofence.

Each function maps measured ages/positions to a decision; the mission state machine applies
them with this priority: link lost > position lost > position stale > geofence.

- Stale position (no fix for > ``stale_timeout_s``): zero-velocity hold setpoints.
- Lost position (stale for a further ``hold_grace_s``): request the autopilot's hold/loiter mode
  (zero velocity while the request waits, ``Handover``).
- Link lost (no autopilot HEARTBEAT for > ``link_timeout_s``): our setpoints no longer arrive;
  the autopilot's own offboard-loss failsafe (PX4 COM_OF_LOSS_T/COM_OBL_RC_ACT, ArduPilot
  GUID_TIMEOUT/FS_GCS_ENABLE) takes over.  The agent reports it and holds (latched).
- Geofence: outside the map's CVs while flowing.  Downstream of the outlet plane this is the
  normal exit; anywhere else the configured policy applies (``hold`` or ``return``).
"""

from __future__ import annotations

from enum import Enum, StrEnum

from fisc_agent.mavlink.adapters import ModeClass


class PositionHealth(str, Enum):
    """Freshness of the position estimate, as the failsafes see it."""
    OK = "ok"
    STALE = "stale"
    """Hold with zero-velocity setpoints."""
    LOST = "lost"
    """Stale beyond the grace time: request the autopilot's hold mode."""


class GeofencePolicy(StrEnum):
    """What a flowing agent does when it leaves the map's CVs other than through the outlet."""

    HOLD = "hold"
    """Latched hold (zero velocity, then the autopilot's hold mode) until a ``resume``."""
    RETURN = "return"
    """Fly back: rejoin the flow of the nearest CV (``fisc_agent.map.lookup.return_command``)."""


class GeofenceVerdict(str, Enum):
    """Where a flowing agent is relative to the map, and what the geofence policy does about it."""
    INSIDE = "inside"
    EXIT = "exit"
    """Downstream of the outlet plane: the pass through the tunnel is complete."""
    HOLD = "hold"
    RETURN = "return"


def position_health(age_s: float, stale_timeout_s: float, hold_grace_s: float) -> PositionHealth:
    """Classify the age of the newest position fix (``inf`` when there never was one)."""
    if not (age_s <= stale_timeout_s):  # also catches NaN
        if not (age_s <= stale_timeout_s + hold_grace_s):  # inf (never) and NaN count as lost
            return PositionHealth.LOST
        return PositionHealth.STALE
    return PositionHealth.OK


def link_ok(heartbeat_age_s: float, link_timeout_s: float) -> bool:
    """True while the autopilot's HEARTBEATs keep arriving."""
    return heartbeat_age_s <= link_timeout_s


def geofence(cv_id: int, x_m: float, x_outlet_m: float, policy: GeofencePolicy | str) -> GeofenceVerdict:
    """What to do at a map-frame point whose CV is ``cv_id`` (-1 = outside the map's CVs)."""
    if cv_id >= 0:
        return GeofenceVerdict.INSIDE
    if x_m >= x_outlet_m:
        return GeofenceVerdict.EXIT
    try:
        p = GeofencePolicy(policy)
    except ValueError:
        raise ValueError(f"unknown geofence policy {policy!r}; choose hold or return") from None
    return GeofenceVerdict.RETURN if p is GeofencePolicy.RETURN else GeofenceVerdict.HOLD


HANDOVER_S = 1.5
"""How long zero velocity is streamed while the agent hands its vehicle to the autopilot's own mode [s]: a request
waits up to a second for a fresh HEARTBEAT (``adapters.FRESH_HEARTBEAT_S``, HEARTBEAT at 1 Hz), then the autopilot
answers.  After it the stream stops, as it did at once before that wait: an autopilot that refuses the mode (PX4's
Hold without a position estimate) is left to its own offboard-loss failsafe."""


class Handover:
    """The setpoint while the agent hands its vehicle to the autopilot's own hold or land mode: zero velocity while
    the vehicle still flies the agent's mode (offboard/guided), for ``HANDOVER_S`` from the first ``velocity``
    after a ``reset``, so that the autopilot's offboard-loss failsafe (PX4's COM_OF_LOSS_T: 1 s) does not take the
    vehicle while the request waits for a fresh HEARTBEAT; None, nothing sent, otherwise (the mission passes the
    mode ``UNKNOWN`` while the link is lost: nothing is streamed blind)."""

    def __init__(self) -> None:
        self._since_s: float | None = None

    def reset(self) -> None:
        """A new state: the next ``velocity`` starts a new handover."""
        self._since_s = None

    def velocity(self, t_s: float, mode: ModeClass) -> tuple[float, float, float] | None:
        """Zero velocity in offboard within ``HANDOVER_S`` of this handover's first call; None otherwise."""
        if self._since_s is None:
            self._since_s = t_s
        return (0.0, 0.0, 0.0) if mode == ModeClass.OFFBOARD and t_s - self._since_s < HANDOVER_S else None
