"""Compact binary agent telemetry (``fisc/<swarm>/agents/<id>/telemetry``), pure codec.

One message is a fixed 104-byte little-endian record; byte 0 is the format version so that a
ground station can refuse (and name) a format it does not know.  Version 1 layout::

    off size field
      0  u8   version (1)
      1  u8   state code (index into ``STATES``; 0 = unknown)
      2  u8   flags (``FLAG_*`` bits)
      3  u8   reason code of the last refused map (index into ``REJECT_REASONS``)
      4  u32  agent id
      8  u32  message sequence number (wraps)
     12  f64  time of the snapshot, UNIX seconds
     20  3f32 position, map frame [m]
     32  3f32 velocity, map frame [m/s]
     44  i32  CV index (-1 outside the map / unknown)
     48  u64  map_version of the map being flown (0 = none)
     56  32s  sha256 of that map (raw digest; zeros = none)
     88  u16  maps refused so far (saturating)
     90  u16  position age [ms] (saturates at 65534; 65535 = none)
     92  u16  autopilot heartbeat age [ms] (saturating)
     94  u8   code of the last fleet command accepted (index into ``ACK_COMMANDS``)
     95  u8   reserved (0)
     96  u64  sequence number of the last fleet command accepted (the acknowledgement)

``decode_many`` decodes a batch into a numpy structured array (vectorised, for monitors that
take thousands of messages per second).
"""

from __future__ import annotations

import math
import struct
from dataclasses import dataclass, field
from typing import Iterable

import numpy as np

VERSION = 1

STATES = ("UNKNOWN", "WAIT_MAP", "WAIT_POSITION", "ARM", "TAKEOFF", "JOIN", "FLOW", "RETURN", "EXIT",
          "HOLD", "LAND", "DONE", "FAILSAFE", "STANDBY")
"""State names by code.  Mission states of ``fisc_agent.flight.mission.State`` plus WAIT_MAP (no map yet)."""

REJECT_REASONS = ("none", "truncated", "magic", "container", "sha256", "signature", "schema",
                  "schema_version", "header", "seal", "trailing", "version_mismatch", "chunks", "other",
                  "old_version")
"""Map-refusal reasons by code (the ``MapError`` check names, plus transport-level ones)."""

ACK_COMMANDS = ("none", "hold", "resume", "land", "start-at")

FLAG_OUTSIDE_MAP = 1 << 0
FLAG_FAILSAFE = 1 << 1
FLAG_MAP_UNSIGNED = 1 << 2
FLAG_MAVLINK_OK = 1 << 3
FLAG_POSITION_FRESH = 1 << 4
FLAG_ARMED = 1 << 5
FLAG_ZENOH_OK = 1 << 6
FLAG_NAMES = {"outside_map": FLAG_OUTSIDE_MAP, "failsafe": FLAG_FAILSAFE, "map_unsigned": FLAG_MAP_UNSIGNED,
              "mavlink_ok": FLAG_MAVLINK_OK, "position_fresh": FLAG_POSITION_FRESH, "armed": FLAG_ARMED,
              "zenoh_ok": FLAG_ZENOH_OK}

_STRUCT = struct.Struct("<BBBBIId3f3fiQ32sHHHBBQ")
SIZE = _STRUCT.size

DTYPE = np.dtype([
    ("version", "u1"), ("state", "u1"), ("flags", "u1"), ("reject_reason", "u1"),
    ("agent_id", "<u4"), ("seq", "<u4"), ("time_s", "<f8"),
    ("position_m", "<f4", (3,)), ("velocity_m_s", "<f4", (3,)), ("cv_index", "<i4"),
    ("map_version", "<u8"), ("map_sha256", "V32"), ("maps_rejected", "<u2"),
    ("position_age_ms", "<u2"), ("heartbeat_age_ms", "<u2"), ("ack_command", "u1"), ("reserved", "u1"),
    ("ack_seq", "<u8"),
])
assert DTYPE.itemsize == SIZE == 104


class TelemetryError(ValueError):
    """A telemetry message could not be decoded (the message says why)."""


@dataclass(frozen=True)
class Telemetry:
    """One agent telemetry message."""

    agent_id: int
    """Agent id (u32)."""
    seq: int
    """Message sequence number (u32, wraps)."""
    time_s: float
    """Time of the snapshot, UNIX seconds."""
    position_m: tuple[float, float, float]
    """Position in the map frame [m] (NaN if unknown)."""
    velocity_m_s: tuple[float, float, float]
    """Velocity in the map frame [m/s] (NaN if unknown)."""
    cv_index: int = -1
    """CV the agent is in, -1 outside the map or unknown."""
    state: str = "UNKNOWN"
    """State name (one of ``STATES``; anything else is sent as UNKNOWN)."""
    map_version: int = 0
    """map_version of the map flown, 0 for none."""
    map_sha256: str = ""
    """Hex sha256 of the map flown, "" for none."""
    flags: frozenset[str] = field(default_factory=frozenset)
    """Set flags by name (keys of ``FLAG_NAMES``)."""
    maps_rejected: int = 0
    """Maps refused so far."""
    reject_reason: str = "none"
    """Check that refused the last refused map (one of ``REJECT_REASONS``)."""
    position_age_s: float = math.inf
    """Age of the newest position [s] (inf: none); ms resolution, saturates at 65.534 s."""
    heartbeat_age_s: float = math.inf
    """Age of the newest autopilot heartbeat [s]; same encoding."""
    ack_command: str = "none"
    """Last fleet command accepted (one of ``ACK_COMMANDS``)."""
    ack_seq: int = 0
    """Sequence number of that command (0: none)."""


