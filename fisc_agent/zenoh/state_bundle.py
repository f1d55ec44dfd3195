"""The ground's latest fleet commands, re-published as one bundle (``<prefix>/<swarm>/cmd/latest``), pure codec.

A bundle carries signed commands exactly as the ground sent them (``fisc_agent.zenoh.fleet_commands``);
the relay that re-publishes them cannot forge or alter one, and an agent checks each as it checks
a live command (``fisc_agent.zenoh.command_gate``, ``Source.STATE``).  Layout (little-endian)::

    b"FCST"   magic
    u8        version (1)
    u8        reserved (0)
    u16       number of commands N
    N times:  u16 length, then that many bytes of one encoded command

The relay orders the commands oldest first (issue time, then sequence), the order the agent applies them in.
"""

from __future__ import annotations

import struct

from fisc_agent.zenoh.fleet_commands import CommandCheck, CommandError

MAGIC = b"FCST"
VERSION = 1
MAX_COMMANDS = 1024
"""Commands one bundle may carry at most."""
_HEAD = struct.Struct("<4sBBH")
_LEN = struct.Struct("<H")


def encode_bundle(commands: list[bytes]) -> bytes:
    """Encoded commands -> one bundle (``CommandError`` ``size`` when too many or one too long)."""
    if len(commands) > MAX_COMMANDS:
        raise CommandError(CommandCheck.SIZE, f"{len(commands)} commands in one bundle, at most {MAX_COMMANDS}")
    parts = [_HEAD.pack(MAGIC, VERSION, 0, len(commands))]
    for raw in commands:
        if not 0 < len(raw) <= 0xFFFF:
            raise CommandError(CommandCheck.SIZE, f"a command of {len(raw)} bytes does not fit a bundle")
        parts += [_LEN.pack(len(raw)), bytes(raw)]
    return b"".join(parts)


def decode_bundle(data: bytes | bytearray | memoryview) -> list[bytes]:
    """One bundle -> its encoded commands, in order; ``CommandError`` (truncated, magic, version,
    size) when the bundle is malformed (the commands themselves are checked by their reader)."""
    data = bytes(data)
    if len(data) < _HEAD.size:
        raise CommandError(CommandCheck.TRUNCATED, f"command bundle has {len(data)} bytes, at least {_HEAD.size} needed")
    magic, version, _, n = _HEAD.unpack_from(data)
    if magic != MAGIC:
        raise CommandError(CommandCheck.MAGIC, "not a FISC command bundle")
    if version != VERSION:
        raise CommandError(CommandCheck.VERSION, f"command bundle format {version} is not supported (expected {VERSION})")
    if n > MAX_COMMANDS:
        raise CommandError(CommandCheck.SIZE, f"bundle claims {n} commands, at most {MAX_COMMANDS}")
    out, pos = [], _HEAD.size
    for _ in range(n):
        if pos + _LEN.size > len(data):
            raise CommandError(CommandCheck.TRUNCATED, f"bundle ends inside command {len(out) + 1} of {n}")
        (size,) = _LEN.unpack_from(data, pos)
        pos += _LEN.size
        if size == 0 or pos + size > len(data):
            raise CommandError(CommandCheck.TRUNCATED, f"bundle ends inside command {len(out) + 1} of {n}")
        out.append(data[pos:pos + size])
        pos += size
    if pos != len(data):
        raise CommandError(CommandCheck.SIZE, f"{len(data) - pos} bytes after the last command of the bundle")
    return out
