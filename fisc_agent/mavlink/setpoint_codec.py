"""The velocity setpoint's MAVLink 2 frame, packed directly (issue 40: the agent sends one every tick).

``pack_velocity_setpoint`` gives, byte for byte, what pymavlink's
``set_position_target_local_ned_encode(...).pack(mav)`` gives for a velocity-only
SET_POSITION_TARGET_LOCAL_NED (MAVLink 2, unsigned: the payload's trailing zeros stripped, the
CRC with the message's CRC extra), without building pymavlink's message and header objects (about a
fifth of a flying agent's tick).  ``send_velocity_setpoint`` writes it as ``MAVLink.send`` does
(sequence number, counters); with signing or a send callback configured it leaves the work to
pymavlink itself.
"""

from __future__ import annotations

import struct

from pymavlink.dialects.v20 import ardupilotmega as mavlink2

MSG_ID = mavlink2.MAVLINK_MSG_ID_SET_POSITION_TARGET_LOCAL_NED
CRC_EXTRA = bytes((mavlink2.MAVLink_set_position_target_local_ned_message.crc_extra,))
_PAYLOAD = struct.Struct("<IfffffffffffHBBB")
_HEADER = struct.Struct("<BBBBBBBHB")
_CRC = struct.Struct("<H")
_MCRF4XX = getattr(mavlink2, "mcrf4xx", None)


def pack_velocity_setpoint(mav, boot_ms: int, target_system: int, target_component: int, frame: int,
                           type_mask: int, vn: float, ve: float, vd: float) -> bytes:
    """The frame of a SET_POSITION_TARGET_LOCAL_NED with velocity (vn, ve, vd) [m/s], position,
    acceleration, yaw and yaw rate zero, from ``mav``'s system, component and next sequence number
    (``mav`` is not changed)."""
    payload = _PAYLOAD.pack(boot_ms, 0.0, 0.0, 0.0, vn, ve, vd, 0.0, 0.0, 0.0, 0.0, 0.0, type_mask, target_system,
                            target_component, frame)
    n = len(payload)
    while n > 1 and payload[n - 1] == 0:  # MAVLink 2 drops the payload's trailing zeros
        n -= 1
    if n < len(payload):
        payload = payload[:n]
    head = _HEADER.pack(253, n, 0, 0, mav.seq, mav.srcSystem, mav.srcComponent, MSG_ID & 0xFFFF, MSG_ID >> 16)
    return head + payload + _CRC.pack(_crc(head[1:] + payload + CRC_EXTRA))


def _crc(buf: bytes) -> int:
    """pymavlink's X.25 CRC (CRC-16/MCRF4XX) of ``buf``: its C routine where installed (``fastcrc``)."""
    if _MCRF4XX is not None:
        return _MCRF4XX(buf, 0xFFFF)
    return mavlink2.x25crc(buf).crc


def send_velocity_setpoint(mav, boot_ms: int, target_system: int, target_component: int, frame: int,
                           type_mask: int, vn: float, ve: float, vd: float) -> None:
    """Send the velocity setpoint through ``mav`` (a pymavlink ``MAVLink``) as ``mav.send`` would."""
    if mav.signing.sign_outgoing or mav.send_callback is not None:
        mav.send(mav.set_position_target_local_ned_encode(boot_ms, target_system, target_component, frame, type_mask,
                                                          0.0, 0.0, 0.0, vn, ve, vd, 0.0, 0.0, 0.0, 0.0, 0.0))
        return
    buf = pack_velocity_setpoint(mav, boot_ms, target_system, target_component, frame, type_mask, vn, ve, vd)
    mav.file.write(buf)
    mav.seq = (mav.seq + 1) % 256
    mav.total_packets_sent += 1
    mav.total_bytes_sent += len(buf)
