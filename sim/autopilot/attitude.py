"""The emulated vehicle's attitude, from the thrust its plant realises (pure functions, floats in and out).

A multicopter points its body's -z axis along its thrust; at a heading ``yaw`` that fixes roll and pitch
(Euler ZYX, the order PX4 and ArduPilot report in ATTITUDE).  ODOMETRY carries the same attitude as a
quaternion and its velocity in the body frame (PX4: ``child_frame_id`` BODY_FRD).
"""

from __future__ import annotations

import math

__all__ = ["attitude_from_thrust", "euler_to_quaternion", "ned_to_body"]


def attitude_from_thrust(thrust_ned_m_s2: tuple[float, float, float], yaw_rad: float) -> tuple[float, float]:
    """(roll, pitch) [rad], Euler ZYX at heading ``yaw_rad``, whose body -z axis points along the thrust
    acceleration ``thrust_ned_m_s2`` (an upward thrust: its down component < 0; a thrust that does not point
    up is taken as barely up)."""
    cy, sy = math.cos(yaw_rad), math.sin(yaw_rad)
    fwd = cy * thrust_ned_m_s2[0] + sy * thrust_ned_m_s2[1]
    right = -sy * thrust_ned_m_s2[0] + cy * thrust_ned_m_s2[1]
    up = max(-thrust_ned_m_s2[2], 1e-6)
    pitch = math.atan2(-fwd, up)
    return math.atan2(right * math.cos(pitch), up), pitch


def euler_to_quaternion(roll_rad: float, pitch_rad: float, yaw_rad: float) -> tuple[float, float, float, float]:
    """The rotation body FRD -> local NED of Euler ZYX angles, as a quaternion (w, x, y, z)."""
    cr, sr = math.cos(roll_rad / 2), math.sin(roll_rad / 2)
    cp, sp = math.cos(pitch_rad / 2), math.sin(pitch_rad / 2)
    cy, sy = math.cos(yaw_rad / 2), math.sin(yaw_rad / 2)
    return (cr * cp * cy + sr * sp * sy, sr * cp * cy - cr * sp * sy,
            cr * sp * cy + sr * cp * sy, cr * cp * sy - sr * sp * cy)  # fmt: skip


def ned_to_body(vec_ned: tuple[float, float, float], q_wxyz: tuple[float, float, float, float]) -> tuple[float, float, float]:
    """A local NED vector in the body frame of attitude ``q_wxyz`` (body -> NED): the quaternion's inverse applied."""
    w, x, y, z = q_wxyz
    n, e, d = vec_ned
    # rows of R(q)^T = columns of R(q)
    return (
        (1 - 2 * (y * y + z * z)) * n + 2 * (x * y + w * z) * e + 2 * (x * z - w * y) * d,
        2 * (x * y - w * z) * n + (1 - 2 * (x * x + z * z)) * e + 2 * (y * z + w * x) * d,
        2 * (x * z + w * y) * n + 2 * (y * z - w * x) * e + (1 - 2 * (x * x + y * y)) * d,
    )
