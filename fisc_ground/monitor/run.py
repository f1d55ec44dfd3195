"""Ground-station monitor: Zenoh telemetry -> live per-CV swarm fields, fleet state, alarms.

Data path (nothing in it waits on the screen)::

    Zenoh callback --(bounded queue, drop counter)--> consumer thread --> recorder (--record, MCAP)
                                                                      \\-> TelemetryAggregator
                                                                      \\-> Foxglove scene (--foxglove)
    renderer (rich Live, its own pace) <-- aggregator.view() under a lock

The aggregator (``fisc_ground.monitor.aggregator``) is pure and deterministic in the message
sequence; this module holds the threads (``TelemetryPipe``), the map follower and the
``fisc-ground monitor`` handler; the dashboard is ``fisc_ground.monitor.view``.
"""

from __future__ import annotations

import logging
import math
import queue
import threading
import time
from typing import Any

import numpy as np

from fisc_agent.map.codec import CommandMap
from fisc_agent.zenoh.keys import Keys
from fisc_ground.monitor.flight_log import FlightLog, LogSettings
from fisc_ground.monitor.alarms import LOW_BATTERY_PCT
from fisc_ground.monitor.aggregator import (  # noqa: F401 - DEFAULT_MAX_AGENTS: imported from here by the CLI
    DEFAULT_MAX_AGENTS,
    NO_AGENT,
    AgentRoster,
    FleetView,
    TelemetryAggregator,
)
from fisc_ground.monitor.view import render

log = logging.getLogger(__name__)

# --------------------------------------------------------------------------------------------
# Zenoh -> queue -> consumer

