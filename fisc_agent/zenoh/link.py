"""Agent side of the Zenoh link: signed map reception, fleet commands, telemetry (session I/O).

The pieces it wires: key expressions (``fisc_agent.zenoh.keys``), sessions and the lab
discovery (``fisc_agent.zenoh.session``), the map-chunk codec and reassembly
(``fisc_agent.map.chunks``), map verification (``fisc_agent.zenoh.maps``), the telemetry
message (``fisc_agent.zenoh.telemetry``).

Map transport.  A map travels as chunks (format: ``fisc_agent.map.chunks``).  The ground
pushes every chunk once when it starts serving a map, answers queries on the map key with
every chunk (late joiners), and announces (kind 2, no data) the current map
periodically.  An agent queries on start and whenever an announcement names a map newer than
its own that is not arriving.  Reassembled bytes must match the header's sha256, then pass
``decode_map`` (schema, content hash, Ed25519 signature from a trusted key) and carry a
``map_version`` above the current one; otherwise the map is refused, counted, logged and
reported in telemetry, and the agent keeps the last good map.  The chunk header is not
authenticated (the map's own seal is): forged chunks can waste bandwidth, not install a map,
and their cost is bounded (``fisc_agent.map.chunks``: memory only for bytes received, a byte
budget, stall timeouts, announced maps first, bounded caches).

This module is onboard code: numpy, the standard library, PyNaCl and zenoh only.
"""

from __future__ import annotations

import logging
import math
import queue
import threading
import time
from dataclasses import dataclass
from typing import Any, Callable

from fisc_agent.zenoh import telemetry_codec as tc
from fisc_agent.zenoh.command_gate import MAX_AGE_S, STANDING_GO_S
from fisc_agent.zenoh.command_rx import CommandReceiver
from fisc_agent.zenoh.fleet_commands import FleetCommand
from fisc_agent.map.chunks import (KIND_ANNOUNCE, AssemblyDrop, AssemblyLimits, ChunkHeader, DropReason,
                                   MapAssembler)
from fisc_agent.map.codec import CommandMap, MapError, MapErrorKind
from fisc_agent.common.ratelimit import RateLimitedLog
from fisc_agent.flight.tick import AgentSnapshot
from fisc_agent.zenoh.neighbours import NeighbourTable
from fisc_agent.zenoh.keys import DEFAULT_PREFIX, Keys
from fisc_agent.zenoh.maps import reject_code, verify_map_bytes
from fisc_agent.zenoh.session import ZenohSessionError, open_session
from fisc_agent.zenoh.telemetry import LinkStatus, telemetry_message

log = logging.getLogger(__name__)

DEFAULT_RX_QUEUE_BYTES = 512 << 20
"""Map-key payloads waiting for the assembler thread, at most [bytes] (more are dropped and counted)."""
DEFAULT_RX_QUEUE_MESSAGES = 4096
"""... and at most this many messages."""
LOG_PERIOD_S = 5.0
"""Refusals of the same kind are logged at most once per this period (all are counted)."""


# --------------------------------------------------------------------------------------------
# The link

@dataclass
class LinkStats:
    """Counters of one agent link (mutable; read them for logs and telemetry)."""

    maps_accepted: int = 0
    """Maps handed to ``on_map`` and adopted."""
    maps_rejected: int = 0
    """Maps refused (any failed check, including the runner's own)."""
    maps_ignored_old: int = 0
    """Maps not newer than the current one (also counted in ``maps_rejected``, reason ``old_version``)."""
    maps_incomplete: int = 0
    """Maps in progress dropped unfinished (stalled, evicted, over the byte budget); also in ``maps_rejected``."""
    map_messages_dropped: int = 0
    """Map-key messages dropped unread: receive queue full, or no reassembly slot free."""
    last_reject_reason: str = "none"
    """Check that refused the last refused map (``REJECT_REASONS``)."""
    last_reject_message: str = ""
    """Full message of that refusal."""
    telemetry_sent: int = 0
    """Telemetry messages published."""
    queries_sent: int = 0
    """Map queries issued (start, announcements of maps not arriving)."""
    state_queries_sent: int = 0
    """Queries of the ground's latest fleet commands (on connect)."""


