"""MAVLink framing of the autopilot emulator, through pymavlink's public API only.

Outgoing: :class:`Encoder` owns one ``pymavlink.dialects.v20.ardupilotmega.MAVLink`` object (MAVLink 2,
the emulator's ``srcSystem``/``srcComponent``) whose output file is the encoder itself:
``MAVLink.send`` packs the message (payload, header, CRC, sequence number) and writes the frame,
which :meth:`Encoder.frame` hands back as bytes.  Incoming: :func:`new_parser` gives a robust
parser per peer (clients may speak MAVLink 1 or 2).

``pymavlink.mavutil`` is not used: it keeps the dialect and the MAVLink 1/2 choice in module
globals driven by environment variables; these objects share no state, so many emulators can
live in one process.
"""

from __future__ import annotations

from pymavlink.dialects.v20 import ardupilotmega as mavlink

from fisc_agent.mavlink.fast_codec import decode_v2, frame_length_v2, pack_v2

__all__ = ["Encoder", "new_parser", "parse"]


class Encoder:
    """MAVLink 2 frames of one system/component: ``frame(msg)`` -> bytes (sequence numbers wrap at 256)."""

    def __init__(self, sysid: int, compid: int) -> None:
        self._frame = b""
        self.mav = mavlink.MAVLink(self, srcSystem=sysid, srcComponent=compid)
        """The pymavlink MAVLink object: its ``*_encode`` methods build the messages to frame."""

    def write(self, data: bytes) -> None:
        """File-like sink of ``MAVLink.send`` (called once per frame)."""
        self._frame = bytes(data)

    def frame(self, msg: mavlink.MAVLink_message) -> bytes:
        """The MAVLink 2 frame of ``msg`` with the next sequence number."""
        self.mav.send(msg)
        return self._frame

    def frame_payload(self, msg_id: int, crc_extra: bytes, payload: bytes) -> bytes:
        """The MAVLink 2 frame ``frame`` gives for the message whose wire-order payload is ``payload``
        (``fisc_agent.mavlink.fast_codec.pack_v2``: no message object), with the next sequence number."""
        mav = self.mav
        buf = pack_v2(mav, msg_id, crc_extra, payload)
        mav.seq = (mav.seq + 1) % 256
        mav.total_packets_sent += 1
        mav.total_bytes_sent += len(buf)
        return buf


def parse(parser: mavlink.MAVLink, data: bytes) -> list:
    """The messages of ``data`` as ``parser.parse_buffer(data)`` gives them (BAD_DATA included);
    a datagram that is exactly one unsigned MAVLink 2 frame, with nothing buffered before it, is
    decoded by ``fisc_agent.mavlink.fast_codec.decode_v2`` (the same message object), the rest by
    the parser."""
    if parser.buf_len() == 0 and frame_length_v2(data) == len(data):
        m = decode_v2(parser, data)
        if m is not None:
            return [m]
    return parser.parse_buffer(data) or []


def new_parser() -> mavlink.MAVLink:
    """A MAVLink 1/2 parser for one peer; bad bytes become BAD_DATA messages, not exceptions."""
    parser = mavlink.MAVLink(None)
    parser.robust_parsing = True
    return parser
