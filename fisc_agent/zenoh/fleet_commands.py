"""Signed fleet commands (``fisc/<swarm>/cmd``): codec and the replay/staleness gate, pure.

Wire format, version 1 (little-endian)::

    b"FCMD"        magic
    u8   version (1)
    u8   command code (1 hold, 2 resume, 3 land, 4 start-at)
    u8   flags (bit 0: signed)
    u8   length L of the swarm name
    u32  target agent id (0xFFFFFFFF = every agent)
    u64  sequence number (strictly increasing per ground key; the ground uses UNIX time in us)
    u64  issued at, UNIX time [ms]
    u64  start-at time, UNIX time [ms] (0 unless start-at)
    L    swarm name (UTF-8)           -- binds the command to one swarm
    64   Ed25519 signature over every byte before it (zeros when unsigned)

An agent accepts a command only if it decodes, names its swarm, targets it (or everyone),
is signed by a trusted key (unless unsigned commands are explicitly allowed), carries a
sequence number above the last one it accepted, and was issued within the freshness window
(``CommandGate``).  A captured command can therefore not be replayed later, nor into another
swarm, nor re-ordered after a newer one.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass
from enum import StrEnum

COMMANDS = ("hold", "resume", "land", "start-at")
ALL_AGENTS = 0xFFFFFFFF
MAGIC = b"FCMD"
VERSION = 1
SIG_LEN = 64
_HEAD = struct.Struct("<4sBBBBIQQQ")


class CommandCheck(StrEnum):
    """The check a fleet command failed (``CommandError.check``; the telemetry counter's key)."""

    TRUNCATED = "truncated"
    MAGIC = "magic"
    VERSION = "version"
    COMMAND = "command"
    SIZE = "size"
    SIGNATURE = "signature"
    SWARM = "swarm"
    START_AT = "start-at"
    TARGET = "target"
    REPLAY = "replay"
    STALE = "stale"
    FUTURE = "future"


class CommandError(ValueError):
    """A fleet command was malformed, unauthenticated, stale or replayed: ``check`` says which,
    the message (``"<check>: <detail>"``) how."""

    def __init__(self, check: CommandCheck, detail: str) -> None:
        super().__init__(f"{check.value}: {detail}")
        self.check = check
        """The failed check."""


@dataclass(frozen=True)
class FleetCommand:
    """A decoded fleet command."""

    name: str
    """``hold``, ``resume``, ``land`` or ``start-at``."""
    swarm: str
    """Swarm the command is for."""
    seq: int
    """Sequence number (strictly increasing per ground key)."""
    issued_unix_s: float
    """When the ground issued it, UNIX seconds (ms resolution)."""
    target_id: int = ALL_AGENTS
    """Agent id, or ``ALL_AGENTS``."""
    start_at_unix_s: float | None = None
    """For ``start-at``: when to start, UNIX seconds (ms resolution)."""
    signed: bool = False
    """True when the command carried a signature that verified against a trusted key."""

    def applies_to(self, agent_id: int) -> bool:
        """True when the command targets every agent or ``agent_id``."""
        return self.target_id == ALL_AGENTS or self.target_id == int(agent_id)


def encode_command(cmd: FleetCommand, signing_key: bytes | None = None) -> bytes:
    """FleetCommand -> bytes; ``signing_key``: 32-byte Ed25519 seed (None: unsigned)."""
    if cmd.name not in COMMANDS:
        raise CommandError(CommandCheck.COMMAND, f"unknown fleet command {cmd.name!r}; known: {', '.join(COMMANDS)}")
    if (cmd.name == "start-at") != (cmd.start_at_unix_s is not None):
        raise CommandError(CommandCheck.START_AT, "start-at needs start_at_unix_s, and only start-at carries one")
    swarm = cmd.swarm.encode()
    if not 0 < len(swarm) < 256:
        raise CommandError(CommandCheck.SWARM, "name must be 1..255 bytes")
    start_ms = 0 if cmd.start_at_unix_s is None else int(round(cmd.start_at_unix_s * 1000))
    head = _HEAD.pack(MAGIC, VERSION, COMMANDS.index(cmd.name) + 1, 1 if signing_key is not None else 0,
                      len(swarm), int(cmd.target_id), int(cmd.seq), int(round(cmd.issued_unix_s * 1000)),
                      start_ms) + swarm
    if signing_key is None:
        return head + b"\0" * SIG_LEN
    from nacl.signing import SigningKey

    return head + SigningKey(signing_key).sign(head).signature


def decode_command(data: bytes | bytearray | memoryview, trusted_keys: list[bytes] | None,
                   allow_unsigned: bool = False) -> FleetCommand:
    """Verify and decode a command.  With ``trusted_keys`` the signature must verify against
    one of them; an unsigned command is refused unless ``allow_unsigned``.  A signed command
    whose signature fails is always refused."""
    data = bytes(data)
    if len(data) < _HEAD.size + SIG_LEN:
        raise CommandError(CommandCheck.TRUNCATED, f"command has {len(data)} bytes, at least {_HEAD.size + SIG_LEN} needed")
    magic, version, code, flags, n_swarm, target, seq, issued_ms, start_ms = _HEAD.unpack_from(data)
    if magic != MAGIC:
        raise CommandError(CommandCheck.MAGIC, "not a FISC fleet command")
    if version != VERSION:
        raise CommandError(CommandCheck.VERSION, f"command format {version} is not supported (expected {VERSION})")
    if not 1 <= code <= len(COMMANDS):
        raise CommandError(CommandCheck.COMMAND, f"unknown command code {code}")
    end = _HEAD.size + n_swarm
    if len(data) != end + SIG_LEN:
        raise CommandError(CommandCheck.SIZE, f"command should have {end + SIG_LEN} bytes, has {len(data)}")
    signed_part, signature = data[:end], data[end:]
    signed = bool(flags & 1)
    if signed:
        if not trusted_keys:
            if not allow_unsigned:
                raise CommandError(CommandCheck.SIGNATURE, "signed command but no trusted key configured")
        else:
            from nacl.exceptions import BadSignatureError
            from nacl.signing import VerifyKey

            for key in trusted_keys:
                try:
                    VerifyKey(key).verify(signed_part, signature)
                    break
                except (BadSignatureError, ValueError):
                    continue
            else:
                raise CommandError(CommandCheck.SIGNATURE, "command is not signed by a trusted key")
    elif not allow_unsigned:
        raise CommandError(CommandCheck.SIGNATURE, "command is unsigned (use --allow-unsigned only in a lab)")
    try:
        swarm = data[_HEAD.size:end].decode()
    except UnicodeDecodeError as exc:
        raise CommandError(CommandCheck.SWARM, "name is not UTF-8") from exc
    name = COMMANDS[code - 1]
    if (name == "start-at") != (start_ms != 0):
        raise CommandError(CommandCheck.START_AT, "start time missing or given to another command")
    return FleetCommand(name=name, swarm=swarm, seq=seq, issued_unix_s=issued_ms / 1000.0, target_id=target,
                        start_at_unix_s=start_ms / 1000.0 if start_ms else None,
                        signed=signed and bool(trusted_keys))


class CommandGate:
    """Replay and staleness filter for one agent (keeps only the last accepted sequence).

    ``check(cmd, now_unix_s)`` raises ``CommandError`` for a command of another swarm or
    agent, a sequence number not above the last accepted one (replayed or re-ordered), or an
    issue time outside ``[now - max_age_s, now + max_future_s]`` (stale, or from a clock far
    ahead).  On success the command's sequence becomes the new floor.
    """

    def __init__(self, swarm: str, agent_id: int, max_age_s: float = 30.0, max_future_s: float = 5.0) -> None:
        self.swarm = swarm
        self.agent_id = int(agent_id)
        self.max_age_s = float(max_age_s)
        self.max_future_s = float(max_future_s)
        self.last_seq = 0

    def check(self, cmd: FleetCommand, now_unix_s: float) -> FleetCommand:
        """Accept ``cmd`` (returned) or raise ``CommandError`` naming the failed check (swarm, target, replay, age)."""
        if cmd.swarm != self.swarm:
            raise CommandError(CommandCheck.SWARM, f"command is for swarm {cmd.swarm!r}, this agent flies in {self.swarm!r}")
        if not cmd.applies_to(self.agent_id):
            raise CommandError(CommandCheck.TARGET, f"command is for agent {cmd.target_id}")
        if cmd.seq <= self.last_seq:
            raise CommandError(CommandCheck.REPLAY, f"sequence {cmd.seq} is not above the last accepted {self.last_seq}")
        age = now_unix_s - cmd.issued_unix_s
        if age > self.max_age_s:
            raise CommandError(CommandCheck.STALE, f"command issued {age:.1f} s ago (window {self.max_age_s:.0f} s)")
        if age < -self.max_future_s:
            raise CommandError(CommandCheck.FUTURE, f"command issued {-age:.1f} s in the future (clock skew?)")
        self.last_seq = cmd.seq
        return cmd
