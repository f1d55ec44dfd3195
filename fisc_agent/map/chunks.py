"""Map transport chunks and their reassembly with bounded memory (pure apart from the clock).

A map (the ``.fiscmap`` bytes) travels as chunks, each a ``CHUNK_HEADER`` (72 bytes) followed
by a slice of the map::

    b"FMCH", u8 version (1), u8 kind (1 chunk, 2 announce), u16 reserved,
    u64 map_version, 32s sha256 of the whole map bytes, u64 total bytes,
    u32 chunk index, u32 chunk count, u64 byte offset of this chunk

The header is not authenticated (the map's own seal is), so ``MapAssembler`` treats every
header as a claim by a possibly hostile peer:

- memory is spent only on bytes actually received (no buffer of the claimed size up front):
  chunks that arrive in order are appended to one growing buffer (hashed as they come),
  chunks ahead of it are kept until the gap fills;
- every byte buffered, plus ``CHUNK_OVERHEAD_BYTES`` per chunk, is charged to one budget
  (``AssemblyLimits.budget_bytes``, per swarm link); over budget, the lowest-priority map in
  progress is dropped;
- at most ``max_pending`` maps in progress; a map with no chunk for ``stall_timeout_s`` is
  dropped; a new map takes the slot of the lowest-priority one.  Priority: a map the ground
  announced (kind 2) within ``announce_ttl_s`` first, then the most recent chunk.  A map's
  claimed ``map_version`` buys it nothing here: it only has to be above the installed one;
- maps claiming a ``map_version`` not above the installed one, maps over the size limit and
  completed maps are remembered by sha256 in bounded LRU caches (``max_remembered``), so a
  replay is refused once and then ignored cheaply.

Everything the assembler drops without raising is reported as an ``AssemblyDrop`` (drained
with ``drain_drops``) so that the caller can count and log it.
"""

from __future__ import annotations

import hashlib
import struct
from collections import OrderedDict
from dataclasses import dataclass, replace
from enum import Enum

from fisc_agent.map.codec import MapError, MapErrorKind

DEFAULT_CHUNK_BYTES = 1 << 20
DEFAULT_MAX_MAP_BYTES = 1 << 30

CHUNK_MAGIC = b"FMCH"
CHUNK_VERSION = 1
KIND_CHUNK = 1
KIND_ANNOUNCE = 2
CHUNK_HEADER = struct.Struct("<4sBBHQ32sQIIQ")
CHUNK_OVERHEAD_BYTES = 256
"""Bookkeeping charged to the budget per chunk held (set entry, dict entry, object headers)."""


@dataclass(frozen=True)
class ChunkHeader:
    """Header of one map-transport message."""

    kind: int
    """``KIND_CHUNK`` or ``KIND_ANNOUNCE``."""
    map_version: int
    """map_version claimed for the map (checked against the decoded map)."""
    sha256: bytes
    """sha256 of the complete map bytes (32 raw bytes)."""
    total_bytes: int
    """Size of the complete map [bytes]."""
    index: int
    """Chunk index (0 for an announcement)."""
    count: int
    """Number of chunks of the map."""
    offset: int
    """Byte offset of this chunk in the map."""


