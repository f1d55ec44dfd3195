"""Which fleet commands an agent accepts: swarm, target, per-key sequence floors and freshness (pure).

The rule (docs/zenoh.md, "Fleet commands"):

- **Replay** is stopped by sequence numbers, not clocks.  The agent keeps, per ground key
  (``key_id``), the highest sequence number it accepted (its *floor*); a command is accepted
  only above its key's floor.  Floors start from what the caller passes in (the integrator
  keeps them in the agent's state file across restarts) and are read back from ``floors``.
  A command of another key has its own floor.
- **Freshness** only bounds how late a captured, never-delivered command can still be used.
  It is judged on the clock the caller passes (the autopilot's GNSS time when it reports one,
  else the companion's clock), with windows wide enough for a 10 s skew between ground and
  companion: a live command (``Source.LIVE``, the cmd key) is accepted from ``max_age_s``
  (30 s) in the past to ``max_future_s`` (20 s) in the future.
- **The latest state** re-published by the ground (``Source.STATE``) is judged the same way
  except for its age: ``hold``, ``resume`` and ``land`` are the fleet's standing state and are
  accepted at any age (obeying an old hold or land never launches a vehicle); a ``go`` only
  while its go time (issue time, or the start-at time) is at most ``standing_go_s`` (120 s) old,
  so an agent switched on long after a go does not launch on it; a ``takeover`` only within
  the live window.  A re-published command at or below its key's floor is one the agent already
  has: ``REPLAY``, which the caller does not count as a refusal.
"""

from __future__ import annotations

from enum import Enum
from typing import Mapping

from fisc_agent.zenoh.fleet_commands import CommandCheck, CommandError, CommandName, FleetCommand

MAX_AGE_S = 30.0
"""A live command issued longer ago than this (agent's clock) is stale [s]."""
MAX_FUTURE_S = 20.0
"""A command issued further ahead than this (agent's clock) is refused as from the future [s]."""
STANDING_GO_S = 120.0
"""A re-published go whose go time is older than this is stale [s]."""
STANDING = frozenset({CommandName.HOLD, CommandName.RESUME, CommandName.LAND})
"""Commands that, re-published as the latest state, are accepted at any age."""


class Source(Enum):
    """Where a command came from."""

    LIVE = "live"
    """Published on the cmd key as the ground sent it."""
    STATE = "state"
    """The ground's re-published latest state (queried on connect, re-published periodically)."""


class CommandGate:
    """Swarm, target, replay and freshness filter of one agent (pure: time passed in).

    ``check(cmd, now_unix_s, source)`` returns ``cmd`` or raises ``CommandError`` naming the
    failed check; on success the command's sequence becomes its key's floor.
    """

    def __init__(self, swarm: str, agent_id: int, floors: Mapping[str, int] | None = None,
                 max_age_s: float = MAX_AGE_S, max_future_s: float = MAX_FUTURE_S,
                 standing_go_s: float = STANDING_GO_S) -> None:
        self.swarm = swarm
        """The agent's swarm."""
        self.agent_id = int(agent_id)
        """The agent's id."""
        self.max_age_s = float(max_age_s)
        """Live window into the past [s]."""
        self.max_future_s = float(max_future_s)
        """Window into the future [s] (live and state)."""
        self.standing_go_s = float(standing_go_s)
        """Age up to which a re-published go is accepted [s]."""
        self._floors: dict[str, int] = {str(k): int(v) for k, v in (floors or {}).items()}

    @property
    def floors(self) -> dict[str, int]:
        """Highest accepted sequence number per ground key id (a copy; persist it across restarts)."""
        return dict(self._floors)

    def floor(self, key_id: str) -> int:
        """The floor of one key (0: nothing accepted from it)."""
        return self._floors.get(key_id, 0)

    def check(self, cmd: FleetCommand, now_unix_s: float, source: Source = Source.LIVE) -> FleetCommand:
        """Accept ``cmd`` (returned, its sequence becomes the key's floor) or raise ``CommandError``
        (swarm, target, replay, stale, future)."""
        if cmd.swarm != self.swarm:
            raise CommandError(CommandCheck.SWARM, f"command is for swarm {cmd.swarm!r}, this agent flies in {self.swarm!r}")
        if not cmd.applies_to(self.agent_id):
            raise CommandError(CommandCheck.TARGET, f"command is for agents {list(cmd.targets)}")
        floor = self.floor(cmd.key_id)
        if cmd.seq <= floor:
            raise CommandError(CommandCheck.REPLAY, f"sequence {cmd.seq} is not above the last accepted {floor} "
                               f"of key {cmd.key_id or '(unsigned)'}")
        age = now_unix_s - cmd.issued_unix_s
        if age < -self.max_future_s:
            raise CommandError(CommandCheck.FUTURE, f"command issued {-age:.1f} s in the future (window "
                               f"{self.max_future_s:.0f} s; clock skew?)")
        self._check_age(cmd, now_unix_s, age, source)
        self._floors[cmd.key_id] = cmd.seq
        return cmd

    def _check_age(self, cmd: FleetCommand, now_unix_s: float, age: float, source: Source) -> None:
        if source is Source.STATE and cmd.name in STANDING:
            return
        if source is Source.STATE and cmd.name in (CommandName.GO, CommandName.START_AT):
            go_at = max(cmd.issued_unix_s, cmd.start_at_unix_s or cmd.issued_unix_s)
            if now_unix_s - go_at > self.standing_go_s:
                raise CommandError(CommandCheck.STALE, f"re-published {cmd.name} for {now_unix_s - go_at:.1f} s ago "
                                   f"(standing window {self.standing_go_s:.0f} s)")
            return
        if age > self.max_age_s:
            raise CommandError(CommandCheck.STALE, f"command issued {age:.1f} s ago (window {self.max_age_s:.0f} s)")
