"""Signed fleet commands (``<prefix>/<swarm>/cmd``): the codec, pure.

Wire format, version 2 (little-endian)::

    b"FCMD"        magic
    u8   version (2)
    u8   command code (``CommandName`` order: 1 hold, 2 resume, 3 land, 4 start-at, 5 go, 6 takeover)
    u8   flags (bit 0: signed)
    u8   length L of the swarm name
    u16  number N of addressed agents (0 = the whole swarm)
    u16  reserved (0)
    u64  sequence number (strictly increasing per ground key; the ground uses UNIX time in us)
    u64  issued at, UNIX time [ms] (the ground's clock)
    u64  start-at time, UNIX time [ms] (0 unless start-at)
    L    swarm name (UTF-8)           -- binds the command to one swarm
    4N   u32 agent ids, ascending, no repeats
    64   Ed25519 signature over every byte before it (zeros when unsigned)

Version 2 replaced version 1's single u32 target (``0xFFFFFFFF`` = every agent) by a list, so
that one signed ``go`` can name agents 1, 3 and 5.  Version-1 commands still decode (their one
target becomes a one-element list); the ground only sends version 2, so ground and agents are
upgraded together.  The acceptance rules (signature, swarm, target, per-key sequence,
freshness) are ``fisc_agent.zenoh.command_gate``'s.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass
from enum import StrEnum


class CommandName(StrEnum):
    """A fleet command on the wire (the value is its CLI name; the order is its wire code - 1)."""

    HOLD = "hold"
    RESUME = "resume"
    LAND = "land"
    START_AT = "start-at"
    """A ``go`` that takes effect at ``start_at_unix_s``."""
    GO = "go"
    TAKEOVER = "takeover"
    """Take an armed vehicle this process did not arm; only valid addressed to listed agents."""


COMMANDS = tuple(c.value for c in CommandName)
"""Command names in wire-code order (code = index + 1)."""
ALL_AGENTS = 0xFFFFFFFF
"""Version 1's "every agent" target; never a valid agent id."""
MAGIC = b"FCMD"
VERSION = 2
SIG_LEN = 64
MAX_TARGETS = 4096
"""Agent ids one command may name at most."""
_HEAD = struct.Struct("<4sBBBBHHQQQ")
_HEAD_V1 = struct.Struct("<4sBBBBIQQQ")


class CommandCheck(StrEnum):
    """The check a fleet command failed (``CommandError.check``; telemetry's refusal reason).

    Append only: the order is the telemetry code (``telemetry_codec.COMMAND_REFUSALS``)."""

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
    ADDRESS = "address"
    """A takeover not addressed to listed agents, or a malformed agent list."""


class CommandError(ValueError):
    """A fleet command was malformed, unauthenticated, stale or replayed: ``check`` says which,
    the message (``"<check>: <detail>"``) how."""

    def __init__(self, check: CommandCheck, detail: str) -> None:
        super().__init__(f"{check.value}: {detail}")
        self.check = check
        """The failed check."""


def key_id_of(public_key: bytes) -> str:
    """The short name of a ground key: hex of the Ed25519 public key's first 8 bytes (the key of
    the per-key sequence floors and ``FleetOrder.key_id``)."""
    return bytes(public_key)[:8].hex()


@dataclass(frozen=True)
class FleetCommand:
    """A decoded fleet command."""

    name: CommandName
    """The command."""
    swarm: str
    """Swarm the command is for."""
    seq: int
    """Sequence number (strictly increasing per ground key)."""
    issued_unix_s: float
    """When the ground issued it, UNIX seconds on the ground's clock (ms resolution)."""
    targets: tuple[int, ...] = ()
    """Agent ids it is addressed to, ascending; () = the whole swarm."""
    start_at_unix_s: float | None = None
    """For ``start-at``: when to go, UNIX seconds (ms resolution)."""
    signed: bool = False
    """True when the command carried a signature that verified against a trusted key."""
    key_id: str = ""
    """``key_id_of`` the trusted key that verified it ("" unsigned, or signed but no key to check)."""

    def __post_init__(self) -> None:
        object.__setattr__(self, "name", CommandName(self.name))
        object.__setattr__(self, "targets", tuple(int(t) for t in self.targets))

    @property
    def addressed(self) -> bool:
        """True when the command names agents (``--agents``), False for the whole swarm."""
        return bool(self.targets)

    def applies_to(self, agent_id: int) -> bool:
        """True when the command is for the whole swarm or names ``agent_id``."""
        return not self.targets or int(agent_id) in self.targets


def check_targets(targets: tuple[int, ...]) -> None:
    """``CommandError`` (``address``) unless ``targets`` are ascending, distinct u32 agent ids
    (not ``ALL_AGENTS``), at most ``MAX_TARGETS``."""
    if len(targets) > MAX_TARGETS:
        raise CommandError(CommandCheck.ADDRESS, f"{len(targets)} agents named, at most {MAX_TARGETS}")
    for a, b in zip(targets, targets[1:]):
        if b <= a:
            raise CommandError(CommandCheck.ADDRESS, f"agent ids must be ascending and distinct ({a} then {b})")
    if targets and not (0 <= targets[0] and targets[-1] < ALL_AGENTS):
        raise CommandError(CommandCheck.ADDRESS, f"agent ids must be within 0..{ALL_AGENTS - 1}")


