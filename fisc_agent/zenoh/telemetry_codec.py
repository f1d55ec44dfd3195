"""Compact binary agent telemetry (``fisc/<swarm>/agents/<id>/telemetry``), pure codec.

One message is a fixed 148-byte little-endian record; byte 0 is the format version so that a
ground station can refuse (and name) a format it does not know.  Version 2 layout::

    off size field
      0  u8   version (2)
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
    --- version 2 appends:
    104  u8   authority (index into ``AUTHORITIES``; 0 = unknown)
    105  u8   landed state (index into ``LANDED``; 0 = unknown)
    106  u8   battery [%] (0-100; 255 = not reported)
    107  u8   number of health problems (saturating)
    108  u16  health flags (``HEALTH_*`` bits: which kinds of problem)
    110  u8   reason of the newest refused fleet command (index into ``COMMAND_REFUSALS``)
    111  u8   the command it refused (index into ``ACK_COMMANDS``; 0 = did not decode)
    112  u16  fleet commands refused so far (saturating)
    114  u16  reserved (0)
    116  32s  the first health problem, UTF-8, NUL-padded (cut at a character boundary)

Version 1 (the first 104 bytes, version byte 1) still decodes: its version-2 fields read as
unknown / not reported.

``decode_many`` decodes a batch into a numpy structured array (vectorised, for monitors that
take thousands of messages per second).
"""

from __future__ import annotations

import math
import struct
from dataclasses import dataclass, field
from typing import Iterable

import numpy as np

VERSION = 2
V1_SIZE = 104
"""Size of a version-1 message (decoded too)."""

STATES = ("UNKNOWN", "WAIT_MAP", "WAIT_POSITION", "ARM", "TAKEOFF", "JOIN", "FLOW", "RETURN", "EXIT",
          "HOLD", "LAND", "DONE", "FAILSAFE", "STANDBY")
"""State names by code.  Mission states of ``fisc_agent.flight.mission.State`` plus WAIT_MAP (no map yet)."""

REJECT_REASONS = ("none", "truncated", "magic", "container", "sha256", "signature", "schema",
                  "schema_version", "header", "seal", "trailing", "version_mismatch", "chunks", "other",
                  "old_version")
"""Map-refusal reasons by code (the ``MapError`` check names, plus transport-level ones)."""

ACK_COMMANDS = ("none", "hold", "resume", "land", "start-at", "go", "takeover")
"""Fleet command names by code (``fisc_agent.zenoh.fleet_commands.CommandName``; append only)."""
AUTHORITIES = ("unknown", "waiting", "not-ours", "command", "hands-off", "released")
"""Authority by code (``fisc_agent.flight.mission_types.Authority`` values)."""
LANDED = ("unknown", "on-ground", "in-air", "takeoff", "landing")
"""Landed state by code (``fisc_agent.flight.health.LandedState`` values)."""
COMMAND_REFUSALS = ("none", "truncated", "magic", "version", "command", "size", "signature", "swarm", "start-at",
                    "target", "replay", "stale", "future", "address")
"""Fleet-command refusal reasons by code (``fisc_agent.zenoh.fleet_commands.CommandCheck`` values; append only)."""
NO_BATTERY = 255
"""Battery byte of "not reported"."""
HEALTH_TEXT_BYTES = 32

HEALTH_ESTIMATOR = 1 << 0
HEALTH_BATTERY = 1 << 1
HEALTH_SYSTEM = 1 << 2
HEALTH_POSITION = 1 << 3
HEALTH_GPS = 1 << 4
HEALTH_ORIGIN = 1 << 5
HEALTH_TAKEOFF = 1 << 6
HEALTH_OTHER = 1 << 15
HEALTH_NAMES = {"estimator": HEALTH_ESTIMATOR, "battery": HEALTH_BATTERY, "system": HEALTH_SYSTEM,
                "position": HEALTH_POSITION, "gps": HEALTH_GPS, "origin": HEALTH_ORIGIN, "takeoff": HEALTH_TAKEOFF,
                "other": HEALTH_OTHER}
"""Health flag bits by name: estimator unhealthy, battery low, autopilot system state critical or
worse, position reset or jump, GNSS, start far from the map's origin, take-off timed out, other."""

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

_STRUCT = struct.Struct("<BBBBIId3f3fiQ32sHHHBBQBBBBHBBHH32s")
SIZE = _STRUCT.size
_V1_PAD = bytes([0, 0, NO_BATTERY]) + bytes(SIZE - V1_SIZE - 3)