def split_map(blob: bytes, map_version: int, chunk_bytes: int = DEFAULT_CHUNK_BYTES) -> list[bytes]:
    """Map bytes -> transport messages (header + slice), in order."""
    if chunk_bytes <= 0:
        raise ValueError("chunk_bytes must be > 0")
    sha = hashlib.sha256(blob).digest()
    count = max(1, -(-len(blob) // chunk_bytes))
    view = memoryview(blob)
    return [CHUNK_HEADER.pack(CHUNK_MAGIC, CHUNK_VERSION, KIND_CHUNK, 0, map_version, sha, len(blob), i, count,
                              i * chunk_bytes) + view[i * chunk_bytes:(i + 1) * chunk_bytes]
            for i in range(count)]


def announce_message(blob_sha256: bytes, map_version: int, total_bytes: int, count: int) -> bytes:
    """The periodic 'current map is ...' message (no data)."""
    return CHUNK_HEADER.pack(CHUNK_MAGIC, CHUNK_VERSION, KIND_ANNOUNCE, 0, map_version, blob_sha256, total_bytes,
                             0, count, 0)


def parse_chunk(msg: bytes | memoryview) -> tuple[ChunkHeader, memoryview]:
    """Split a transport message into header and data; ``MapError`` if malformed."""
    view = memoryview(msg)
    if len(view) < CHUNK_HEADER.size:
        raise MapError(MapErrorKind.CHUNKS, f"message of {len(view)} bytes is shorter than the chunk header")
    magic, version, kind, _, map_version, sha, total, index, count, offset = CHUNK_HEADER.unpack_from(view)
    if magic != CHUNK_MAGIC:
        raise MapError(MapErrorKind.CHUNKS, "bad magic (not a FISC map chunk)")
    if version != CHUNK_VERSION:
        raise MapError(MapErrorKind.CHUNKS, f"chunk format {version} is not supported")
    if kind not in (KIND_CHUNK, KIND_ANNOUNCE):
        raise MapError(MapErrorKind.CHUNKS, f"unknown message kind {kind}")
    data = view[CHUNK_HEADER.size:]
    if kind == KIND_CHUNK and (index >= count or offset + len(data) > total or (count > 1 and len(data) == 0)):
        raise MapError(MapErrorKind.CHUNKS, f"chunk {index}/{count} at offset {offset} does not fit a {total}-byte map")
    return ChunkHeader(kind, map_version, sha, total, index, count, offset), data


# --------------------------------------------------------------------------------------------
# Reassembly

@dataclass(frozen=True)
class AssemblyLimits:
    """Resource limits of one ``MapAssembler`` (one swarm link)."""

    max_map_bytes: int = DEFAULT_MAX_MAP_BYTES
    """Largest map accepted [bytes]; a header claiming more is refused at once."""
    budget_bytes: int = DEFAULT_MAX_MAP_BYTES + (64 << 20)
    """Bytes all maps in progress may hold together (received data + per-chunk overhead)."""
    max_pending: int = 4
    """Maps in progress at once."""
    stall_timeout_s: float = 10.0
    """A map in progress with no new chunk for this long is dropped [s]."""
    announce_ttl_s: float = 5.0
    """An announcement gives its map priority for this long [s] (the ground repeats it every second)."""
    max_announced: int = 8
    """Announcements remembered (most recent first)."""
    max_remembered: int = 256
    """Completed and refused map hashes remembered (each cache)."""

    def __post_init__(self) -> None:
        for name in ("max_map_bytes", "budget_bytes", "max_pending", "max_announced", "max_remembered"):
            if getattr(self, name) < 1:
                raise ValueError(f"AssemblyLimits.{name} must be >= 1, got {getattr(self, name)}")
        for name in ("stall_timeout_s", "announce_ttl_s"):
            if not getattr(self, name) > 0:
                raise ValueError(f"AssemblyLimits.{name} must be > 0, got {getattr(self, name)}")


class DropReason(str, Enum):
    """Why a map (or a chunk of one) was dropped without an exception."""

    OLD_VERSION = "old_version"
    """The header claims a map_version not above the installed map's (a replayed or rolled-back map)."""
    TIMEOUT = "timeout"
    """No chunk of this map for ``stall_timeout_s``."""
    EVICTED = "evicted"
    """Its slot went to a map of higher priority."""
    BUDGET = "budget"
    """The byte budget was exhausted and this was the lowest-priority map."""
    NO_SLOT = "no_slot"
    """A new map not started: every slot holds a map of higher priority (announced)."""


@dataclass(frozen=True)
class AssemblyDrop:
    """One map (or chunk) dropped by the assembler."""

    reason: DropReason
    """Why."""
    head: ChunkHeader
    """Header of the chunk that started (or triggered) the drop."""
    received_bytes: int
    """Bytes of that map received before it was dropped."""


class _LRU:
    """A bounded set of keys (oldest forgotten first) with a value per key."""

    def __init__(self, size: int) -> None:
        self.size = size
        self._d: OrderedDict = OrderedDict()

    def add(self, key: bytes, value: object = True) -> None:
        self._d[key] = value
        self._d.move_to_end(key)
        while len(self._d) > self.size:
            self._d.popitem(last=False)

    def discard(self, key: bytes) -> None:
        self._d.pop(key, None)

    def get(self, key: bytes, default: object = None) -> object:
        return self._d.get(key, default)

    def __contains__(self, key: object) -> bool:
        return key in self._d

    def __len__(self) -> int:
        return len(self._d)


class _Assembly:
    """One map in progress: a contiguous, incrementally hashed prefix plus chunks ahead of it."""

    __slots__ = ("head", "buf", "ahead", "have", "cost", "hasher", "last_chunk_s")

    def __init__(self, head: ChunkHeader, now_s: float) -> None:
        self.head = head
        self.buf = bytearray()
        self.ahead: dict[int, bytes] = {}
        self.have: set[int] = set()
        self.cost = 0
        self.hasher = hashlib.sha256()
        self.last_chunk_s = now_s

    @property
    def received(self) -> int:
        return len(self.buf) + sum(len(b) for b in self.ahead.values())

    def add(self, head: ChunkHeader, data: memoryview) -> int:
        """Take one chunk; returns the bytes charged (0 for a duplicate)."""
        if head.index in self.have:
            return 0
        end = len(self.buf)
        if head.offset == end:
            self.buf += data
            self.hasher.update(data)
            while len(self.buf) in self.ahead:  # the gap closed: move what followed it
                nxt = self.ahead.pop(len(self.buf))
                self.buf += nxt
                self.hasher.update(nxt)
        elif head.offset > end:
            if head.offset in self.ahead:
                raise MapError(MapErrorKind.CHUNKS,
                               f"two chunks claim offset {head.offset} (corrupted or forged chunks)")
            self.ahead[head.offset] = bytes(data)
        else:
            raise MapError(MapErrorKind.CHUNKS,
                           f"chunk {head.index} at offset {head.offset} overlaps bytes already received "
                           "(corrupted or forged chunks)")
        self.have.add(head.index)
        charged = len(data) + CHUNK_OVERHEAD_BYTES
        self.cost += charged
        return charged

    @property
    def complete(self) -> bool:
        return len(self.have) >= self.head.count


class MapAssembler:
    """Reassembles maps from chunks (any order, duplicates ignored) within ``AssemblyLimits``.

    ``feed(msg, now_s)`` returns ``(header, blob)`` when a map completes (``blob`` is a
    bytearray whose sha256 matched the header's) and ``(header, None)`` otherwise.  Raises
    ``MapError`` for a malformed chunk, a map over the size limit (once per map), chunks that
    overlap, and a completed map whose bytes do not hash to its header: each is a refusal to
    count.  Everything dropped without an exception is listed by ``drain_drops``.
    """

    def __init__(self, max_bytes: int | None = None, max_pending: int | None = None,
                 limits: AssemblyLimits | None = None) -> None:
        limits = limits or AssemblyLimits()
        if max_bytes is not None:
            limits = replace(limits, max_map_bytes=int(max_bytes), budget_bytes=max(limits.budget_bytes, int(max_bytes)))
        if max_pending is not None:
            limits = replace(limits, max_pending=int(max_pending))
        self.limits = limits
        self.floor_version = 0
        self.current_sha256: bytes | None = None
        """sha256 of the installed map (its chunks are ignored, not refused)."""
        self.pending: dict[bytes, _Assembly] = {}
        self.buffered_bytes = 0
        """Bytes charged to the budget right now (received data + per-chunk overhead)."""
        self.done = _LRU(limits.max_remembered)
        """sha256 of maps completed (handed out, or refused after completion)."""
        self.refused = _LRU(limits.max_remembered)
        """sha256 -> reason of maps refused by their header (old version, too large)."""
        self._announced: OrderedDict[bytes, tuple[int, float]] = OrderedDict()
        self._drops: list[AssemblyDrop] = []

    @property
    def max_bytes(self) -> int:
        """Largest map accepted [bytes]."""
        return self.limits.max_map_bytes

    # ---- queries -----------------------------------------------------------------------
    def announced(self, sha256: bytes, now_s: float) -> bool:
        """True when ``sha256`` was announced within ``announce_ttl_s``."""
        got = self._announced.get(sha256)
        return got is not None and now_s - got[1] <= self.limits.announce_ttl_s

    def progressing(self, sha256: bytes, now_s: float, within_s: float) -> bool:
        """True when chunks of this map arrived within the last ``within_s`` seconds."""
        asm = self.pending.get(sha256)
        return asm is not None and now_s - asm.last_chunk_s < within_s

    def wanted(self, head: ChunkHeader) -> bool:
        """An announced map worth fetching: newer than the installed one, not completed or refused."""
        return head.map_version > self.floor_version and head.sha256 not in self.done \
            and head.sha256 not in self.refused

    def drain_drops(self) -> list[AssemblyDrop]:
        """Maps and chunks dropped since the last call (oldest first)."""
        drops, self._drops = self._drops, []
        return drops

    # ---- the work ----------------------------------------------------------------------
    def _priority(self, asm: _Assembly, now_s: float) -> tuple[bool, float]:
        return self.announced(asm.head.sha256, now_s), asm.last_chunk_s

    def _drop(self, asm: _Assembly, reason: DropReason) -> None:
        del self.pending[asm.head.sha256]
        self.buffered_bytes -= asm.cost
        self._drops.append(AssemblyDrop(reason, asm.head, asm.received))

    def expire(self, now_s: float) -> None:
        """Drop maps in progress that stalled for ``stall_timeout_s``."""
        for asm in [a for a in self.pending.values() if now_s - a.last_chunk_s > self.limits.stall_timeout_s]:
            self._drop(asm, DropReason.TIMEOUT)

    def _note_announce(self, head: ChunkHeader, now_s: float) -> None:
        self._announced[head.sha256] = (head.map_version, now_s)
        self._announced.move_to_end(head.sha256)
        while len(self._announced) > self.limits.max_announced:
            self._announced.popitem(last=False)

    def feed(self, msg: bytes | memoryview, now_s: float = 0.0,
             verify: bool = True) -> tuple[ChunkHeader, bytearray | None]:
        """Take one transport message (``verify`` is accepted for compatibility: the sha256 is
        always checked, incrementally, as the chunks arrive)."""
        head, data = parse_chunk(msg)
        self.expire(now_s)
        if head.kind == KIND_ANNOUNCE:
            self._note_announce(head, now_s)
            return head, None
        sha = head.sha256
        if head.map_version <= self.floor_version and sha != self.current_sha256:
            if self.refused.get(sha) != DropReason.OLD_VERSION:  # reported once per map
                self.refused.add(sha, DropReason.OLD_VERSION)
                self._drops.append(AssemblyDrop(DropReason.OLD_VERSION, head, 0))
            return head, None
        if sha in self.done or sha in self.refused:
            return head, None
        if head.total_bytes > self.limits.max_map_bytes or head.total_bytes > self.limits.budget_bytes:
            self.refused.add(sha, "too_large")
            limit = min(self.limits.max_map_bytes, self.limits.budget_bytes)
            raise MapError(MapErrorKind.CHUNKS, f"map of {head.total_bytes} bytes exceeds the {limit}-byte limit")
        asm = self.pending.get(sha)
        if asm is None:
            if len(self.pending) >= self.limits.max_pending:
                victim = min(self.pending.values(), key=lambda a: self._priority(a, now_s))
                if self._priority(victim, now_s) > (self.announced(sha, now_s), now_s):
                    self._drops.append(AssemblyDrop(DropReason.NO_SLOT, head, 0))
                    return head, None
                self._drop(victim, DropReason.EVICTED)
            asm = self.pending[sha] = _Assembly(head, now_s)
        elif (asm.head.total_bytes, asm.head.count, asm.head.map_version) != (head.total_bytes, head.count,
                                                                              head.map_version):
            raise MapError(MapErrorKind.CHUNKS, "chunk disagrees with earlier chunks of the same map")
        asm.last_chunk_s = now_s
        try:
            charged = asm.add(head, data)
        except MapError:
            self._drop(asm, DropReason.EVICTED)
            self._drops.pop()  # reported by the exception instead
            raise
        self.buffered_bytes += charged
        while self.buffered_bytes > self.limits.budget_bytes and self.pending:
            victim = min(self.pending.values(), key=lambda a: self._priority(a, now_s))
            self._drop(victim, DropReason.BUDGET)
            if victim is asm:
                return head, None
        if not asm.complete:
            return head, None
        del self.pending[sha]
        self.buffered_bytes -= asm.cost
        self.done.add(sha)
        if asm.ahead or len(asm.buf) != head.total_bytes:
            self.done.discard(sha)
            raise MapError(MapErrorKind.CHUNKS,
                           "chunk sizes do not add up to the map size (corrupted or forged chunks)")
        if asm.hasher.digest() != sha:
            self.done.discard(sha)  # a later query may bring good chunks
            raise MapError(MapErrorKind.CHUNKS,
                           "reassembled map does not match its sha256 (corrupted or forged chunks)")
        return head, asm.buf

    def verify(self, head: ChunkHeader, blob: bytearray) -> None:
        """Check a completed map against its header's sha256 again; on mismatch forget it and
        raise ``MapError`` (``feed`` already did this incrementally)."""
        if hashlib.sha256(blob).digest() != head.sha256:
            self.done.discard(head.sha256)
            raise MapError(MapErrorKind.CHUNKS,
                           "reassembled map does not match its sha256 (corrupted or forged chunks)")

    def accept(self, map_version: int, sha256: bytes | None = None) -> None:
        """A map of this version (and sha256) was installed: drop everything not newer.  Chunks
        of the installed map are ignored from then on; chunks of any other map not newer,
        including maps installed before (a replay), are refused as ``OLD_VERSION``."""
        self.floor_version = max(self.floor_version, int(map_version))
        if sha256 is not None:
            self.current_sha256 = bytes(sha256)
        for asm in [a for a in self.pending.values() if a.head.map_version <= self.floor_version]:
            del self.pending[asm.head.sha256]
            self.buffered_bytes -= asm.cost
