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
from pymavlink.dialects.v20.ardupilotmega import (POSITION_TARGET_TYPEMASK_AX_IGNORE, POSITION_TARGET_TYPEMASK_AY_IGNORE,
                                                  POSITION_TARGET_TYPEMASK_AZ_IGNORE, POSITION_TARGET_TYPEMASK_X_IGNORE,
                                                  POSITION_TARGET_TYPEMASK_Y_IGNORE, POSITION_TARGET_TYPEMASK_YAW_IGNORE,
                                                  POSITION_TARGET_TYPEMASK_YAW_RATE_IGNORE,
                                                  POSITION_TARGET_TYPEMASK_Z_IGNORE)

from fisc_agent.mavlink.fast_codec import can_pack_fast, pack_v2, write_frame

MSG_ID = mavlink2.MAVLINK_MSG_ID_SET_POSITION_TARGET_LOCAL_NED
CRC_EXTRA = bytes((mavlink2.MAVLink_set_position_target_local_ned_message.crc_extra,))
_PAYLOAD = struct.Struct("<IfffffffffffHBBB")

#: SET_POSITION_TARGET_LOCAL_NED type mask: use vx, vy, vz only; ignore position,
#: acceleration, yaw and yaw rate (= 3527).
TYPEMASK_VELOCITY_ONLY = (POSITION_TARGET_TYPEMASK_X_IGNORE | POSITION_TARGET_TYPEMASK_Y_IGNORE
                          | POSITION_TARGET_TYPEMASK_Z_IGNORE | POSITION_TARGET_TYPEMASK_AX_IGNORE
                          | POSITION_TARGET_TYPEMASK_AY_IGNORE | POSITION_TARGET_TYPEMASK_AZ_IGNORE
                          | POSITION_TARGET_TYPEMASK_YAW_IGNORE | POSITION_TARGET_TYPEMASK_YAW_RATE_IGNORE)
#: the same with the acceleration used (feed-forward; = 3079).
TYPEMASK_VELOCITY_ACCEL = (POSITION_TARGET_TYPEMASK_X_IGNORE | POSITION_TARGET_TYPEMASK_Y_IGNORE
                           | POSITION_TARGET_TYPEMASK_Z_IGNORE | POSITION_TARGET_TYPEMASK_YAW_IGNORE
                           | POSITION_TARGET_TYPEMASK_YAW_RATE_IGNORE)


def pack_velocity_setpoint(mav, boot_ms: int, target_system: int, target_component: int, frame: int,
                           type_mask: int, vn: float, ve: float, vd: float,
                           an: float = 0.0, ae: float = 0.0, ad: float = 0.0) -> bytes:
    """The frame of a SET_POSITION_TARGET_LOCAL_NED with velocity (vn, ve, vd) [m/s] and acceleration
    (an, ae, ad) [m/s^2, zero by default], position, yaw and yaw rate zero, from ``mav``'s system,
    component and next sequence number (``mav`` is not changed)."""
    payload = _PAYLOAD.pack(boot_ms, 0.0, 0.0, 0.0, vn, ve, vd, an, ae, ad, 0.0, 0.0, type_mask, target_system,
                            target_component, frame)
    return pack_v2(mav, MSG_ID, CRC_EXTRA, payload)


def send_velocity_setpoint(mav, boot_ms: int, target_system: int, target_component: int, frame: int,
                           type_mask: int, vn: float, ve: float, vd: float,
                           an: float = 0.0, ae: float = 0.0, ad: float = 0.0) -> None:
    """Send the velocity setpoint through ``mav`` (a pymavlink ``MAVLink``) as ``mav.send`` would."""
    if not can_pack_fast(mav):
        mav.send(mav.set_position_target_local_ned_encode(boot_ms, target_system, target_component, frame, type_mask,
                                                          0.0, 0.0, 0.0, vn, ve, vd, an, ae, ad, 0.0, 0.0))
        return
    write_frame(mav, pack_velocity_setpoint(mav, boot_ms, target_system, target_component, frame, type_mask,
                                            vn, ve, vd, an, ae, ad))
