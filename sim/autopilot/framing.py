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

__all__ = ["Encoder", "new_parser"]


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


def new_parser() -> mavlink.MAVLink:
    """A MAVLink 1/2 parser for one peer; bad bytes become BAD_DATA messages, not exceptions."""
    parser = mavlink.MAVLink(None)
    parser.robust_parsing = True
    return parser