class TelemetryPipe:
    """Zenoh subscriber feeding an aggregator (and optionally a flight log) through a bounded queue.

    The Zenoh callback never blocks: when the queue is full the message is counted in
    ``dropped``.  The consumer thread writes each batch to the flight log first (``--record``
    MCAP, ``--foxglove`` server), then ingests it and lets the log publish the scene, so a slow
    *renderer* (which only reads ``view()``) can never cause a loss.
    """

    def __init__(self, keys: Keys, aggregator: TelemetryAggregator, recorder: FlightLog | None = None,
                 maxsize: int = 200_000, batch: int = 8192) -> None:
        self.keys = keys
        self.aggregator = aggregator
        self.recorder = recorder
        self.lock = threading.Lock()
        self.dropped = 0
        self.received = 0
        self.worker_errors = 0
        """Batches the consumer failed to process (each logged; the consumer keeps running)."""
        self.lost_to_errors = 0
        """Messages in those batches (not ingested; recorded if the failure came after recording)."""
        self.last_error = ""
        """``Type: message`` of the newest worker error (shown on the dashboard)."""
        self._error_types: set[str] = set()
        self._q: queue.Queue = queue.Queue(maxsize)
        self._batch = int(batch)
        self._stop = threading.Event()
        self._sub = None
        self._thread = threading.Thread(target=self._consume, name="fisc-monitor-consumer", daemon=True)
        self._thread.start()

    def attach(self, session: Any) -> "TelemetryPipe":
        """Subscribe to every agent's telemetry of the swarm on ``session``."""
        self._sub = session.declare_subscriber(self.keys.all_telemetry, self.on_sample)
        return self

    def on_sample(self, sample: Any) -> None:
        """Zenoh subscriber callback: enqueue the sample with its receive time."""
        self.offer(time.time(), str(sample.key_expr), sample.payload.to_bytes())

    def offer(self, recv_s: float, key: str, payload: bytes) -> None:
        """Enqueue one message (never blocks; counts a drop when full)."""
        self.received += 1
        try:
            self._q.put_nowait((recv_s, key, payload))
        except queue.Full:
            self.dropped += 1

    def set_map(self, cmap: CommandMap, blob: bytes | None = None) -> None:
        """Switch the aggregator (and the recording) to a map, in stream order."""
        self._q.put(("map", cmap, blob))

    def _consume(self) -> None:
        while not self._stop.is_set() or not self._q.empty():
            try:
                items = [self._q.get(timeout=0.05)]
            except queue.Empty:
                continue
            while len(items) < self._batch:
                try:
                    items.append(self._q.get_nowait())
                except queue.Empty:
                    break
            try:
                self._process(items)
            except Exception as exc:  # noqa: BLE001 - no message may kill the consumer: count, log, show
                self._worker_error(exc, items)
            finally:
                for _ in items:
                    self._q.task_done()

    def _worker_error(self, exc: Exception, items: list) -> None:
        name = type(exc).__name__
        self.worker_errors += 1
        self.lost_to_errors += sum(1 for it in items if it[0] != "map")
        self.last_error = f"{name}: {exc}"
        if name not in self._error_types:  # full traceback once per exception type, then a count
            self._error_types.add(name)
            log.error("monitor worker: a batch of %d items failed (%s); the worker keeps running",
                      len(items), self.last_error, exc_info=exc)
        else:
            log.debug("monitor worker: batch failed again (%s), %d failures so far", self.last_error,
                      self.worker_errors)

    def _process(self, items: list) -> None:
        run: list = []
        for it in items:
            if it[0] == "map":
                self._flush_run(run)
                run = []
                _, cmap, blob = it
                if self.recorder is not None and blob is not None:
                    last = self.aggregator.last_receive_s
                    self.recorder.write_map(last if math.isfinite(last) else time.time(), blob, cmap)
                with self.lock:
                    self.aggregator.set_map(cmap)
            else:
                run.append(it)
        self._flush_run(run)

    def _flush_run(self, run: list) -> None:
        if not run:
            return
        recv = np.fromiter((r[0] for r in run), dtype=float, count=len(run))
        ids = np.fromiter((_key_id(self.keys, r[1]) for r in run), dtype=np.int64, count=len(run))
        payloads = [r[2] for r in run]
        if self.recorder is not None:
            self.recorder.write_telemetry(recv, ids, payloads)
        with self.lock:
            self.aggregator.ingest(recv, ids, payloads)
            if self.recorder is not None:
                self.recorder.publish(self.aggregator)

    def drain(self, timeout_s: float = 10.0) -> bool:
        """Wait until everything queued so far is processed."""
        end = time.monotonic() + timeout_s
        while self._q.unfinished_tasks and time.monotonic() < end:
            time.sleep(0.01)
        return not self._q.unfinished_tasks

    def view(self) -> FleetView:
        """The aggregator's fleet view now (under the pipe's lock)."""
        with self.lock:
            return self.aggregator.view(time.time())

    def close(self) -> None:
        """Undeclare the subscriber and stop the consumer thread."""
        if self._sub is not None:
            self._sub.undeclare()
            self._sub = None
        self._stop.set()
        self._thread.join(timeout=10.0)


def _key_id(keys: Keys, key: str) -> int:
    """Agent id from a telemetry key; ``NO_AGENT`` unless it is a u32 below ``NO_AGENT``
    (``.../agents/99999999999999999999/telemetry`` names no agent)."""
    aid = keys.agent_of(key)
    return aid if aid is not None and 0 <= aid < NO_AGENT else NO_AGENT


# --------------------------------------------------------------------------------------------
# Map discovery for the monitor

def verify_monitor_map(blob: bytes | bytearray, trusted_keys: list[bytes] | None, allow_unsigned: bool,
                       claimed_version: int | None = None, source: str = "<zenoh>") -> CommandMap:
    """The monitor's rule for a map: with trusted keys, signed by one of them; without, any valid
    signature; an unsigned map only with ``allow_unsigned`` (``MapError`` names the refusal)."""
    from fisc_agent.map.codec import MapError, MapErrorKind
    from fisc_agent.zenoh.maps import verify_map_bytes

    if trusted_keys:
        return verify_map_bytes(blob, trusted_keys, allow_unsigned=False, claimed_version=claimed_version,
                                source=source)
    cmap = verify_map_bytes(blob, None, allow_unsigned=True, claimed_version=claimed_version, source=source)
    if not cmap.signed and not allow_unsigned:
        raise MapError(MapErrorKind.SIGNATURE, "the map is unsigned (refused; --allow-unsigned accepts it in a lab)",
                       source=source)
    return cmap