def _code(table: tuple[str, ...], name: str) -> int:
    try:
        return table.index(str(name))
    except ValueError:
        return table.index("other") if "other" in table else 0


def _age_ms(age_s: float) -> int:
    if not math.isfinite(age_s) or age_s < 0:
        return 0xFFFF
    return min(int(round(age_s * 1000.0)), 0xFFFE)


def encode(t: Telemetry) -> bytes:
    """Telemetry -> bytes (``SIZE`` long)."""
    flags = 0
    for name in t.flags:
        try:
            flags |= FLAG_NAMES[name]
        except KeyError:
            raise TelemetryError(f"unknown telemetry flag {name!r}; known: {sorted(FLAG_NAMES)}") from None
    sha = bytes.fromhex(t.map_sha256) if t.map_sha256 else b"\0" * 32
    if len(sha) != 32:
        raise TelemetryError(f"map_sha256 must be 64 hex digits, got {len(t.map_sha256)}")
    state = t.state.value if hasattr(t.state, "value") else t.state
    return _STRUCT.pack(
        VERSION, _code(STATES, state), flags, _code(REJECT_REASONS, t.reject_reason),
        int(t.agent_id) & 0xFFFFFFFF, int(t.seq) & 0xFFFFFFFF, float(t.time_s),
        *(float(v) for v in t.position_m), *(float(v) for v in t.velocity_m_s), int(t.cv_index),
        int(t.map_version), sha, min(int(t.maps_rejected), 0xFFFF), _age_ms(t.position_age_s),
        _age_ms(t.heartbeat_age_s), _code(ACK_COMMANDS, t.ack_command), 0, int(t.ack_seq))


def _check(data: bytes | bytearray | memoryview) -> None:
    if len(data) < 1:
        raise TelemetryError("telemetry: empty message")
    if data[0] != VERSION:
        raise TelemetryError(f"telemetry: format version {data[0]} is not supported (expected {VERSION})")
    if len(data) != SIZE:
        raise TelemetryError(f"telemetry: version-1 message has {SIZE} bytes, got {len(data)}")


def _name(table: tuple[str, ...], code: int) -> str:
    return table[code] if code < len(table) else table[0]


def decode(data: bytes | bytearray | memoryview) -> Telemetry:
    """bytes -> Telemetry; raises ``TelemetryError`` on a wrong version or size."""
    _check(data)
    (_, state, flags, reason, agent_id, seq, time_s, px, py, pz, vx, vy, vz, cv, map_version, sha,
     n_rej, pos_age, hb_age, ack_cmd, _, ack_seq) = _STRUCT.unpack(bytes(data))
    return Telemetry(
        agent_id=agent_id, seq=seq, time_s=time_s, position_m=(px, py, pz), velocity_m_s=(vx, vy, vz),
        cv_index=cv, state=_name(STATES, state), map_version=map_version,
        map_sha256="" if sha == b"\0" * 32 else sha.hex(),
        flags=frozenset(n for n, bit in FLAG_NAMES.items() if flags & bit), maps_rejected=n_rej,
        reject_reason=_name(REJECT_REASONS, reason),
        position_age_s=math.inf if pos_age == 0xFFFF else pos_age / 1000.0,
        heartbeat_age_s=math.inf if hb_age == 0xFFFF else hb_age / 1000.0,
        ack_command=_name(ACK_COMMANDS, ack_cmd), ack_seq=ack_seq)


def decode_many(messages: Iterable[bytes]) -> tuple[np.ndarray, np.ndarray]:
    """Decode a batch: returns ``(records, ok)`` where ``records`` is a structured array of
    ``DTYPE`` (one row per message, zeros for bad ones) and ``ok`` a bool mask of the messages
    with the right version and size."""
    msgs = list(messages)
    ok = np.array([len(m) == SIZE and m[0] == VERSION for m in msgs], dtype=bool)
    buf = b"".join(m if good else b"\0" * SIZE for m, good in zip(msgs, ok))
    records = np.frombuffer(buf, dtype=DTYPE).copy() if msgs else np.zeros(0, dtype=DTYPE)
    return records, ok


def sha_hex(records: np.ndarray) -> list[str]:
    """Hex map digests of a ``DTYPE`` array ("" where none)."""
    return ["" if bytes(r) == b"\0" * 32 else bytes(r).hex() for r in records["map_sha256"]]


def state_names(codes: np.ndarray) -> list[str]:
    """State names for an array of state codes."""
    return [_name(STATES, int(c)) for c in codes]