class AgentZenohLink:
    """One agent's Zenoh link: map subscription + late-joiner query, commands, telemetry.

    ``on_map(cmap)`` is called from the link's worker thread with each verified map newer than
    the last; the runner installs it at its next safe point.  Returning ``False`` refuses it
    (``Runner.offer_map``'s own checks) and it is then counted as refused.  ``on_command(cmd)``
    gets each fleet command that passed signature, swarm, target, replay and staleness checks
    (``commands``, a ``CommandReceiver``: live ones from the cmd key, and the ground's re-published
    latest ones, queried on connect and re-published by the ground every few seconds, oldest
    first).  Freshness is judged on ``command_clock`` (default ``clock``; the agent passes the
    autopilot's GNSS time), replay by per-key sequence floors starting at ``command_floors``
    (read them back from ``commands.floors``).  Neither callback is called for anything refused:
    refusals are logged, counted and reported in telemetry.  ``session_config``: a ``zenoh.Config``, a JSON5 file path or None (lab
    default); or pass an open ``session`` to share one (it is then not closed by ``close``).

    Threads: Zenoh's callbacks only queue map-key payloads (``rx_queue_bytes`` /
    ``rx_queue_messages``, beyond that dropped and counted in ``stats.map_messages_dropped``);
    the assembler thread reassembles within ``assembly_limits`` (``max_map_bytes`` overrides
    its size limit); the install thread decodes, verifies and calls ``on_map``.  ``rlog``
    counts every refusal by kind and logs at most one line per kind per ``LOG_PERIOD_S``.
    """

    def __init__(self, session_config: Any, swarm: str, agent_id: int, trusted_keys: list[bytes] | None,
                 allow_unsigned: bool, on_map: Callable[[CommandMap], object],
                 on_command: Callable[[FleetCommand], None], *, prefix: str = DEFAULT_PREFIX,
                 session: Any = None, query_timeout_s: float = 10.0, max_map_bytes: int | None = None,
                 command_max_age_s: float = MAX_AGE_S, clock: Callable[[], float] = time.time,
                 command_clock: Callable[[], float] | None = None, command_floors: dict[str, int] | None = None,
                 standing_go_s: float = STANDING_GO_S,
                 assembly_limits: AssemblyLimits | None = None, rx_queue_bytes: int = DEFAULT_RX_QUEUE_BYTES,
                 rx_queue_messages: int = DEFAULT_RX_QUEUE_MESSAGES, neighbours: NeighbourTable | None = None) -> None:
        if not trusted_keys and not allow_unsigned:
            raise ValueError("no trusted key given: pass --trusted-key (or --allow-unsigned in a lab)")
        self.keys = Keys(prefix, swarm)
        self.agent_id = int(agent_id)
        self.trusted_keys = list(trusted_keys) if trusted_keys else None
        self.allow_unsigned = bool(allow_unsigned)
        self.on_map = on_map
        self.on_command = on_command
        self.query_timeout_s = float(query_timeout_s)
        self.clock = clock
        self.reconnect_period_s = 1.0
        self.stats = LinkStats()
        self.current: CommandMap | None = None
        self._session_config = session_config
        self._session = session
        self._own_session = session is None
        self._assembler = MapAssembler(max_bytes=max_map_bytes, limits=assembly_limits)
        self.rlog = RateLimitedLog(log, LOG_PERIOD_S)
        """Refusal counters by kind (``map:<reason>``, ``cmd:<reason>``, ``rx:<what>``) and their rate-limited log."""
        self._rx: queue.Queue = queue.Queue()
        self._rx_bytes = 0
        self._rx_limits = (int(rx_queue_bytes), int(rx_queue_messages))
        self._assembler_thread: threading.Thread | None = None
        self.commands = CommandReceiver(swarm, self.agent_id, self.trusted_keys, self.allow_unsigned,
                                        command_clock or clock, command_floors, self.rlog,
                                        max_age_s=command_max_age_s, standing_go_s=standing_go_s)
        """Fleet-command intake: counters, newest refusal, per-key sequence floors."""
        self._lock = threading.Lock()
        self._asm_lock = threading.Lock()
        self._work: queue.Queue = queue.Queue()
        self._entities: list[Any] = []
        self._pub = None
        self._seq = 0
        self._last_query_s = -math.inf
        self._worker: threading.Thread | None = None
        self._telemetry_thread: threading.Thread | None = None
        self._stop = threading.Event()
        self.close_hooks: list[Callable[[], None]] = []
        self.neighbours = neighbours
        """Fed with the swarm's telemetry once connected (the safety net's ears; one table may be shared
        by the links of one session); None: the link does not listen to other vehicles."""
        if self.allow_unsigned:
            log.warning("*** --allow-unsigned: this agent accepts UNSIGNED maps and commands. Lab use only. ***")

    # -- lifecycle ---------------------------------------------------------------------------
    def start(self) -> "AgentZenohLink":
        """Start the link: open the session (retried in the background while no router/peer
        answers, e.g. in client mode before the ground is up), subscribe to map and commands,
        query the current map.  Never blocks for long."""
        self._worker = threading.Thread(target=self._work_loop, name=f"fisc-zenoh-map-{self.agent_id}", daemon=True)
        self._worker.start()
        self._assembler_thread = threading.Thread(target=self._assemble_loop, name=f"fisc-zenoh-asm-{self.agent_id}",
                                                  daemon=True)
        self._assembler_thread.start()
        if not self._try_connect():
            threading.Thread(target=self._connect_loop, name=f"fisc-zenoh-open-{self.agent_id}", daemon=True).start()
        return self

    def _try_connect(self) -> bool:
        import zenoh

        if self._session is None:
            try:
                session = open_session(self._session_config)
            except ZenohSessionError as exc:
                log.warning("Zenoh session not open yet (%s); retrying", exc)
                return False
            with self._lock:
                if self._stop.is_set():
                    session.close()
                    return True
                self._session = session
        s = self._session
        self._entities.append(s.declare_subscriber(self.keys.map, self._on_map_sample))
        self._entities.append(s.declare_subscriber(self.keys.cmd, self._on_cmd_sample))
        self._entities.append(s.declare_subscriber(self.keys.cmd_latest, self._on_state_sample))
        pub = s.declare_publisher(self.keys.telemetry(self.agent_id), congestion_control=zenoh.CongestionControl.DROP)
        self._entities.append(pub)
        if self.neighbours is not None:
            sub = self.neighbours.attach(s, self.keys.all_telemetry)
            if sub is not None:
                self._entities.append(sub)
        self._pub = pub
        self.query_map()
        self.query_commands()
        return True

    def _connect_loop(self) -> None:
        while not self._stop.wait(self.reconnect_period_s):
            if self._try_connect():
                return

    @property
    def connected(self) -> bool:
        """True once the session is open and the link declared."""
        return self._pub is not None

    def close(self) -> None:
        """Undeclare everything, stop the threads, close the session if this link opened it."""
        with self._lock:
            self._stop.set()
        for hook in self.close_hooks:
            hook()
        self._work.put(None)
        self._rx.put(None)
        for t in (self._telemetry_thread, self._worker, self._assembler_thread):
            if t is not None and t is not threading.current_thread():
                t.join(timeout=5.0)
        self._pub = None
        for ent in reversed(self._entities):
            try:
                ent.undeclare()
            except Exception as exc:  # session may already be closed
                log.debug("undeclare failed: %s", exc)
        self._entities.clear()
        if self._own_session and self._session is not None:
            self._session.close()
        self._session = None

    def __enter__(self) -> "AgentZenohLink":
        return self.start()

    def __exit__(self, *exc: Any) -> None:
        self.close()

    # -- maps --------------------------------------------------------------------------------
    def query_map(self) -> None:
        """Ask the ground for the current map (replies arrive as chunks)."""
        import zenoh

        if self._session is None:
            return
        self._last_query_s = self.clock()
        self.stats.queries_sent += 1
        self._session.get(self.keys.map, self._on_reply,
                          consolidation=zenoh.QueryConsolidation(zenoh.ConsolidationMode.NONE),
                          timeout=self.query_timeout_s)

    def _on_reply(self, reply: Any) -> None:
        sample = reply.ok
        if sample is not None:
            self._enqueue(sample.payload)

    def _on_map_sample(self, sample: Any) -> None:
        self._enqueue(sample.payload)

    def _enqueue(self, zbytes: Any) -> None:
        """Zenoh's thread: hand the payload to the assembler thread (never blocks, never parses);
        dropped and counted when the queue is full (checked before the payload is copied)."""
        max_bytes, max_msgs = self._rx_limits
        size = len(zbytes)
        with self._lock:
            full = self._rx_bytes + size > max_bytes or self._rx.qsize() >= max_msgs
            if not full:
                self._rx_bytes += size
        if not full:
            self._rx.put(zbytes.to_bytes())
            return
        with self._lock:
            self.stats.map_messages_dropped += 1
        self.rlog.event("rx:queue_full", logging.WARNING, "map message of %d bytes dropped: receive queue full "
                        "(%d bytes / %d messages)", size, max_bytes, max_msgs)

    def _assemble_loop(self) -> None:
        """Assembler thread: parse, reassemble and hash map chunks; completed maps go to the
        install worker.  Off Zenoh's threads and off the control loop."""
        while True:
            try:
                payload = self._rx.get(timeout=1.0)
            except queue.Empty:
                payload = b""
            if payload is None or self._stop.is_set():
                return
            if payload:
                with self._lock:
                    self._rx_bytes -= len(payload)
            try:
                self._on_map_payload(payload)
            except Exception as exc:  # never let one message kill the thread; counted and shown
                with self._lock:
                    self._reject(MapError(MapErrorKind.OTHER,
                                          f"map message could not be processed ({exc!r})", source=self.keys.map))

    def _on_map_payload(self, payload: bytes) -> None:
        now = self.clock()
        with self._asm_lock:
            try:
                if not payload:
                    self._assembler.expire(now)
                    head, blob = None, None
                else:
                    head, blob = self._assembler.feed(payload, now)
            except MapError as exc:
                with self._lock:
                    self._reject(exc)
                head = blob = None
            drops = self._assembler.drain_drops()
            if head is not None and head.kind == KIND_ANNOUNCE:
                if self._assembler.wanted(head) and not self._assembler.progressing(head.sha256, now, 1.0) \
                        and now - self._last_query_s > 1.0:
                    self._work.put(("query", None, None))
        for drop in drops:
            self._on_drop(drop)
        if blob is not None:
            self._work.put(("map", head, blob))

    def _on_drop(self, drop: AssemblyDrop) -> None:
        """Count and (rate-limited) log a map the assembler dropped."""
        head = drop.head
        what = f"map {head.sha256.hex()[:12]} (map_version {head.map_version}, {drop.received_bytes} of " \
               f"{head.total_bytes} bytes received)"
        if drop.reason == DropReason.NO_SLOT:
            with self._lock:
                self.stats.map_messages_dropped += 1
            self.rlog.event("map:no_slot", logging.WARNING, "map chunk dropped: every reassembly slot holds an "
                            "announced map (%s)", what)
            return
        with self._lock:
            if drop.reason == DropReason.OLD_VERSION:
                self.stats.maps_ignored_old += 1
                floor = self._assembler.floor_version
                exc = MapError(MapErrorKind.OLD_VERSION, f"{what} is not newer than map_version {floor} in use "
                               "(replayed or rolled back)", source=self.keys.map)
            else:
                self.stats.maps_incomplete += 1
                exc = MapError(MapErrorKind.CHUNKS,
                               f"{what} dropped unfinished ({drop.reason.value})", source=self.keys.map)
            self._reject(exc, key=f"map:{drop.reason.value}")

    def _work_loop(self) -> None:
        while True:
            item = self._work.get()
            if item is None or self._stop.is_set():
                return
            kind, head, blob = item
            if kind == "query":
                try:
                    self.query_map()
                except Exception as exc:  # session closing under us
                    log.warning("map query failed: %s", exc)
                continue
            self._install(head, blob)

    def _install(self, head: ChunkHeader, blob: bytearray) -> None:
        """Install worker thread: decode and verify a completed map (its sha256 was checked as
        the chunks arrived), hand it to ``on_map``."""
        try:
            cmap = verify_map_bytes(blob, self.trusted_keys, self.allow_unsigned, head.map_version,
                                    source=self.keys.map)
        except MapError as exc:
            with self._lock:
                self._reject(exc)
            return
        with self._lock:
            current = self.current
            if current is not None and cmap.map_version <= current.map_version:
                if cmap.sha256 != current.sha256:
                    self.stats.maps_ignored_old += 1
                    self._reject(MapError(MapErrorKind.OLD_VERSION, f"map {cmap.sha256[:12]} has map_version "
                                          f"{cmap.map_version}, not newer than {current.map_version} in use",
                                          source=self.keys.map))
                return
        if not cmap.signed:
            log.warning("*** UNSIGNED map %s (map_version %d) offered to the agent ***", cmap.sha256[:12],
                        cmap.map_version)
        if self.on_map(cmap) is False:  # the runner's own checks refused it
            with self._lock:
                self._reject(MapError(MapErrorKind.OTHER, f"map {cmap.sha256[:12]} refused by the agent's "
                                      "checks (see its log)", source=self.keys.map))
            return
        with self._lock:
            self.current = cmap
            self.stats.maps_accepted += 1
        with self._asm_lock:
            self._assembler.accept(cmap.map_version, head.sha256)
        log.info("map %s accepted (map_version %d, %d CVs)", cmap.sha256[:12], cmap.map_version, cmap.n_cv)

    def _reject(self, exc: Exception, key: str | None = None) -> None:
        """Count a refused map (caller holds ``_lock``) and log it, at most once per
        ``LOG_PERIOD_S`` per kind."""
        self.stats.maps_rejected += 1
        self.stats.last_reject_reason = reject_code(exc)
        self.stats.last_reject_message = str(exc)
        self.rlog.event(key or f"map:{self.stats.last_reject_reason}", logging.ERROR,
                        "map refused (%s): %s; keeping the %s", self.stats.last_reject_reason, exc,
                        "current map" if self.current is not None else "ground hold (no map yet)")

    # -- commands ----------------------------------------------------------------------------
    def query_commands(self) -> None:
        """Ask the ground for its latest fleet commands (``fisc-ground publish`` answers)."""
        import zenoh

        if self._session is None:
            return
        self.stats.state_queries_sent += 1
        self._session.get(self.keys.cmd_latest, self._on_state_reply,
                          consolidation=zenoh.QueryConsolidation(zenoh.ConsolidationMode.NONE),
                          timeout=self.query_timeout_s)

    def _on_state_reply(self, reply: Any) -> None:
        if reply.ok is not None:
            self._on_state_sample(reply.ok)

    def _on_state_sample(self, sample: Any) -> None:
        for cmd in self.commands.state(sample.payload.to_bytes()):
            self._deliver(cmd)

    def _on_cmd_sample(self, sample: Any) -> None:
        cmd = self.commands.live(sample.payload.to_bytes())
        if cmd is not None:
            self._deliver(cmd)

    def _deliver(self, cmd: FleetCommand) -> None:
        try:
            self.on_command(cmd)
        except Exception as exc:  # a flying agent never loses its link to a callback's bug
            log.error("fleet command %s (seq %d) could not be applied: %r", cmd.name.value, cmd.seq, exc)

    # -- telemetry ---------------------------------------------------------------------------
    def telemetry_from(self, snap: AgentSnapshot | None) -> tc.Telemetry:
        """The telemetry message for a runner snapshot (None before its first tick) plus this
        link's counters (``fisc_agent.zenoh.telemetry.telemetry_message``)."""
        with self._lock:
            stats, current = self.stats, self.current
            self._seq = (self._seq + 1) & 0xFFFFFFFF
            seq = self._seq
            sha = snap.map_sha256 if snap is not None else None
            cmds = self.commands.stats
            status = LinkStatus(maps_rejected=stats.maps_rejected, reject_reason=stats.last_reject_reason,
                                ack_command=cmds.last_accepted, ack_seq=cmds.last_accepted_seq,
                                commands_refused=cmds.refused, refusal=cmds.last_refusal,
                                refused_command=cmds.last_refused_command,
                                zenoh_ok=self._pub is not None,
                                map_unsigned=current is not None and current.sha256 == sha and not current.signed)
        return telemetry_message(snap, self.agent_id, seq, status, self.clock())

    def publish_telemetry(self, snap: AgentSnapshot | None) -> None:
        """Encode and publish one telemetry message (never blocks: dropped under congestion)."""
        if self._pub is None:
            return
        self._pub.put(tc.encode(self.telemetry_from(snap)))
        self.stats.telemetry_sent += 1

    def start_telemetry(self, snapshot: Callable[[], AgentSnapshot | None], rate_hz: float = 5.0) -> None:
        """Publish ``snapshot()`` at ``rate_hz`` from a background thread until ``close``."""
        if not rate_hz > 0:
            raise ValueError(f"telemetry rate must be > 0 Hz, got {rate_hz}")
        period = 1.0 / rate_hz

        def loop() -> None:
            next_t = time.monotonic()
            while not self._stop.is_set():
                try:
                    self.publish_telemetry(snapshot())
                except Exception as exc:  # keep flying; telemetry is best effort
                    log.warning("telemetry publish failed: %s", exc)
                next_t += period
                self._stop.wait(max(0.0, next_t - time.monotonic()))

        self._telemetry_thread = threading.Thread(target=loop, name=f"fisc-telemetry-{self.agent_id}", daemon=True)
        self._telemetry_thread.start()
