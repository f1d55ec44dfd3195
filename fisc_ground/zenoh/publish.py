"""Serve the current command map of a swarm over Zenoh (``fisc-ground publish``).

``MapServer.serve(blob)`` makes a map current: it is pushed once as chunks on
``<prefix>/<swarm>/map`` (agents already running), answered to every query on that key (agents
that start later), and announced periodically (agents that missed chunks re-query).  A newer
map (higher ``map_version``) replaces the current one; an older or equal one is refused.
Transport format: ``fisc_agent.map.chunks`` (chunk header with the map's sha256, index, count).
"""

from __future__ import annotations

import logging
import threading
from pathlib import Path
from typing import Any

from fisc_agent.map.codec import CommandMap, MapError, MapErrorKind, MapFileError, decode_map
from fisc_agent.map.chunks import DEFAULT_CHUNK_BYTES, announce_message, parse_chunk, split_map
from fisc_agent.zenoh.keys import DEFAULT_PREFIX, Keys

log = logging.getLogger(__name__)


class MapServer:
    """Serves one swarm's current map on an open Zenoh session (thread-safe)."""

    def __init__(self, session: Any, swarm: str, prefix: str = DEFAULT_PREFIX,
                 chunk_bytes: int = DEFAULT_CHUNK_BYTES, announce_period_s: float = 1.0) -> None:
        import zenoh

        self.session = session
        self.keys = Keys(prefix, swarm)
        self.chunk_bytes = int(chunk_bytes)
        self.announce_period_s = float(announce_period_s)
        self.current: CommandMap | None = None
        self._chunks: list[bytes] = []
        self._announce: bytes | None = None
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._pub = session.declare_publisher(self.keys.map, congestion_control=zenoh.CongestionControl.BLOCK,
                                              reliability=zenoh.Reliability.RELIABLE)
        self._queryable = session.declare_queryable(self.keys.map, self._on_query)
        self._thread = threading.Thread(target=self._announce_loop, name="fisc-map-announce", daemon=True)
        self._thread.start()
        self.queries_answered = 0

    def serve(self, blob: bytes, source: str = "<map>") -> CommandMap:
        """Verify ``blob`` (hash and signature if present) and make it the current map."""
        cmap = decode_map(blob, source=source)
        if not cmap.signed:
            log.warning("serving an UNSIGNED map %s: agents refuse it unless started with --allow-unsigned",
                        cmap.sha256[:12])
        with self._lock:
            if self.current is not None and cmap.map_version <= self.current.map_version:
                raise MapError(MapErrorKind.OLD_VERSION, f"map_version {cmap.map_version} is not newer than the "
                               f"served {self.current.map_version}", source=source)
            chunks = split_map(bytes(blob), cmap.map_version, self.chunk_bytes)
            self.current, self._chunks = cmap, chunks
            head, _ = parse_chunk(chunks[0])
            self._announce = announce_message(head.sha256, cmap.map_version, head.total_bytes, head.count)
        log.info("serving map %s (map_version %d, %d bytes in %d chunks) on %s", cmap.sha256[:12],
                 cmap.map_version, len(blob), len(chunks), self.keys.map)
        for chunk in chunks:
            self._pub.put(chunk)
        return cmap

    def serve_file(self, path: str | Path) -> CommandMap:
        """Read a ``.fiscmap`` file and serve it."""
        from fisc_agent.map.codec import MAGIC, MAX_MAP_FILE_BYTES
        from fisc_agent.common.safe_files import read_regular_file

        data = read_regular_file(path, what="FISC map", max_bytes=MAX_MAP_FILE_BYTES, magic=MAGIC, error=MapFileError)
        return self.serve(data, source=str(path))

    def _on_query(self, query: Any) -> None:
        with self._lock:
            chunks = list(self._chunks)
        for chunk in chunks:
            query.reply(self.keys.map, chunk)
        self.queries_answered += 1

    def _announce_loop(self) -> None:
        while not self._stop.wait(self.announce_period_s):
            with self._lock:
                msg = self._announce
            if msg is not None:
                try:
                    self._pub.put(msg)
                except Exception as exc:  # session closed under us
                    log.debug("announce failed: %s", exc)
                    return

    def close(self) -> None:
        """Stop announcing and undeclare (the session stays open)."""
        self._stop.set()
        self._thread.join(timeout=5.0)
        for ent in (self._queryable, self._pub):
            try:
                ent.undeclare()
            except Exception as exc:
                log.debug("undeclare failed: %s", exc)

    def __enter__(self) -> "MapServer":
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()
