"""An agent's fleet-command intake: decode, verify, gate, count and log (no I/O but the log; clock passed in).

``CommandReceiver.live(payload)`` judges a command from the cmd key, ``state(bundle)`` the ground's
re-published latest commands (``fisc_agent.zenoh.state_bundle``), applied oldest first.  Each
returns what was accepted; every refusal is counted, remembered as the newest refusal (its check
and the command it refused, for telemetry) and logged (at most once per 5 s per kind, with the
number suppressed).  Not refusals: a command for other agents (``target``), a re-published
command the agent already has (``replay`` from the state), and the live copy of a command accepted
from the state at most ``LATE_LIVE_COPY_S`` before (the same command arriving late by the other
path).  A re-published command refused for good (anything but ``future``) is judged once, not at
every re-publication.
"""

from __future__ import annotations

import logging
import math
import threading
from dataclasses import dataclass, replace
from typing import Callable, Mapping

from fisc_agent.common.ratelimit import RateLimitedLog
from fisc_agent.zenoh.command_gate import CommandGate, Source
from fisc_agent.zenoh.state_bundle import decode_bundle
from fisc_agent.zenoh.fleet_commands import CommandCheck, CommandError, FleetCommand, decode_command

log = logging.getLogger(__name__)

MEMO_MAX = 1024
"""Re-published commands remembered as judged (refused for good) at most."""


@dataclass(frozen=True)
class CommandStats:
    """Counters of an agent's fleet commands (a snapshot)."""

    accepted: int = 0
    """Commands accepted (live and from the state)."""
    refused: int = 0
    """Commands refused (every check but ``target``; ``replay`` of the state is no refusal)."""
    last_accepted: str = "none"
    """Name of the newest accepted command ("none")."""
    last_accepted_seq: int = 0
    """Its sequence number."""
    last_refusal: str = "none"
    """``CommandCheck`` value of the newest refusal ("none")."""
    last_refused_command: str = "none"
    """Name of the command it refused ("none" when the command did not decode that far)."""
    last_refusal_message: str = ""
    """The newest refusal's message."""
    bundles: int = 0
    """State bundles received."""


LATE_LIVE_COPY_S = 0.5
"""A live command byte-identical to one accepted from the re-published state at most this long before
is that command arriving late by the other path (the ground's relay re-publishes what it hears at once,
and its bundle can overtake the live sample), not a replay: ignored, not counted [s].  Counted as a
refusal, it failed ``tests/zenoh/test_fleet_state.py`` once in a clean-clone run (2026-12-05) and would
show the ground a refusal nobody made."""


class CommandReceiver:
    """Decode + signature + ``CommandGate`` for one agent, with counters (thread-safe)."""

    def __init__(self, swarm: str, agent_id: int, trusted_keys: list[bytes] | None, allow_unsigned: bool,
                 clock: Callable[[], float], floors: Mapping[str, int] | None = None,
                 rlog: RateLimitedLog | None = None, **windows: float) -> None:
        self.gate = CommandGate(swarm, agent_id, floors, **windows)
        """The replay/freshness gate (``floors`` in and out)."""
        self.trusted_keys = list(trusted_keys) if trusted_keys else None
        self.allow_unsigned = bool(allow_unsigned)
        self.clock = clock
        """UNIX time [s] that freshness is judged on (the autopilot's GNSS time when it has one)."""
        self.rlog = rlog or RateLimitedLog(log)
        self._stats = CommandStats()
        self._memo: set[bytes] = set()
        self._from_state: dict[bytes, float] = {}
        """Raw commands accepted from the state -> when (``clock``), for ``LATE_LIVE_COPY_S``."""
        self._lock = threading.Lock()

    @property
    def stats(self) -> CommandStats:
        """The counters now."""
        with self._lock:
            return self._stats

    @property
    def floors(self) -> dict[str, int]:
        """Highest accepted sequence per ground key id (persist these across restarts)."""
        with self._lock:
            return self.gate.floors

    def live(self, payload: bytes) -> FleetCommand | None:
        """Judge one command from the cmd key: the command if accepted, else None."""
        with self._lock:
            return self._judge(bytes(payload), Source.LIVE)

    def state(self, bundle: bytes) -> list[FleetCommand]:
        """Judge the re-published latest commands, oldest first: the ones accepted, in order."""
        with self._lock:
            self._stats = replace(self._stats, bundles=self._stats.bundles + 1)
            try:
                items = decode_bundle(bundle)
            except CommandError as exc:
                self._refuse(exc, "none", "command bundle")
                return []
            accepted = []
            for raw in items:
                if raw in self._memo:
                    continue
                cmd = self._judge(raw, Source.STATE)
                if cmd is not None:
                    accepted.append(cmd)
            return accepted

    def _judge(self, raw: bytes, source: Source) -> FleetCommand | None:
        name = "none"
        try:
            cmd = decode_command(raw, self.trusted_keys, self.allow_unsigned)
            name = cmd.name.value
            self.gate.check(cmd, self.clock(), source)
        except CommandError as exc:
            if exc.check is CommandCheck.TARGET or (source is Source.STATE and exc.check is CommandCheck.REPLAY):
                return None  # another agent's command; a state the agent already has
            late_s = self.clock() - self._from_state.get(raw, -math.inf)
            if exc.check is CommandCheck.REPLAY and late_s <= LATE_LIVE_COPY_S:
                return None  # the live copy of a command the state brought first
            if source is Source.STATE and exc.check is not CommandCheck.FUTURE:
                if len(self._memo) >= MEMO_MAX:
                    self._memo.clear()
                self._memo.add(raw)
            self._refuse(exc, name, "re-published fleet command" if source is Source.STATE else "fleet command")
            return None
        if source is Source.STATE:
            if len(self._from_state) >= MEMO_MAX:
                self._from_state.clear()
            self._from_state[raw] = self.clock()
        s = self._stats
        self._stats = replace(s, accepted=s.accepted + 1, last_accepted=cmd.name.value, last_accepted_seq=cmd.seq)
        log.info("fleet command %s (seq %d, key %s%s) accepted%s", cmd.name.value, cmd.seq, cmd.key_id or "-",
                 f", agents {list(cmd.targets)}" if cmd.targets else "",
                 " from the re-published state" if source is Source.STATE else "")
        return cmd

    def _refuse(self, exc: CommandError, name: str, what: str) -> None:
        s = self._stats
        self._stats = replace(s, refused=s.refused + 1, last_refusal=exc.check.value, last_refused_command=name,
                              last_refusal_message=str(exc))
        self.rlog.event(f"cmd:{exc.check.value}", logging.WARNING, "%s %s refused: %s", what, name, exc)