def fetch_map(session: Any, keys: Keys, trusted_keys: list[bytes] | None, timeout_s: float = 5.0,
              allow_unsigned: bool = False) -> tuple[CommandMap, bytes] | None:
    """Query the swarm's current map, verified by ``verify_monitor_map``."""
    import zenoh

    from fisc_agent.map.codec import MapError
    from fisc_agent.map.chunks import MapAssembler

    asm = MapAssembler()
    for reply in session.get(keys.map, consolidation=zenoh.QueryConsolidation(zenoh.ConsolidationMode.NONE),
                             timeout=timeout_s):
        if reply.ok is None:
            continue
        try:
            head, blob = asm.feed(reply.ok.payload.to_bytes())
        except MapError as exc:
            log.warning("map chunk refused: %s", exc)
            continue
        if blob is not None:
            cmap = verify_monitor_map(blob, trusted_keys, allow_unsigned, claimed_version=head.map_version,
                                      source=keys.map)
            return cmap, bytes(blob)
    return None


class MapFollower:
    """Keeps the monitor on the swarm's current map: on an announcement of a newer map, fetch
    and verify it, then switch the pipe to it (in stream order, so replays switch there too)."""

    def __init__(self, session: Any, keys: Keys, pipe: TelemetryPipe, trusted_keys: list[bytes] | None,
                 current_version: int = 0, allow_unsigned: bool = False) -> None:
        self.session, self.keys, self.pipe, self.trusted = session, keys, pipe, trusted_keys
        self.allow_unsigned = bool(allow_unsigned)
        self.version = int(current_version)
        self.refused: set[int] = set()
        """map_versions announced, fetched and refused (not fetched again)."""
        self._busy = threading.Lock()
        self._sub = session.declare_subscriber(keys.map, self._on_sample)

    def _on_sample(self, sample: Any) -> None:
        from fisc_agent.map.codec import MapError
        from fisc_agent.map.chunks import KIND_ANNOUNCE, parse_chunk

        try:
            head, _ = parse_chunk(sample.payload.to_bytes()[:96])
        except MapError:
            return
        if head.kind == KIND_ANNOUNCE and head.map_version > self.version and head.map_version not in self.refused \
                and self._busy.acquire(blocking=False):
            threading.Thread(target=self._fetch, args=(head.map_version,), daemon=True, name="fisc-monitor-map").start()

    def _fetch(self, announced_version: int = 0) -> None:
        from fisc_agent.map.codec import MapError

        try:
            got = fetch_map(self.session, self.keys, self.trusted, allow_unsigned=self.allow_unsigned)
            if got is not None and got[0].map_version > self.version:
                self.version = got[0].map_version
                self.pipe.set_map(*got)
                log.info("monitor switched to map %s (map_version %d)", got[0].sha256[:12], self.version)
        except MapError as exc:
            self.refused.add(announced_version)
            log.warning("newer map announced but refused: %s", exc)
        finally:
            self._busy.release()

    def close(self) -> None:
        """Stop following the map key."""
        self._sub.undeclare()