DTYPE = np.dtype([
    ("version", "u1"), ("state", "u1"), ("flags", "u1"), ("reject_reason", "u1"),
    ("agent_id", "<u4"), ("seq", "<u4"), ("time_s", "<f8"),
    ("position_m", "<f4", (3,)), ("velocity_m_s", "<f4", (3,)), ("cv_index", "<i4"),
    ("map_version", "<u8"), ("map_sha256", "V32"), ("maps_rejected", "<u2"),
    ("position_age_ms", "<u2"), ("heartbeat_age_ms", "<u2"), ("ack_command", "u1"), ("reserved", "u1"),
    ("ack_seq", "<u8"), ("authority", "u1"), ("landed", "u1"), ("battery_pct", "u1"), ("health_count", "u1"),
    ("health", "<u2"), ("cmd_refusal", "u1"), ("cmd_refused", "u1"), ("cmds_refused", "<u2"), ("reserved2", "<u2"),
    ("health_text", "S32"),
])
assert DTYPE.itemsize == SIZE == 148


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
    authority: str = "unknown"
    """Who is in charge of the vehicle (one of ``AUTHORITIES``)."""
    landed: str = "unknown"
    """Landed state (one of ``LANDED``)."""
    battery_pct: float | None = None
    """Remaining battery [%], whole percent (None: not reported)."""
    health: frozenset[str] = field(default_factory=frozenset)
    """Kinds of health problem (keys of ``HEALTH_NAMES``); empty: healthy or not reported."""
    health_count: int = 0
    """Number of health problems (0: healthy)."""
    health_text: str = ""
    """The first health problem in words (at most 32 UTF-8 bytes)."""
    commands_refused: int = 0
    """Fleet commands refused so far."""
    command_refusal: str = "none"
    """Reason of the newest refusal (one of ``COMMAND_REFUSALS``)."""
    refused_command: str = "none"
    """The command it refused (one of ``ACK_COMMANDS``; "none": it did not decode)."""


def _code(table: tuple[str, ...], name: str) -> int:
    try:
        return table.index(str(name))
    except ValueError:
        return table.index("other") if "other" in table else 0


def _age_ms(age_s: float) -> int:
    if not math.isfinite(age_s) or age_s < 0:
        return 0xFFFF
    return min(int(round(age_s * 1000.0)), 0xFFFE)


def _bits(names: frozenset[str], table: dict[str, int], what: str) -> int:
    bits = 0
    for name in names:
        try:
            bits |= table[name]
        except KeyError:
            raise TelemetryError(f"unknown {what} {name!r}; known: {sorted(table)}") from None
    return bits


def _battery(pct: float | None) -> int:
    if pct is None or not math.isfinite(pct):
        return NO_BATTERY
    return min(max(int(round(pct)), 0), 100)


def _text(text: str, size: int) -> bytes:
    raw = text.encode()[:size]
    return raw.decode(errors="ignore").encode()  # cut at a character boundary


def encode(t: Telemetry) -> bytes:
    """Telemetry -> bytes (``SIZE`` long)."""
    flags = _bits(t.flags, FLAG_NAMES, "telemetry flag")
    health = _bits(t.health, HEALTH_NAMES, "health flag")
    sha = bytes.fromhex(t.map_sha256) if t.map_sha256 else b"\0" * 32
    if len(sha) != 32:
        raise TelemetryError(f"map_sha256 must be 64 hex digits, got {len(t.map_sha256)}")
    state = t.state.value if hasattr(t.state, "value") else t.state
    return _STRUCT.pack(
        VERSION, _code(STATES, state), flags, _code(REJECT_REASONS, t.reject_reason),
        int(t.agent_id) & 0xFFFFFFFF, int(t.seq) & 0xFFFFFFFF, float(t.time_s),
        *(float(v) for v in t.position_m), *(float(v) for v in t.velocity_m_s), int(t.cv_index),
        int(t.map_version), sha, min(int(t.maps_rejected), 0xFFFF), _age_ms(t.position_age_s),
        _age_ms(t.heartbeat_age_s), _code(ACK_COMMANDS, t.ack_command), 0, int(t.ack_seq),
        _code(AUTHORITIES, t.authority), _code(LANDED, t.landed), _battery(t.battery_pct),
        min(int(t.health_count), 255), health, _code(COMMAND_REFUSALS, t.command_refusal),
        _code(ACK_COMMANDS, t.refused_command), min(int(t.commands_refused), 0xFFFF), 0,
        _text(t.health_text, HEALTH_TEXT_BYTES))


