"""Who flies the vehicle (pure): the authority model of the mission, its typed causes, the
detector of mode changes the agent did not ask for, and the fleet-command rules.

The rules (docs/deployment.md, "Authority"):

- **A go to arm.** The agent arms only after a go: ``--go`` on the command line, a fleet ``go`` (or a
  ``start-at`` reaching its time) for the swarm or addressed to this agent.  A go is good for one
  flight of one process.
- **Never take over.** A vehicle already armed when the agent first sees it (or armed by someone
  else while the agent waits) is not the agent's: it sends no mode request and no setpoint.  Only a
  ``takeover`` addressed to this agent hands it over.
- **Hands off.** A mode change the agent did not ask for (a pilot, a ground station, an autopilot
  failsafe such as Land or RTL) ends the agent's authority for the flight, in every state.  A
  swarm-wide ``resume`` does not restore it; only a ``resume`` or ``takeover`` addressed to this agent.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from enum import Enum

from fisc_agent.flight.mission_types import Authority, FleetOrder, MissionCommand
from fisc_agent.mavlink.adapters import ModeClass


class AuthorityCause(str, Enum):
    """Why the authority changed; the value is the logged text."""

    START = "started: waiting for a go"
    RESTORED_HANDS_OFF = "restarted hands-off (state file): waiting for a command addressed to this agent"
    ARMED_BY_OTHER = "vehicle armed by someone else: not ours, never taken over"
    ARMING = "go: arming the vehicle"
    TAKEOVER = "takeover addressed to this agent"
    MODE_CHANGED = "mode changed outside the agent"
    GIVEN_BACK = "command addressed to this agent gives the vehicle back"
    DISARMED = "vehicle disarmed by someone else: not ours any more"
    FLIGHT_OVER = "flight over: the go is used up"


MODE_ECHO_S = 3.0
"""A mode the agent asked for within this long counts as its own when the autopilot reports it [s]
(the autopilot's answer and HEARTBEAT arrive up to a few hundred ms late; retries repeat the request)."""
SUPERSEDED_ECHO_S = 1.0
"""A mode the agent asked for and then stopped asking for (it wants another one now) counts as its own
for this long only [s]: the autopilot's late answer to the old request.  With ``MODE_ECHO_S`` for it
too, a PX4 ground station's Hold 1-2 s after the agent's own brief Hold request (a position-jump hold
that ended on the next tick) read as the agent's own, and the agent took OFFBOARD back from the ground
for 10 s (real PX4 SITL, the authority test)."""


@dataclass
class ModeWatch:
    """Tells a mode change the agent asked for from one it did not (pure, time passed in).

    ``want(t, mode)`` every tick with the mode the agent wants (None: none); ``observe(t, mode)``
    with the mode the autopilot reports.  A change of the reported mode to one the agent did not
    want within ``echo_s`` is foreign: someone else (pilot, ground station, an autopilot failsafe)
    changed it.  ``UNKNOWN`` (no HEARTBEAT, no adapter yet) is never a change."""

    echo_s: float = MODE_ECHO_S
    """How long a wanted mode stays the agent's own [s]."""
    last_seen: ModeClass = ModeClass.UNKNOWN
    """The last known mode reported."""
    superseded_echo_s: float = SUPERSEDED_ECHO_S
    """How long a wanted mode stays the agent's own once it wants another one [s]."""
    _wanted_at: dict[ModeClass, float] = field(default_factory=dict)
    _current: ModeClass | None = None

    def want(self, t_s: float, mode: ModeClass | None) -> None:
        """The agent wants ``mode`` at ``t_s`` (None: it wants none)."""
        if mode is not None:
            self._wanted_at[mode] = t_s
            self._current = mode

    def observe(self, t_s: float, mode: ModeClass) -> ModeClass | None:
        """The foreign mode the vehicle changed to at ``t_s``, or None (no change, or one the agent asked for)."""
        if mode == ModeClass.UNKNOWN:
            return None
        previous, self.last_seen = self.last_seen, mode
        if previous in (ModeClass.UNKNOWN, mode):
            return None
        asked = self._wanted_at.get(mode)
        window = self.echo_s if self._current in (None, mode) else min(self.echo_s, self.superseded_echo_s)
        if asked is not None and t_s - asked <= window:
            return None
        return mode

    def forget(self) -> None:
        """Forget what was wanted (authority lost: from now on every change is foreign)."""
        self._wanted_at.clear()
        self._current = None


class FleetAction(Enum):
    """What the mission does with a fleet order (``fleet_action``)."""

    IGNORE = "ignore"
    HOLD = "hold"
    LAND = "land"
    END = "end"
    """On the ground and not flying: the mission ends (a fleet land before take-off)."""
    RESUME = "resume"
    GO = "go"
    TAKEOVER = "takeover"


@dataclass(frozen=True)
class FleetVerdict:
    """A fleet order's action and, when it is ignored or refused, why (logged)."""

    action: FleetAction
    """What to do."""
    note: str = ""
    """Why it is ignored ("" when acted on)."""


def fleet_action(order: FleetOrder, authority: Authority, armed: bool, holding: bool) -> FleetVerdict:
    """The authority rules applied to one fleet order (pure).

    ``armed``: the vehicle is armed; ``holding``: the mission is in HOLD.  Orders to a vehicle that is
    not the agent's (``NOT_OURS``) are ignored except an addressed ``takeover``; a ``HANDS_OFF``
    vehicle comes back only by an addressed ``resume`` or ``takeover``; after the flight
    (``RELEASED``) nothing applies."""
    cmd = order.command
    if authority == Authority.RELEASED:
        return FleetVerdict(FleetAction.IGNORE, "the flight is over (a go is good for one flight of one process)")
    if cmd == MissionCommand.TAKEOVER:
        if not order.addressed:
            return FleetVerdict(FleetAction.IGNORE, "takeover must be addressed to this agent (--agents ID)")
        if authority == Authority.COMMAND:
            return FleetVerdict(FleetAction.IGNORE, "already in command")
        return FleetVerdict(FleetAction.TAKEOVER if armed else FleetAction.GO)
    if authority == Authority.NOT_OURS:
        return FleetVerdict(FleetAction.IGNORE, "the vehicle is not ours (armed by someone else); only an "
                                                "addressed takeover hands it over")
    if authority == Authority.HANDS_OFF:
        if cmd == MissionCommand.RESUME and order.addressed:
            return FleetVerdict(FleetAction.TAKEOVER if armed else FleetAction.IGNORE,
                                "" if armed else "hands-off vehicle is disarmed: nothing to resume")
        return FleetVerdict(FleetAction.IGNORE, "hands off (the mode was changed outside the agent): only a resume "
                                                "or takeover addressed to this agent gives it back")
    if cmd == MissionCommand.GO:
        if authority == Authority.COMMAND:
            return FleetVerdict(FleetAction.IGNORE, "already flying")
        return FleetVerdict(FleetAction.GO)
    if cmd == MissionCommand.HOLD:
        return FleetVerdict(FleetAction.HOLD)
    if cmd == MissionCommand.LAND:
        if armed and authority == Authority.COMMAND:
            return FleetVerdict(FleetAction.LAND)
        return FleetVerdict(FleetAction.END)  # disarmed (an armed vehicle not in command is NOT_OURS or HANDS_OFF)
    # RESUME
    if not holding:
        return FleetVerdict(FleetAction.IGNORE, "not holding")
    return FleetVerdict(FleetAction.RESUME)
