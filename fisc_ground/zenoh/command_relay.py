"""The ground's latest fleet commands, kept and re-published so that a late or restarted agent learns them.

``LatestCommands`` (pure) keeps, for the whole swarm and for each addressed agent, the newest
``go`` (or ``start-at``) and the newest of ``hold`` / ``resume`` / ``land``, as the signed bytes
the ground sent.  ``takeover`` is never kept: it is one operator's act on one vehicle at one
moment.  A swarm-wide command drops the addressed ones of its kind it supersedes.
``CommandRelay`` (``fisc-ground publish``) feeds it from ``<prefix>/<swarm>/cmd``, answers
queries on ``<prefix>/<swarm>/cmd/latest`` with one bundle (``fisc_agent.zenoh.state_bundle``)
and puts the bundle there every ``period_s``.  It stores only commands that verify against its
trusted keys (``--trusted-key``, and the key that signed the map it serves): it relays what the
ground signed and cannot forge; the agents check every relayed command themselves.
"""

from __future__ import annotations

import logging
import threading
from typing import Any

from fisc_agent.common.ratelimit import RateLimitedLog
from fisc_agent.zenoh.state_bundle import MAX_COMMANDS, encode_bundle
from fisc_agent.zenoh.fleet_commands import CommandCheck, CommandError, CommandName, FleetCommand, decode_command
from fisc_agent.zenoh.keys import DEFAULT_PREFIX, Keys

log = logging.getLogger(__name__)

KIND = {CommandName.GO: "go", CommandName.START_AT: "go", CommandName.HOLD: "hold", CommandName.RESUME: "hold",
        CommandName.LAND: "hold"}
"""Which slot a command takes: the latest go, or the latest hold state (takeover: none)."""


class LatestCommands:
    """The newest go and hold-state command per scope (swarm, or one agent), pure."""

    def __init__(self, swarm: str, trusted_keys: list[bytes] | None, allow_unsigned: bool = False,
                 max_commands: int = 256) -> None:
        self.swarm = swarm
        """Swarm whose commands are kept (others are ignored)."""
        self.trusted_keys = list(trusted_keys or [])
        """Keys a command must verify against (grows with ``trust``)."""
        self.allow_unsigned = bool(allow_unsigned)
        """Keep unsigned commands (lab only)."""
        self.max_commands = min(int(max_commands), MAX_COMMANDS)
        """Distinct commands kept at most (the oldest addressed ones go first)."""
        self._slots: dict[tuple[int | None, str], tuple[FleetCommand, bytes]] = {}

    def trust(self, key: bytes) -> None:
        """Also accept commands signed by ``key`` (e.g. the key of the map served)."""
        if bytes(key) not in self.trusted_keys:
            self.trusted_keys.append(bytes(key))

    def offer(self, raw: bytes) -> FleetCommand | None:
        """Keep ``raw`` if it is a valid command of this swarm newer than its slots'; the command if
        kept, None if not (``CommandError`` when it does not decode or verify)."""
        if not self.trusted_keys and not self.allow_unsigned:
            raise CommandError(CommandCheck.SIGNATURE, "no trusted key to check commands against "
                               "(give fisc-ground publish --trusted-key, or serve a signed map)")
        cmd = decode_command(raw, self.trusted_keys or None, self.allow_unsigned)
        kind = KIND.get(cmd.name)
        if cmd.swarm != self.swarm or kind is None:
            return None
        order = (cmd.issued_unix_s, cmd.seq)
        scopes = list(cmd.targets) if cmd.targets else [None]
        kept = False
        for scope in scopes:
            old = self._slots.get((scope, kind))
            if old is None or (old[0].issued_unix_s, old[0].seq) < order:
                self._slots[(scope, kind)] = (cmd, bytes(raw))
                kept = True
        if kept and not cmd.targets:  # a swarm-wide command supersedes older addressed ones of its kind
            for slot in [s for s, (c, _) in self._slots.items()
                         if s[0] is not None and s[1] == kind and (c.issued_unix_s, c.seq) < order]:
                del self._slots[slot]
        self._bound()
        return cmd if kept else None

    def _bound(self) -> None:
        while len(self.commands()) > self.max_commands:
            addressed = [(c.issued_unix_s, c.seq, s) for s, (c, _) in self._slots.items() if s[0] is not None]
            if not addressed:
                return
            del self._slots[min(addressed)[2]]

    def commands(self) -> list[bytes]:
        """The distinct commands kept, oldest first (issue time, then sequence)."""
        unique = {raw: cmd for cmd, raw in self._slots.values()}
        return [raw for raw, _ in sorted(unique.items(), key=lambda kv: (kv[1].issued_unix_s, kv[1].seq))]

    def bundle(self) -> bytes:
        """The kept commands as one bundle (``fisc_agent.zenoh.state_bundle``)."""
        return encode_bundle(self.commands())


class CommandRelay:
    """``LatestCommands`` on a Zenoh session: listens on the cmd key, answers and re-publishes the bundle."""

    def __init__(self, session: Any, swarm: str, prefix: str = DEFAULT_PREFIX, trusted_keys: list[bytes] | None = None,
                 allow_unsigned: bool = False, period_s: float = 2.0) -> None:
        if not period_s > 0:
            raise ValueError(f"re-publication period must be > 0 s, got {period_s}")
        self.keys = Keys(prefix, swarm)
        self.latest = LatestCommands(swarm, trusted_keys, allow_unsigned)
        """The commands kept."""
        self.period_s = float(period_s)
        self.rlog = RateLimitedLog(log)
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._sub = session.declare_subscriber(self.keys.cmd, self._on_cmd)
        self._pub = session.declare_publisher(self.keys.cmd_latest)
        self._queryable = session.declare_queryable(self.keys.cmd_latest, self._on_query)
        self._thread = threading.Thread(target=self._loop, name="fisc-cmd-relay", daemon=True)
        self._thread.start()

    def trust(self, key: bytes) -> None:
        """Also keep commands signed by ``key``."""
        with self._lock:
            self.latest.trust(key)

    def _on_cmd(self, sample: Any) -> None:
        try:
            with self._lock:
                cmd = self.latest.offer(sample.payload.to_bytes())
        except CommandError as exc:
            self.rlog.event(f"relay:{exc.check.value}", logging.WARNING, "fleet command not re-published: %s", exc)
            return
        if cmd is not None:
            log.info("re-publishing %s (seq %d%s) as the latest state", cmd.name.value, cmd.seq,
                     f", agents {list(cmd.targets)}" if cmd.targets else "")

    def _bundle(self) -> bytes | None:
        with self._lock:
            return self.latest.bundle() if self.latest.commands() else None

    def _on_query(self, query: Any) -> None:
        bundle = self._bundle()
        if bundle is not None:
            query.reply(self.keys.cmd_latest, bundle)

    def _loop(self) -> None:
        while not self._stop.wait(self.period_s):
            bundle = self._bundle()
            if bundle is None:
                continue
            try:
                self._pub.put(bundle)
            except Exception as exc:  # session closed under us
                log.debug("re-publication failed: %s", exc)
                return

    def close(self) -> None:
        """Stop re-publishing and undeclare (the session stays open)."""
        self._stop.set()
        self._thread.join(timeout=5.0)
        for ent in (self._queryable, self._pub, self._sub):
            try:
                ent.undeclare()
            except Exception as exc:
                log.debug("undeclare failed: %s", exc)
