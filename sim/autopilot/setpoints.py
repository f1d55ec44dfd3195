"""SET_POSITION_TARGET_* fields -> a :class:`~sim.autopilot.vehicle_types.Setpoint` in local NED (pure).

``type_mask`` bits set = ignore (pymavlink's ``POSITION_TARGET_TYPEMASK_*``: position X/Y/Z,
velocity VX/VY/VZ, acceleration AX/AY/AZ, YAW, YAW_RATE); an acceleration is kept unless FORCE_SET
says the fields are a force (not flown).  An axis with neither position nor velocity holds zero velocity.
"""

from __future__ import annotations

import math

from pymavlink.dialects.v20 import ardupilotmega as mavlink

from fisc_agent.flight.frames import GeodeticAnchor
from sim.autopilot.vehicle_types import Setpoint

__all__ = ["GLOBAL_FRAMES", "resolve_global_setpoint", "resolve_local_setpoint", "takeoff_altitude_m"]

_POS_BITS = (
    mavlink.POSITION_TARGET_TYPEMASK_X_IGNORE, mavlink.POSITION_TARGET_TYPEMASK_Y_IGNORE,
    mavlink.POSITION_TARGET_TYPEMASK_Z_IGNORE,
)  # fmt: skip
_VEL_BITS = (
    mavlink.POSITION_TARGET_TYPEMASK_VX_IGNORE, mavlink.POSITION_TARGET_TYPEMASK_VY_IGNORE,
    mavlink.POSITION_TARGET_TYPEMASK_VZ_IGNORE,
)  # fmt: skip
_ACC_BITS = (
    mavlink.POSITION_TARGET_TYPEMASK_AX_IGNORE, mavlink.POSITION_TARGET_TYPEMASK_AY_IGNORE,
    mavlink.POSITION_TARGET_TYPEMASK_AZ_IGNORE,
)  # fmt: skip
_FORCE_SET = mavlink.POSITION_TARGET_TYPEMASK_FORCE_SET
_YAW_IGNORE = mavlink.POSITION_TARGET_TYPEMASK_YAW_IGNORE
_YAW_RATE_IGNORE = mavlink.POSITION_TARGET_TYPEMASK_YAW_RATE_IGNORE

_RELATIVE_ALT_FRAMES = (mavlink.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT, mavlink.MAV_FRAME_GLOBAL_RELATIVE_ALT)
GLOBAL_FRAMES = (mavlink.MAV_FRAME_GLOBAL_INT, mavlink.MAV_FRAME_GLOBAL, *_RELATIVE_ALT_FRAMES)
"""Frames SET_POSITION_TARGET_GLOBAL_INT is flown in (altitude AMSL or relative to home)."""


def _axes(values: tuple[float, float, float], mask: int, bits: tuple[int, int, int]) -> list[float]:
    return [float(v) if not (mask & b) and math.isfinite(v) else math.nan for v, b in zip(values, bits)]


def _rotate_yaw(v: list[float], yaw: float) -> list[float]:
    c, s = math.cos(yaw), math.sin(yaw)
    return [c * v[0] - s * v[1], s * v[0] + c * v[1], v[2]]


def resolve_local_setpoint(
    frame: int,
    type_mask: int,
    position: tuple[float, float, float],
    velocity: tuple[float, float, float],
    yaw: float,
    yaw_rate: float,
    current_ned_m: tuple[float, float, float],
    current_yaw_rad: float,
    accel: tuple[float, float, float] = (math.nan, math.nan, math.nan),
) -> Setpoint | None:
    """SET_POSITION_TARGET_LOCAL_NED fields -> :class:`Setpoint` in local NED (None: frame unsupported).

    Frames: LOCAL_NED; LOCAL_OFFSET_NED (position relative to the vehicle); BODY_NED (position as
    LOCAL_NED, velocity and acceleration rotated by the heading); BODY_OFFSET_NED / BODY_FRD (position
    offset, velocity and acceleration rotated by the heading, offset relative to the vehicle).
    ``accel``: the afx/afy/afz fields (dropped when FORCE_SET marks them a force).
    """
    pos = _axes(position, type_mask, _POS_BITS)
    vel = _axes(velocity, type_mask, _VEL_BITS)
    acc = [math.nan] * 3 if type_mask & _FORCE_SET else _axes(accel, type_mask, _ACC_BITS)
    if frame == mavlink.MAV_FRAME_LOCAL_NED:
        pass
    elif frame == mavlink.MAV_FRAME_LOCAL_OFFSET_NED:
        pos = [c + p for c, p in zip(current_ned_m, pos)]
    elif frame == mavlink.MAV_FRAME_BODY_NED:
        vel, acc = _rotate_yaw(vel, current_yaw_rad), _rotate_yaw(acc, current_yaw_rad)
    elif frame in (mavlink.MAV_FRAME_BODY_OFFSET_NED, mavlink.MAV_FRAME_BODY_FRD):
        rp = _rotate_yaw(pos, current_yaw_rad)
        pos = [c + p for c, p in zip(current_ned_m, rp)]
        vel, acc = _rotate_yaw(vel, current_yaw_rad), _rotate_yaw(acc, current_yaw_rad)
    else:
        return None
    y = float(yaw) if not (type_mask & _YAW_IGNORE) and math.isfinite(yaw) else math.nan
    yr = float(yaw_rate) if not (type_mask & _YAW_RATE_IGNORE) and math.isfinite(yaw_rate) else math.nan
    return Setpoint(tuple(pos), tuple(vel), y, yr, tuple(acc))  # type: ignore[arg-type]


def resolve_global_setpoint(
    frame: int,
    type_mask: int,
    lat_int: int,
    lon_int: int,
    alt_m: float,
    velocity: tuple[float, float, float],
    yaw: float,
    yaw_rate: float,
    anchor: GeodeticAnchor,
    home_down_m: float,
    current_ned_m: tuple[float, float, float],
    current_yaw_rad: float,
    accel: tuple[float, float, float] = (math.nan, math.nan, math.nan),
) -> Setpoint | None:
    """SET_POSITION_TARGET_GLOBAL_INT fields -> :class:`Setpoint` in local NED (None: frame unsupported).

    ``anchor``: the geodetic origin of local NED (WGS-84, :class:`fisc_agent.flight.frames.GeodeticAnchor`);
    ``home_down_m``: home's D [m], the datum of the relative-altitude frames.
    """
    if frame not in GLOBAL_FRAMES:
        return None
    if frame in _RELATIVE_ALT_FRAMES:
        alt_m = alt_m + anchor.alt_m - home_down_m
    ned = anchor.geodetic_to_ned(lat_int * 1e-7, lon_int * 1e-7, alt_m)
    return resolve_local_setpoint(
        mavlink.MAV_FRAME_LOCAL_NED, type_mask, ned, velocity, yaw, yaw_rate, current_ned_m, current_yaw_rad, accel
    )


def takeoff_altitude_m(param7: float, frame: int | None, home_amsl_m: float, px4: bool) -> float | None:
    """MAV_CMD_NAV_TAKEOFF param7 -> altitude above home [m] (None: not given).

    A COMMAND_INT's global frame says what param7 is (relative or AMSL); a COMMAND_LONG has no
    frame: PX4 reads param7 as AMSL, ArduPilot as relative to home."""
    if not math.isfinite(param7):
        return None
    if frame in _RELATIVE_ALT_FRAMES:
        return param7
    if frame in (mavlink.MAV_FRAME_GLOBAL, mavlink.MAV_FRAME_GLOBAL_INT) or px4:
        return param7 - home_amsl_m
    return param7