def _check(data: bytes | bytearray | memoryview) -> bytes:
    """The message as version-2 bytes (a version-1 one padded: its new fields unknown)."""
    if len(data) < 1:
        raise TelemetryError("telemetry: empty message")
    size = {1: V1_SIZE, VERSION: SIZE}.get(data[0])
    if size is None:
        raise TelemetryError(f"telemetry: format version {data[0]} is not supported (expected 1 or {VERSION})")
    if len(data) != size:
        raise TelemetryError(f"telemetry: version-{data[0]} message has {size} bytes, got {len(data)}")
    return bytes(data) + (_V1_PAD if data[0] == 1 else b"")


def battery_pct(records: np.ndarray) -> np.ndarray:
    """Battery [%] of a ``DTYPE`` array as floats (NaN where not reported)."""
    b = records["battery_pct"].astype(float)
    b[b > 100] = np.nan
    return b


def _name(table: tuple[str, ...], code: int) -> str:
    return table[code] if code < len(table) else table[0]


def decode(data: bytes | bytearray | memoryview) -> Telemetry:
    """bytes -> Telemetry; raises ``TelemetryError`` on a wrong version or size."""
    (_, state, flags, reason, agent_id, seq, time_s, px, py, pz, vx, vy, vz, cv, map_version, sha,
     n_rej, pos_age, hb_age, ack_cmd, _, ack_seq, authority, landed, battery, n_health, health, refusal,
     refused, n_refused, _, text) = _STRUCT.unpack(_check(data))
    return Telemetry(
        agent_id=agent_id, seq=seq, time_s=time_s, position_m=(px, py, pz), velocity_m_s=(vx, vy, vz),
        cv_index=cv, state=_name(STATES, state), map_version=map_version,
        map_sha256="" if sha == b"\0" * 32 else sha.hex(),
        flags=frozenset(n for n, bit in FLAG_NAMES.items() if flags & bit), maps_rejected=n_rej,
        reject_reason=_name(REJECT_REASONS, reason),
        position_age_s=math.inf if pos_age == 0xFFFF else pos_age / 1000.0,
        heartbeat_age_s=math.inf if hb_age == 0xFFFF else hb_age / 1000.0,
        ack_command=_name(ACK_COMMANDS, ack_cmd), ack_seq=ack_seq, authority=_name(AUTHORITIES, authority),
        landed=_name(LANDED, landed), battery_pct=None if battery > 100 else float(battery),
        health=frozenset(n for n, bit in HEALTH_NAMES.items() if health & bit), health_count=n_health,
        health_text=text.rstrip(b"\0").decode(errors="replace"), commands_refused=n_refused,
        command_refusal=_name(COMMAND_REFUSALS, refusal), refused_command=_name(ACK_COMMANDS, refused))


def decode_many(messages: Iterable[bytes]) -> tuple[np.ndarray, np.ndarray]:
    """Decode a batch: returns ``(records, ok)`` where ``records`` is a structured array of
    ``DTYPE`` (one row per message, zeros for bad ones; a version-1 row keeps ``version`` 1 and
    reads its version-2 fields as unknown) and ``ok`` a bool mask of the messages with a known
    version and its size."""
    msgs = list(messages)
    ok = np.array([(len(m) == SIZE and m[0] == VERSION) or (len(m) == V1_SIZE and m[0] == 1) for m in msgs],
                  dtype=bool)
    buf = b"".join((bytes(m) + (_V1_PAD if len(m) == V1_SIZE else b"")) if good else b"\0" * SIZE
                   for m, good in zip(msgs, ok))
    records = np.frombuffer(buf, dtype=DTYPE).copy() if msgs else np.zeros(0, dtype=DTYPE)
    return records, ok


def sha_hex(records: np.ndarray) -> list[str]:
    """Hex map digests of a ``DTYPE`` array ("" where none)."""
    return ["" if bytes(r) == b"\0" * 32 else bytes(r).hex() for r in records["map_sha256"]]


def state_names(codes: np.ndarray) -> list[str]:
    """State names for an array of state codes."""
    return [_name(STATES, int(c)) for c in codes]