def _check_fields(name: CommandName, targets: tuple[int, ...], start_ms: int) -> None:
    if (name is CommandName.START_AT) != (start_ms != 0):
        raise CommandError(CommandCheck.START_AT, "start-at needs a start time, and only start-at carries one")
    if name is CommandName.TAKEOVER and not targets:
        raise CommandError(CommandCheck.ADDRESS, "takeover must name its agents (--agents): never swarm-wide")
    check_targets(targets)


def encode_command(cmd: FleetCommand, signing_key: bytes | None = None) -> bytes:
    """FleetCommand -> version-2 bytes; ``signing_key``: 32-byte Ed25519 seed (None: unsigned)."""
    swarm = cmd.swarm.encode()
    if not 0 < len(swarm) < 256:
        raise CommandError(CommandCheck.SWARM, "name must be 1..255 bytes")
    start_ms = 0 if cmd.start_at_unix_s is None else int(round(cmd.start_at_unix_s * 1000))
    _check_fields(cmd.name, cmd.targets, start_ms)
    head = _HEAD.pack(MAGIC, VERSION, COMMANDS.index(cmd.name) + 1, 1 if signing_key is not None else 0,
                      len(swarm), len(cmd.targets), 0, int(cmd.seq), int(round(cmd.issued_unix_s * 1000)),
                      start_ms) + swarm + struct.pack(f"<{len(cmd.targets)}I", *cmd.targets)
    if signing_key is None:
        return head + b"\0" * SIG_LEN
    from nacl.signing import SigningKey

    return head + SigningKey(signing_key).sign(head).signature


def _verify(signed_part: bytes, signature: bytes, signed: bool, trusted_keys: list[bytes] | None,
            allow_unsigned: bool) -> str:
    """The key id that verified the signature ("" when none was needed or none could check)."""
    if not signed:
        if not allow_unsigned:
            raise CommandError(CommandCheck.SIGNATURE, "command is unsigned (use --allow-unsigned only in a lab)")
        return ""
    if not trusted_keys:
        if not allow_unsigned:
            raise CommandError(CommandCheck.SIGNATURE, "signed command but no trusted key configured")
        return ""
    from nacl.exceptions import BadSignatureError
    from nacl.signing import VerifyKey

    for key in trusted_keys:
        try:
            VerifyKey(key).verify(signed_part, signature)
            return key_id_of(key)
        except (BadSignatureError, ValueError):
            continue
    raise CommandError(CommandCheck.SIGNATURE, "command is not signed by a trusted key")


def decode_command(data: bytes | bytearray | memoryview, trusted_keys: list[bytes] | None,
                   allow_unsigned: bool = False) -> FleetCommand:
    """Verify and decode a command (version 2, or version 1).  With ``trusted_keys`` the
    signature must verify against one of them; an unsigned command is refused unless
    ``allow_unsigned``.  A signed command whose signature fails is always refused."""
    data = bytes(data)
    if len(data) < 6:
        raise CommandError(CommandCheck.TRUNCATED, f"command has {len(data)} bytes")
    if data[:4] != MAGIC:
        raise CommandError(CommandCheck.MAGIC, "not a FISC fleet command")
    version = data[4]
    if version not in (1, VERSION):
        raise CommandError(CommandCheck.VERSION, f"command format {version} is not supported (expected 1 or {VERSION})")
    head = _HEAD if version == VERSION else _HEAD_V1
    if len(data) < head.size + SIG_LEN:
        raise CommandError(CommandCheck.TRUNCATED, f"command has {len(data)} bytes, at least {head.size + SIG_LEN} needed")
    if version == VERSION:
        _, _, code, flags, n_swarm, n_targets, _, seq, issued_ms, start_ms = head.unpack_from(data)
    else:
        _, _, code, flags, n_swarm, target, seq, issued_ms, start_ms = head.unpack_from(data)
        n_targets = 0
    if not 1 <= code <= len(COMMANDS):
        raise CommandError(CommandCheck.COMMAND, f"unknown command code {code}")
    end = head.size + n_swarm + 4 * n_targets
    if len(data) != end + SIG_LEN:
        raise CommandError(CommandCheck.SIZE, f"command should have {end + SIG_LEN} bytes, has {len(data)}")
    signed_part, signature = data[:end], data[end:]
    key_id = _verify(signed_part, signature, bool(flags & 1), trusted_keys, allow_unsigned)
    try:
        swarm = data[head.size:head.size + n_swarm].decode()
    except UnicodeDecodeError as exc:
        raise CommandError(CommandCheck.SWARM, "name is not UTF-8") from exc
    if version == VERSION:
        targets = struct.unpack_from(f"<{n_targets}I", data, head.size + n_swarm)
    else:
        targets = () if target == ALL_AGENTS else (target,)
    name = CommandName(COMMANDS[code - 1])
    _check_fields(name, targets, start_ms)
    return FleetCommand(name=name, swarm=swarm, seq=seq, issued_unix_s=issued_ms / 1000.0, targets=targets,
                        start_at_unix_s=start_ms / 1000.0 if start_ms else None, signed=bool(key_id),
                        key_id=key_id)
