"""A map that arrived over Zenoh: the transport checks on top of ``decode_map`` (pure).

The chunk codec and the reassembly live in ``fisc_agent.map.chunks``; this module turns the
reassembled bytes into a verified, read-only ``CommandMap`` and names the check that refused
one (the telemetry's ``REJECT_REASONS``).
"""

from __future__ import annotations

from fisc_agent.zenoh import telemetry_codec as tc
from fisc_agent.map.codec import CommandMap, MapError, MapErrorKind, decode_map


def reject_code(exc: Exception) -> str:
    """The ``REJECT_REASONS`` name of a map refusal: a ``MapError``'s kind where the telemetry
    has a code for it, ``other`` for the rest (and for any other exception)."""
    kind = exc.kind.value if isinstance(exc, MapError) else MapErrorKind.OTHER.value
    return kind if kind in tc.REJECT_REASONS[1:] else MapErrorKind.OTHER.value


def verify_map_bytes(blob: bytes | bytearray, trusted_keys: list[bytes] | None, allow_unsigned: bool,
                     claimed_version: int | None = None, source: str = "<zenoh>") -> CommandMap:
    """decode_map plus the transport checks; arrays are made read-only."""
    if allow_unsigned:
        cmap = decode_map(memoryview(blob), None, source=source)
        if cmap.signed and trusted_keys and bytes.fromhex(cmap.public_key or "") not in trusted_keys:
            raise MapError(MapErrorKind.SIGNATURE, "signed by a key that is not trusted", source=source)
    else:
        if not trusted_keys:
            raise MapError(MapErrorKind.SIGNATURE, "no trusted key configured", source=source)
        cmap = decode_map(memoryview(blob), trusted_keys, source=source)
    if claimed_version is not None and cmap.map_version != claimed_version:
        raise MapError(MapErrorKind.VERSION_MISMATCH, f"chunks claim map_version {claimed_version}, "
                       f"the map says {cmap.map_version}", source=source)
    for arr in cmap.arrays.values():
        arr.flags.writeable = False
    return cmap