def run_monitor(args: Any) -> int:
    """``fisc-ground monitor --swarm NAME [--map MAP] [--record FILE.mcap] [--foxglove [PORT]] [--duration S]``."""
    from rich.console import Console
    from rich.live import Live

    from fisc_agent.map.codec import MAGIC, MAX_MAP_FILE_BYTES, MapError, MapFileError, read_public_key
    from fisc_agent.common.safe_files import read_regular_file
    from fisc_ground.zenoh.config import open_ground_session, silence_hint, zenoh_neighbours

    keys = Keys(args.prefix, args.swarm)
    trusted = [read_public_key(p) for p in (args.trusted_key or [])]
    roster = args.roster if args.roster is None or isinstance(args.roster, AgentRoster) else AgentRoster.parse(args.roster)
    if args.map:  # read before opening the session: a bad file fails fast
        map_file_blob = read_regular_file(args.map, what="FISC map", max_bytes=MAX_MAP_FILE_BYTES, magic=MAGIC,
                                          error=MapFileError)
        map_file = verify_monitor_map(map_file_blob, trusted, args.allow_unsigned, source=str(args.map))
    console = Console(stderr=False)
    session = open_ground_session(args.zenoh_config)
    recorder = None
    try:
        cmap, blob = None, None
        if args.map:
            cmap, blob = map_file, map_file_blob
        else:
            try:
                got = fetch_map(session, keys, trusted, timeout_s=args.map_timeout, allow_unsigned=args.allow_unsigned)
                if got is None:
                    log.warning("no map on %s yet: showing fleet state only", keys.map)
            except MapError as exc:  # e.g. a map signed by a stranger: the fleet is what to watch now
                log.error("the swarm's map was refused (%s): showing fleet state only", exc)
                got = None
            if got is not None:
                cmap, blob = got
        low_battery = getattr(args, "low_battery", LOW_BATTERY_PCT)
        agg = TelemetryAggregator(None, sample_period_s=args.sample_period, stale_after_s=args.stale_after,
                                  roster=roster, max_agents=args.max_agents, low_battery_pct=low_battery)
        foxglove_port = getattr(args, "foxglove", None)
        if args.record or foxglove_port is not None:
            recorder = FlightLog(LogSettings(sample_period_s=args.sample_period, stale_after_s=args.stale_after,
                                             swarm=args.swarm, prefix=args.prefix,
                                             roster=roster.spec() if roster else None, max_agents=args.max_agents,
                                             low_battery_pct=low_battery),
                                 mcap_path=args.record, ws_port=foxglove_port)
            if recorder.port is not None:
                console.print(f"Foxglove WebSocket: ws://127.0.0.1:{recorder.port} (open it in Foxglove; "
                              "layout: docs/foxglove_layout.json)")
        pipe = TelemetryPipe(keys, agg, recorder)
        if cmap is not None:
            pipe.set_map(cmap, blob)
        pipe.attach(session)
        follower = None if args.map else MapFollower(session, keys, pipe, trusted,
                                                     cmap.map_version if cmap is not None else 0,
                                                     allow_unsigned=args.allow_unsigned)
        end = time.monotonic() + args.duration if args.duration else math.inf
        started, hinted = time.monotonic(), False
        title = f"FISC swarm {args.swarm}" + (f"  recording {args.record}" if args.record else "") + (
            f"  Foxglove ws://127.0.0.1:{recorder.port}" if recorder is not None and recorder.port else "")
        try:
            with Live(console=console, refresh_per_second=4, screen=False) as live:
                while time.monotonic() < end:
                    with pipe.lock:
                        view = agg.view(time.time())
                        fields = agg.fields()
                        shown_map = agg.cmap
                    if recorder is not None:  # silence too ("every agent stale") reaches the log
                        recorder.log_alarms(view)
                    live.update(render(view, fields, shown_map, pipe.dropped, title, pipe.worker_errors,
                                       pipe.last_error))
                    hint = None if hinted or view.n_agents else silence_hint(
                        0, time.monotonic() - started, keys, args.zenoh_config, zenoh_neighbours(session))
                    if hint:  # once: why nobody is heard and what to start
                        log.warning("%s", hint)
                        hinted = True
                    time.sleep(0.5)
        except KeyboardInterrupt:
            pass
        if follower is not None:
            follower.close()
        pipe.close()
        console.print(f"{pipe.received} messages received, {pipe.dropped} dropped"
                      + (f", {pipe.worker_errors} worker errors ({pipe.lost_to_errors} messages lost; "
                         f"last: {pipe.last_error})" if pipe.worker_errors else "")
                      + (f", recorded to {args.record}" if args.record else ""))
    finally:
        if recorder is not None:
            recorder.close()
        session.close()
    return 0
