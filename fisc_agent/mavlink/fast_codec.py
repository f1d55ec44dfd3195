"""Fast MAVLink 2 framing of the hot messages, byte- and object-identical to pymavlink (issue 40).

pymavlink's ``MAVLink.decode`` and ``MAVLink.send`` are general (MAVLink 1 and 2, signing, arrays,
strings, callbacks) and build header objects per message; an emulated swarm moves tens of thousands
of messages a second through them.  This module does the common case directly:

* ``decode_v2(mav, frame)``: one complete, *unsigned* MAVLink 2 frame of a message without arrays
  or strings, CRC checked, gives the same message object ``mav.decode(bytearray(frame))`` gives
  (same class, fields, header, ``_msgbuf``, ``_payload``, ``_crc``).  Anything else -- MAVLink 1,
  a signed frame, ``mav`` holding a signing key, a message with arrays or strings, an unknown id,
  a wrong length or CRC -- returns None, and the caller hands the frame to pymavlink (which
  decodes it or raises as before).
* ``pack_v2(mav, msg_id, crc_extra, payload)``: the unsigned MAVLink 2 frame ``mav.send`` writes
  for that payload (trailing zeros stripped, ``mav``'s ids and sequence number); ``mav`` is not
  changed.  ``write_frame`` then writes it and advances the counters as ``MAVLink.send`` does.
"""

from __future__ import annotations

import struct

from pymavlink.dialects.v20 import ardupilotmega as mavlink2

_HEADER = struct.Struct("<BBBBBBBHB")
_CRC = struct.Struct("<H")
_MCRF4XX = getattr(mavlink2, "mcrf4xx", None)
_NO_FAST_PATH = None
MAGIC_V2 = 0xFD
HEADER_LEN_V2 = 10


def crc_x25(buf: bytes | bytearray) -> int:
    """pymavlink's X.25 CRC (CRC-16/MCRF4XX) of ``buf``: its C routine where installed (``fastcrc``)."""
    if _MCRF4XX is not None:
        return _MCRF4XX(buf, 0xFFFF)
    return mavlink2.x25crc(buf).crc


class _Layout:
    """How to decode one message type without pymavlink's generic path."""

    __slots__ = ("cls", "unpack", "size", "order", "crc_extra")

    def __init__(self, cls) -> None:
        self.cls = cls
        """The pymavlink message class."""
        self.unpack = cls.unpacker.unpack
        """Its payload unpacker (wire order)."""
        self.size = cls.unpacker.size
        """Full payload length [bytes] (MAVLink 2 may send fewer: trailing zeros stripped)."""
        self.order = tuple(cls.orders)
        """Wire index of each constructor argument."""
        self.crc_extra = bytes((cls.crc_extra,))
        """The message's CRC extra byte."""


_LAYOUTS: dict[int, _Layout | None] = {}


def _layout(msg_id: int) -> _Layout | None:
    """The fast layout of ``msg_id``, or None (unknown id, arrays or strings: pymavlink's path)."""
    try:
        return _LAYOUTS[msg_id]
    except KeyError:
        pass
    cls = mavlink2.mavlink_map.get(msg_id)
    ok = (cls is not None and sum(cls.lengths) == len(cls.lengths)
          and not any(t == "char" or t.startswith("char[") for t in cls.fieldtypes))
    layout = _LAYOUTS[msg_id] = _Layout(cls) if ok else None
    return layout


def frame_length_v2(buf: bytes | bytearray) -> int | None:
    """Length of the unsigned MAVLink 2 frame that starts ``buf``; None when ``buf`` does not start
    with one's complete header."""
    if len(buf) < HEADER_LEN_V2 or buf[0] != MAGIC_V2 or buf[2] != 0:
        return None
    return HEADER_LEN_V2 + buf[1] + 2


def decode_v2(mav, frame: bytes | bytearray):
    """The message of one complete unsigned MAVLink 2 ``frame`` as ``mav.decode`` builds it, or None
    when the fast path does not apply (the caller then calls ``mav.decode``, which decodes or raises)."""
    n = len(frame)
    if n < HEADER_LEN_V2 + 2 or frame[0] != MAGIC_V2 or frame[2] != 0 or mav.signing.secret_key is not None:
        return _NO_FAST_PATH
    mlen = frame[1]
    if mlen != n - HEADER_LEN_V2 - 2:
        return _NO_FAST_PATH
    msg_id = frame[7] | (frame[8] << 8) | (frame[9] << 16)
    layout = _LAYOUTS.get(msg_id, False)
    if layout is False:
        layout = _layout(msg_id)
    if layout is None:
        return _NO_FAST_PATH
    crc = frame[n - 2] | (frame[n - 1] << 8)
    if crc_x25(bytes(frame[1:n - 2]) + layout.crc_extra) != crc:
        return _NO_FAST_PATH
    payload = frame[HEADER_LEN_V2:n - 2]
    if mlen < layout.size:
        payload = bytes(payload) + bytes(layout.size - mlen)
    elif mlen > layout.size:
        payload = payload[:layout.size]
    t = layout.unpack(payload)
    m = layout.cls(*[t[i] for i in layout.order])
    msgbuf = bytearray(frame)
    m._signed = False
    m._msgbuf = msgbuf
    m._payload = msgbuf[6:n - 2]  # pymavlink's slice (it starts inside the MAVLink 2 header)
    m._crc = crc
    m._header = mavlink2.MAVLink_header(msg_id, 0, frame[3], mlen, frame[4], frame[5], frame[6])
    return m


def pack_v2(mav, msg_id: int, crc_extra: bytes, payload: bytes) -> bytes:
    """The unsigned MAVLink 2 frame of ``payload`` (full length, wire order) from ``mav``'s system,
    component and next sequence number, as ``mav.send`` packs it; ``mav`` is not changed."""
    n = len(payload)
    while n > 1 and payload[n - 1] == 0:  # MAVLink 2 drops the payload's trailing zeros
        n -= 1
    if n < len(payload):
        payload = payload[:n]
    head = _HEADER.pack(MAGIC_V2, n, 0, 0, mav.seq, mav.srcSystem, mav.srcComponent, msg_id & 0xFFFF, msg_id >> 16)
    return head + payload + _CRC.pack(crc_x25(head[1:] + payload + crc_extra))


def can_pack_fast(mav) -> bool:
    """True when ``mav.send`` would write what ``pack_v2`` packs (no signing, no send callback)."""
    return not mav.signing.sign_outgoing and mav.send_callback is None


def write_frame(mav, buf: bytes) -> None:
    """Write ``buf`` to ``mav.file`` and advance the sequence number and counters as ``mav.send`` does."""
    mav.file.write(buf)
    mav.seq = (mav.seq + 1) % 256
    mav.total_packets_sent += 1
    mav.total_bytes_sent += len(buf)


def fast_decoder(mav):
    """A ``decode(buf)`` with ``mav.decode``'s results and errors: ``decode_v2`` first, ``mav.decode`` for the rest."""
    def decode(buf):
        m = decode_v2(mav, buf)
        return mav.decode(buf) if m is None else m
    return decode
